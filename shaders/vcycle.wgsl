// The multilevel preconditioner's V-cycle on the device (src/gpu/pcg/multilevel.rs): the
// CPU's z = M⁻¹r of src/solve/multilevel, level by level, with the factors and matrices
// built for the current system (on the device, mlsetup.wgsl, or on the host).
//
// One bind group per level l: its index arrays (`idx`) and f64 arrays (`vals`), its
// vectors b (right-hand side), x (correction) and ax (= A_l x, its residual being b − ax)
// and the next level's b and x. Level 0's b, x and ax are the PCG's r, z and q, and its
// product is the PCG's own matvec (pcg_product.wgsl, `world_z` then `matvec`): the operator a
// device Newton loop reads in place. Per level, down and up:
//
//   smooth_pre   x = ω B⁺ b                 (the coarsest level: ω = 1, the solve)
//   A x          level_ax here, the PCG's product at level 0
//   restrict_down b' = Pᵀ (b − ax)
//   …            the level below
//   prolong_up   x += P x'
//   A x
//   smooth_post  x += ω B⁺ (b − ax)
//
// B⁺ is the block-diagonal pseudo-inverse of the level's clusters (dense, symmetric,
// one per cluster). Every kernel writes each output from one invocation summing in a
// fixed order: no atomics, the same bits on any launch. Once the PCG's stop flag is set
// every kernel is a no-op, as the PCG's own are.

