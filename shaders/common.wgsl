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
