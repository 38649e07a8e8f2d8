//! The device side of the aggregates' E⁺ as the CG sees it: a run's start, which reads
//! `prepare`'s flag for a coarse matrix the device could not factor with its status and
//! answers it by forming E⁺ on the host, and E read back for tests.

use super::{DeviceCg, DeviceFrames};
use crate::gpu::kernels::slots;
use crate::gpu::schedule::ChunkStatus;
use crate::gpu::GpuError;

impl DeviceCg {
    /// Zeroes the state of a run's start: flags and iteration count, not the coarse
    /// factorization's flag of the last `prepare` (the start's status reports it).
    pub(super) fn clear_state(&self) {
        self.ctx
            .write_buffer(&self.buf.state, 0, &[0u8; 4 * slots::STATE_RESET as usize]);
    }

    /// Submits a run's start as `record` records it and reads its status. Where the status
    /// shows that `prepare` could not factor the aggregates' E on the device and the start
    /// used E⁺ (`co` = 2), E⁺ comes from the host ([`DeviceCg::upload_aggregate_einv`]) and
    /// the start runs again, fresh: a resumed direction was rescaled in place by the first
    /// (no resume follows a prepare before a fresh start has met the flag).
    pub(super) fn start_status(
        &mut self,
        frames: &DeviceFrames,
        co: usize,
        what: &str,
        record: &dyn Fn(&DeviceCg) -> wgpu::CommandEncoder,
    ) -> Result<ChunkStatus, GpuError> {
        let st = self.submit_and_read(record(self), what)?;
        if !(st.coarse_failed && co == 2) {
            return Ok(st);
        }
        self.upload_aggregate_einv(frames)?;
        self.clear_flags();
        let acc = self.ty.acc;
        self.ctx.write_buffer(
            &self.buf.scal,
            acc.size() * slots::SCAL_PSCALE as u64,
            &acc.bytes(&[0.0]),
        );
        self.submit_and_read(record(self), what)
    }

    /// E of the aggregates (K×K, row-major, not symmetrized) as the last `prepare`
    /// reduced it; `None` for frames without aggregates. For tests and diagnostics (a
    /// read-back).
    pub fn aggregate_galerkin(&self, frames: &DeviceFrames) -> Result<Option<Vec<f64>>, GpuError> {
        self.own(frames)?;
        let Some(a) = &frames.agg else {
            return Ok(None);
        };
        let e = self.read_coarse(frames, a.e_at, a.k * a.k, "reading back the aggregates' E")?;
        Ok(Some(e))
    }
}
