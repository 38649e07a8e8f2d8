// The device Newton loop's vector operations, reductions and per-node updates
// (src/sim/device/newton_ops/mod.rs), the device side of the CPU's `Stepper` (src/sim/integrator/stepper.rs):
//
// - begin_step: xn = x, x̃ = x + h v (x unprojected, as the CPU's start of step);
//   project_static: x_i = P_i x_i + c_i for each listed node; the host then copies x to the
//   evaluation positions `pos`.
// - trial: pos = x + α Δx (α from a result slot); step_bound: the line search's first α
//   from the CCD and inversion bounds' slots; end_step: v = (x − xn)/h; gather_nodes: x of listed nodes.
// - add_moving: per unsnapped moving node, g += k m r − P(√m λ) and H_ii += k m P.
// - reduce / finish: deterministic two-pass reductions. `reduce` runs a fixed number of
//   workgroups; each invocation combines its grid-stride items in index order, each
//   workgroup combines its invocations by a fixed tree into partials[slot], and `finish`
//   (one workgroup per slot) combines the partials of a slot the same way into result.
//   Every value is a vec4: sums (energy and barrier flags, g·Δx, moving energy), max |Δx|
//   with a NaN count, and arg-mins (value, index, first NaN index) whose ties go to the
//   smaller index (node-major, then plane), like the CPU's first strict minimum.
//
// Infinity comes from the host (`scal[S_INF]`): WGSL has no portable literal for it.

override D: u32 = 3u;
// WG (the workgroup size) comes with the prelude (shaders/common.wgsl).

// Mirrors `OpsParams` in src/sim/device/newton_ops/mod.rs (four u32, 16 bytes, size-asserted there).
struct OpsParams {
    // Items of the dispatch (DOFs, nodes, entries, terms; `finish`: partials per slot).
    count: u32,
    // Reduction: what an item contributes and how values combine (MODE_*).
    mode: u32,
    // First result slot of a reduction.
    slot: u32,
    // ENERGY: 1 when `flags` holds the term's barrier flags; CCD, MIN_DISTANCE: planes.
    aux: u32,
}

const MODE_ENERGY: u32 = 0u;
const MODE_DOT: u32 = 1u;
const MODE_MAX_ABS: u32 = 2u;
const MODE_CCD: u32 = 3u;
const MODE_MIN_DISTANCE: u32 = 4u;
const MODE_MOVING_ENERGY: u32 = 5u;

// Slots of `scal`; half-space j (normal xyz, offset) at S_PLANES + 4j.
const S_H: u32 = 0u;
const S_FRACTION: u32 = 1u;
const S_INF: u32 = 2u;
const S_INV_FRACTION: u32 = 3u;
const S_PLANES: u32 = 4u;

// Reals per static projection (P row-major 3×3, c) and per moving term (see ops.rs).
const PROJ_STRIDE: u32 = 12u;
const MOVING_STRIDE: u32 = 12u;
// u32 per moving term: node, kind, diagonal block, unused.
const MOVING_INDEX_STRIDE: u32 = 4u;
const KIND_STICKY: u32 = 0u;
const KIND_PLANE: u32 = 1u;
const KIND_LINE: u32 = 2u;

// No index: larger than every node·planes + plane (exact in f32 and f64).
const NO_INDEX: f32 = 4503599627370496.0;

