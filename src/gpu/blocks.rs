//! A block matrix on the device as the PCG reads it ([`crate::gpu::pcg`]): block CSR
//! (both triangles, row-major d×d blocks, the CPU's [`BlockCsr`] order) whose values lie in
//! one or more buffers of consecutive block rows ([`ValuesChunk`]), because one storage
//! binding caps a buffer's size. The device assembly of the Newton loop writes its blocks
//! into such chunks; [`HostBlocks`] uploads a host [`BlockCsr`] into the same layout.

use super::kernels::Real;
use super::{GpuContext, GpuError};
use crate::core::sparse::BlockCsr;

/// One buffer of block values: the blocks of consecutive block rows.
#[derive(Debug)]
pub struct ValuesChunk {
    /// Block rows (mesh nodes) whose blocks this buffer holds.
    pub rows: std::ops::Range<usize>,
    /// Global block indices (the pattern's order) of its blocks; block k is at
    /// (k − blocks.start)·d² in the buffer.
    pub blocks: std::ops::Range<usize>,
    /// The values, row-major d×d per block.
    pub buffer: wgpu::Buffer,
}

/// A run of consecutive block rows and the (global) blocks they hold.
pub type RowRun = (std::ops::Range<usize>, std::ops::Range<usize>);

/// Splits the block rows of `row_ptr` into runs of consecutive rows whose blocks
/// (`block_bytes` each) fit `limit` bytes once padded to 16: (rows, blocks) per run. A
/// row whose blocks alone exceed the limit is [`GpuError::BufferTooLarge`], named
/// "`what` of row i".
pub fn plan_rows(
    row_ptr: &[usize],
    block_bytes: u64,
    limit: u64,
    what: &str,
    adapter: &str,
) -> Result<Vec<RowRun>, GpuError> {
    let n = row_ptr.len().saturating_sub(1);
    let padded = |blocks: usize| (blocks as u64 * block_bytes).max(16).div_ceil(16) * 16;
    let mut out = Vec::new();
    let mut start = 0;
    for i in 0..n {
        if padded(row_ptr[i + 1] - row_ptr[i]) > limit {
            return Err(GpuError::BufferTooLarge {
                label: format!("{what} of row {i}"),
                bytes: padded(row_ptr[i + 1] - row_ptr[i]),
                limit,
                what: "storage binding",
                adapter: adapter.to_string(),
            });
        }
        if padded(row_ptr[i + 1] - row_ptr[start]) > limit {
            out.push((start..i, row_ptr[start]..row_ptr[i]));
            start = i;
        }
    }
    if start < n || out.is_empty() {
        out.push((start..n, row_ptr[start]..row_ptr[n]));
    }
    Ok(out)
}

/// The values buffers of a block pattern (`row_ptr`, `block_bytes` per block), split by
/// [`plan_rows`] under `values_limit(ctx, forced)`: one buffer per run, labelled `what`
/// (with its rows when there are several), holding its blocks' part of `data` (all the
/// blocks' bytes in pattern order) or zeroed without it.
pub fn values_chunks(
    ctx: &GpuContext,
    row_ptr: &[usize],
    block_bytes: u64,
    forced: Option<u64>,
    what: &str,
    data: Option<&[u8]>,
) -> Result<Vec<ValuesChunk>, GpuError> {
    let limit = values_limit(ctx, forced);
    let plan = plan_rows(row_ptr, block_bytes, limit, what, ctx.adapter_name())?;
    let single = plan.len() == 1;
    plan.into_iter()
        .map(|(rows, blocks)| {
            let label = if single {
                what.to_string()
            } else {
                format!("{what} of rows {}..{}", rows.start, rows.end)
            };
            let bytes = blocks.len() as u64 * block_bytes;
            let buffer = match data {
                Some(d) => {
                    let at = (blocks.start as u64 * block_bytes) as usize;
                    ctx.storage_with(&label, &d[at..at + bytes as usize])?
                }
                None => ctx.storage_zeroed(&label, bytes)?,
            };
            Ok(ValuesChunk {
                buffer,
                rows,
                blocks,
            })
        })
        .collect()
}

