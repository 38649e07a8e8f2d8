// Declarations every stickslip kernel shares, prepended by `gpu::kernels::prelude` after
// the scalar-type aliases and the shared constants (the slots of `scal`, `state` and the
// partial sums, NO_ROTATION, ...: `gpu::kernels::SHARED`). WGSL has no include,
// so this is the one copy.

// Workgroup size: a power of two, set per pipeline.
override WG: u32 = 64u;

// The workgroup reduction of every kernel: up to five sums at once share one tree (on CPU
// adapters each level's barrier costs more than its adds, so fused sums beat separate
// trees). Sums 0..3 of invocation i are the components of wg_sum[i], the fifth (only the
// coarse correction's fused reduction in 3D has one) is wg_sum5[i]. SUM_LANES, set per
// pipeline, is the most sums one call in the kernel carries; wg_sum5 has one entry unless
// it is 5, because workgroup memory costs time whether it is used or not (it is
// zero-initialized per workgroup).
override SUM_LANES: u32 = 5u;
override WG_SUM5_LEN: u32 = max(1u, SUM_LANES / 5u * WG);
var<workgroup> wg_sum: array<vec4<acc>, WG>;
var<workgroup> wg_sum5: array<acc, WG_SUM5_LEN>;
var<workgroup> wg_sums: array<acc, 5>;

// Sums the first `n` entries of every invocation's `v` over the workgroup, in a fixed
// order (deterministic); `summed(c)` then reads sum c in every invocation (the tree ends
// on a barrier). Every invocation calls it, in uniform control flow, with the same
// constant n (1 to SUM_LANES): the branches on n fold away. One sum moves one component
// per level, more move the whole vec4 (one address for all of them).
fn workgroup_sum(lid: u32, v: array<acc, 5>, n: u32) {
    if (n == 1u) {
        wg_sum[lid].x = v[0];
    } else {
        wg_sum[lid] = vec4<acc>(v[0], v[1], v[2], v[3]);
    }
    if (n > 4u) {
        wg_sum5[lid] = v[4];
    }
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            if (n == 1u) {
                wg_sum[lid].x += wg_sum[lid + h].x;
            } else {
                wg_sum[lid] += wg_sum[lid + h];
            }
            if (n > 4u) {
                wg_sum5[lid] += wg_sum5[lid + h];
            }
        }
        workgroupBarrier();
    }
}

// Sum c of the last workgroup_sum.
fn summed(c: u32) -> acc {
    if (c < 4u) {
        return wg_sum[0][c];
    }
    return wg_sum5[0];
}

// workgroup_sum of one value, returned as a uniform value (one that later barriers may
// depend on).
fn workgroup_sum_uniform1(lid: u32, s: acc) -> acc {
    workgroup_sum(lid, sum1(s), 1u);
    return workgroupUniformLoad(&wg_sum[0]).x;
}

// workgroup_sum, with the sums returned as uniform values; entries from n on are
// unspecified.
fn workgroup_sum_uniform(lid: u32, v: array<acc, 5>, n: u32) -> array<acc, 5> {
    workgroup_sum(lid, v, n);
    if (lid == 0u) {
        for (var c = 0u; c < n; c++) {
            wg_sums[c] = summed(c);
        }
    }
    return workgroupUniformLoad(&wg_sums);
}

// One value as the first entry of workgroup_sum's operand.
fn sum1(s: acc) -> array<acc, 5> {
    return array<acc, 5>(s, acc(0.0), acc(0.0), acc(0.0), acc(0.0));
}

// Launch geometry (src/gpu/launch.rs): a dispatch is (x, y, 1) workgroups, x and y each
// within the adapter's per-dimension limit. An invocation's linear index and the
// grid-stride step of per-item loops; a workgroup's linear index and the workgroup count
// (reductions: one partial per workgroup, dispatched with exactly that many).
fn grid_index(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * (nwg.x * WG);
}
fn grid_stride(nwg: vec3<u32>) -> u32 {
    return nwg.x * nwg.y * WG;
}
fn group_index(wid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wid.x + wid.y * nwg.x;
}
fn group_count(nwg: vec3<u32>) -> u32 {
    return nwg.x * nwg.y;
}

// The one block-Jacobi specification of every device CG (src/solve/precond.rs,
// `jacobi_inverse` and `block_jacobi_inverse`, does the same operations in the same order
// on the CPU). Jacobi: 1/v where the diagonal entry v is positive and finite, else 1.
// Block Jacobi: B⁻¹ through the Cholesky factor when every pivot is positive and finite,
// else the Jacobi diagonal (B is not SPD where H is indefinite: CG then meets the negative
// curvature itself rather than through the preconditioner).
fn positive_finite(v: real) -> bool {
    return v > real(0.0) && real(1.0) / v > real(0.0);
}

fn jacobi_inverse(v: real) -> real {
    return select(real(1.0), real(1.0) / v, positive_finite(v));
}

