//! The device PCG (shaders/pcg_*.wgsl): the eliminated system of
//! [`crate::core::elimination`] solved where its block matrix lies,
//!
//! ```text
//! Ĥ y = b̂,   Ĥ = P VᵀHV P + (I − P),   b̂ = −P Vᵀ g (or given),   Δx = V P y
//! ```
//!
//! for both users of the GPU: the device Newton loop, whose assembly leaves H and g in
//! device buffers ([`crate::gpu::blocks::BlockMatrix`]; a Newton step has no prescribed
//! part), and `solve --solver gpu`, which uploads H ([`crate::gpu::blocks::HostBlocks`])
//! and b̂ (with the lift of prescribed values in it) and recovers Δx on the host. H is
//! read in place: the product q = Ĥp is one invocation per block row, rotating only at
//! rotated nodes. CG scalars stay on the device: per iteration three dispatches (the
//! product with its p·q partials; α fused with the y/r/z update and its r·z and r·r
//! partials; β fused with the p update; five with the aggregates), many iterations per
//! submit, each chunk ending in its verification (the true residual once the recurrence
//! has met the tolerance, and Δx where it holds), and one small status read-back (the
//! scalars and flags, 336 bytes) per chunk. Every reduction has a fixed number of partials
//! and a fixed order: the same inputs give the same y bit for bit.
//!
//! The preconditioner is the multilevel V-cycle of [`crate::solve::multilevel`] (levels
//! built on the device from the H it holds, [`DeviceCg::set_multilevel_on_device`], or on
//! the host and uploaded, [`DeviceCg::set_multilevel`]; applied by shaders/vcycle.wgsl
//! between `update_yr` and `ml_dot`), or Jacobi or block Jacobi plus a coarse correction of
//! [`crate::solve::coarse`]: M⁻¹r = M_J⁻¹r + Z E⁺ Zᵀr, Z_i = P_i V_iᵀ. Why: a body that
//! can translate or slide has Ĥ's smallest eigenvalues on its translations (the mass
//! term), and a soft one on its smooth modes, which a point-wise preconditioner cannot see.
//! - [`crate::solve::coarse::CoarseSpace::Translations`]: `prepare` reduces E = ZᵀĤZ (D×D) on the device from
//!   the assembled blocks; the first `iterate` reads it back, pseudo-inverts it on the host
//!   as the CPU does ([`crate::solve::coarse::pseudo_inverse`]) and writes E⁺ back. In the
//!   iteration Zᵀr rides in the tree of r·z and r·r, and Z E⁺ Zᵀr is added where p is
//!   updated: no extra dispatch per iteration.
//! - [`crate::solve::coarse::CoarseSpace::Aggregates`] (the CPU loop's default, and so the device loop's): the
//!   translations of each aggregate of [`crate::solve::coarse::Aggregation`] on H's block
//!   pattern (frames built for them: [`DeviceCg::frames`], index arrays in
//!   [`aggregates`]). `prepare` sums E (K×K, K = D·aggregates) on
//!   the device in the CPU's order and forms E⁺ there too (`coarse_factor`: the
//!   operations of [`crate::solve::coarse::aggregates_einv_with_basis`], so the CPU CG's
//!   bits); only where E has a pivot that is not positive and finite does the first
//!   `iterate` read E back and write E⁺ from
//!   [`crate::solve::coarse::aggregates_einv_from_galerkin`]. Per iteration two more
//!   dispatches: w = Zᵀr (a workgroup per aggregate) and c = E⁺w.
//!
//! H's values may come in several buffers of consecutive block rows
//! ([`crate::gpu::blocks::ValuesChunk`]; one storage binding caps each). The kernels that read
//! them run once per chunk with a bind group built once per chunk and constraint set; a
//! reduction segment cut by a chunk's end carries each invocation's running sum to the
//! next chunk's dispatch, so Δx and the iteration count are the same bits however H is
//! split.
//!
//! Precision ([`Scalars`]): H, the frames' rotations and the CG vectors are in H's
//! precision (`real`: f64, or f32 for `solve --solver gpu --precision f32`), every sum and
//! scalar in f64 wherever the device has SHADER_F64 (`acc`). An f32 product may take the
//! difference form (the DIFF override): (H w)_i = Σ_j H_ij (w_j − w_i) + S_i w_i with
//! w = V P p in the world frame and S_i = Σ_j H_ij summed in f64 on the host
//! ([`crate::gpu::blocks::row_sums`]), each row summed in `acc`. Rounding H to f32 breaks
//! H·t = 0 for a rigid translation t by ε_f32‖H‖, which moves a free body's smallest
//! eigenvalues (its mass term) by κ·ε_f32; in this form a translation still maps to S t,
//! at rotated nodes too.
//!
//! Reductions are segmented ([`crate::gpu::SegmentPolicy`]): one partial per segment of
//! consecutive nodes, whatever number of workgroups the device's policy launches (one per
//! segment on a GPU, so the product and the updates run an invocation per node), then one
//! workgroup sums the partials in a fixed order: the same bits on any workgroup count.

pub mod aggregates;
mod cg;
mod coarse_factor;
mod frame_layout;
mod host;
mod mllevels;
mod mlsetup;
mod multilevel;
mod policy;
pub mod refine;
mod solver;

pub use cg::{
    DeviceCg, DeviceCgInfo, DeviceCgParams, DeviceFrames, DispatchRecord, IterationProfile,
    Scalars, SegmentEnd, SegmentInfo, SegmentStart, Tail, Watch, LANCZOS_HIST, PCG_COARSE,
    PCG_PRODUCT, PCG_UPDATE,
};
pub use frame_layout::frame_words;
pub use mlsetup::multilevel_setup_bytes;
pub use multilevel::{multilevel_bytes, LevelValues};
pub use solver::PcgSolver;
