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
pub const ROTATE: &str = include_str!("../../shaders/rotate.wgsl");
pub const ROTATE_BLOCKS: &str = include_str!("../../shaders/rotate_blocks.wgsl");
pub const PRECOND: &str = include_str!("../../shaders/precond.wgsl");
pub const CG: &str = include_str!("../../shaders/cg.wgsl");
pub const RECOVER: &str = include_str!("../../shaders/recover.wgsl");
pub const REFINE: &str = include_str!("../../shaders/refine.wgsl");
pub const SPRINGS: &str = include_str!("../../shaders/springs.wgsl");

/// The (real, acc) pairs the solver instantiates.
pub const PRELUDES: [(&str, &str); 3] = [("f32", "f64"), ("f32", "f32"), ("f64", "f64")];

/// The prelude of a kernel instance: the scalar-type aliases and the shared declarations.
pub fn prelude(real: &str, acc: &str) -> String {
    format!("alias real = {real};\nalias acc = {acc};\n{COMMON}\n")
}
