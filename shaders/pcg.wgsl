// The eliminated PCG on the device-assembled Newton system (src/gpu/pcg/mod.rs):
//
//   Ĥ y = b̂,  Ĥ = P VᵀHV P + (I − P),  b̂ = −P Vᵀ g,  Δx = V P y
//
// H is read where the assembly left it (assemble.wgsl: block CSR, both triangles,
// row-major D×D blocks), never copied; V_i is applied only at rotated nodes.
//
// Per CG iteration the host records five dispatches:
//   matvec       q = Ĥp, p·q partials (one invocation per block row)
//   scalar_alpha one workgroup: p·q, α = ρ / p·q, curvature check
//   update_yr    y += αp, r −= αq, z = M⁻¹r, r·z and r·r partials
//   scalar_beta  one workgroup: ρ' = r·z, r·r, stop flags, β = ρ'/ρ, iteration count
//   update_p     p = z + βp
// and with the aggregates (COARSE = 2) agg_restrict and agg_solve before scalar_beta;
// with the multilevel preconditioner (PRECOND = 3) the V-cycle (vcycle.wgsl, world_z and
// matvec for its level-0 products) and ml_dot between update_yr and scalar_beta.
// A (re)start is `init` (r = b̂ − q with q = Ĥy, z = M⁻¹r, p = z, partials) and
// `scalar_start` (then `update_p` with β = 0 under COARSE), whose r·r is the true residual.
// A resumed segment (src/gpu/pcg/cg/segment.rs) keeps p through init, and its update_p
// forms p = z (+ Zc) + βp with the β of scalar_start.
// `prepare` adds `coarse_e` and `coarse_e_sum` (E = ZᵀĤZ of the translations, below) and,
// with the aggregates, `agg_rows` and `agg_e` to `rhs` and `precond`.
// Once a stop flag is set, every later CG dispatch of the submit is a no-op.
//
// Reductions are segmented (src/gpu/launch.rs, SegmentPolicy): the nodes are cut into
// segments of SEG = WG·ITEMS consecutive nodes (n_partials of them); invocation lid of
// the workgroup that takes segment s sums nodes s·SEG + lid + m·WG, m = 0, 1, …, in that
// order, and one tree per segment writes partial s; the one-workgroup scalar kernels sum
// the partials in a fixed order. Workgroups loop over segments, so how many run (one per
// segment on a GPU, a few on a CPU adapter) changes nothing in the sums, bit for bit.
//
// H's values come in chunks of consecutive block rows, one buffer each (one storage
// binding caps its size). The kernels that read them (matvec, precond, coarse_e) run once
// per chunk, each over its rows with `hvals` that chunk's buffer. A segment cut by a
// chunk's end carries each invocation's running sum to the next chunk's dispatch (the
// CARRY slots of `partials`), which goes on from it; only the dispatch holding the
// segment's last node sums the tree: the same additions in the same order, so the
// results are those of one chunk, bit for bit.

override D: u32 = 3u;
// 0: none, 1: Jacobi, 2: block Jacobi (the preconditioner applied by init and update_yr),
// 3: multilevel (vcycle.wgsl applies it between update_yr and ml_dot, or init and
// ml_start: init and update_yr then leave z alone and their r·z partials zero, and
// ml_dot or ml_start writes them; only with COARSE = 0).
override PRECOND: u32 = 1u;
// The coarse correction (src/solve/coarse.rs, docs/coarse.md): 0 none, 1 the rigid
// translations, 2 the translations of each aggregate. M⁻¹r = M_J⁻¹r + Z E⁺ Zᵀr with
// Z_i = P_i V_iᵀ from the frames (no basis stored). Why: a body that can translate or
// slide has Ĥ's smallest eigenvalues on its translations (the mass term), and a soft
// body's on its smooth modes, which M_J cannot see.
// 1: E⁺ (D×D, from the host) is in `scal`; update_yr and init sum Zᵀr in the tree of
// r·M_J⁻¹r and r·r; scalar_beta and scalar_start form c = E⁺Zᵀr and ρ = r·M_J⁻¹r + Zᵀr·c;
// update_p adds Z_i c to p. No dispatch in the iteration.
// 2: E⁺ (K×K, K = D·aggregates, formed by coarse_factor.wgsl in `prepare`, or by the host
// where that fails) is in `coarse`; after update_yr (init)
// agg_restrict forms w = Zᵀr (a workgroup per aggregate) and agg_solve c = E⁺w (a
// workgroup per coarse row); scalar_beta (scalar_start) adds w·c to ρ and update_p adds
// Z_i c_{aggregate of i} to p. Two dispatches per iteration.
override COARSE: u32 = 0u;
// Nodes per invocation within a segment (the device's SegmentPolicy).
override ITEMS: u32 = 1u;
// Lanczos coefficients recorded (0: none): scalar_beta of iteration j < HIST (counted from
// the solve's start, restarts included) writes α_j at SCAL_HIST + 2j and, when CG goes on,
// β_{j+1} at SCAL_HIST + 2j + 1; the host cuts the sequence at restarts and estimates
// κ(M⁻¹Ĥ) from each run (src/solve/cg.rs, lanczos_condition).
override HIST: u32 = 0u;
// The difference form of the product (f32 values only, src/gpu/pcg/mod.rs):
//   (H pw)_i = Σ_j H_ij (pw_j − pw_i) + S_i pw_i,   S_i = Σ_j H_ij (`rowsum`, summed in
// f64 on the host), each row summed in `acc`. Equal to Σ_j H_ij pw_j in exact arithmetic.
// Why: rounding H's blocks to f32 breaks H·(translation) = 0 by ε_f32‖H‖, which moves the
// small eigenvalue of a nearly free body (its mass) by κ·ε_f32; in this form a
// translation t still maps to S t, and a smooth mode's terms, of size ‖H‖|pw_j − pw_i|,
// cancel to its small eigenvalue without each being rounded to f32 (the products of two
// f32 are exact in f64). Taken in the world frame, it holds at rotated nodes too.
override DIFF: bool = false;

// Mirrors `PcgParams` in src/gpu/pcg/mod.rs (four u32, 16 bytes, size-asserted
// there).
struct PcgParams {
    n_nodes: u32,
    // Partials per reduction (the workgroups of the grid-stride kernels).
    n_partials: u32,
    // Where the column indices and the diagonal block indices start in `pattern` (the
    // n + 1 row pointers start at 0).
    col_at: u32,
    diag_at: u32,
    // The values chunk bound as `hvals`: its rows, its first (global) block and its index.
    row_begin: u32,
    row_end: u32,
    block_first: u32,
    chunk: u32,
}