@group(0) @binding(0) var<uniform> params: OpsParams;
@group(0) @binding(1) var<storage, read> scal: array<real>;
// Accepted iterate, start of step, velocity (node-major).
@group(0) @binding(2) var<storage, read_write> x: array<real>;
@group(0) @binding(3) var<storage, read_write> xn: array<real>;
@group(0) @binding(4) var<storage, read_write> v: array<real>;
// The element terms' evaluation positions and inertia target x̃.
@group(0) @binding(5) var<storage, read_write> pos: array<real>;
@group(0) @binding(6) var<storage, read_write> xt: array<real>;
// The Newton direction Δx (world frame).
@group(0) @binding(7) var<storage, read> dx: array<real>;
// The assembled gradient and Hessian blocks.
@group(0) @binding(8) var<storage, read_write> grad: array<real>;
@group(0) @binding(9) var<storage, read_write> hvals: array<real>;
// A term's per-item energies and (barrier) flags.
@group(0) @binding(10) var<storage, read> src: array<real>;
@group(0) @binding(11) var<storage, read> flags: array<u32>;
// Static projections or moving terms, and their nodes (or the nodes of gather_nodes).
@group(0) @binding(12) var<storage, read> table: array<real>;
@group(0) @binding(13) var<storage, read> index: array<u32>;
@group(0) @binding(14) var<storage, read_write> partials: array<vec4<real>>;
@group(0) @binding(15) var<storage, read_write> result: array<vec4<real>>;
@group(0) @binding(16) var<storage, read_write> node_vals: array<real>;

var<workgroup> wg_red: array<vec4<real>, WG>;

@compute @workgroup_size(WG)
fn begin_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let h = scal[S_H];
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        xn[k] = x[k];
        xt[k] = x[k] + h * v[k];
    }
}

@compute @workgroup_size(WG)
fn project_static(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var e = grid_index(gid, nwg); e < params.count; e += grid_stride(nwg)) {
        let node = index[e];
        let o = e * PROJ_STRIDE;
        var y = array<real, 3>();
        for (var a = 0u; a < D; a++) {
            var s = real(0.0);
            for (var b = 0u; b < D; b++) {
                s += table[o + a * 3u + b] * x[node * D + b];
            }
            y[a] = s + table[o + 9u + a];
        }
        for (var a = 0u; a < D; a++) {
            x[node * D + a] = y[a];
        }
    }
}

// pos = x + α Δx with α in result[params.slot] (the host's, or step_bound's).
@compute @workgroup_size(WG)
fn trial(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let alpha = result[params.slot].x;
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        pos[k] = x[k] + alpha * dx[k];
    }
}

// The line search's first step α_C as src/sim/integrator/stepper.rs (`line_search`)
// takes it, into result[params.slot].x (one invocation): the CCD bound of result[mode]
// (aux bit 0; else 1), NaN and negative ones 0 as `Ccd` reads them, lowered to
// INVERSION_FRACTION (scal[S_INV_FRACTION]) of the first inverting step of
// result[count] (aux bit 1) where it has one and no element is already inverted.
@compute @workgroup_size(WG)
fn step_bound(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x != 0u) {
        return;
    }
    var alpha = real(1.0);
    if ((params.aux & 1u) != 0u) {
        let c = result[params.mode].x;
        alpha = select(real(0.0), c, c > real(0.0));
    }
    if ((params.aux & 2u) != 0u) {
        let inv = result[params.count];
        if (inv.z >= real(NO_INDEX) && inv.y < real(NO_INDEX)) {
            let b = scal[S_INV_FRACTION] * inv.x;
            if (b < alpha) {
                alpha = b;
            }
        }
    }
    result[params.slot] = vec4<real>(alpha, real(0.0), real(0.0), real(0.0));
}

@compute @workgroup_size(WG)
fn end_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let h = scal[S_H];
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        v[k] = (x[k] - xn[k]) / h;
    }
}

@compute @workgroup_size(WG)
fn gather_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        let node = index[k];
        for (var a = 0u; a < D; a++) {
            node_vals[k * D + a] = x[node * D + a];
        }
    }
}

// A moving term: its offset r (three components, positions zero-padded) and the
// projector P (row-major 3×3) onto its constrained directions, as the CPU's `offset` and
// `projector`.
struct Moving {
    r: array<real, 3>,
    p: array<real, 9>,
}