/// The bytes one values buffer may take on this device: its buffer and storage binding
/// limits, lowered to `forced` where that is given (tests of the split path).
pub fn values_limit(ctx: &GpuContext, forced: Option<u64>) -> u64 {
    let l = &ctx.limits;
    let limit = l.max_buffer_size.min(l.max_storage_buffer_binding_size);
    forced.map_or(limit, |c| c.min(limit))
}

/// A block matrix whose blocks are on the device: what [`crate::gpu::pcg::DeviceCg`]
/// multiplies by.
#[derive(Debug, Clone, Copy)]
pub struct BlockMatrix<'a> {
    pub dim: usize,
    pub row_ptr: &'a [usize],
    pub col_idx: &'a [usize],
    /// The values in chunks of consecutive block rows covering every row in order.
    pub chunks: &'a [ValuesChunk],
    /// Whether the values are f64 (else f32).
    pub f64: bool,
}

/// A host [`BlockCsr`] uploaded in f64 or rounded to f32 into chunks that fit the
/// device's bindings.
#[derive(Debug)]
pub struct HostBlocks {
    real: Real,
    dim: usize,
    row_ptr: Vec<usize>,
    col_idx: Vec<usize>,
    chunks: Vec<ValuesChunk>,
}

impl HostBlocks {
    /// Uploads `h`'s values as `real`, each chunk at most `values_limit(ctx, forced)`
    /// bytes.
    pub fn upload(
        ctx: &GpuContext,
        h: &BlockCsr,
        real: Real,
        forced: Option<u64>,
    ) -> Result<Self, GpuError> {
        let chunks = values_chunks(
            ctx,
            &h.row_ptr,
            real.size() * (h.dim * h.dim) as u64,
            forced,
            "matrix blocks",
            Some(&real.bytes(&h.values)),
        )?;
        Ok(HostBlocks {
            real,
            dim: h.dim,
            row_ptr: h.row_ptr.clone(),
            col_idx: h.col_idx.clone(),
            chunks,
        })
    }

    /// Writes new values of the same pattern (refused otherwise).
    pub fn write(&self, ctx: &GpuContext, h: &BlockCsr) -> Result<(), GpuError> {
        if h.dim != self.dim || h.row_ptr != self.row_ptr || h.col_idx != self.col_idx {
            return Err(GpuError::Mismatch(
                "the Hessian's block pattern changed; build a new solver".into(),
            ));
        }
        let dd = self.dim * self.dim;
        for c in &self.chunks {
            let values = &h.values[c.blocks.start * dd..c.blocks.end * dd];
            ctx.write_buffer(&c.buffer, 0, &self.real.bytes(values));
        }
        Ok(())
    }

    /// The buffers H's values are split over (one unless they exceed a binding).
    pub fn chunk_count(&self) -> usize {
        self.chunks.len()
    }

    /// The uploaded matrix.
    pub fn matrix(&self) -> BlockMatrix<'_> {
        BlockMatrix {
            dim: self.dim,
            row_ptr: &self.row_ptr,
            col_idx: &self.col_idx,
            chunks: &self.chunks,
            f64: self.real == Real::F64,
        }
    }
}

/// The row sums S_i = Σ_j H_ij of a block matrix (d×d per block row, row-major), summed
/// in f64: what the difference form of an f32 product ([`crate::gpu::pcg`]) adds back.
pub fn row_sums(h: &BlockCsr) -> Vec<f64> {
    let dd = h.dim * h.dim;
    let mut s = vec![0.0; h.n * dd];
    for i in 0..h.n {
        let row = &mut s[i * dd..(i + 1) * dd];
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            for (a, v) in row.iter_mut().zip(&h.values[k * dd..(k + 1) * dd]) {
                *a += v;
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Runs break before the row that would overflow; a row too large alone is named.
    #[test]
    fn rows_split_where_the_limit_falls() {
        // Rows of 1, 2, 3 and 1 blocks of 16 bytes.
        let row_ptr = [0usize, 1, 3, 6, 7];
        let runs = plan_rows(&row_ptr, 16, 48, "blocks", "test").expect("fits");
        assert_eq!(runs, vec![(0..2, 0..3), (2..3, 3..6), (3..4, 6..7)]);
        match plan_rows(&row_ptr, 16, 32, "blocks", "test") {
            Err(GpuError::BufferTooLarge { label, .. }) => assert_eq!(label, "blocks of row 2"),
            other => panic!("{other:?}"),
        }
    }
}
