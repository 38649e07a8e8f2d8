// The eliminated PCG on the device-assembled Newton system (src/gpu/pcg/cg/):
//
//   Ĥ y = b̂,  Ĥ = P VᵀHV P + (I − P),  b̂ = −P Vᵀ g,  Δx = V P y
//
// H is read where the assembly left it (assemble.wgsl: block CSR, both triangles,
// row-major D×D blocks), never copied; V_i is applied only at rotated nodes. This file is
// what the PCG's shader files share (each is compiled as this file followed by its own):
// pcg_product.wgsl (the product and the world-frame copies), pcg_update.wgsl (b̂, the
// preconditioners, starts, the iteration's updates and scalars) and pcg_coarse.wgsl (the
// coarse spaces). They share one bind group.
//
// One CG iteration is three dispatches:
//   matvec     q = Ĥp, the p·q partials (one invocation per block row)
//   update_yr  α = ρ/p·q (every workgroup sums the partials in the same order), y += αp,
//              r −= αq, z = M⁻¹r, the r·z and r·r partials
//   update_p   β = ρ'/ρ likewise, the stop test, p = z + βp and pw = V P p
// and with the aggregates (COARSE = 2) agg_restrict and agg_solve between update_yr and
// update_p; with the multilevel preconditioner (PRECOND = 3) the V-cycle (vcycle.wgsl,
// world_z and matvec for its level-0 products) and ml_dot there instead. No kernel of an
// iteration waits on one workgroup's scalar: there is no one-workgroup dispatch in it.
// A (re)start is `init` (r = b̂ − q with q = Ĥy, z = M⁻¹r, p = z, partials) and
// `scalar_start` (then `start_p` under COARSE), whose r·r is the true residual; at a
// solve's first start scalar_start also evaluates the tolerance rule on ‖b̂‖ where the
// host gave one (rule_tolerance). A resumed segment (src/gpu/pcg/cg/segment.rs) keeps p
// through init, and its start_p forms p = z (+ Zc) + βp with the β of scalar_start.
// `prepare` adds `coarse_e` and `coarse_e_sum` (E = ZᵀĤZ of the translations) and, with
// the aggregates, `agg_rows` and `agg_e` to `rhs` and `precond`.
//
// Once a stop flag is set every later iteration dispatch of the submit is a no-op. A
// chunk of iterations ends with its verification: the kernels of a restart compiled with
// VERIFY, which run only when the recurrence has met the tolerance and its true residual
// is not yet known (q = Ĥy by world_y and matvec, then init, scalar_start, start_p), then
// `verified`; where the true residual meets the tolerance too (STATE_TRUE_OK) the
// verified `recover` forms Δx in the same submit. So the status the host reads after the
// chunk already holds the true residual, and a solve that converges within its first
// chunk costs one round trip.
//
// Reductions are segmented (src/gpu/launch.rs, SegmentPolicy): the nodes are cut into
// segments of SEG = WG·ITEMS consecutive nodes (n_partials of them); invocation lid of
// the workgroup that takes segment s sums nodes s·SEG + lid + m·WG, m = 0, 1, …, in that
// order, and one tree per segment writes partial s; the kernels that need the total sum
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
// r·M_J⁻¹r and r·r; update_p and scalar_start form c = E⁺Zᵀr and ρ = r·M_J⁻¹r + Zᵀr·c;
// update_p (start_p) adds Z_i c to p. No dispatch in the iteration.
// 2: E⁺ (K×K, K = D·aggregates, formed by coarse_factor.wgsl in `prepare`, or by the host
// where that fails) is in `coarse`; after update_yr (init)
// agg_restrict forms w = Zᵀr (a workgroup per aggregate) and agg_solve c = E⁺w (a
// workgroup per coarse row); update_p (scalar_start) adds w·c to ρ and update_p (start_p)
// adds Z_i c_{aggregate of i} to p. Two dispatches per iteration.
override COARSE: u32 = 0u;
// Nodes per invocation within a segment (the device's SegmentPolicy).
override ITEMS: u32 = 1u;
// Lanczos coefficients recorded (0: none): update_p of iteration j < HIST (counted from
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
// A verification's kernel (see above): runs only while the recurrence has converged and
// its true residual is unchecked; the iteration's kernels run while no stop flag is set.
override VERIFY: bool = false;

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

// Slots of `scal`, `state` and the partial sums: the one table of the device PCG
// (`gpu::kernels::slots`, declared by the prelude, says who writes and reads each).
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

// The recurrence has met the tolerance (no other stop) and its true residual is unchecked.
fn verifying() -> bool {
    return state[STATE_DONE] != 0u && state[STATE_CONVERGED] != 0u
        && state[STATE_VERIFIED] == 0u && state[STATE_HALT] == 0u
        && state[STATE_BREAKDOWN] == 0u;
}

// `on` (read by invocation 0) as a workgroup-uniform value (later barriers may depend on
// it).
fn uniform_flag(lid: u32, on: bool) -> bool {
    if (lid == 0u) {
        wg_flag = select(0u, 1u, on);
    }
    return workgroupUniformLoad(&wg_flag) != 0u;
}

// Whether an iteration's kernel runs: no stop flag set (VERIFY: while verifying).
fn running(lid: u32) -> bool {
    var on = state[STATE_DONE] == 0u;
    if (VERIFY) {
        on = verifying();
    }
    return uniform_flag(lid, on);
}

// Whether a start's kernel runs: always, when the host records it (VERIFY: while
// verifying).
fn starting(lid: u32) -> bool {
    var on = true;
    if (VERIFY) {
        on = verifying();
    }
    return uniform_flag(lid, on);
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

// c = E⁺ Zᵀr (COARSE = 1, E⁺ from the host in scal); returns Zᵀr·c, the coarse share of
// ρ = r·M⁻¹r.
fn coarse_c(zr: array<acc, 3>, c: ptr<function, array<acc, 3>>) -> acc {
    var wc = acc(0.0);
    for (var a = 0u; a < D; a++) {
        var s = acc(0.0);
        for (var b = 0u; b < D; b++) {
            s += scal[SCAL_EINV + a * D + b] * zr[b];
        }
        (*c)[a] = s;
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

// A segment that resumes the last one's search direction (a reliable update: the host
// wrote SCAL_PSCALE > 0 and SCAL_RHO_PREV; see `DeviceCg::segment`).
fn resuming() -> bool {
    return scal[SCAL_PSCALE] > acc(0.0);
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
// V_ac V_bc (V = I at unrotated nodes), in the order src/solve/coarse.rs sums it.
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