fn moving_term(k: u32) -> Moving {
    let node = index[k * MOVING_INDEX_STRIDE];
    let kind = index[k * MOVING_INDEX_STRIDE + 1u];
    let o = k * MOVING_STRIDE;
    var q = array<real, 3>();
    for (var a = 0u; a < D; a++) {
        q[a] = pos[node * D + a];
    }
    var out: Moving;
    if (kind == KIND_STICKY) {
        for (var a = 0u; a < 3u; a++) {
            out.r[a] = q[a] - table[o + a];
        }
        for (var a = 0u; a < D; a++) {
            out.p[a * 3u + a] = real(1.0);
        }
    } else if (kind == KIND_PLANE) {
        var dist = real(0.0);
        for (var a = 0u; a < 3u; a++) {
            dist += table[o + a] * q[a];
        }
        dist -= table[o + 3u];
        for (var a = 0u; a < 3u; a++) {
            out.r[a] = dist * table[o + a];
            for (var c = 0u; c < 3u; c++) {
                out.p[a * 3u + c] = table[o + a] * table[o + c];
            }
        }
    } else {
        var w = array<real, 3>();
        var s = real(0.0);
        for (var a = 0u; a < 3u; a++) {
            w[a] = q[a] - table[o + a];
            s += w[a] * table[o + 4u + a];
        }
        for (var a = 0u; a < 3u; a++) {
            out.r[a] = w[a] - s * table[o + 4u + a];
            for (var c = 0u; c < 3u; c++) {
                out.p[a * 3u + c] = select(real(0.0), real(1.0), a == c) - table[o + 4u + a] * table[o + 4u + c];
            }
        }
    }
    return out;
}

// Each moving node appears once (the host checks), so no two invocations write one node.
@compute @workgroup_size(WG)
fn add_moving(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        let node = index[k * MOVING_INDEX_STRIDE];
        // The diagonal block within its values chunk, and that chunk: this dispatch
        // (aux: its chunk) writes the blocks of its chunk, the first the gradient.
        let blk = index[k * MOVING_INDEX_STRIDE + 2u];
        let chunk = index[k * MOVING_INDEX_STRIDE + 3u];
        let o = k * MOVING_STRIDE;
        let coef = table[o + 7u];
        let m = moving_term(k);
        for (var a = 0u; a < D; a++) {
            var pl = real(0.0);
            for (var c = 0u; c < D; c++) {
                pl += m.p[a * 3u + c] * table[o + 8u + c];
            }
            if (params.aux == 0u) {
                grad[node * D + a] += coef * m.r[a] - pl;
            }
            if (chunk == params.aux) {
                for (var c = 0u; c < D; c++) {
                    hvals[blk * D * D + a * D + c] += coef * m.p[a * 3u + c];
                }
            }
        }
    }
}

fn identity() -> vec4<real> {
    switch params.mode {
        case MODE_CCD: {
            return vec4<real>(real(1.0), real(NO_INDEX), real(NO_INDEX), real(0.0));
        }
        case MODE_MIN_DISTANCE: {
            return vec4<real>(scal[S_INF], real(NO_INDEX), real(NO_INDEX), real(0.0));
        }
        default: {
            return vec4<real>();
        }
    }
}

fn combine(a: vec4<real>, b: vec4<real>) -> vec4<real> {
    switch params.mode {
        case MODE_MAX_ABS: {
            return vec4<real>(max(a.x, b.x), a.y + b.y, real(0.0), real(0.0));
        }
        case MODE_CCD, MODE_MIN_DISTANCE: {
            // Values are never NaN here (NaN distances go to the third lane).
            var out = a;
            if (b.x < a.x || (b.x == a.x && b.y < a.y)) {
                out = b;
            }
            out.z = min(a.z, b.z);
            return out;
        }
        default: {
            return a + b;
        }
    }
}

