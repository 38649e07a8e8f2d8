//! WGSL sources and the scalar-type prelude.
//!
//! WGSL `override` constants specialize values (block size D, workgroup size, masking,
//! preconditioner kind) but cannot change types, so the scalar types come from a one-line
//! alias prelude: `real` (vector and matrix storage) and `acc` (reduction accumulators,
//! f64 wherever the device has SHADER_F64), followed by the declarations every kernel
//! shares (shaders/common.wgsl: the `Params` uniform and `WG_MAX`).

/// Shared declarations, prepended to every kernel by [`prelude`].
pub const COMMON: &str = include_str!("../../shaders/common.wgsl");
pub const MATVEC: &str = include_str!("../../shaders/matvec.wgsl");
pub const ROTATE_BLOCKS: &str = include_str!("../../shaders/rotate_blocks.wgsl");
pub const PRECOND: &str = include_str!("../../shaders/precond.wgsl");
pub const CG: &str = include_str!("../../shaders/cg.wgsl");
pub const COARSE: &str = include_str!("../../shaders/coarse.wgsl");
pub const REFINE: &str = include_str!("../../shaders/refine.wgsl");
pub const SPRINGS: &str = include_str!("../../shaders/springs.wgsl");

/// The (real, acc, packed) triples the solver instantiates; `packed` is f32 blocks read
/// as u64 pairs (see [`prelude`]).
pub const PRELUDES: [(&str, &str, bool); 5] = [
    ("f32", "f64", false),
    ("f32", "f32", false),
    ("f32", "f64", true),
    ("f32", "f32", true),
    ("f64", "f64", false),
];

/// The prelude of a kernel instance: the scalar-type aliases, the block-load type
/// `blk4` with its `unpack4`, and the shared declarations.
///
/// `packed` (f32 only, needs SHADER_INT64) reads four f32 block entries as two u64:
/// the bytes are the same as a `vec4<f32>`, so no writer changes. Why: llvmpipe
/// (lavapipe) loads a storage vector one component at a time in a loop over the SIMD
/// lanes, whatever the component's width, so halving the components read per block
/// is what makes an f32 matvec cheaper than an f64 one there; on a GPU both are one
/// 16-byte load.
pub fn prelude(real: &str, acc: &str, packed: bool) -> String {
    let blk = if packed {
        "alias blk4 = vec2<u64>;\n\
         fn unpack4(v: vec2<u64>) -> vec4<f32> {\n\
         \x20   return bitcast<vec4<f32>>(vec4<u32>(u32(v.x), u32(v.x >> 32u), u32(v.y), u32(v.y >> 32u)));\n\
         }\n"
            .to_string()
    } else {
        format!("alias blk4 = vec4<{real}>;\nfn unpack4(v: vec4<{real}>) -> vec4<{real}> {{ return v; }}\n")
    };
    format!("alias real = {real};\nalias acc = {acc};\n{blk}{COMMON}\n")
}
