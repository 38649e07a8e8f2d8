// Declarations every stickslip kernel shares, prepended by `gpu::kernels::prelude`
// after the scalar-type aliases. WGSL has no include, so this is the one copy.

// Uniform parameters of every kernel; mirrors `Params` in src/gpu/solver/mod.rs
// (four u32, 16 bytes, size-asserted there).
struct Params {
    n_nodes: u32,
    n_rot: u32,
    n_partials: u32,
    n_blocks: u32,
}

// Upper bound of the workgroup size (the `WG` override), for workgroup arrays.
const WG_MAX: u32 = 256u;
