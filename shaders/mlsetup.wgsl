// The multilevel preconditioner's levels built on the device (src/gpu/pcg/mlsetup.rs):
// the CPU's Multilevel::new and Multilevel::refresh (src/solve/multilevel) from the H the
// device assembled, written where the V-cycle (vcycle.wgsl) reads them. Every operation
// is the CPU's, in the CPU's order (the dense factorisations, the block products, the
// Galerkin sums), so the values match the host's to rounding; only the power estimates'
// dot products are summed in another fixed order (two-pass trees).
//
// One bind group per level l (per values chunk of H and per buffer of inverses where
// there are several): l's index arrays (`idx`, the V-cycle's; `sidx`, the setup's), l's
// values (`vals`: ω, A_l below the finest, P_l, P_lᵀ) and level l + 1's (`nidx`, `nvals`,
// where A_{l+1} goes), the finest matrix (the PCG's `pattern`, a chunk of H in `hvals`,
// the constraint frames), one buffer of l's cluster inverses (`inv`) and the scratch
// `work` (D_i⁻¹, the power iteration's vectors, partial sums and scalars) and Q = A P
// (`qv`).
//
// Level 0's matrix is Ĥ in the node frames, P VᵀHV P + (I − P), each block formed from
// H's where it is read (frame_block): it is never stored. The kernels that read it run
// once per chunk of H, over that chunk's rows.
//
// Per level l below the coarsest (Multilevel::new):
//   item_dinv          D_i⁻¹ of the item blocks of A_l
//   power_* (dinv)     λ̂ of D⁻¹A_l, omega_prolong: ω = 4/(3λ̂)
//   p_values           P_l = (I − ω D⁻¹A_l) T_l, row by row
//   q_values           Q = A_l P_l, row by row
//   galerkin           A_{l+1} = P_lᵀ Q, row by row of A_{l+1}
//   transpose_p        P_lᵀ in the restriction's order
// then per level: cluster_zero, cluster_gather, cluster_factor, cluster_invert,
// cluster_gram (the pseudo-inverses B⁺),
// mask_inverses at level 0 (the constrained rows and columns zero, as the V-cycle wants),
// and below the coarsest power_* (inv) and omega_smooth: ω_l from λ̂ of B_l⁺A_l.
// Kept levels (Multilevel::refresh) run the last step at level 0 only; remasked ones
// first mask_inverses, mask_p and transpose_p at level 0.
//
// Every output is written by one invocation summing in a fixed order: no atomics.

