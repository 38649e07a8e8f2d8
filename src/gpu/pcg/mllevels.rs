//! The multilevel preconditioner's levels on the device, as the V-cycle reads them
//! (`multilevel`) and the device setup writes them (`mlsetup`): each level's index arrays,
//! values and cluster inverses in buffers under the binding limit, with their parameters.

use crate::gpu::GpuError;
use std::ops::Range;

/// Workgroup size of the V-cycle's kernels.
pub(super) const WORKGROUP: u32 = 64;

/// Offsets of one level's arrays and the range of one smoothing dispatch (mirrors
/// `VcycleParams` in the WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct VcycleParams {
    pub(super) n: u32,
    pub(super) clusters: u32,
    pub(super) of_at: u32,
    pub(super) pos_at: u32,
    pub(super) ptr_at: u32,
    pub(super) items_at: u32,
    pub(super) inv_start_at: u32,
    pub(super) row_at: u32,
    pub(super) col_at: u32,
    pub(super) p_ptr_at: u32,
    pub(super) p_col_at: u32,
    pub(super) pt_ptr_at: u32,
    pub(super) pt_row_at: u32,
    pub(super) omega_at: u32,
    pub(super) a_at: u32,
    pub(super) p_at: u32,
    pub(super) pt_at: u32,
    pub(super) has_next: u32,
    pub(super) t_begin: u32,
    pub(super) t_end: u32,
    pub(super) inv_base: u32,
    pub(super) _pad: [u32; 3],
}
const _: () = assert!(std::mem::size_of::<VcycleParams>() == 96);

/// One buffer of cluster inverses: the clusters it holds, where its values start in the
/// level's inverses and its unknowns in cluster order (what its smoothing dispatch covers).
pub(super) struct InverseChunk {
    pub(super) clusters: Range<usize>,
    pub(super) base: usize,
    pub(super) unknowns: Range<usize>,
    /// Its values (its buffer may be padded beyond them).
    pub(super) len: usize,
    pub(super) buffer: wgpu::Buffer,
}

/// One level on the device.
pub(super) struct DeviceLevel {
    pub(super) n: usize,
    pub(super) clusters: usize,
    /// The index arrays and their offsets (`params`, also those of `vals`).
    pub(super) idx: wgpu::Buffer,
    pub(super) params: VcycleParams,
    /// ω, the matrix below the finest, P and Pᵀ (rewritten per system on the same
    /// hierarchy), and its length.
    pub(super) vals: wgpu::Buffer,
    pub(super) vals_len: usize,
    /// The cluster inverses in buffers of consecutive clusters (one storage binding caps
    /// each).
    pub(super) inverses: Vec<InverseChunk>,
    /// One bind group per inverse chunk (the kernels that do not smooth use the first).
    pub(super) groups: Vec<wgpu::BindGroup>,
    /// Kept alive with the bind groups: params, and below the finest b, x, ax.
    pub(super) _keep: Vec<wgpu::Buffer>,
}

/// The clusters of each buffer of inverses: runs of consecutive clusters whose values
/// (`inverses[c]` f64 each) stay within `limit` bytes; the error names the first cluster
/// whose inverse alone exceeds it.
pub(super) fn inverse_chunks(
    inverses: &[usize],
    limit: u64,
    level: usize,
) -> Result<Vec<Range<usize>>, GpuError> {
    let per = (limit / 8) as usize;
    let mut out = Vec::new();
    let (mut start, mut run) = (0, 0usize);
    for (c, &v) in inverses.iter().enumerate() {
        if v > per {
            return Err(GpuError::Unsupported(format!(
                "multilevel level {level}: cluster {c}'s inverse takes {} bytes, more than one \
                 storage binding ({limit} bytes)",
                8 * v
            )));
        }
        if run + v > per {
            out.push(start..c);
            (start, run) = (c, 0);
        }
        run += v;
    }
    out.push(start..inverses.len());
    Ok(out)
}

/// `x` as a u32 index of the device arrays, or the error that the levels exceed them.
pub(super) fn index(x: usize) -> Result<u32, GpuError> {
    u32::try_from(x).map_err(|_| {
        GpuError::Unsupported(
            "the multilevel preconditioner's arrays exceed the device's u32 indices".into(),
        )
    })
}

/// Where each cluster's inverse starts in its level's inverses (m² values for m = d·|c|
/// unknowns), and their total at the end: the layout the host's factors have too.
pub(super) fn inverse_starts(ptr: &[usize], d: usize) -> Vec<usize> {
    let mut start = Vec::with_capacity(ptr.len());
    let mut total = 0;
    start.push(0);
    for w in ptr.windows(2) {
        let m = (w[1] - w[0]) * d;
        total += m * m;
        start.push(total);
    }
    start
}
