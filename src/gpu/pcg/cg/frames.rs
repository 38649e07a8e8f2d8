//! A constraint set on the device: per node its mask and rotation, the aggregates of the
//! coarse space, and the bind groups that use them.

use super::super::frame_layout::frame_words;
use super::{DeviceCg, DeviceFrames, NEXT_ID};
use crate::core::constraints::Frames;
use crate::gpu::kernels;
use crate::gpu::GpuError;
use crate::solve::coarse::CoarseSpace;
use std::sync::atomic::Ordering;

use super::super::aggregates;
use super::super::coarse_factor::CoarseFactor;

/// The arrays a constraint set shares with the last one where their contents are equal.
#[derive(Clone, Copy)]
enum Shared {
    Rotations,
    Aggregates,
}

impl DeviceCg {
    /// The frame words (mask, rotation index per node) in a buffer of their own: a copy of
    /// the last set's on the device with the words that differ written over it (a few
    /// moving nodes), or uploaded whole the first time.
    fn upload_frame_words(&self, words: &[u32]) -> Result<wgpu::Buffer, GpuError> {
        let mut up = self.uploaded.borrow_mut();
        let bytes = 4 * words.len() as u64;
        let buf = match up.frame.as_ref().filter(|(w, _)| w.len() == words.len()) {
            None => self
                .ctx
                .storage_with("pcg frames", bytemuck::cast_slice(words))?,
            Some((last, last_buf)) => {
                let buf = self.ctx.storage_zeroed("pcg frames", bytes)?;
                let mut enc = self.encoder("pcg frames from the last set");
                enc.copy_buffer_to_buffer(last_buf, 0, &buf, 0, bytes);
                self.ctx.submit(enc);
                // Runs of differing words, each written after the copy.
                let mut k = 0;
                while k < words.len() {
                    if words[k] == last[k] {
                        k += 1;
                        continue;
                    }
                    let start = k;
                    while k < words.len() && words[k] != last[k] {
                        k += 1;
                    }
                    self.ctx.write_buffer(
                        &buf,
                        4 * start as u64,
                        bytemuck::cast_slice(&words[start..k]),
                    );
                }
                buf
            }
        };
        up.frame = Some((words.to_vec(), buf.clone()));
        Ok(buf)
    }

    /// `data` in a buffer, shared with the last set's where equal.
    fn upload_shared(&self, what: Shared, data: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        let mut up = self.uploaded.borrow_mut();
        let (slot, label) = match what {
            Shared::Rotations => (&mut up.rotations, "pcg rotations"),
            Shared::Aggregates => (&mut up.aggregates, "pcg aggregates"),
        };
        if let Some((last, buf)) = slot.as_ref() {
            if last[..] == data[..] {
                return Ok(buf.clone());
            }
        }
        let buf = self.ctx.storage_with(label, data)?;
        *slot = Some((data.to_vec(), buf.clone()));
        Ok(buf)
    }

