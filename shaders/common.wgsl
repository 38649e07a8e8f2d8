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

// The workgroup reduction of every kernel. Up to five sums at once (a vec4 and a
// scalar) share one tree: on CPU adapters each level's barrier costs more than its adds
// (llvmpipe runs barriers as coroutine switches), so fused sums are cheaper than trees.
var<workgroup> wg_sum4: array<vec4<acc>, WG>;
var<workgroup> wg_sum1: array<acc, WG>;

// Sums every invocation's (v, w) over the workgroup, in a fixed order (deterministic).
// The sums are left in wg_sum4[0] and wg_sum1[0] for every invocation to read (the tree
// ends on a barrier). Every invocation calls it, in uniform control flow.
fn workgroup_sum(lid: u32, v: vec4<acc>, w: acc) {
    wg_sum4[lid] = v;
    wg_sum1[lid] = w;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            wg_sum4[lid] += wg_sum4[lid + h];
            wg_sum1[lid] += wg_sum1[lid + h];
        }
        workgroupBarrier();
    }
}

// The workgroup sum of a scalar, as a uniform value (one that later barriers may depend on).
fn workgroup_sum_uniform(lid: u32, s: acc) -> acc {
    workgroup_sum(lid, vec4<acc>(acc(0.0)), s);
    return workgroupUniformLoad(&wg_sum1[0]);
}