// B⁻¹ of the d×d block `h` (row-major in the first d² entries; the rest is zero).
fn block_jacobi_inverse(h: array<real, 9>, d: u32) -> array<real, 9> {
    var out: array<real, 9>;
    for (var e = 0u; e < 9u; e++) {
        out[e] = real(0.0);
    }
    // h = L Lᵀ.
    var l: array<real, 9>;
    for (var e = 0u; e < 9u; e++) {
        l[e] = real(0.0);
    }
    for (var j = 0u; j < d; j++) {
        var s = h[j * d + j];
        for (var m = 0u; m < j; m++) {
            s -= l[j * d + m] * l[j * d + m];
        }
        if (!positive_finite(s)) {
            for (var a = 0u; a < d; a++) {
                out[a * d + a] = jacobi_inverse(h[a * d + a]);
            }
            return out;
        }
        let ljj = sqrt(s);
        l[j * d + j] = ljj;
        for (var a = j + 1u; a < d; a++) {
            var t = h[a * d + j];
            for (var m = 0u; m < j; m++) {
                t -= l[a * d + m] * l[j * d + m];
            }
            l[a * d + j] = t / ljj;
        }
    }
    // Column c of h⁻¹: L u = e_c, then Lᵀ x = u.
    for (var c = 0u; c < d; c++) {
        var u: array<real, 3>;
        for (var a = 0u; a < d; a++) {
            var s = select(real(0.0), real(1.0), a == c);
            for (var m = 0u; m < a; m++) {
                s -= l[a * d + m] * u[m];
            }
            u[a] = s / l[a * d + a];
        }
        for (var aa = 0u; aa < d; aa++) {
            let a = d - 1u - aa;
            var s = u[a];
            for (var m = a + 1u; m < d; m++) {
                s -= l[m * d + a] * u[m];
            }
            u[a] = s / l[a * d + a];
        }
        for (var a = 0u; a < d; a++) {
            out[a * d + c] = u[a];
        }
    }
    return out;
}

// Natural logarithm in `real` (Vulkan's log is f32-only): the element kernels' energies and
// the force balance's barrier forces.
const LN2_HI = 0.693147180369123816490;
const LN2_LO = 1.90821492927058770002e-10;
const SQRT2 = 1.41421356237309504880;

// 2 atanh(t) = ln((1 + t)/(1 − t)) for |t| ≤ 0.172, by its series to t^23 (the next term
// is below 2^-60 relative).
fn ln_series(t: real) -> real {
    let t2 = t * t;
    var p = real(1.0) / real(23.0);
    for (var k = 21; k >= 3; k -= 2) {
        p = p * t2 + real(1.0) / real(k);
    }
    return real(2.0) * t * (p * t2 + real(1.0));
}

// ln x for finite x > 0: x = 2^e m with m in [1/√2, √2] by exact power-of-two scaling,
// ln m = 2 atanh((m − 1)/(m + 1)), ln 2 split in two so that e·ln 2 keeps full precision.
fn ln(x: real) -> real {
    var m = x;
    var e = real(0.0);
    let big = real(4294967296.0);
    for (var i = 0; i < 40 && m > big; i++) {
        m = m / big;
        e += real(32.0);
    }
    for (var i = 0; i < 40 && m < real(1.0) / big; i++) {
        m = m * big;
        e -= real(32.0);
    }
    for (var i = 0; i < 40 && m > real(SQRT2); i++) {
        m = m * real(0.5);
        e += real(1.0);
    }
    for (var i = 0; i < 40 && m < real(0.5) * real(SQRT2); i++) {
        m = m * real(2.0);
        e -= real(1.0);
    }
    return e * real(LN2_HI) + (ln_series((m - real(1.0)) / (m + real(1.0))) + e * real(LN2_LO));
}

// The determinant and the cofactor matrix (∂det/∂F) of the d×d row-major matrix in the
// first d² entries of f, d = 2 or 3: the neo-Hookean elements' J and ∂J/∂F, and the
// inversion bound's det(Ds + αΔDs) (src/sim/energy/neohookean.rs, `det` and `cofactor`).
fn det_of(f: array<real, 9>, d: u32) -> real {
    if (d == 2u) {
        return f[0] * f[3] - f[1] * f[2];
    }
    return f[0] * (f[4] * f[8] - f[5] * f[7]) - f[1] * (f[3] * f[8] - f[5] * f[6])
        + f[2] * (f[3] * f[7] - f[4] * f[6]);
}

fn cofactor_of(f: array<real, 9>, d: u32) -> array<real, 9> {
    var c = array<real, 9>();
    if (d == 2u) {
        c[0] = f[3];
        c[1] = -f[2];
        c[2] = -f[1];
        c[3] = f[0];
        return c;
    }
    for (var i = 0u; i < 3u; i++) {
        for (var j = 0u; j < 3u; j++) {
            let i1 = (i + 1u) % 3u;
            let i2 = (i + 2u) % 3u;
            let j1 = (j + 1u) % 3u;
            let j2 = (j + 2u) % 3u;
            c[i * 3u + j] = f[i1 * 3u + j1] * f[i2 * 3u + j2] - f[i1 * 3u + j2] * f[i2 * 3u + j1];
        }
    }
    return c;
}