// Slots of `scal`, `state` and the partial sums: the one table of both device CGs
// (`gpu::kernels::slots`, declared by the prelude). This CG uses, in scal: ρ = r·z
// (scalar_start, scalar_beta), p·q and α (scalar_alpha), β (scalar_beta), r·r of the last
// reduction, tol² (host), ‖b̂‖² (scalar_start), ρ_prev and the direction scale of a
// resumed segment (host; scalar_start); then (COARSE) c = E⁺Zᵀr, D values
// (scalar_beta, scalar_start), E⁺, D² row-major (host), and E = ZᵀĤZ unsymmetrized, D²
// row-major, then per world axis a 2^-64 · Σ|entries| of the rows of component a of
// ZᵀĤ's blocks, D values (coarse_e_sum, read back by the host, which asks whether a
// translation is pinned by nothing). Partial sums, each n_partials long: p·q, r·z, r·r,
// D slots of Zᵀr (COARSE), ‖b̂‖², D² of E then D of its rows' absolute sums (coarse_e).
// The header of `aggregates` (src/gpu/pcg/aggregates.rs): the aggregate count, K,
// then where each index array starts in `aggregates` (u32 words) and each f64 array in
// `coarse`: the aggregate of each node, the aggregates' node lists (offsets, nodes), per
// block row the range of its row-pair slots, per block its slot, per aggregate pair its
// slots (offsets, slots in row order), the pair of each (a, b) (dense, count²), then E,
// E⁺, w = Zᵀr and c = E⁺w in `coarse` (whose first entries are the slots' D² sums).
const AGG_COUNT: u32 = 0u;
const AGG_K: u32 = 1u;
const AGG_OF: u32 = 2u;
const AGG_PTR: u32 = 3u;
const AGG_NODES: u32 = 4u;
const AGG_SLOT_PTR: u32 = 5u;
const AGG_SLOT_OF: u32 = 6u;
const AGG_PAIR_PTR: u32 = 7u;
const AGG_PAIR_SLOTS: u32 = 8u;
const AGG_PAIR_OF: u32 = 9u;
const AGG_E: u32 = 10u;
const AGG_EINV: u32 = 11u;
const AGG_W: u32 = 12u;
const AGG_C: u32 = 13u;
// After the partial-sum slots (PART_CARRY · n_partials): per boundary between H's chunks
// (the segment that straddles it) and per invocation, CARRY_LEN running sums carried
// between the dispatches of H's chunks.
// 2^-64: the scale of the absolute row sums (src/solve/coarse.rs, ABS_SUM_SCALE).
const ABS_SUM_SCALE = 0x1p-64;

@group(0) @binding(0) var<uniform> params: PcgParams;
// Row pointers, column indices and per node its diagonal block (see PcgParams).
@group(0) @binding(1) var<storage, read> pattern: array<u32>;
// The assembly's blocks and gradient.
// (hvals: the values chunk of this dispatch, block block_first at 0.)
@group(0) @binding(2) var<storage, read> hvals: array<real>;
@group(0) @binding(3) var<storage, read> grad: array<real>;
// Per node: its constraint mask (bit a: component a of the frame is constrained) and its
// index into `rotations` or NO_ROTATION.
@group(0) @binding(4) var<storage, read> frame: array<u32>;
// D×D per rotated node, row-major V_i (its columns are the frame basis).
@group(0) @binding(5) var<storage, read> rotations: array<real>;
@group(0) @binding(6) var<storage, read_write> y: array<real>;
@group(0) @binding(7) var<storage, read_write> r: array<real>;
@group(0) @binding(8) var<storage, read_write> z: array<real>;
@group(0) @binding(9) var<storage, read_write> p: array<real>;
@group(0) @binding(10) var<storage, read_write> q: array<real>;
@group(0) @binding(11) var<storage, read_write> b: array<real>;
// The inverse diagonal blocks of Ĥ (n·D², block Jacobi), then 1/diag(Ĥ) (n·D, Jacobi).
@group(0) @binding(12) var<storage, read_write> minv: array<real>;
@group(0) @binding(13) var<storage, read_write> dx: array<real>;
@group(0) @binding(14) var<storage, read_write> partials: array<acc>;
@group(0) @binding(15) var<storage, read_write> scal: array<acc>;
@group(0) @binding(16) var<storage, read_write> state: array<u32>;
// The aggregate coarse space (COARSE = 2): its index arrays after the header above, and
// its f64 data (a 16-byte placeholder each for frames built without it).
@group(0) @binding(17) var<storage, read> aggregates: array<u32>;
@group(0) @binding(18) var<storage, read_write> coarse: array<acc>;
// p in the world frame, V P p: what matvec multiplies H's blocks by (written with p, so
// each node is rotated once per iteration, not once per block that reads it).
@group(0) @binding(19) var<storage, read_write> pw: array<real>;
// The difference form's S_i (D² per node, row-major; a placeholder without DIFF).
@group(0) @binding(20) var<storage, read> rowsum: array<real>;

var<workgroup> wg_flag: u32;

// The stop flag as a workgroup-uniform value (later barriers may depend on it).
fn stopped(lid: u32) -> bool {
    if (lid == 0u) {
        wg_flag = state[STATE_DONE];
    }
    return workgroupUniformLoad(&wg_flag) != 0u;
}

fn fixed(i: u32, a: u32) -> bool {
    return ((frame[2u * i] >> a) & 1u) != 0u;
}

// The constrained components of a mask word, as vectors (select's condition).
fn mask_bits3(m: u32) -> vec3<bool> {
    return ((vec3<u32>(m) >> vec3<u32>(0u, 1u, 2u)) & vec3<u32>(1u)) != vec3<u32>(0u);
}
fn mask_bits2(m: u32) -> vec2<bool> {
    return ((vec2<u32>(m) >> vec2<u32>(0u, 1u)) & vec2<u32>(1u)) != vec2<u32>(0u);
}

fn rot_of(i: u32) -> u32 {
    return frame[2u * i + 1u];
}

