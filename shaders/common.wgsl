// Declarations every stickslip kernel shares, prepended by `gpu::kernels::prelude` after
// the scalar-type aliases and the shared constants (the slots of `scal`, `state` and the
// partial sums, COL_BITS, NO_ROTATION, ...: `gpu::kernels::SHARED`). WGSL has no include,
// so this is the one copy.

// Uniform parameters of every kernel; mirrors `Params` in src/gpu/solver/builder.rs
// (four u32, 16 bytes, size-asserted there).
struct Params {
    n_nodes: u32,
    n_rot: u32,
    n_partials: u32,
    n_blocks: u32,
}

// Workgroup size: a power of two, at most WG_MAX, set per pipeline.
override WG: u32 = 64u;

// The workgroup reduction of every kernel: up to five sums at once share one tree (on CPU
// adapters each level's barrier costs more than its adds, so fused sums beat separate
// trees). Sum c of invocation i lives at wg_sum[c * WG + i]: each sum is contiguous.
// SUM_LANES, set per pipeline, is the most sums one call of the kernel carries: the tree's
// memory is sized to it, because workgroup memory costs time whether it is used or not
// (zero-initialized per workgroup; five lanes where two suffice cost lavapipe 20% more
// instructions per CG iteration).
override SUM_LANES: u32 = 5u;
override WG_SUM_LEN: u32 = SUM_LANES * WG;
var<workgroup> wg_sum: array<acc, WG_SUM_LEN>;
var<workgroup> wg_sums: array<acc, 5>;

// Sums the first `n` entries of every invocation's `v` over the workgroup, in a fixed
// order (deterministic). Sum c is left in wg_sum[c * WG] for every invocation to read
// (the tree ends on a barrier). Every invocation calls it, in uniform control flow, with
// the same constant n (1 to SUM_LANES). Straight-line code, one guarded statement per sum: the
// guards fold away on the constant n, with no loop to unroll and no dynamic indexing.
fn workgroup_sum(lid: u32, v: array<acc, 5>, n: u32) {
    wg_sum[lid] = v[0];
    if (n > 1u) {
        wg_sum[WG + lid] = v[1];
    }
    if (n > 2u) {
        wg_sum[2u * WG + lid] = v[2];
    }
    if (n > 3u) {
        wg_sum[3u * WG + lid] = v[3];
    }
    if (n > 4u) {
        wg_sum[4u * WG + lid] = v[4];
    }
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            wg_sum[lid] += wg_sum[lid + h];
            if (n > 1u) {
                wg_sum[WG + lid] += wg_sum[WG + lid + h];
            }
            if (n > 2u) {
                wg_sum[2u * WG + lid] += wg_sum[2u * WG + lid + h];
            }
            if (n > 3u) {
                wg_sum[3u * WG + lid] += wg_sum[3u * WG + lid + h];
            }
            if (n > 4u) {
                wg_sum[4u * WG + lid] += wg_sum[4u * WG + lid + h];
            }
        }
        workgroupBarrier();
    }
}

// workgroup_sum of one value, returned as a uniform value (one that later barriers may
// depend on).
fn workgroup_sum_uniform1(lid: u32, s: acc) -> acc {
    workgroup_sum(lid, sum1(s), 1u);
    return workgroupUniformLoad(&wg_sum[0]);
}

// workgroup_sum, with the sums returned as uniform values; entries from n on are
// unspecified.
fn workgroup_sum_uniform(lid: u32, v: array<acc, 5>, n: u32) -> array<acc, 5> {
    workgroup_sum(lid, v, n);
    if (lid == 0u) {
        for (var c = 0u; c < n; c++) {
            wg_sums[c] = wg_sum[c * WG];
        }
    }
    return workgroupUniformLoad(&wg_sums);
}

// One value as the first entry of workgroup_sum's operand.
fn sum1(s: acc) -> array<acc, 5> {
    return array<acc, 5>(s, acc(0.0), acc(0.0), acc(0.0), acc(0.0));
}