// Mirrors `SetupParams` in src/gpu/pcg/mlsetup.rs (size-asserted there). Offsets are in
// u32 words of idx, sidx, nidx, pattern and in f64 entries of vals, nvals, work.
struct SetupParams {
    // The CPU's constants, bit for bit: OMEGA_MAX, OMEGA_LAMBDA, PIVOT_DROP, and the
    // largest finite f64 (v is finite where |v| ≤ it: false for NaN and ±∞).
    omega_max: f64,
    omega_lambda: f64,
    pivot_drop: f64,
    finite_max: f64,
    // Items and clusters of the level; 1 at level 0 (its matrix is Ĥ, formed from H).
    n: u32,
    clusters: u32,
    finest: u32,
    has_next: u32,
    // idx: as VcycleParams.
    of_at: u32,
    pos_at: u32,
    ptr_at: u32,
    items_at: u32,
    inv_start_at: u32,
    row_at: u32,
    col_at: u32,
    p_ptr_at: u32,
    p_col_at: u32,
    pt_ptr_at: u32,
    pt_row_at: u32,
    // vals: as VcycleParams.
    omega_at: u32,
    a_at: u32,
    p_at: u32,
    pt_at: u32,
    // sidx: Q's row pointers and columns, the P block of each Pᵀ entry, each item's
    // diagonal block below the finest level (NO_BLOCK where there is none).
    q_ptr_at: u32,
    q_col_at: u32,
    pt_blk_at: u32,
    diag_at: u32,
    // nidx: the next level's row pointers and columns; nvals: its matrix.
    next_row_at: u32,
    next_col_at: u32,
    next_a_at: u32,
    // The rows of this dispatch [row_begin, row_end) (level 0: a chunk of H, whose first
    // block is block_first) and, in `pattern`, where the columns and diagonal blocks start.
    row_begin: u32,
    row_end: u32,
    block_first: u32,
    h_col_at: u32,
    h_diag_at: u32,
    // The clusters of the bound inverses [c_begin, c_end), their unknowns in cluster
    // order [t_begin, t_end) and where `inv` starts in the level's inverses.
    c_begin: u32,
    c_end: u32,
    t_begin: u32,
    t_end: u32,
    inv_base: u32,
    // work: D_i⁻¹, the power iteration's x, A x and y, its partials (segments per slot)
    // and scalars.
    dinv_at: u32,
    x_at: u32,
    ax_at: u32,
    y_at: u32,
    part_at: u32,
    scal_at: u32,
    segments: u32,
    // P's blocks; the level's index (where its smoother's λ̂ is kept).
    p_blocks: u32,
    level: u32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

override D: u32 = 3u;

const NO_BLOCK: u32 = 0xffffffffu;
// Scalars in work[scal_at..]: λ̂, a stop flag (the CPU's break), x·Ax, y·Ax, max|y|, ‖y‖,
// the prolongation's ω; from SC_LEVELS on, each level's smoother λ̂ (read back by tests).
const SC_LAM: u32 = 0u;
const SC_STOP: u32 = 1u;
const SC_XAX: u32 = 2u;
const SC_YAX: u32 = 3u;
const SC_MAX: u32 = 4u;
const SC_NRM: u32 = 5u;
const SC_OMEGA_P: u32 = 6u;
const SC_LEVELS: u32 = 8u;

@group(0) @binding(0) var<uniform> sp: SetupParams;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read> sidx: array<u32>;
@group(0) @binding(3) var<storage, read> nidx: array<u32>;
@group(0) @binding(4) var<storage, read_write> vals: array<real>;
@group(0) @binding(5) var<storage, read_write> nvals: array<real>;
// Level 0: the PCG's pattern (row pointers, columns, diagonal blocks), one chunk of H,
// the frames (mask and rotation index per node) and the rotations.
@group(0) @binding(6) var<storage, read> pattern: array<u32>;
@group(0) @binding(7) var<storage, read> hvals: array<real>;
@group(0) @binding(8) var<storage, read> frame: array<u32>;
@group(0) @binding(9) var<storage, read> rotations: array<real>;
@group(0) @binding(10) var<storage, read_write> inv: array<real>;
@group(0) @binding(11) var<storage, read_write> work: array<real>;
// Q = A P on Q's pattern (its own buffer: the largest of the setup's arrays).
@group(0) @binding(12) var<storage, read_write> qv: array<real>;

fn finite(v: real) -> bool {
    return abs(v) <= real(sp.finite_max);
}

fn fixed(i: u32, a: u32) -> bool {
    return ((frame[2u * i] >> a) & 1u) != 0u;
}

// The level matrix's row pointers, columns and diagonal blocks.
fn row_start(i: u32) -> u32 {
    if (sp.finest != 0u) {
        return pattern[i];
    }
    return idx[sp.row_at + i];
}

fn col(k: u32) -> u32 {
    if (sp.finest != 0u) {
        return pattern[sp.h_col_at + k];
    }
    return idx[sp.col_at + k];
}

fn diag_block(i: u32) -> u32 {
    if (sp.finest != 0u) {
        return pattern[sp.h_diag_at + i];
    }
    return sidx[sp.diag_at + i];
}

// Stored block k = (i, j) of the level's matrix, D×D row-major in the first D² entries.
fn a_block(i: u32, k: u32, j: u32) -> array<real, 9> {
    if (sp.finest != 0u) {
        return frame_block(i, k, j);
    }
    var b: array<real, 9>;
    let o = sp.a_at + k * D * D;
    for (var e = 0u; e < D * D; e++) {
        b[e] = vals[o + e];
    }
    return b;
}

// Ĥ_ij for H's block k = (i, j) (in this dispatch's chunk): V_iᵀ H_ij V_j, the constrained
// rows and columns zero and 1 on the constrained diagonal (the CPU's frame_block with
// D = I, the device PCG's constrained diagonal). Sums as rotate_block's.
fn frame_block(i: u32, k: u32, j: u32) -> array<real, 9> {
    let dd = D * D;
    var h: array<real, 9>;
    let o = (k - sp.block_first) * dd;
    for (var e = 0u; e < dd; e++) {
        h[e] = hvals[o + e];
    }
    let ri = frame[2u * i + 1u];
    let rj = frame[2u * j + 1u];
    var t = h;
    if (rj != NO_ROTATION) {
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                var s = h[r * D] * rotations[rj * dd + c];
                for (var m = 1u; m < D; m++) {
                    s += h[r * D + m] * rotations[rj * dd + m * D + c];
                }
                t[r * D + c] = s;
            }
        }
    }
    var out = t;
    if (ri != NO_ROTATION) {
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                var s = rotations[ri * dd + r] * t[c];
                for (var m = 1u; m < D; m++) {
                    s += rotations[ri * dd + m * D + r] * t[m * D + c];
                }
                out[r * D + c] = s;
            }
        }
    }
    let mi = frame[2u * i];
    let mj = frame[2u * j];
    if ((mi | mj) != 0u) {
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                if (((mi >> r) & 1u) != 0u || ((mj >> c) & 1u) != 0u) {
                    out[r * D + c] = real(0.0);
                }
            }
            if (i == j && ((mi >> r) & 1u) != 0u) {
                out[r * D + r] = real(1.0);
            }
        }
    }
    return out;
}

