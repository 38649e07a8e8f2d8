// The device Newton loop's per-iteration checks reduced to scalars (src/sim/device/checks.rs),
// each the host's computation operation by operation:
//
// - reduce, MODE_INVERSION: per classical neo-Hookean element of one chunk, det(Ds + αΔDs)
//   as a polynomial in α and its first root in (0, max] (`det_polynomial` and `first_root`
//   of src/sim/energy/neohookean.rs); the smallest root with its element, and the first
//   element with c₀ ≤ 0 (or NaN) with its J.
// - sizes_init, sizes_add: per node the sizes of its potential forces, m‖g‖ + Σ_e ‖∇_iΨ_e‖,
//   one element chunk per sizes_add in element order, through the assembly's node gather
//   lists (`Model::add_potential_force_scale`).
// - reduce, MODE_BALANCE: per node ‖P_i V_iᵀ ∇_iE‖ (the first largest, with its node), the
//   node's force scale h²(sizes + Σ_planes |∇B|) + ‖m(x − x̃)‖ and max_a |x_ia|
//   (`force_balance_of` in src/sim/integrator/balance.rs).
// - finish: one workgroup combines a reduction's partials into its result slot.
//
// `reduce` runs a fixed number of workgroups, each writing one partial; every combine is a
// minimum, a maximum or a comparison, which round nothing, so a result does not depend on
// the workgroups or the tree. Ties go to the smaller index, as the host's first strict
// minimum or maximum; NaN never wins a maximum, as in `f64::max`.

override D: u32 = 3u;
// WG (the workgroup size) comes with the prelude (shaders/common.wgsl).

// Mirrors `CheckParams` in src/sim/device/checks.rs (eight u32, 32 bytes, size-asserted there).
struct CheckParams {
    // Items of the dispatch (elements of the chunk, nodes; finish: partials).
    count: u32,
    // What the reduction combines (MODE_*).
    mode: u32,
    // finish: the result slot.
    slot: u32,
    // reduce: the row of partials it writes (one per workgroup); finish: the first partial
    // it combines.
    row: u32,
    // inversion_reduce: the global element index (over every element set) of item 0.
    first: u32,
    // balance_reduce: the half-spaces in `consts`.
    n_planes: u32,
    _pad0: u32,
    _pad1: u32,
}

const MODE_INVERSION: u32 = 0u;
const MODE_BALANCE: u32 = 1u;

// Slots of `scal`.
const S_MAX: u32 = 0u;
const S_H2: u32 = 1u;
const S_GNORM: u32 = 2u;
const S_INF: u32 = 3u;

// Reals per neo-Hookean element of `rest` (Dm⁻¹ D×D, volume, μ, λ, law) after the D² of Dm⁻¹.
const REST_EXTRA: u32 = 4u;
// Reals per half-space in `consts` after the three of gravity.
const PLANE_STRIDE: u32 = 6u;
// Bisection steps of first_root: from (0, max] down to two adjacent floats takes at most
// about 1,100 (the exponent range and the mantissa); the cap only guards a driver whose
// arithmetic would never make the bracket adjacent.
const MAX_BISECTIONS: u32 = 4096u;

// No index: larger than every element or node index (exact in f32 and f64).
const NO_INDEX: f32 = 4503599627370496.0;

@group(0) @binding(0) var<uniform> params: CheckParams;
@group(0) @binding(1) var<storage, read> scal: array<real>;
// The element terms' constants: gravity (3), then per half-space normal xyz, offset, d̂, κ.
@group(0) @binding(2) var<storage, read> consts: array<real>;
// Per node (lumped mass, contact weight).
@group(0) @binding(3) var<storage, read> node_data: array<real>;
// The accepted iterate x, the inertia target x̃, the direction Δx, the assembled ∇E.
@group(0) @binding(4) var<storage, read> x: array<real>;
@group(0) @binding(5) var<storage, read> xt: array<real>;
@group(0) @binding(6) var<storage, read> dx: array<real>;
@group(0) @binding(7) var<storage, read> grad: array<real>;
// One element chunk: its node indices, rest data and per-element gradients.
@group(0) @binding(8) var<storage, read> nodes: array<u32>;
@group(0) @binding(9) var<storage, read> rest: array<real>;
@group(0) @binding(10) var<storage, read> egrad: array<real>;
// The chunk's node gather lists into `egrad` (src/sim/device/assembly.rs, `NodeGather`).
@group(0) @binding(11) var<storage, read> offsets: array<u32>;
@group(0) @binding(12) var<storage, read> entries: array<u32>;
// The constraint set: per node (mask, rotation index), and the rotations V_i row-major.
@group(0) @binding(13) var<storage, read> frame: array<u32>;
@group(0) @binding(14) var<storage, read> rotations: array<real>;
// Per node: the sizes of its potential forces (unscaled).
@group(0) @binding(15) var<storage, read_write> sizes: array<real>;
@group(0) @binding(16) var<storage, read_write> partials: array<vec4<real>>;
// The loop's scalar results (src/sim/device/newton_ops/mod.rs), one vec4 per slot.
@group(0) @binding(17) var<storage, read_write> result: array<vec4<real>>;