// V_i v: frame to world.
fn from_frame(i: u32, v: array<real, 3>) -> array<real, 3> {
    let ri = rot_of(i);
    if (ri == NO_ROTATION) {
        return v;
    }
    var o: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        var s = real(0.0);
        for (var c = 0u; c < D; c++) {
            s += rotations[ri * D * D + a * D + c] * v[c];
        }
        o[a] = s;
    }
    return o;
}

// V_iᵀ v: world to frame.
fn to_frame(i: u32, v: array<real, 3>) -> array<real, 3> {
    let ri = rot_of(i);
    if (ri == NO_ROTATION) {
        return v;
    }
    var o: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        var s = real(0.0);
        for (var c = 0u; c < D; c++) {
            s += rotations[ri * D * D + c * D + a] * v[c];
        }
        o[a] = s;
    }
    return o;
}

// z_i = M_i⁻¹ r_i.
fn apply_precond(i: u32, rv: array<real, 3>) -> array<real, 3> {
    var o = rv;
    if (PRECOND == 1u) {
        let base = params.n_nodes * D * D + i * D;
        for (var a = 0u; a < D; a++) {
            o[a] = minv[base + a] * rv[a];
        }
    } else if (PRECOND == 2u) {
        let base = i * D * D;
        for (var a = 0u; a < D; a++) {
            var s = real(0.0);
            for (var c = 0u; c < D; c++) {
                s += minv[base + a * D + c] * rv[c];
            }
            o[a] = s;
        }
    }
    return o;
}

// Z_iᵀ r_i = V_i P_i r_i: node i's share of Zᵀr.
fn zt(i: u32, rv: array<real, 3>) -> array<real, 3> {
    var w: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        w[a] = select(rv[a], real(0.0), fixed(i, a));
    }
    return from_frame(i, w);
}

// Z_i c = P_i V_iᵀ c.
fn zc(i: u32, c: array<real, 3>) -> array<real, 3> {
    var w = to_frame(i, c);
    for (var a = 0u; a < D; a++) {
        w[a] = select(w[a], real(0.0), fixed(i, a));
    }
    return w;
}

// c = E⁺ Zᵀr into scal (lane 0 of a one-workgroup kernel); returns Zᵀr·c, the coarse
// share of ρ = r·M⁻¹r.
fn coarse_c(zr: array<acc, 3>) -> acc {
    var wc = acc(0.0);
    for (var a = 0u; a < D; a++) {
        var s = acc(0.0);
        for (var b = 0u; b < D; b++) {
            s += scal[SCAL_EINV + a * D + b] * zr[b];
        }
        scal[SCAL_C + a] = s;
        wc += zr[a] * s;
    }
    return wc;
}

// Index of carried sum m of invocation lid across the boundary after chunk c (see
// PART_CARRY): a segment begun in an earlier chunk reads the boundary before this chunk,
// one going on to a later chunk writes the boundary after it (a segment across several
// chunks passes its sums on at each).
fn carry(c: u32, lid: u32, m: u32) -> u32 {
    return PART_CARRY * params.n_partials + (c * WG + lid) * CARRY_LEN + m;
}

// The segments a chunk's dispatch takes: those holding a row of [row_begin, row_end).
fn chunk_segments() -> vec2<u32> {
    let seg = WG * ITEMS;
    return vec2<u32>(params.row_begin / seg, (params.row_end + seg - 1u) / seg);
}

// Whether segment s began in an earlier chunk (its invocations go on from their carried
// sums) and whether it ends in a later one (they carry them on).
fn segment_begun(s: u32) -> bool {
    return s * WG * ITEMS < params.row_begin;
}
fn segment_goes_on(s: u32) -> bool {
    return min((s + 1u) * WG * ITEMS, params.n_nodes) > params.row_end;
}

// Sum of partial slot `slot`, in a fixed order, in one workgroup.
fn reduce_slot(slot: u32, lid: u32) -> acc {
    var s = acc(0.0);
    for (var t = lid; t < params.n_partials; t += WG) {
        s += partials[slot * params.n_partials + t];
    }
    return workgroup_sum_uniform1(lid, s);
}

// b̂ = −P Vᵀ g into b, or (`form` false) b as the host wrote it, with the ‖b̂‖² partials.
fn rhs_partials(lid: u32, wid: vec3<u32>, nwg: vec3<u32>, form: bool) {
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var bb = acc(0.0);
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid;
            if (i >= params.n_nodes) {
                break;
            }
            if (form) {
                var g: array<real, 3>;
                for (var a = 0u; a < D; a++) {
                    g[a] = grad[i * D + a];
                }
                let t = to_frame(i, g);
                for (var a = 0u; a < D; a++) {
                    b[i * D + a] = select(-t[a], real(0.0), fixed(i, a));
                }
            }
            for (var a = 0u; a < D; a++) {
                let v = b[i * D + a];
                bb += acc(v) * acc(v);
            }
        }
        workgroup_sum(lid, sum1(bb), 1u);
        if (lid == 0u) {
            partials[PART_BB * params.n_partials + s] = summed(0u);
        }
        // The tree's memory is reused by the next segment.
        workgroupBarrier();
    }
}

@compute @workgroup_size(WG)
fn rhs(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    rhs_partials(lid.x, wid, nwg, true);
}

@compute @workgroup_size(WG)
fn rhs_given(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    rhs_partials(lid.x, wid, nwg, false);
}

// The preconditioners from the diagonal blocks of Ĥ: B = P V_iᵀ H_ii V_i P + (I − P).
// Jacobi and block Jacobi by the one specification (common.wgsl, block_jacobi_inverse).
@compute @workgroup_size(WG)
fn precond(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var i = params.row_begin + grid_index(gid, nwg); i < params.row_end; i += grid_stride(nwg)) {
        let k = pattern[params.diag_at + i] - params.block_first;
        var h: array<real, 9>;
        for (var t = 0u; t < dd; t++) {
            h[t] = hvals[k * dd + t];
        }
        let ri = rot_of(i);
        if (ri != NO_ROTATION) {
            // h := V_iᵀ h V_i.
            var t1: array<real, 9>;
            for (var a = 0u; a < D; a++) {
                for (var c = 0u; c < D; c++) {
                    var s = real(0.0);
                    for (var m = 0u; m < D; m++) {
                        s += h[a * D + m] * rotations[ri * dd + m * D + c];
                    }
                    t1[a * D + c] = s;
                }
            }
            for (var a = 0u; a < D; a++) {
                for (var c = 0u; c < D; c++) {
                    var s = real(0.0);
                    for (var m = 0u; m < D; m++) {
                        s += rotations[ri * dd + m * D + a] * t1[m * D + c];
                    }
                    h[a * D + c] = s;
                }
            }
        }
        for (var a = 0u; a < D; a++) {
            for (var c = 0u; c < D; c++) {
                if (fixed(i, a) || fixed(i, c)) {
                    h[a * D + c] = select(real(0.0), real(1.0), a == c);
                }
            }
        }
        for (var a = 0u; a < D; a++) {
            minv[params.n_nodes * dd + i * D + a] = jacobi_inverse(h[a * D + a]);
        }
        let inv = block_jacobi_inverse(h, D);
        for (var e = 0u; e < dd; e++) {
            minv[i * dd + e] = inv[e];
        }
    }
}