// T_i, the tentative prolongation's block of item i: at level 0 P_i V_iᵀ (row a is column
// a of V_i, zero where a is constrained), deeper the identity.
fn translation(i: u32) -> array<real, 9> {
    var o: array<real, 9>;
    var ri = NO_ROTATION;
    if (sp.finest != 0u) {
        ri = frame[2u * i + 1u];
    }
    for (var a = 0u; a < D; a++) {
        if (sp.finest != 0u && fixed(i, a)) {
            continue;
        }
        for (var b = 0u; b < D; b++) {
            if (ri == NO_ROTATION) {
                o[a * D + b] = select(real(0.0), real(1.0), a == b);
            } else {
                o[a * D + b] = rotations[ri * D * D + b * D + a];
            }
        }
    }
    return o;
}

// a·b for D×D row-major blocks, each entry summed from zero (the CPU's `mul`).
fn mul(a: array<real, 9>, b: array<real, 9>) -> array<real, 9> {
    var o: array<real, 9>;
    for (var r = 0u; r < D; r++) {
        for (var c = 0u; c < D; c++) {
            var s = real(0.0);
            for (var k = 0u; k < D; k++) {
                s += a[r * D + k] * b[k * D + c];
            }
            o[r * D + c] = s;
        }
    }
    return o;
}

// In place: the lower Cholesky factor of a D×D block, pivots at or below PIVOT_DROP times
// the largest diagonal entry dropped with their column (the CPU's cholesky_dropping;
// the upper part is left, no one reads it). Returns the pivots dropped.
fn cholesky_small(a: ptr<function, array<real, 9>>) -> u32 {
    var scale = real(0.0);
    for (var k = 0u; k < D; k++) {
        scale = max(scale, abs((*a)[k * D + k]));
    }
    let lim = real(sp.pivot_drop) * scale;
    var dropped = 0u;
    for (var k = 0u; k < D; k++) {
        var p = (*a)[k * D + k];
        for (var s = 0u; s < k; s++) {
            p -= (*a)[k * D + s] * (*a)[k * D + s];
        }
        if (!(p > lim)) {
            dropped++;
            for (var r = k; r < D; r++) {
                (*a)[r * D + k] = real(0.0);
            }
            continue;
        }
        let l = sqrt(p);
        (*a)[k * D + k] = l;
        for (var r = k + 1u; r < D; r++) {
            var v = (*a)[r * D + k];
            for (var s = 0u; s < k; s++) {
                v -= (*a)[r * D + s] * (*a)[k * D + s];
            }
            (*a)[r * D + k] = v / l;
        }
    }
    return dropped;
}

// (L Lᵀ)⁺ of a factor from cholesky_small (the CPU's inverse_from_factor).
fn inverse_small(l: array<real, 9>) -> array<real, 9> {
    var x: array<real, 9>;
    for (var k = 0u; k < D; k++) {
        let piv = l[k * D + k];
        if (piv == real(0.0)) {
            continue;
        }
        for (var j = 0u; j <= k; j++) {
            var v = select(real(0.0), real(1.0), j == k);
            for (var s = j; s < k; s++) {
                v -= l[k * D + s] * x[s * D + j];
            }
            x[k * D + j] = v / piv;
        }
    }
    var o: array<real, 9>;
    for (var i = 0u; i < D; i++) {
        for (var j = 0u; j <= i; j++) {
            var v = real(0.0);
            for (var k = i; k < D; k++) {
                v += x[k * D + i] * x[k * D + j];
            }
            o[i * D + j] = v;
            o[j * D + i] = v;
        }
    }
    return o;
}

// D_i⁻¹ of each item's diagonal block of the level matrix: the inverse where its
// factorisation keeps every pivot, else the inverse diagonal (1 where an entry is not
// positive), as smoothed_p on the CPU.
@compute @workgroup_size(WG)
fn item_dinv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var i = sp.row_begin + grid_index(gid, nwg); i < sp.row_end; i += grid_stride(nwg)) {
        let k = diag_block(i);
        var b: array<real, 9>;
        if (k != NO_BLOCK) {
            b = a_block(i, k, i);
        }
        var l = b;
        var o: array<real, 9>;
        if (cholesky_small(&l) == 0u) {
            o = inverse_small(l);
        } else {
            for (var a = 0u; a < D; a++) {
                let v = b[a * D + a];
                o[a * D + a] = select(real(1.0), real(1.0) / v, v > real(0.0));
            }
        }
        for (var e = 0u; e < dd; e++) {
            work[sp.dinv_at + i * dd + e] = o[e];
        }
    }
}