var<workgroup> wg_red: array<vec4<real>, WG>;

// False for NaN only, against the host's +∞ (drivers fold `v != v` where they assume no NaN).
fn is_number(v: real) -> bool {
    return abs(v) <= scal[S_INF];
}

// Σ_k p[k]·q[k] over the D² entries, in order.
fn contract(p: array<real, 9>, q: array<real, 9>) -> real {
    var s = p[0] * q[0];
    for (var k = 1u; k < D * D; k++) {
        s += p[k] * q[k];
    }
    return s;
}

// det(A + αB) = c0 + c1 α + c2 α² + c3 α³ (D = 2: c3 = 0), as `det_polynomial`.
fn det_polynomial(a: array<real, 9>, b: array<real, 9>) -> array<real, 4> {
    let c1 = contract(cofactor_of(a, D), b);
    if (D == 2u) {
        return array<real, 4>(det_of(a, D), c1, det_of(b, D), real(0.0));
    }
    let c2 = contract(cofactor_of(b, D), a);
    return array<real, 4>(det_of(a, D), c1, c2, det_of(b, D));
}

fn poly(c: array<real, 4>, t: real) -> real {
    return ((c[3] * t + c[2]) * t + c[1]) * t + c[0];
}

// Rust's f64::signum for a number: ±1 by the sign bit, −0 included.
fn signum(v: real) -> real {
    if (v > real(0.0)) {
        return real(1.0);
    }
    if (v < real(0.0)) {
        return real(-1.0);
    }
    return select(real(1.0), real(-1.0), real(1.0) / v < real(0.0));
}

// The real roots of a t² + b t + c, as `quadratic_roots`: `n` of them in `r`, in its order.
struct Roots {
    n: u32,
    r: array<real, 2>,
}

fn quadratic_roots(a: real, b: real, c: real) -> Roots {
    var out: Roots;
    out.n = 0u;
    if (a == real(0.0)) {
        if (b != real(0.0)) {
            out.n = 1u;
            out.r[0] = -c / b;
        }
        return out;
    }
    let disc = b * b - real(4.0) * a * c;
    if (!is_number(disc) || disc < real(0.0)) {
        return out;
    }
    let q = real(-0.5) * (b + signum(b) * sqrt(disc));
    if (q == real(0.0)) {
        out.n = 1u;
        out.r[0] = real(0.0);
        return out;
    }
    out.n = 2u;
    out.r[0] = q / a;
    out.r[1] = c / q;
    return out;
}

struct Root {
    found: bool,
    r: real,
}