// (H pw)_i, D = 3: Σ_k H_ik pw_j over the row's blocks in this chunk's buffer, each entry
// summed in column order. Straight-line vector code: llvmpipe runs loops over
// dynamically indexed private arrays far slower (2.3× on this product).
fn hrow3(i: u32) -> vec3<real> {
    if (DIFF) {
        return hrow3_difference(i);
    }
    var s = vec3<real>(real(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 9u;
        let w = vec3<real>(pw[3u * j], pw[3u * j + 1u], pw[3u * j + 2u]);
        s += vec3<real>(hvals[o], hvals[o + 3u], hvals[o + 6u]) * w.x;
        s += vec3<real>(hvals[o + 1u], hvals[o + 4u], hvals[o + 7u]) * w.y;
        s += vec3<real>(hvals[o + 2u], hvals[o + 5u], hvals[o + 8u]) * w.z;
    }
    return s;
}

// (H pw)_i, D = 2.
fn hrow2(i: u32) -> vec2<real> {
    if (DIFF) {
        return hrow2_difference(i);
    }
    var s = vec2<real>(real(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 4u;
        let w = vec2<real>(pw[2u * j], pw[2u * j + 1u]);
        s += vec2<real>(hvals[o], hvals[o + 2u]) * w.x;
        s += vec2<real>(hvals[o + 1u], hvals[o + 3u]) * w.y;
    }
    return s;
}

// (H pw)_i in the difference form (DIFF), D = 3.
fn hrow3_difference(i: u32) -> vec3<real> {
    let wi = vec3<real>(pw[3u * i], pw[3u * i + 1u], pw[3u * i + 2u]);
    var s = vec3<acc>(acc(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 9u;
        let w = vec3<real>(pw[3u * j], pw[3u * j + 1u], pw[3u * j + 2u]) - wi;
        s += vec3<acc>(vec3<real>(hvals[o], hvals[o + 3u], hvals[o + 6u])) * acc(w.x);
        s += vec3<acc>(vec3<real>(hvals[o + 1u], hvals[o + 4u], hvals[o + 7u])) * acc(w.y);
        s += vec3<acc>(vec3<real>(hvals[o + 2u], hvals[o + 5u], hvals[o + 8u])) * acc(w.z);
    }
    let m = 9u * i;
    let a = vec3<acc>(wi);
    s += vec3<acc>(vec3<real>(rowsum[m], rowsum[m + 3u], rowsum[m + 6u])) * a.x;
    s += vec3<acc>(vec3<real>(rowsum[m + 1u], rowsum[m + 4u], rowsum[m + 7u])) * a.y;
    s += vec3<acc>(vec3<real>(rowsum[m + 2u], rowsum[m + 5u], rowsum[m + 8u])) * a.z;
    return vec3<real>(s);
}

// (H pw)_i in the difference form (DIFF), D = 2.
fn hrow2_difference(i: u32) -> vec2<real> {
    let wi = vec2<real>(pw[2u * i], pw[2u * i + 1u]);
    var s = vec2<acc>(acc(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 4u;
        let w = vec2<real>(pw[2u * j], pw[2u * j + 1u]) - wi;
        s += vec2<acc>(vec2<real>(hvals[o], hvals[o + 2u])) * acc(w.x);
        s += vec2<acc>(vec2<real>(hvals[o + 1u], hvals[o + 3u])) * acc(w.y);
    }
    let m = 4u * i;
    let a = vec2<acc>(wi);
    s += vec2<acc>(vec2<real>(rowsum[m], rowsum[m + 2u])) * a.x;
    s += vec2<acc>(vec2<real>(rowsum[m + 1u], rowsum[m + 3u])) * a.y;
    return vec2<real>(s);
}

// q = Ĥp = P Vᵀ H V P p + (I − P) p, one invocation per block row, with the p·q partials.
@compute @workgroup_size(WG)
fn matvec(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let segs = chunk_segments();
    for (var s = segs.x + group_index(wid, nwg); s < segs.y; s += group_count(nwg)) {
        var pq = acc(0.0);
        if (segment_begun(s)) {
            pq = partials[carry(params.chunk - 1u, lid.x, 0u)];
        }
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid.x;
            if (i >= params.row_end) {
                break;
            }
            if (i < params.row_begin) {
                continue;
            }
            let m = frame[2u * i];
            let ri = rot_of(i);
            if (D == 3u) {
                var v = hrow3(i);
                if (ri != NO_ROTATION) {
                    // V_iᵀ v: the columns of this matrix are the rows of V_i.
                    let o = ri * 9u;
                    v = mat3x3<real>(
                        vec3<real>(rotations[o], rotations[o + 1u], rotations[o + 2u]),
                        vec3<real>(rotations[o + 3u], rotations[o + 4u], rotations[o + 5u]),
                        vec3<real>(rotations[o + 6u], rotations[o + 7u], rotations[o + 8u]),
                    ) * v;
                }
                let pi = vec3<real>(p[3u * i], p[3u * i + 1u], p[3u * i + 2u]);
                let qv = select(v, pi, mask_bits3(m));
                q[3u * i] = qv.x;
                q[3u * i + 1u] = qv.y;
                q[3u * i + 2u] = qv.z;
                pq += acc(pi.x) * acc(qv.x);
                pq += acc(pi.y) * acc(qv.y);
                pq += acc(pi.z) * acc(qv.z);
            } else {
                var v = hrow2(i);
                if (ri != NO_ROTATION) {
                    let o = ri * 4u;
                    v = mat2x2<real>(
                        vec2<real>(rotations[o], rotations[o + 1u]),
                        vec2<real>(rotations[o + 2u], rotations[o + 3u]),
                    ) * v;
                }
                let pi = vec2<real>(p[2u * i], p[2u * i + 1u]);
                let qv = select(v, pi, mask_bits2(m));
                q[2u * i] = qv.x;
                q[2u * i + 1u] = qv.y;
                pq += acc(pi.x) * acc(qv.x);
                pq += acc(pi.y) * acc(qv.y);
            }
        }
        if (segment_goes_on(s)) {
            partials[carry(params.chunk, lid.x, 0u)] = pq;
            continue;
        }
        workgroup_sum(lid.x, sum1(pq), 1u);
        if (lid.x == 0u) {
            partials[PART_PQ * params.n_partials + s] = summed(0u);
        }
        workgroupBarrier();
    }
}

// α = ρ / p·q (one workgroup); a non-positive p·q halts, a NaN one is a breakdown.
@compute @workgroup_size(WG)
fn scalar_alpha(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let pq = reduce_slot(PART_PQ, lid.x);
    if (lid.x == 0u) {
        scal[SCAL_PQ] = pq;
        if (pq > acc(0.0)) {
            scal[SCAL_ALPHA] = scal[SCAL_RHO] / pq;
        } else {
            state[STATE_DONE] = 1u;
            if (pq <= acc(0.0)) {
                state[STATE_HALT] = 1u;
            } else {
                state[STATE_BREAKDOWN] = 1u;
            }
        }
    }
}

// The r·z and r·r partials of one workgroup and, with COARSE, those of Zᵀr (one tree).
// `sums`: r·z, r·r, then (COARSE = 1) Zᵀr.
fn write_rz_rr(lid: u32, wg: u32, sums: array<acc, 5>) {
    let n = select(2u, 2u + D, COARSE == 1u);
    workgroup_sum(lid, sums, n);
    if (lid == 0u) {
        let np = params.n_partials;
        partials[PART_RZ * np + wg] = summed(0u);
        partials[PART_RR * np + wg] = summed(1u);
        for (var a = 0u; a + 2u < n; a++) {
            partials[(PART_ZR + a) * np + wg] = summed(2u + a);
        }
    }
}

// z_i = M⁻¹r_i (and p_i = z_i at a start), with node i's shares of r·z and r·r and
// (COARSE = 1) Zᵀr added to sums[0], sums[1] and sums[2..].
fn precondition(i: u32, rv: array<real, 3>, start: bool, sums: ptr<function, array<acc, 5>>) {
    if (PRECOND == 3u) {
        for (var a = 0u; a < D; a++) {
            (*sums)[1] += acc(rv[a]) * acc(rv[a]);
        }
        return;
    }
    let zv = apply_precond(i, rv);
    for (var a = 0u; a < D; a++) {
        z[i * D + a] = zv[a];
        if (start) {
            p[i * D + a] = zv[a];
        }
        (*sums)[0] += acc(rv[a]) * acc(zv[a]);
        (*sums)[1] += acc(rv[a]) * acc(rv[a]);
    }
    if (COARSE == 1u) {
        let w = zt(i, rv);
        for (var a = 0u; a < D; a++) {
            (*sums)[2u + a] += acc(w[a]);
        }
    }
}

// y += αp, r −= αq, z = M⁻¹r, with the r·z and r·r partials.
@compute @workgroup_size(WG)
fn update_yr(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let alpha = real(scal[SCAL_ALPHA]);
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var sums: array<acc, 5>;
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid.x;
            if (i >= params.n_nodes) {
                break;
            }
            var rv: array<real, 3>;
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                y[k] += alpha * p[k];
                rv[a] = r[k] - alpha * q[k];
                r[k] = rv[a];
            }
            precondition(i, rv, false, &sums);
        }
        write_rz_rr(lid.x, s, sums);
        workgroupBarrier();
    }
}