// Where column `c` is among the sorted columns b..e of a row (of P in idx, of Q in sidx,
// of the next level's matrix in nidx): present by construction of the patterns, so the
// binary search finds the CPU's slot.
fn p_slot(b: u32, e: u32, c: u32) -> u32 {
    var lo = b;
    var hi = e;
    while (lo + 1u < hi) {
        let mid = (lo + hi) / 2u;
        if (idx[sp.p_col_at + mid] <= c) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

fn q_slot(b: u32, e: u32, c: u32) -> u32 {
    var lo = b;
    var hi = e;
    while (lo + 1u < hi) {
        let mid = (lo + hi) / 2u;
        if (sidx[sp.q_col_at + mid] <= c) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

fn next_slot(b: u32, e: u32, c: u32) -> u32 {
    var lo = b;
    var hi = e;
    while (lo + 1u < hi) {
        let mid = (lo + hi) / 2u;
        if (nidx[sp.next_col_at + mid] <= c) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// P's row i: δ_{c,c(i)} T_i − ω Σ_j D_i⁻¹ (A_ij T_j), the sum by the row's blocks in order
// and T_i added last (the CPU's p_values).
@compute @workgroup_size(WG)
fn p_values(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let omega = work[sp.scal_at + SC_OMEGA_P];
    for (var i = sp.row_begin + grid_index(gid, nwg); i < sp.row_end; i += grid_stride(nwg)) {
        let p0 = idx[sp.p_ptr_at + i];
        let p1 = idx[sp.p_ptr_at + i + 1u];
        for (var e = p0 * dd; e < p1 * dd; e++) {
            vals[sp.p_at + e] = real(0.0);
        }
        var di: array<real, 9>;
        for (var e = 0u; e < dd; e++) {
            di[e] = work[sp.dinv_at + i * dd + e];
        }
        for (var k = row_start(i); k < row_start(i + 1u); k++) {
            let j = col(k);
            let st = mul(di, mul(a_block(i, k, j), translation(j)));
            let o = sp.p_at + p_slot(p0, p1, idx[sp.of_at + j]) * dd;
            for (var e = 0u; e < dd; e++) {
                vals[o + e] = vals[o + e] - omega * st[e];
            }
        }
        let ti = translation(i);
        let o = sp.p_at + p_slot(p0, p1, idx[sp.of_at + i]) * dd;
        for (var e = 0u; e < dd; e++) {
            vals[o + e] = vals[o + e] + ti[e];
        }
    }
}

// Q's row i: Σ_j A_ij P_j, by the row's blocks, each by P_j's blocks (the CPU's order).
@compute @workgroup_size(WG)
fn q_values(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var i = sp.row_begin + grid_index(gid, nwg); i < sp.row_end; i += grid_stride(nwg)) {
        let q0 = sidx[sp.q_ptr_at + i];
        let q1 = sidx[sp.q_ptr_at + i + 1u];
        for (var e = q0 * dd; e < q1 * dd; e++) {
            qv[e] = real(0.0);
        }
        for (var k = row_start(i); k < row_start(i + 1u); k++) {
            let j = col(k);
            let h = a_block(i, k, j);
            for (var pk = idx[sp.p_ptr_at + j]; pk < idx[sp.p_ptr_at + j + 1u]; pk++) {
                var pb: array<real, 9>;
                for (var e = 0u; e < dd; e++) {
                    pb[e] = vals[sp.p_at + pk * dd + e];
                }
                let m = mul(h, pb);
                let o = q_slot(q0, q1, idx[sp.p_col_at + pk]) * dd;
                for (var e = 0u; e < dd; e++) {
                    qv[o + e] = qv[o + e] + m[e];
                }
            }
        }
    }
}

// A_{l+1}'s row c: Σ over cluster c's P blocks by item i, over Q's row i by column, of
// P_icᵀ Q_i· (the CPU's galerkin).
@compute @workgroup_size(WG)
fn galerkin(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var c = grid_index(gid, nwg); c < sp.clusters; c += grid_stride(nwg)) {
        let r0 = nidx[sp.next_row_at + c];
        let r1 = nidx[sp.next_row_at + c + 1u];
        for (var e = r0 * dd; e < r1 * dd; e++) {
            nvals[sp.next_a_at + e] = real(0.0);
        }
        for (var t = idx[sp.pt_ptr_at + c]; t < idx[sp.pt_ptr_at + c + 1u]; t++) {
            let i = idx[sp.pt_row_at + t];
            let pk = sidx[sp.pt_blk_at + t];
            for (var qk = sidx[sp.q_ptr_at + i]; qk < sidx[sp.q_ptr_at + i + 1u]; qk++) {
                let o = sp.next_a_at + next_slot(r0, r1, sidx[sp.q_col_at + qk]) * dd;
                for (var r = 0u; r < D; r++) {
                    for (var cc = 0u; cc < D; cc++) {
                        var s = real(0.0);
                        for (var k = 0u; k < D; k++) {
                            s += vals[sp.p_at + pk * dd + k * D + r] * qv[qk * dd + k * D + cc];
                        }
                        nvals[o + r * D + cc] = nvals[o + r * D + cc] + s;
                    }
                }
            }
        }
    }
}

// Pᵀ's blocks in the restriction's order (cluster by cluster), each P block transposed.
@compute @workgroup_size(WG)
fn transpose_p(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var t = grid_index(gid, nwg); t < sp.p_blocks; t += grid_stride(nwg)) {
        let pk = sidx[sp.pt_blk_at + t];
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                vals[sp.pt_at + t * dd + r * D + c] = vals[sp.p_at + pk * dd + c * D + r];
            }
        }
    }
}

// Level 0 after a constraint set grew: the constrained rows of P zero (the CPU's
// mask_new; rows constrained at the build are zero already).
@compute @workgroup_size(WG)
fn mask_p(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var i = grid_index(gid, nwg); i < sp.n; i += grid_stride(nwg)) {
        for (var a = 0u; a < D; a++) {
            if (!fixed(i, a)) {
                continue;
            }
            for (var pk = idx[sp.p_ptr_at + i]; pk < idx[sp.p_ptr_at + i + 1u]; pk++) {
                for (var c = 0u; c < D; c++) {
                    vals[sp.p_at + pk * dd + a * D + c] = real(0.0);
                }
            }
        }
    }
}