// The smallest root in (0, max] of the cubic c with c0 > 0, as `first_root`: the critical
// points cut (0, max] into monotone pieces, the first piece whose right end has p ≤ 0 is
// bisected until its bracket is two adjacent floats, and the right one is the root.
fn first_root(c: array<real, 4>, maxv: real) -> Root {
    var cuts = array<real, 3>(maxv, maxv, maxv);
    var n = 0u;
    var crit = quadratic_roots(real(3.0) * c[3], real(2.0) * c[2], c[1]);
    for (var k = 0u; k < crit.n; k++) {
        let r = crit.r[k];
        if (r > real(0.0) && r < maxv) {
            cuts[n] = r;
            n++;
        }
    }
    if (n == 2u && cuts[1] < cuts[0]) {
        let t = cuts[0];
        cuts[0] = cuts[1];
        cuts[1] = t;
    }
    cuts[n] = maxv;
    var lo = real(0.0);
    for (var k = 0u; k <= n; k++) {
        let end = cuts[k];
        if (poly(c, end) <= real(0.0)) {
            var hi = end;
            for (var it = 0u; it < MAX_BISECTIONS; it++) {
                let mid = real(0.5) * (lo + hi);
                if (mid <= lo || mid >= hi) {
                    break;
                }
                if (poly(c, mid) > real(0.0)) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return Root(true, hi);
        }
        lo = end;
    }
    return Root(false, real(0.0));
}

fn identity() -> vec4<real> {
    if (params.mode == MODE_INVERSION) {
        return vec4<real>(scal[S_INF], real(NO_INDEX), real(NO_INDEX), real(0.0));
    }
    return vec4<real>(real(0.0), real(NO_INDEX), real(0.0), real(0.0));
}

fn combine(a: vec4<real>, b: vec4<real>) -> vec4<real> {
    var out = a;
    if (params.mode == MODE_INVERSION) {
        // (smallest root, its element), (first inverted element, its J).
        if (b.x < a.x || (b.x == a.x && b.y < a.y)) {
            out.x = b.x;
            out.y = b.y;
        }
        if (b.z < a.z) {
            out.z = b.z;
            out.w = b.w;
        }
    } else {
        // (largest residual, its node), largest scale, largest |x|: NaN never wins.
        if (b.x > a.x || (b.x == a.x && b.y < a.y)) {
            out.x = b.x;
            out.y = b.y;
        }
        if (b.z > a.z) {
            out.z = b.z;
        }
        if (b.w > a.w) {
            out.w = b.w;
        }
    }
    return out;
}

// Element e of the chunk: (root, element) or (first inverted element, J), as
// `NeoHookean::inversion_bound`.
fn inversion_item(e: u32) -> vec4<real> {
    var a = array<real, 9>();
    var b = array<real, 9>();
    let base = e * (D + 1u);
    let n0 = nodes[base];
    for (var k = 1u; k <= D; k++) {
        let nk = nodes[base + k];
        for (var i = 0u; i < D; i++) {
            a[i * D + k - 1u] = x[nk * D + i] - x[n0 * D + i];
            b[i * D + k - 1u] = dx[nk * D + i] - dx[n0 * D + i];
        }
    }
    let c = det_polynomial(a, b);
    let idx = real(params.first + e);
    if (!is_number(c[0]) || c[0] <= real(0.0)) {
        let factor = select(real(6.0), real(2.0), D == 2u);
        let volume = rest[e * (D * D + REST_EXTRA) + D * D];
        return vec4<real>(scal[S_INF], real(NO_INDEX), idx, c[0] / (factor * volume));
    }
    let root = first_root(c, scal[S_MAX]);
    if (root.found) {
        return vec4<real>(root.r, idx, real(NO_INDEX), real(0.0));
    }
    return identity();
}

fn norm3(v: array<real, 3>) -> real {
    var s = v[0] * v[0];
    for (var a = 1u; a < D; a++) {
        s += v[a] * v[a];
    }
    return sqrt(s);
}

// Node i: (‖P V_iᵀ ∇_iE‖ or 0, i or NO_INDEX, force scale, max |x_ia|).
fn balance_item(i: u32) -> vec4<real> {
    var g = array<real, 3>();
    for (var a = 0u; a < D; a++) {
        g[a] = grad[i * D + a];
    }
    var y = g;
    let ri = frame[2u * i + 1u];
    if (ri != NO_ROTATION) {
        for (var c = 0u; c < D; c++) {
            var s = real(0.0);
            for (var k = 0u; k < D; k++) {
                s += rotations[ri * D * D + k * D + c] * g[k];
            }
            y[c] = s;
        }
    }
    let mask = frame[2u * i];
    for (var a = 0u; a < D; a++) {
        if ((mask & (1u << a)) != 0u) {
            y[a] = real(0.0);
        }
    }
    let r = norm3(y);
    let h2 = scal[S_H2];
    var o = h2 * sizes[i];
    let w = node_data[2u * i + 1u];
    if (w > real(0.0)) {
        for (var j = 0u; j < params.n_planes; j++) {
            let p = 3u + PLANE_STRIDE * j;
            var dist = x[i * D] * consts[p];
            for (var a = 1u; a < D; a++) {
                dist += x[i * D + a] * consts[p + a];
            }
            dist -= consts[p + 3u];
            let dhat = consts[p + 4u];
            let kappa = consts[p + 5u];
            if (dist < dhat) {
                // b'(d) of `barrier::scalar`; −∞ where the node touches or crosses.
                var gb = -scal[S_INF];
                if (dist > real(0.0)) {
                    let s = dist / dhat;
                    gb = real(0.5) * kappa * (ln(s) + real(1.0) - real(1.0) / s);
                }
                o += h2 * abs(w * gb);
            }
        }
    }
    let m = node_data[2u * i];
    var inertia = array<real, 3>();
    var xmax = real(0.0);
    for (var a = 0u; a < D; a++) {
        inertia[a] = m * (x[i * D + a] - xt[i * D + a]);
        let v = abs(x[i * D + a]);
        if (v > xmax) {
            xmax = v;
        }
    }
    let scale = o + norm3(inertia);
    if (r > real(0.0)) {
        return vec4<real>(r, real(i), scale, xmax);
    }
    return vec4<real>(real(0.0), real(NO_INDEX), scale, xmax);
}

@compute @workgroup_size(WG)
fn sizes_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        sizes[i] = node_data[2u * i] * scal[S_GNORM];
    }
}

// Continues every node's sum with the elements of one chunk (chunks run in order).
@compute @workgroup_size(WG)
fn sizes_add(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        var s = sizes[i];
        for (var k = offsets[i]; k < offsets[i + 1u]; k++) {
            let o = entries[k];
            var q = egrad[o] * egrad[o];
            for (var c = 1u; c < D; c++) {
                q += egrad[o + c] * egrad[o + c];
            }
            s += sqrt(q);
        }
        sizes[i] = s;
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

fn item(i: u32) -> vec4<real> {
    if (params.mode == MODE_INVERSION) {
        return inversion_item(i);
    }
    return balance_item(i);
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
        partials[params.row * group_count(nwg) + group_index(wid, nwg)] = wg_red[0];
    }
}

// One workgroup: params.count partials from params.row on into result[params.slot].
@compute @workgroup_size(WG)
fn finish(@builtin(local_invocation_id) lid: vec3<u32>) {
    var acc = identity();
    for (var k = lid.x; k < params.count; k += WG) {
        acc = combine(acc, partials[params.row + k]);
    }
    workgroup_combine(lid.x, acc);
    if (lid.x == 0u) {
        result[params.slot] = wg_red[0];
    }
}