    /// Uploads one constraint set (mask per node, rotation per rotated node) and builds
    /// its bind group, once: callers keep it for as long as the constraints hold. With
    /// `coarse` = `Aggregates` also the aggregates of the pattern and their index arrays
    /// ([`aggregates`]); frames built for another coarse space refuse it in `iterate`.
    /// Refuses frames of another mesh and prescribed (non-zero) constraint values, which
    /// a Newton step never has.
    pub fn frames(&self, f: &Frames, coarse: CoarseSpace) -> Result<DeviceFrames, GpuError> {
        let (n, d) = (self.n_nodes, self.dim);
        if f.dim != d || f.n_nodes != n {
            return Err(GpuError::Mismatch(format!(
                "the constraints are for {} nodes in {}D, the mesh has {n} in {d}D",
                f.n_nodes, f.dim
            )));
        }
        if !f.homogeneous && !self.given_rhs {
            return Err(GpuError::Unsupported(
                "the device PCG forms b̂ from a gradient for homogeneous constraints only \
                 (a Newton step prescribes no displacement)"
                    .into(),
            ));
        }
        let frame = frame_words(f)?;
        let frame_buf = self.upload_frame_words(&frame)?;
        let rot_buf = self.upload_shared(Shared::Rotations, &self.ty.real.bytes(&f.rotations))?;
        let agg = match coarse {
            CoarseSpace::Aggregates => {
                let (row_ptr, col_idx) = self.usize_pattern();
                aggregates::aggregate_index(&row_ptr, &col_idx, f)?
            }
            _ => None,
        };
        let mut agg = agg;
        // The index words live on the device only: taken, not kept on the host.
        let (agg_words, coarse_bytes) = match agg.as_mut() {
            Some(a) => (
                std::mem::take(&mut a.words),
                self.ty.acc.size() * a.values as u64,
            ),
            None => (vec![0u32; 4], 16),
        };
        let agg_buf = self.upload_shared(Shared::Aggregates, bytemuck::cast_slice(&agg_words))?;
        let coarse_buf = self.ctx.storage_zeroed("pcg coarse space", coarse_bytes)?;
        let factor = match &agg {
            Some(a) => Some(CoarseFactor::new(
                &self.ctx,
                d,
                self.ty.acc,
                a,
                &coarse_buf,
                &self.buf.state,
            )?),
            None => None,
        };
        let b = &self.buf;
        let mut groups = Vec::with_capacity(b.hvals.len());
        for (params, hvals) in b.params.iter().zip(&b.hvals) {
            let bufs: [&wgpu::Buffer; 21] = [
                params,
                &b.pattern,
                hvals,
                &b.grad,
                &frame_buf,
                &rot_buf,
                &b.y,
                &b.r,
                &b.z,
                &b.p,
                &b.q,
                &b.b,
                &b.minv,
                &b.dx,
                &b.partials,
                &b.scal,
                &b.state,
                &agg_buf,
                &coarse_buf,
                &b.pw,
                &b.rowsum,
            ];
            groups.push(kernels::bind_group(
                &self.ctx.device,
                &self.kernels.layout,
                "pcg bind group",
                &bufs,
            ));
        }
        self.ctx.check("uploading the constraint frames")?;
        Ok(DeviceFrames {
            owner: self.id,
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            groups,
            gram: crate::solve::coarse::translation_gram(f),
            coarse,
            agg,
            _frame: frame_buf,
            _rotations: rot_buf,
            _aggregates: agg_buf,
            coarse_buf,
            factor,
        })
    }
    /// The block pattern's row pointers and column indices as `usize` (from the uploaded
    /// u32 copy; only while aggregates are built).
    pub(super) fn usize_pattern(&self) -> (Vec<usize>, Vec<usize>) {
        let n = self.n_nodes;
        let p = &self.host_pattern;
        let row_ptr: Vec<usize> = p[..=n].iter().map(|&v| v as usize).collect();
        let nnz = row_ptr[n];
        let col_idx = p[n + 1..n + 1 + nnz].iter().map(|&v| v as usize).collect();
        (row_ptr, col_idx)
    }
    pub(super) fn own(&self, frames: &DeviceFrames) -> Result<(), GpuError> {
        if frames.owner != self.id {
            return Err(GpuError::Mismatch(
                "these device frames were built by another device CG".into(),
            ));
        }
        Ok(())
    }
}

impl DeviceFrames {
    /// The frame words (mask and rotation index per node, u32 pairs) and the rotations
    /// (d×d per rotated node, row-major, in the PCG's precision), for kernels of other
    /// modules that read the same constraint set.
    pub fn buffers(&self) -> (&wgpu::Buffer, &wgpu::Buffer) {
        (&self._frame, &self._rotations)
    }

    /// The number of aggregates of the coarse space these frames were built for (`None`
    /// without the aggregates, or when every node is fixed).
    pub fn aggregate_count(&self) -> Option<usize> {
        self.agg.as_ref().map(|a| a.count)
    }
}