// ρ' = r·z (with COARSE r·M_J⁻¹r + Zᵀr·c, and c = E⁺Zᵀr) and r·r (one workgroup); stops
// on r·r ≤ tol²‖b̂‖² (the recurrence residual) or a non-finite value, else β = ρ'/ρ.
// Counts the iteration.
@compute @workgroup_size(WG)
fn scalar_beta(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    var v = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    let np = params.n_partials;
    var n = 2u;
    if (COARSE == 1u) {
        n = 2u + D;
    } else if (COARSE == 2u) {
        n = 3u;
        v[2] = agg_wc(lid.x);
    }
    for (var t = lid.x; t < np; t += WG) {
        v[0] += partials[PART_RZ * np + t];
        v[1] += partials[PART_RR * np + t];
        if (COARSE == 1u) {
            for (var a = 0u; a < D; a++) {
                v[2u + a] += partials[(PART_ZR + a) * np + t];
            }
        }
    }
    let s = workgroup_sum_uniform(lid.x, v, n);
    if (lid.x == 0u) {
        var rz = s[0];
        let rr = s[1];
        if (COARSE == 1u) {
            rz += coarse_c(array<acc, 3>(s[2], s[3], s[4]));
        } else if (COARSE == 2u) {
            rz += s[2];
        }
        let it = state[STATE_ITERS];
        state[STATE_ITERS] = it + 1u;
        if (it < HIST) {
            scal[SCAL_HIST + 2u * it] = scal[SCAL_ALPHA];
        }
        scal[SCAL_RR] = rr;
        // NaN fails every comparison: a non-finite ρ or r·r is a breakdown.
        if (!(rz >= acc(0.0)) || !(rr >= acc(0.0))) {
            state[STATE_DONE] = 1u;
            state[STATE_BREAKDOWN] = 1u;
        } else if (rr <= scal[SCAL_TOL2] * scal[SCAL_BB]) {
            state[STATE_DONE] = 1u;
            state[STATE_CONVERGED] = 1u;
        } else {
            scal[SCAL_BETA] = rz / scal[SCAL_RHO];
            scal[SCAL_RHO] = rz;
            if (it < HIST) {
                scal[SCAL_HIST + 2u * it + 1u] = scal[SCAL_BETA];
            }
        }
    }
}

// pw_i = V_i P_i p_i, from the p_i this invocation has just written.
fn write_world(i: u32) {
    var w: array<real, 3>;
    for (var c = 0u; c < D; c++) {
        w[c] = select(p[i * D + c], real(0.0), fixed(i, c));
    }
    let o = from_frame(i, w);
    for (var c = 0u; c < D; c++) {
        pw[i * D + c] = o[c];
    }
}