// Mirrors `VcycleParams` in src/gpu/pcg/multilevel.rs (size-asserted there). Offsets
// are in u32 words of `idx` and f64 entries of `vals`.
struct VcycleParams {
    // Items of this level, clusters of this level (the items of the next).
    n: u32,
    clusters: u32,
    // idx: cluster of each item, position in its cluster, cluster item ranges (clusters
    // + 1), items by cluster, each cluster's inverse offset in the level's inverses.
    of_at: u32,
    pos_at: u32,
    ptr_at: u32,
    items_at: u32,
    inv_start_at: u32,
    // idx: the level's matrix pattern (row pointers, columns; levels below the finest).
    row_at: u32,
    col_at: u32,
    // idx: P's rows (pointers, cluster columns) and Pᵀ's (per cluster: pointers, then per
    // block its row item).
    p_ptr_at: u32,
    p_col_at: u32,
    pt_ptr_at: u32,
    pt_row_at: u32,
    // vals: ω, the matrix values, P's and Pᵀ's blocks (D×D row-major).
    omega_at: u32,
    a_at: u32,
    p_at: u32,
    pt_at: u32,
    // 1 where this level has a level below (restrict_down and prolong_up are then defined).
    has_next: u32,
    // A smoothing dispatch: its unknowns in cluster order [t_begin, t_end) and where the
    // `inv` buffer bound with it starts in the level's inverses (those of its clusters).
    t_begin: u32,
    t_end: u32,
    inv_base: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

override D: u32 = 3u;
// The kernels of a chunk's verification (src/gpu/pcg/cg/run.rs): they run while the PCG
// verifies a converged recurrence, not while it iterates.
override VERIFY: bool = false;

@group(0) @binding(0) var<uniform> vp: VcycleParams;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read> vals: array<real>;
@group(0) @binding(3) var<storage, read_write> b: array<real>;
@group(0) @binding(4) var<storage, read_write> x: array<real>;
@group(0) @binding(5) var<storage, read_write> ax: array<real>;
@group(0) @binding(6) var<storage, read_write> bn: array<real>;
@group(0) @binding(7) var<storage, read_write> xn: array<real>;
// The PCG's state: its stop flag.
@group(0) @binding(8) var<storage, read> state: array<u32>;
// The cluster inverses of one run of consecutive clusters (one storage binding caps each
// buffer; a smoothing runs once per buffer).
@group(0) @binding(9) var<storage, read> inv: array<real>;

// Whether this dispatch does nothing: once the PCG's stop flag is set (VERIFY: unless the
// PCG is verifying a converged recurrence, whose restart applies the V-cycle too).
fn halted() -> bool {
    if (VERIFY) {
        return !(state[STATE_DONE] != 0u && state[STATE_CONVERGED] != 0u
            && state[STATE_VERIFIED] == 0u && state[STATE_HALT] == 0u
            && state[STATE_BREAKDOWN] == 0u);
    }
    return state[STATE_DONE] != 0u;
}

// (B⁺ v) at the q-th item in cluster order (the items of cluster 0, then of cluster 1,
// …), v = b (post: b − ax): the item and its D values. Each value sums over the cluster's
// unknowns in order, as the CPU's. One invocation forms an item's D rows together, so each
// entry of v it reads serves D rows: on a CPU adapter, where every load is a per-lane
// gather, loads are what a smoothing costs.
// Why cluster order: consecutive invocations then read neighbouring entries of one
// cluster's inverse (entry (row, col) is read at col·m + row: the inverse is symmetric,
// stored both ways bit for bit), which a GPU coalesces; in node order they would belong
// to unrelated clusters.
struct Item {
    node: u32,
    value: array<real, 3>,
}

fn cluster_rows(q: u32, post: bool) -> Item {
    let i = idx[vp.items_at + q];
    let c = idx[vp.of_at + i];
    let t0 = idx[vp.ptr_at + c];
    let t1 = idx[vp.ptr_at + c + 1u];
    let m = (t1 - t0) * D;
    let base = idx[vp.inv_start_at + c] - vp.inv_base + (q - t0) * D;
    var s: array<real, 3>;
    for (var u = t0; u < t1; u++) {
        let j = idx[vp.items_at + u];
        let col = base + (u - t0) * D * m;
        for (var e = 0u; e < D; e++) {
            var v = b[j * D + e];
            if (post) {
                v -= ax[j * D + e];
            }
            let o = col + e * m;
            for (var a = 0u; a < D; a++) {
                s[a] += inv[o + a] * v;
            }
        }
    }
    return Item(i, s);
}

// x = ω B⁺ b, over the items of this dispatch's unknowns [t_begin, t_end) (whole clusters).
@compute @workgroup_size(WG)
fn smooth_pre(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (halted()) {
        return;
    }
    let omega = vals[vp.omega_at];
    for (var q = vp.t_begin / D + grid_index(gid, nwg); q < vp.t_end / D; q += grid_stride(nwg)) {
        let r = cluster_rows(q, false);
        for (var a = 0u; a < D; a++) {
            x[r.node * D + a] = r.value[a] * omega;
        }
    }
}

// x += ω B⁺ (b − ax).
@compute @workgroup_size(WG)
fn smooth_post(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (halted()) {
        return;
    }
    let omega = vals[vp.omega_at];
    for (var q = vp.t_begin / D + grid_index(gid, nwg); q < vp.t_end / D; q += grid_stride(nwg)) {
        let r = cluster_rows(q, true);
        for (var a = 0u; a < D; a++) {
            x[r.node * D + a] += omega * r.value[a];
        }
    }
}

// ax = A x for a level below the finest (D×D blocks on the level's pattern), each entry
// summed block by block in column order.
@compute @workgroup_size(WG)
fn level_ax(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (halted()) {
        return;
    }
    for (var i = grid_index(gid, nwg); i < vp.n; i += grid_stride(nwg)) {
        var acc3: array<real, 3>;
        for (var k = idx[vp.row_at + i]; k < idx[vp.row_at + i + 1u]; k++) {
            let j = idx[vp.col_at + k];
            let o = vp.a_at + k * D * D;
            // x_j read once for the block's D rows (each load is a gather on a CPU adapter).
            var xj: array<real, 3>;
            for (var c = 0u; c < D; c++) {
                xj[c] = x[j * D + c];
            }
            for (var r = 0u; r < D; r++) {
                var s = vals[o + r * D] * xj[0];
                for (var c = 1u; c < D; c++) {
                    s += vals[o + r * D + c] * xj[c];
                }
                acc3[r] += s;
            }
        }
        for (var r = 0u; r < D; r++) {
            ax[i * D + r] = acc3[r];
        }
    }
}

// b'_c = Σ_i P_icᵀ (b_i − ax_i) over the blocks of cluster c's column of P, by item.
@compute @workgroup_size(WG)
fn restrict_down(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (halted() || vp.has_next == 0u) {
        return;
    }
    for (var c = grid_index(gid, nwg); c < vp.clusters; c += grid_stride(nwg)) {
        var o3: array<real, 3>;
        for (var t = idx[vp.pt_ptr_at + c]; t < idx[vp.pt_ptr_at + c + 1u]; t++) {
            let i = idx[vp.pt_row_at + t];
            let o = vp.pt_at + t * D * D;
            // The residual at item i, formed once for the block's D rows.
            var ri: array<real, 3>;
            for (var k = 0u; k < D; k++) {
                ri[k] = b[i * D + k] - ax[i * D + k];
            }
            for (var a = 0u; a < D; a++) {
                var s = real(0.0);
                for (var k = 0u; k < D; k++) {
                    s += vals[o + a * D + k] * ri[k];
                }
                o3[a] += s;
            }
        }
        for (var a = 0u; a < D; a++) {
            bn[c * D + a] = o3[a];
        }
    }
}

// x_i += Σ_c P_ic x'_c over row i's blocks of P.
@compute @workgroup_size(WG)
fn prolong_up(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (halted() || vp.has_next == 0u) {
        return;
    }
    for (var i = grid_index(gid, nwg); i < vp.n; i += grid_stride(nwg)) {
        var z3: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            z3[a] = x[i * D + a];
        }
        for (var pk = idx[vp.p_ptr_at + i]; pk < idx[vp.p_ptr_at + i + 1u]; pk++) {
            let c = idx[vp.p_col_at + pk];
            let o = vp.p_at + pk * D * D;
            var xc: array<real, 3>;
            for (var k = 0u; k < D; k++) {
                xc[k] = xn[c * D + k];
            }
            for (var a = 0u; a < D; a++) {
                var s = real(0.0);
                for (var k = 0u; k < D; k++) {
                    s += vals[o + a * D + k] * xc[k];
                }
                z3[a] += s;
            }
        }
        for (var a = 0u; a < D; a++) {
            x[i * D + a] = z3[a];
        }
    }
}