// False for NaN only. Compared with the host's +∞ (a value the compiler cannot see):
// drivers fold `v != v` and `abs(v) >= 0` to constants where they assume no NaNs (Mesa
// does for SPIR-V without NaN-preserving float controls).
fn is_number(v: real) -> bool {
    return abs(v) <= scal[S_INF];
}

fn plane_distance(node: u32, j: u32) -> real {
    let o = S_PLANES + 4u * j;
    var s = real(0.0);
    for (var a = 0u; a < D; a++) {
        s += x[node * D + a] * scal[o + a];
    }
    return s - scal[o + 3u];
}

fn item(i: u32) -> vec4<real> {
    switch params.mode {
        case MODE_ENERGY: {
            var f = real(0.0);
            if (params.aux != 0u) {
                f = real(flags[i]);
            }
            return vec4<real>(src[i], f, real(0.0), real(0.0));
        }
        case MODE_DOT: {
            return vec4<real>(grad[i] * dx[i], real(0.0), real(0.0), real(0.0));
        }
        case MODE_MAX_ABS: {
            let a = abs(dx[i]);
            if (is_number(a)) {
                return vec4<real>(a, real(0.0), real(0.0), real(0.0));
            }
            return vec4<real>(real(0.0), real(1.0), real(0.0), real(0.0));
        }
        case MODE_CCD: {
            // α = fraction·d/(−n·Δx) of every approaching (node, plane), as Barrier::ccd.
            var best = identity();
            for (var j = 0u; j < params.aux; j++) {
                let o = S_PLANES + 4u * j;
                var rate = real(0.0);
                for (var a = 0u; a < D; a++) {
                    rate += dx[i * D + a] * scal[o + a];
                }
                if (rate < real(0.0)) {
                    let al = scal[S_FRACTION] * plane_distance(i, j) / -rate;
                    if (al < best.x) {
                        best = vec4<real>(al, real(i * params.aux + j), real(NO_INDEX), real(0.0));
                    }
                }
            }
            return best;
        }
        case MODE_MIN_DISTANCE: {
            var best = identity();
            for (var j = 0u; j < params.aux; j++) {
                let dist = plane_distance(i, j);
                let idx = real(i * params.aux + j);
                if (!is_number(dist)) {
                    best.z = min(best.z, idx);
                } else if (dist < best.x) {
                    best.x = dist;
                    best.y = idx;
                }
            }
            return best;
        }
        default: {
            // MODE_MOVING_ENERGY: ½ k m ‖r‖² − √m λ·r at the evaluation positions.
            let m = moving_term(i);
            let o = i * MOVING_STRIDE;
            var rr = real(0.0);
            var lr = real(0.0);
            for (var a = 0u; a < 3u; a++) {
                rr += m.r[a] * m.r[a];
                lr += table[o + 8u + a] * m.r[a];
            }
            return vec4<real>(real(0.5) * table[o + 7u] * rr - lr, real(0.0), real(0.0), real(0.0));
        }
    }
}

// Combines the workgroup's values by a fixed tree; the result is in wg_red[0].
fn workgroup_combine(lid: u32, val: vec4<real>) {
    wg_red[lid] = val;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            wg_red[lid] = combine(wg_red[lid], wg_red[lid + h]);
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(WG)
fn reduce(
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    var acc = identity();
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.count; i += grid_stride(nwg)) {
        acc = combine(acc, item(i));
    }
    workgroup_combine(lid.x, acc);
    if (lid.x == 0u) {
        partials[params.slot * group_count(nwg) + group_index(wid, nwg)] = wg_red[0];
    }
}

// One workgroup per slot, from params.slot on; params.count partials per slot.
@compute @workgroup_size(WG)
fn finish(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let slot = params.slot + group_index(wid, nwg);
    var acc = identity();
    for (var k = lid.x; k < params.count; k += WG) {
        acc = combine(acc, partials[slot * params.count + k]);
    }
    workgroup_combine(lid.x, acc);
    if (lid.x == 0u) {
        result[slot] = wg_red[0];
    }
}
