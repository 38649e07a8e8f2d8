//! A constraint set as the device's kernels read it: two u32 words per node (its mask,
//! then its rotation's index or NO_ROTATION; `frame` in shaders/pcg_common.wgsl and
//! shaders/newton_checks.wgsl), shared by the PCG and the Newton loop's checks.

use crate::core::constraints::{Frames, NO_ROTATION};
use crate::gpu::GpuError;

/// The frame words of the device's kernels (per node its mask, then its rotation's index
/// or NO_ROTATION), after checking that the arrays of `f` agree with its node count and
/// that every rotation index names a rotation.
pub fn frame_words(f: &Frames) -> Result<Vec<u32>, GpuError> {
    let (n, d) = (f.n_nodes, f.dim);
    if f.mask.len() != n || f.rot_index.len() != n || f.rotations.len() != d * d * f.rot_nodes.len()
    {
        return Err(GpuError::Mismatch(
            "the constraint frames' arrays disagree with their node count".into(),
        ));
    }
    let mut words = Vec::with_capacity(2 * n);
    for i in 0..n {
        let ri = f.rot_index[i];
        if ri != NO_ROTATION && ri as usize >= f.rot_nodes.len() {
            return Err(GpuError::Mismatch(format!(
                "node {i} names rotation {ri} of {}",
                f.rot_nodes.len()
            )));
        }
        words.extend_from_slice(&[f.mask[i] as u32, ri]);
    }
    Ok(words)
}