// pw = V P p for every node (after the host copied y into p: the true residual's product).
@compute @workgroup_size(WG)
fn world_p(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.n_nodes; i += grid_stride(nwg)) {
        write_world(i);
    }
}

// pw = V P z: the multilevel V-cycle's product at level 0 (then `matvec`, whose q = Ĥz
// and throw-away p·q partials the V-cycle reads before the next iteration's product).
@compute @workgroup_size(WG)
fn world_z(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (state[STATE_DONE] != 0u) {
        return;
    }
    for (var i = grid_index(gid, nwg); i < params.n_nodes; i += grid_stride(nwg)) {
        var w: array<real, 3>;
        for (var c = 0u; c < D; c++) {
            w[c] = select(z[i * D + c], real(0.0), fixed(i, c));
        }
        let o = from_frame(i, w);
        for (var c = 0u; c < D; c++) {
            pw[i * D + c] = o[c];
        }
    }
}

// The r·z partials after the V-cycle (PRECOND = 3); at a start (ml_start) also p = z and
// pw = V P p.
fn ml_rz(lid: u32, wid: vec3<u32>, nwg: vec3<u32>, start: bool) {
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var rz = acc(0.0);
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid;
            if (i >= params.n_nodes) {
                break;
            }
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                rz += acc(r[k]) * acc(z[k]);
                if (start) {
                    p[k] = z[k];
                }
            }
            if (start) {
                write_world(i);
            }
        }
        workgroup_sum(lid, sum1(rz), 1u);
        if (lid == 0u) {
            partials[PART_RZ * params.n_partials + s] = summed(0u);
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(WG)
fn ml_dot(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    ml_rz(lid.x, wid, nwg, false);
}

@compute @workgroup_size(WG)
fn ml_start(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    ml_rz(lid.x, wid, nwg, true);
}

// p = z + βp (and pw); with COARSE p = (z + Zc) + βp, the preconditioned residual
// completed.
@compute @workgroup_size(WG)
fn update_p(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let beta = real(scal[SCAL_BETA]);
    if (COARSE == 0u) {
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                p[k] = z[k] + beta * p[k];
            }
            write_world(i);
        }
        return;
    }
    var c: array<real, 3>;
    if (COARSE == 1u) {
        for (var a = 0u; a < D; a++) {
            c[a] = real(scal[SCAL_C + a]);
        }
    }
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
        if (COARSE == 2u) {
            let ag = aggregates[aggregates[AGG_OF] + i];
            for (var a = 0u; a < D; a++) {
                c[a] = real(0.0);
                if (ag != NO_AGGREGATE) {
                    c[a] = real(coarse[aggregates[AGG_C] + ag * D + a]);
                }
            }
        }
        let w = zc(i, c);
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            p[k] = (z[k] + w[a]) + beta * p[k];
        }
        write_world(i);
    }
}

// A (re)start from y, with q = Ĥy already in q: r = b̂ − q, z = M⁻¹r, p = z, and the r·z
// and r·r partials (r·r of the true residual); with COARSE z = M_J⁻¹r and the Zᵀr
// partials too, and update_p (β = 0) then adds Zc to p.
@compute @workgroup_size(WG)
fn init(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var sums: array<acc, 5>;
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid.x;
            if (i >= params.n_nodes) {
                break;
            }
            var rv: array<real, 3>;
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                rv[a] = b[k] - q[k];
                r[k] = rv[a];
            }
            // A resumed segment keeps p: update_p then forms p = z + βp and writes pw.
            let fresh = !resuming();
            precondition(i, rv, fresh, &sums);
            // With COARSE, the update_p that completes p writes pw; with the multilevel
            // preconditioner ml_start does.
            if (COARSE == 0u && PRECOND != 3u && fresh) {
                write_world(i);
            }
        }
        write_rz_rr(lid.x, s, sums);
        workgroupBarrier();
    }
}

// A segment that resumes the last one's search direction (a reliable update: the host
// wrote SCAL_PSCALE > 0 and SCAL_RHO_PREV; see `DeviceCg::segment`).
fn resuming() -> bool {
    return scal[SCAL_PSCALE] > acc(0.0);
}

// After init (one workgroup): ρ, the true r·r and ‖b̂‖²; stops when the true residual
// meets the tolerance (always when b̂ = 0 and y = 0). With COARSE also c = E⁺Zᵀr (Zᵀr in
// a second tree), ρ += Zᵀr·c, and β = 0 for the update_p that completes p = z + Zc.
// Resuming, β = s·ρ/ρ_prev (s = SCAL_PSCALE, the old direction's rescaling, ρ_prev
// already in the new scaling) for the update_p that forms p = z (+ Zc) + β p_old.
@compute @workgroup_size(WG)
fn scalar_start(@builtin(local_invocation_id) lid: vec3<u32>) {
    var v = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    var w = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    let np = params.n_partials;
    for (var t = lid.x; t < np; t += WG) {
        v[0] += partials[PART_RZ * np + t];
        v[1] += partials[PART_RR * np + t];
        v[2] += partials[PART_BB * np + t];
        if (COARSE == 1u) {
            for (var a = 0u; a < D; a++) {
                w[a] += partials[(PART_ZR + a) * np + t];
            }
        }
    }
    let s = workgroup_sum_uniform(lid.x, v, 3u);
    var zr: array<acc, 3>;
    if (COARSE == 1u) {
        let sw = workgroup_sum_uniform(lid.x, w, D);
        zr = array<acc, 3>(sw[0], sw[1], sw[2]);
    }
    var wc = acc(0.0);
    if (COARSE == 2u) {
        wc = workgroup_sum_uniform1(lid.x, agg_wc(lid.x));
    }
    if (lid.x == 0u) {
        var rz = s[0];
        let rr = s[1];
        let bb = s[2];
        if (COARSE == 1u) {
            rz += coarse_c(zr);
        } else if (COARSE == 2u) {
            rz += wc;
        }
        if (resuming()) {
            scal[SCAL_BETA] = scal[SCAL_PSCALE] * rz / scal[SCAL_RHO_PREV];
        } else if (COARSE != 0u) {
            scal[SCAL_BETA] = acc(0.0);
        }
        scal[SCAL_RHO] = rz;
        scal[SCAL_RR] = rr;
        scal[SCAL_BB] = bb;
        if (!(rz >= acc(0.0)) || !(rr >= acc(0.0)) || !(bb >= acc(0.0))) {
            state[STATE_DONE] = 1u;
            state[STATE_BREAKDOWN] = 1u;
        } else if (rr <= scal[SCAL_TOL2] * bb) {
            state[STATE_DONE] = 1u;
            state[STATE_CONVERGED] = 1u;
        }
    }
}