// The bound inverses' values zero (before the gathers fill the cluster blocks).
@compute @workgroup_size(WG)
fn cluster_zero(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let len = idx[sp.inv_start_at + sp.c_end] - sp.inv_base;
    for (var e = grid_index(gid, nwg); e < len; e += grid_stride(nwg)) {
        inv[e] = real(0.0);
    }
}

// Cluster c's dense block of the level matrix (m×m, row-major, in its inverse's place):
// the blocks of its items' rows (in this dispatch's rows) whose column is in c.
@compute @workgroup_size(WG)
fn cluster_gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var c = sp.c_begin + grid_index(gid, nwg); c < sp.c_end; c += grid_stride(nwg)) {
        let u0 = idx[sp.ptr_at + c];
        let u1 = idx[sp.ptr_at + c + 1u];
        let m = (u1 - u0) * D;
        let base = idx[sp.inv_start_at + c] - sp.inv_base;
        for (var u = u0; u < u1; u++) {
            let i = idx[sp.items_at + u];
            if (i < sp.row_begin || i >= sp.row_end) {
                continue;
            }
            let p = u - u0;
            for (var k = row_start(i); k < row_start(i + 1u); k++) {
                let j = col(k);
                if (idx[sp.of_at + j] != c) {
                    continue;
                }
                let q = idx[sp.pos_at + j];
                let b = a_block(i, k, j);
                for (var r = 0u; r < D; r++) {
                    for (var s = 0u; s < D; s++) {
                        inv[base + (p * D + r) * m + q * D + s] = b[r * D + s];
                    }
                }
            }
        }
    }
}

// In place at `base`: the Cholesky factor of the m×m block with pivots dropped (the CPU's
// cholesky_dropping, the upper part left: nothing reads it).
fn factor_in_place(base: u32, m: u32) {
    var scale = real(0.0);
    for (var k = 0u; k < m; k++) {
        scale = max(scale, abs(inv[base + k * m + k]));
    }
    let lim = real(sp.pivot_drop) * scale;
    for (var k = 0u; k < m; k++) {
        var p = inv[base + k * m + k];
        for (var s = 0u; s < k; s++) {
            p -= inv[base + k * m + s] * inv[base + k * m + s];
        }
        if (!(p > lim)) {
            for (var r = k; r < m; r++) {
                inv[base + r * m + k] = real(0.0);
            }
            continue;
        }
        let l = sqrt(p);
        inv[base + k * m + k] = l;
        for (var r = k + 1u; r < m; r++) {
            var v = inv[base + r * m + k];
            for (var s = 0u; s < k; s++) {
                v -= inv[base + r * m + s] * inv[base + k * m + s];
            }
            inv[base + r * m + k] = v / l;
        }
    }
}

