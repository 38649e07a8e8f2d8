// The aggregate coarse correction of the CG preconditioner (src/coarse.rs, `--coarse
// aggregates`): z = M⁻¹r + Z E⁺ Zᵀr with Z the d translations of each aggregate, in frame
// coordinates (Z_i = P_i V_iᵀ on the nodes of its aggregate). Two dispatches after every
// update_xrz (and init), before update_p:
//   restrict: w = Zᵀr, one workgroup tree per aggregate (nodes listed aggregate by
//             aggregate in agg_nodes[agg_ptr[a]..agg_ptr[a + 1]]);
//   solve:    c = E⁺w, one thread per coarse row (E⁺ is dense, K = D·N_AGG rows).
// update_p (cg.wgsl, AGG) then adds w·c to ρ and Z_i c to p. The rigid translations alone
// (one aggregate) stay fused into update_xrz's reduction (cg.wgsl, COARSE).

override D: u32 = 3u;
override MASKED: bool = false;
override ROTATED: bool = false;
override N_AGG: u32 = 1u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> r: array<real>;
@group(0) @binding(2) var<storage, read> state: array<u32>;
@group(0) @binding(3) var<storage, read> cmask: array<u32>;
@group(0) @binding(4) var<storage, read> rot_index: array<u32>;
@group(0) @binding(5) var<storage, read> rotations: array<real>;
@group(0) @binding(6) var<storage, read> agg_ptr: array<u32>;
@group(0) @binding(7) var<storage, read> agg_nodes: array<u32>;
@group(0) @binding(8) var<storage, read> einv: array<acc>;
// w = Zᵀr in [0, K), c = E⁺w in [K, 2K).
@group(0) @binding(9) var<storage, read_write> wc: array<acc>;

var<workgroup> wg_u: u32;

// Z_iᵀ r_i = V_i P_i r_i, as three components (the third is zero for D = 2).
fn zt(i: u32) -> vec3<acc> {
    var w = vec3<real>(real(0.0));
    for (var a = 0u; a < D; a++) {
        w[a] = r[D * i + a];
    }
    if (MASKED) {
        let m = cmask[i];
        w = select(w, vec3<real>(real(0.0)), ((vec3<u32>(m) >> vec3<u32>(0u, 1u, 2u)) & vec3<u32>(1u)) != vec3<u32>(0u));
    }
    if (ROTATED) {
        let ri = rot_index[i];
        if (ri != NO_ROTATION) {
            var t = vec3<real>(real(0.0));
            for (var a = 0u; a < D; a++) {
                for (var c = 0u; c < D; c++) {
                    t[a] += rotations[ri * D * D + a * D + c] * w[c];
                }
            }
            w = t;
        }
    }
    return vec3<acc>(w);
}

// A converged (or halted) CG makes every later dispatch of its chunk a no-op.
fn done(lid: u32) -> bool {
    if (lid == 0u) {
        wg_u = state[STATE_DONE];
    }
    return workgroupUniformLoad(&wg_u) != 0u;
}

@compute @workgroup_size(WG)
fn restrict_r(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    if (done(lid.x)) {
        return;
    }
    for (var a = group_index(wid, nwg); a < N_AGG; a += group_count(nwg)) {
        var s = vec3<acc>(acc(0.0));
        let end = agg_ptr[a + 1u];
        for (var t = agg_ptr[a] + lid.x; t < end; t += WG) {
            s += zt(agg_nodes[t]);
        }
        workgroup_sum(lid.x, array<acc, 5>(s.x, s.y, s.z, acc(0.0), acc(0.0)), D);
        if (lid.x < D) {
            wc[a * D + lid.x] = summed(lid.x);
        }
        // The tree's memory is reused by the next aggregate.
        workgroupBarrier();
    }
}

@compute @workgroup_size(WG)
fn solve(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    if (done(lid.x)) {
        return;
    }
    let k = D * N_AGG;
    // E⁺ is symmetric: row `row` is read as column `row`, so neighbouring threads read
    // neighbouring addresses.
    for (var row = group_index(wid, nwg) * WG + lid.x; row < k; row += grid_stride(nwg)) {
        var s = acc(0.0);
        for (var col = 0u; col < k; col++) {
            s += einv[col * k + row] * wc[col];
        }
        wc[k + row] = s;
    }
}