// Node i has no constrained component and no rotation: Z_i = Q_i = I.
fn plain(i: u32) -> bool {
    return frame[2u * i] == 0u && rot_of(i) == NO_ROTATION;
}

// Every component of node i is constrained: Z_i = 0.
fn all_fixed(i: u32) -> bool {
    let full = (1u << D) - 1u;
    return (frame[2u * i] & full) == full;
}

// Q_i = Z_iᵀZ_i = V_i P_i V_iᵀ, row-major: Q_ab = Σ_c over the free frame components of
// V_ac V_bc (V = I at unrotated nodes), in the order src/coarse.rs sums it.
fn proj(i: u32) -> array<real, 9> {
    let ri = rot_of(i);
    var o: array<real, 9>;
    for (var a = 0u; a < D; a++) {
        for (var b = 0u; b < D; b++) {
            var s = real(0.0);
            for (var c = 0u; c < D; c++) {
                if (!fixed(i, c)) {
                    var va = select(real(0.0), real(1.0), a == c);
                    var vb = select(real(0.0), real(1.0), b == c);
                    if (ri != NO_ROTATION) {
                        va = rotations[ri * D * D + a * D + c];
                        vb = rotations[ri * D * D + b * D + c];
                    }
                    s += va * vb;
                }
            }
            o[a * D + b] = s;
        }
    }
    return o;
}

// x y for row-major D×D x and y.
fn mat_mul(x: array<real, 9>, y: array<real, 9>) -> array<real, 9> {
    var o: array<real, 9>;
    for (var a = 0u; a < D; a++) {
        for (var c = 0u; c < D; c++) {
            var s = real(0.0);
            for (var m = 0u; m < D; m++) {
                s += x[a * D + m] * y[m * D + c];
            }
            o[a * D + c] = s;
        }
    }
    return o;
}

// The partials of E = ZᵀĤZ = Σ_i Q_i (Σ_j H_ij Q_j), D² slots (Ĥ's identity on the
// constrained components never meets Z), and of the D absolute row sums 2^-64 ·
// Σ_j |(Q_i H_ij Q_j)_a·| (each block projected on its own, as src/solve/coarse.rs sums
// them; scaled so that rows near the top of the range do not overflow). Row i's blocks are
// summed before Q_i is applied, as src/solve/coarse.rs does: for a nearly free body they
// cancel to the mass term, and summing every block into E would carry the rounding of the
// stiffness into the small E.
@compute @workgroup_size(WG)
fn coarse_e(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let n_sums = dd + D;
    let np = params.n_partials;
    let segs = chunk_segments();
    for (var s = segs.x + group_index(wid, nwg); s < segs.y; s += group_count(nwg)) {
        // E's D² entries, then the D absolute row sums.
        var e: array<acc, 12>;
        if (segment_begun(s)) {
            for (var m = 0u; m < n_sums; m++) {
                e[m] = partials[carry(params.chunk - 1u, lid.x, m)];
            }
        }
        for (var mi = 0u; mi < ITEMS; mi++) {
            let i = (s * ITEMS + mi) * WG + lid.x;
            if (i >= params.row_end) {
                break;
            }
            if (i < params.row_begin || all_fixed(i)) {
                continue;
            }
            var part: array<real, 9>;
            for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
                let j = pattern[params.col_at + k];
                if (all_fixed(j)) {
                    continue;
                }
                var t: array<real, 9>;
                for (var m = 0u; m < dd; m++) {
                    t[m] = hvals[(k - params.block_first) * dd + m];
                }
                if (!plain(j)) {
                    t = mat_mul(t, proj(j));
                }
                for (var m = 0u; m < dd; m++) {
                    part[m] += t[m];
                }
                var b = t;
                if (!plain(i)) {
                    b = mat_mul(proj(i), t);
                }
                for (var a = 0u; a < D; a++) {
                    var sa = real(0.0);
                    for (var c = 0u; c < D; c++) {
                        sa += abs(b[a * D + c]) * ABS_SUM_SCALE;
                    }
                    e[dd + a] += acc(sa);
                }
            }
            if (!plain(i)) {
                part = mat_mul(proj(i), part);
            }
            for (var m = 0u; m < dd; m++) {
                e[m] += acc(part[m]);
            }
        }
        if (segment_goes_on(s)) {
            for (var m = 0u; m < n_sums; m++) {
                partials[carry(params.chunk, lid.x, m)] = e[m];
            }
            continue;
        }
        // The sums in trees of at most five.
        for (var base = 0u; base < n_sums; base += 5u) {
            let n = min(n_sums - base, 5u);
            var v: array<acc, 5>;
            for (var m = 0u; m < n; m++) {
                v[m] = e[base + m];
            }
            workgroup_sum(lid.x, v, n);
            if (lid.x == 0u) {
                for (var m = 0u; m < n; m++) {
                    partials[(PART_E + base + m) * np + s] = summed(m);
                }
            }
            workgroupBarrier();
        }
    }
}

// E and the absolute row sums from coarse_e's partials (one workgroup, fixed order) into
// scal, for the host, which symmetrizes and pseudo-inverts E as the CPU does
// (src/solve/coarse.rs).
@compute @workgroup_size(WG)
fn coarse_e_sum(@builtin(local_invocation_id) lid: vec3<u32>) {
    let dd = D * D;
    let n_sums = dd + D;
    let np = params.n_partials;
    for (var base = 0u; base < n_sums; base += 5u) {
        let n = min(n_sums - base, 5u);
        var v: array<acc, 5>;
        for (var t = lid.x; t < np; t += WG) {
            for (var m = 0u; m < n; m++) {
                v[m] += partials[(PART_E + base + m) * np + t];
            }
        }
        let s = workgroup_sum_uniform(lid.x, v, n);
        if (lid.x == 0u) {
            for (var m = 0u; m < n; m++) {
                let at = base + m;
                if (at < dd) {
                    scal[SCAL_E + at] = s[m];
                } else {
                    scal[SCAL_EABS + at - dd] = s[m];
                }
            }
        }
    }
}