// In place: X = L⁺ over the factor's lower triangle, row by row, each row by ascending
// column. Entry (k, j) reads L's row k at columns j..k−1, none of them overwritten yet,
// and X's rows above: the CPU's inverse_from_factor into the same storage (a dropped
// pivot's row is zero).
fn invert_factor_in_place(base: u32, m: u32) {
    for (var k = 0u; k < m; k++) {
        let piv = inv[base + k * m + k];
        if (piv == real(0.0)) {
            for (var j = 0u; j < k; j++) {
                inv[base + k * m + j] = real(0.0);
            }
            continue;
        }
        for (var j = 0u; j <= k; j++) {
            var v = select(real(0.0), real(1.0), j == k);
            for (var s = j; s < k; s++) {
                v -= inv[base + k * m + s] * inv[base + s * m + j];
            }
            inv[base + k * m + j] = v / piv;
        }
    }
}

// In place: XᵀX from X in the lower triangle, symmetric. Entry (i, j ≤ i) reads X's rows
// i.. at columns i and j; it overwrites X(i, j), which no later entry reads (later rows
// read rows below i, later entries of row i read X(i, i) and X(i, j' > j)), and the upper
// (j, i), which X does not use.
fn gram_in_place(base: u32, m: u32) {
    for (var i = 0u; i < m; i++) {
        for (var j = 0u; j <= i; j++) {
            var v = real(0.0);
            for (var k = i; k < m; k++) {
                v += inv[base + k * m + i] * inv[base + k * m + j];
            }
            inv[base + i * m + j] = v;
            inv[base + j * m + i] = v;
        }
    }
}

// Each cluster's (L Lᵀ)⁺ in place of its gathered block, one invocation per cluster, in
// three dispatches: the factor, X = L⁺, XᵀX. Why three: in one kernel, lavapipe (LLVM 15)
// read stale X in the last step for the clusters of full SIMD groups; a dispatch
// boundary orders the steps on any device.
@compute @workgroup_size(WG)
fn cluster_factor(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var c = sp.c_begin + grid_index(gid, nwg); c < sp.c_end; c += grid_stride(nwg)) {
        let m = (idx[sp.ptr_at + c + 1u] - idx[sp.ptr_at + c]) * D;
        factor_in_place(idx[sp.inv_start_at + c] - sp.inv_base, m);
    }
}

@compute @workgroup_size(WG)
fn cluster_invert(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var c = sp.c_begin + grid_index(gid, nwg); c < sp.c_end; c += grid_stride(nwg)) {
        let m = (idx[sp.ptr_at + c + 1u] - idx[sp.ptr_at + c]) * D;
        invert_factor_in_place(idx[sp.inv_start_at + c] - sp.inv_base, m);
    }
}

@compute @workgroup_size(WG)
fn cluster_gram(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var c = sp.c_begin + grid_index(gid, nwg); c < sp.c_end; c += grid_stride(nwg)) {
        let m = (idx[sp.ptr_at + c + 1u] - idx[sp.ptr_at + c]) * D;
        gram_in_place(idx[sp.inv_start_at + c] - sp.inv_base, m);
    }
}

// Level 0: the constrained rows and columns of the cluster inverses zero (the V-cycle's
// z stays zero there, as the CPU's does with r zero there).
@compute @workgroup_size(WG)
fn mask_inverses(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var c = sp.c_begin + grid_index(gid, nwg); c < sp.c_end; c += grid_stride(nwg)) {
        let u0 = idx[sp.ptr_at + c];
        let m = (idx[sp.ptr_at + c + 1u] - u0) * D;
        let base = idx[sp.inv_start_at + c] - sp.inv_base;
        for (var u = u0; u < idx[sp.ptr_at + c + 1u]; u++) {
            let i = idx[sp.items_at + u];
            for (var a = 0u; a < D; a++) {
                if (!fixed(i, a)) {
                    continue;
                }
                let row = (u - u0) * D + a;
                for (var k = 0u; k < m; k++) {
                    inv[base + row * m + k] = real(0.0);
                    inv[base + k * m + row] = real(0.0);
                }
            }
        }
    }
}

// The power iteration's start (the CPU's power_estimate: every entry non-zero, the same
// on every run; (7919 k) mod 13 = (2 k) mod 13 without overflow) and its scalars.
@compute @workgroup_size(WG)
fn power_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let len = sp.n * D;
    let first = grid_index(gid, nwg);
    for (var k = first; k < len; k += grid_stride(nwg)) {
        work[sp.x_at + k] = real(1.0) + real(((k % 13u) * 2u) % 13u) / real(13.0);
    }
    if (first == 0u) {
        work[sp.scal_at + SC_LAM] = real(0.0);
        work[sp.scal_at + SC_STOP] = real(0.0);
    }
}

