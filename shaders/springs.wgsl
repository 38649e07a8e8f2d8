// Matrix-free Hessian-vector product of a mass-spring incremental potential, element by
// element, never assembling H:
//   (H w)_i = m_i w_i + Σ_{springs e = (i, j)} K_e (w_i − w_j),
//   K_e = k̃_e [ (1 − t) u uᵀ + t I ],  u = (x_i − x_j)/l,  t = max(0, 1 − L_e/l)
// with k̃ = h²·k premultiplied on the host: the spring Hessian with its transverse
// eigenvalue k(1 − L/l) clamped at zero (positive semi-definite). Each node walks its own
// springs, so no atomics are needed and the sum order is fixed. The change of basis is
// applied on the fly: w = V P p, and q_i = P_i V_iᵀ (H w)_i + (I − P_i) D_i p_i, fused with
// the p·q partial sums like matvec.wgsl.

override D: u32 = 3u;
override MASKED: bool = true;
override ROTATE: bool = true;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> adj_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> adj: array<u32>;        // (other node, spring) pairs
@group(0) @binding(3) var<storage, read> pos: array<real>;
@group(0) @binding(4) var<storage, read> springs: array<real>;   // (rest length, h²k) pairs
@group(0) @binding(5) var<storage, read> mass: array<real>;
@group(0) @binding(6) var<storage, read> rot_index: array<u32>;
@group(0) @binding(7) var<storage, read> rotations: array<real>;
@group(0) @binding(8) var<storage, read> mask: array<u32>;
@group(0) @binding(9) var<storage, read> dvals: array<real>;
@group(0) @binding(10) var<storage, read> p: array<real>;
@group(0) @binding(11) var<storage, read_write> q: array<real>;
@group(0) @binding(12) var<storage, read_write> partials: array<acc>;
@group(0) @binding(13) var<storage, read> state: array<u32>;

var<workgroup> wg_done: u32;

// w_j = V_j P_j p_j in world coordinates.
fn world(j: u32) -> array<real, 3> {
    var w = array<real, 3>(real(0.0), real(0.0), real(0.0));
    var m = 0u;
    if (MASKED) {
        m = mask[j];
    }
    for (var a = 0u; a < D; a++) {
        if (((m >> a) & 1u) == 0u) {
            w[a] = p[j * D + a];
        }
    }
    if (ROTATE) {
        let r = rot_index[j];
        if (r != NO_ROTATION) {
            var t = array<real, 3>(real(0.0), real(0.0), real(0.0));
            for (var a = 0u; a < D; a++) {
                for (var c = 0u; c < D; c++) {
                    t[a] += rotations[r * D * D + a * D + c] * w[c];
                }
            }
            w = t;
        }
    }
    return w;
}

@compute @workgroup_size(WG)
fn spring_matvec(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (lid.x == 0u) {
        wg_done = state[STATE_DONE];
    }
    if (workgroupUniformLoad(&wg_done) != 0u) {
        return;
    }
    var part = acc(0.0);
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += params.n_partials * WG) {
        let wi = world(i);
        var s = array<real, 3>(real(0.0), real(0.0), real(0.0));
        let mi = mass[i];
        for (var a = 0u; a < D; a++) {
            s[a] = mi * wi[a];
        }
        for (var e = adj_ptr[i]; e < adj_ptr[i + 1u]; e++) {
            let j = adj[2u * e];
            let sp = adj[2u * e + 1u];
            let wj = world(j);
            var dxv = array<real, 3>(real(0.0), real(0.0), real(0.0));
            var l2 = real(0.0);
            for (var a = 0u; a < D; a++) {
                dxv[a] = pos[i * D + a] - pos[j * D + a];
                l2 += dxv[a] * dxv[a];
            }
            let l = sqrt(l2);
            if (l > real(0.0)) {
                let rest = springs[2u * sp];
                let kk = springs[2u * sp + 1u];
                let t = max(real(0.0), real(1.0) - rest / l);
                var udw = real(0.0);
                for (var a = 0u; a < D; a++) {
                    udw += dxv[a] / l * (wi[a] - wj[a]);
                }
                for (var a = 0u; a < D; a++) {
                    s[a] += kk * ((real(1.0) - t) * (dxv[a] / l) * udw + t * (wi[a] - wj[a]));
                }
            }
        }
        if (ROTATE) {
            let r = rot_index[i];
            if (r != NO_ROTATION) {
                var t = array<real, 3>(real(0.0), real(0.0), real(0.0));
                for (var a = 0u; a < D; a++) {
                    for (var c = 0u; c < D; c++) {
                        t[a] += rotations[r * D * D + c * D + a] * s[c];
                    }
                }
                s = t;
            }
        }
        var m = 0u;
        if (MASKED) {
            m = mask[i];
        }
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            let pk = p[k];
            var v = s[a];
            if (((m >> a) & 1u) != 0u) {
                v = dvals[k] * pk;
            }
            q[k] = v;
            part += acc(pk) * acc(v);
        }
    }
    workgroup_sum(lid.x, sum1(part), 1u);
    if (lid.x == 0u) {
        partials[PART_PQ * params.n_partials + group_index(wid, nwg)] = summed(0u);
    }
}