// Δx = V P y (the prescribed part is zero in a Newton step).
@compute @workgroup_size(WG)
fn recover(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.n_nodes; i += grid_stride(nwg)) {
        var w: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            w[a] = select(y[i * D + a], real(0.0), fixed(i, a));
        }
        let o = from_frame(i, w);
        for (var a = 0u; a < D; a++) {
            dx[i * D + a] = o[a];
        }
    }
}

// This invocation's share of w·c = Zᵀr·E⁺Zᵀr (COARSE = 2), the coarse part of ρ: lane
// `lid` of one workgroup sums rows lid, lid + WG, … (a fixed order).
fn agg_wc(lid: u32) -> acc {
    let k = aggregates[AGG_K];
    let w = aggregates[AGG_W];
    let c = aggregates[AGG_C];
    var s = acc(0.0);
    for (var t = lid; t < k; t += WG) {
        s += coarse[w + t] * coarse[c + t];
    }
    return s;
}

// Row i's share of E = ZᵀĤZ over the aggregates: per slot (one per column aggregate b of
// the row, in the order of first appearance) Q_i Σ_{j∈b} H_ij Q_j, D² values. The row's
// blocks are summed per column aggregate before Q_i is applied, as
// src/solve/coarse.rs does: for a nearly free body they cancel to the mass term, and
// summing each block into E would carry the rounding of the stiffness into a small E.
// One invocation per block row of the values chunk; no reduction.
@compute @workgroup_size(WG)
fn agg_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let slot_ptr = aggregates[AGG_SLOT_PTR];
    let slot_of = aggregates[AGG_SLOT_OF];
    for (var i = params.row_begin + grid_index(gid, nwg); i < params.row_end; i += grid_stride(nwg)) {
        let s0 = aggregates[slot_ptr + i];
        let s1 = aggregates[slot_ptr + i + 1u];
        if (s0 == s1) {
            continue;
        }
        for (var t = s0 * dd; t < s1 * dd; t++) {
            coarse[t] = acc(0.0);
        }
        for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
            let sl = aggregates[slot_of + k];
            if (sl == NO_AGGREGATE) {
                continue;
            }
            let j = pattern[params.col_at + k];
            var t: array<real, 9>;
            for (var m = 0u; m < dd; m++) {
                t[m] = hvals[(k - params.block_first) * dd + m];
            }
            if (!plain(j)) {
                t = mat_mul(t, proj(j));
            }
            for (var m = 0u; m < dd; m++) {
                coarse[sl * dd + m] += acc(t[m]);
            }
        }
        if (!plain(i)) {
            let qi = proj(i);
            for (var sl = s0; sl < s1; sl++) {
                var t: array<real, 9>;
                for (var m = 0u; m < dd; m++) {
                    t[m] = real(coarse[sl * dd + m]);
                }
                t = mat_mul(qi, t);
                for (var m = 0u; m < dd; m++) {
                    coarse[sl * dd + m] = acc(t[m]);
                }
            }
        }
    }
}

// E (K×K, row-major, not symmetrized: coarse_factor.wgsl does that): entry (a·D + x, b·D + y) sums
// component (x, y) of the slots of aggregate pair (a, b) in row order, as the CPU adds
// them. One invocation per entry.
@compute @workgroup_size(WG)
fn agg_e(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n_agg = aggregates[AGG_COUNT];
    let k = aggregates[AGG_K];
    let pair_ptr = aggregates[AGG_PAIR_PTR];
    let pair_slots = aggregates[AGG_PAIR_SLOTS];
    for (var t = grid_index(gid, nwg); t < k * k; t += grid_stride(nwg)) {
        let row = t / k;
        let col = t % k;
        let pair = aggregates[aggregates[AGG_PAIR_OF] + (row / D) * n_agg + col / D];
        var s = acc(0.0);
        if (pair != NO_AGGREGATE) {
            let at = (row % D) * D + col % D;
            for (var m = aggregates[pair_ptr + pair]; m < aggregates[pair_ptr + pair + 1u]; m++) {
                s += coarse[aggregates[pair_slots + m] * D * D + at];
            }
        }
        coarse[aggregates[AGG_E] + t] = s;
    }
}

// w = Zᵀr per aggregate (COARSE = 2): one workgroup per aggregate over its nodes, in a
// fixed order.
@compute @workgroup_size(WG)
fn agg_restrict(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let n_agg = aggregates[AGG_COUNT];
    let ptr = aggregates[AGG_PTR];
    let nodes = aggregates[AGG_NODES];
    for (var a = group_index(wid, nwg); a < n_agg; a += group_count(nwg)) {
        var s: array<acc, 5>;
        for (var t = aggregates[ptr + a] + lid.x; t < aggregates[ptr + a + 1u]; t += WG) {
            let i = aggregates[nodes + t];
            var rv: array<real, 3>;
            for (var x = 0u; x < D; x++) {
                rv[x] = r[i * D + x];
            }
            let w = zt(i, rv);
            for (var x = 0u; x < D; x++) {
                s[x] += acc(w[x]);
            }
        }
        workgroup_sum(lid.x, s, D);
        if (lid.x < D) {
            coarse[aggregates[AGG_W] + a * D + lid.x] = summed(lid.x);
        }
        // The tree's memory is reused by the next aggregate.
        workgroupBarrier();
    }
}

// c = E⁺w (COARSE = 2), one workgroup per coarse row: its lanes take the columns
// lid, lid + WG, … (a fixed order) and one tree sums them, so a row costs K/WG loads in
// sequence, not K. E⁺ is symmetric: row `row` is read as column `row`.
@compute @workgroup_size(WG)
fn agg_solve(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let k = aggregates[AGG_K];
    let einv = aggregates[AGG_EINV];
    let w = aggregates[AGG_W];
    for (var row = group_index(wid, nwg); row < k; row += group_count(nwg)) {
        var s = acc(0.0);
        for (var col = lid.x; col < k; col += WG) {
            s += coarse[einv + col * k + row] * coarse[w + col];
        }
        workgroup_sum(lid.x, sum1(s), 1u);
        if (lid.x == 0u) {
            coarse[aggregates[AGG_C] + row] = summed(0u);
        }
        workgroupBarrier();
    }
}