// ax = A x for this dispatch's rows (the CPU's block_matvec: per block, each entry summed
// over the block's columns, then added to the row's sum).
@compute @workgroup_size(WG)
fn power_matvec(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = sp.row_begin + grid_index(gid, nwg); i < sp.row_end; i += grid_stride(nwg)) {
        var acc3: array<real, 3>;
        for (var k = row_start(i); k < row_start(i + 1u); k++) {
            let j = col(k);
            let b = a_block(i, k, j);
            for (var r = 0u; r < D; r++) {
                var s = b[r * D] * work[sp.x_at + j * D];
                for (var c = 1u; c < D; c++) {
                    s += b[r * D + c] * work[sp.x_at + j * D + c];
                }
                acc3[r] += s;
            }
        }
        for (var r = 0u; r < D; r++) {
            work[sp.ax_at + i * D + r] = acc3[r];
        }
    }
}

// y = D⁻¹ ax, item by item.
@compute @workgroup_size(WG)
fn power_dinv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var i = grid_index(gid, nwg); i < sp.n; i += grid_stride(nwg)) {
        for (var r = 0u; r < D; r++) {
            var s = work[sp.dinv_at + i * dd + r * D] * work[sp.ax_at + i * D];
            for (var c = 1u; c < D; c++) {
                s += work[sp.dinv_at + i * dd + r * D + c] * work[sp.ax_at + i * D + c];
            }
            work[sp.y_at + i * D + r] = s;
        }
    }
}

// y = B⁺ ax at the unknowns of the bound inverses, in cluster order (the CPU's
// solve_level: each entry summed over the cluster's items in order). At level 0 a
// constrained component's inverse row is zero on the device; the CPU's is 1 on the
// diagonal (D = I) and zero elsewhere, so y = ax there.
@compute @workgroup_size(WG)
fn power_inv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var t = sp.t_begin + grid_index(gid, nwg); t < sp.t_end; t += grid_stride(nwg)) {
        let q = t / D;
        let a = t % D;
        let i = idx[sp.items_at + q];
        if (sp.finest != 0u && fixed(i, a)) {
            work[sp.y_at + i * D + a] = work[sp.ax_at + i * D + a];
            continue;
        }
        let c = idx[sp.of_at + i];
        let t0 = idx[sp.ptr_at + c];
        let t1 = idx[sp.ptr_at + c + 1u];
        let m = (t1 - t0) * D;
        let base = idx[sp.inv_start_at + c] - sp.inv_base + (q - t0) * D + a;
        var s = real(0.0);
        for (var u = t0; u < t1; u++) {
            let j = idx[sp.items_at + u];
            let colu = (u - t0) * D;
            for (var e = 0u; e < D; e++) {
                s += inv[base + (colu + e) * m] * work[sp.ax_at + j * D + e];
            }
        }
        work[sp.y_at + i * D + a] = s;
    }
}

// One workgroup's tree over (sum, sum, max) per invocation, in a fixed order; returns
// the workgroup's result (uniform).
fn tree3(lid: u32, v: vec3<acc>) -> vec3<acc> {
    wg_sum[lid] = vec4<acc>(v, acc(0.0));
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            let o = wg_sum[lid + h];
            let w = wg_sum[lid];
            wg_sum[lid] = vec4<acc>(w.x + o.x, w.y + o.y, max(w.z, o.z), acc(0.0));
        }
        workgroupBarrier();
    }
    return workgroupUniformLoad(&wg_sum[0]).xyz;
}

fn partial(slot: u32, s: u32) -> u32 {
    return sp.part_at + slot * sp.segments + s;
}

// Per segment of WG items: Σ x·ax, Σ y·ax and max |y| (partials 0, 1, 2).
@compute @workgroup_size(WG)
fn power_sums(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var s = group_index(wid, nwg); s < sp.segments; s += group_count(nwg)) {
        let i = s * WG + lid.x;
        var v = vec3<acc>(acc(0.0));
        if (i < sp.n) {
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                v.x += acc(work[sp.x_at + k]) * acc(work[sp.ax_at + k]);
                v.y += acc(work[sp.y_at + k]) * acc(work[sp.ax_at + k]);
                v.z = max(v.z, acc(abs(work[sp.y_at + k])));
            }
        }
        let w = tree3(lid.x, v);
        if (lid.x == 0u) {
            work[partial(0u, s)] = real(w.x);
            work[partial(1u, s)] = real(w.y);
            work[partial(2u, s)] = real(w.z);
        }
        workgroupBarrier();
    }
}

// One workgroup: x·Ax, y·Ax and s = max |y| from the partials.
@compute @workgroup_size(WG)
fn power_reduce(@builtin(local_invocation_id) lid: vec3<u32>) {
    var v = vec3<acc>(acc(0.0));
    for (var t = lid.x; t < sp.segments; t += WG) {
        v.x += acc(work[partial(0u, t)]);
        v.y += acc(work[partial(1u, t)]);
        v.z = max(v.z, acc(work[partial(2u, t)]));
    }
    let w = tree3(lid.x, v);
    if (lid.x == 0u) {
        work[sp.scal_at + SC_XAX] = real(w.x);
        work[sp.scal_at + SC_YAX] = real(w.y);
        work[sp.scal_at + SC_MAX] = real(w.z);
    }
}

// Per segment: Σ (y/s)² (partial 3), the scaled norm's sum (the CPU's norm2).
@compute @workgroup_size(WG)
fn power_scaled(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let sc = work[sp.scal_at + SC_MAX];
    for (var s = group_index(wid, nwg); s < sp.segments; s += group_count(nwg)) {
        let i = s * WG + lid.x;
        var v = vec3<acc>(acc(0.0));
        if (i < sp.n && sc > real(0.0) && finite(sc)) {
            for (var a = 0u; a < D; a++) {
                let q = work[sp.y_at + i * D + a] / sc;
                v.x += acc(q * q);
            }
        }
        let w = tree3(lid.x, v);
        if (lid.x == 0u) {
            work[partial(3u, s)] = real(w.x);
        }
        workgroupBarrier();
    }
}

// One workgroup: ‖y‖ = s √Σ(y/s)², then the CPU's step: stop where x·Ax or ‖y‖ is not
// positive or ‖y‖ not finite (λ̂ stays), else λ̂ = y·Ax / x·Ax.
@compute @workgroup_size(WG)
fn power_step(@builtin(local_invocation_id) lid: vec3<u32>) {
    var v = vec3<acc>(acc(0.0));
    for (var t = lid.x; t < sp.segments; t += WG) {
        v.x += acc(work[partial(3u, t)]);
    }
    let w = tree3(lid.x, v);
    if (lid.x != 0u || work[sp.scal_at + SC_STOP] != real(0.0)) {
        return;
    }
    let sc = work[sp.scal_at + SC_MAX];
    var nrm = sc;
    if (sc > real(0.0) && finite(sc)) {
        nrm = sc * sqrt(real(w.x));
    }
    let xax = work[sp.scal_at + SC_XAX];
    if (!(xax > real(0.0)) || !(nrm > real(0.0)) || !finite(nrm)) {
        work[sp.scal_at + SC_STOP] = real(1.0);
        return;
    }
    work[sp.scal_at + SC_LAM] = work[sp.scal_at + SC_YAX] / xax;
    work[sp.scal_at + SC_NRM] = nrm;
}

// x = y / ‖y‖ (unless the iteration stopped).
@compute @workgroup_size(WG)
fn power_next(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (work[sp.scal_at + SC_STOP] != real(0.0)) {
        return;
    }
    let nrm = work[sp.scal_at + SC_NRM];
    for (var k = grid_index(gid, nwg); k < sp.n * D; k += grid_stride(nwg)) {
        work[sp.x_at + k] = work[sp.y_at + k] / nrm;
    }
}

fn lambda_usable() -> bool {
    let lam = work[sp.scal_at + SC_LAM];
    return lam > real(0.0) && finite(lam);
}

// The prolongation's ω = 4 / (3 λ̂) of D⁻¹A (0 without a usable λ̂), as smoothed_p.
@compute @workgroup_size(1)
fn omega_prolong() {
    var omega = real(0.0);
    if (lambda_usable()) {
        omega = real(4.0) / (real(3.0) * work[sp.scal_at + SC_LAM]);
    }
    work[sp.scal_at + SC_OMEGA_P] = omega;
}

// The smoother's ω = min(OMEGA_MAX, OMEGA_LAMBDA / λ̂) of B⁺A (OMEGA_MAX without a usable
// λ̂), as Multilevel::omega_of, where the V-cycle reads it.
@compute @workgroup_size(1)
fn omega_smooth() {
    work[sp.scal_at + SC_LEVELS + sp.level] = work[sp.scal_at + SC_LAM];
    var omega = real(sp.omega_max);
    if (lambda_usable()) {
        omega = min(real(sp.omega_max), real(sp.omega_lambda) / work[sp.scal_at + SC_LAM]);
    }
    vals[sp.omega_at] = omega;
}
