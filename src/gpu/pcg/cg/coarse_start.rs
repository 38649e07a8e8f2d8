//! The device side of the aggregates' E⁺ as a run's start sees it: `prepare`'s flag for a
//! coarse matrix the device could not factor, read with the start's status and answered
//! by forming E⁺ on the host, and E read back for tests.

use super::{Co, DeviceCg, DeviceFrames};
use crate::gpu::kernels::slots;
use crate::gpu::schedule::ChunkStatus;
use crate::gpu::GpuError;

impl DeviceCg {
    /// Zeroes the state of a run's start: flags and iteration count, not the coarse
    /// factorization's flag of the last `prepare` (the start's status reports it).
    pub(super) fn clear_state(&self) {
        self.clear_flags();
        let (at, words) = (slots::STATE_ITERS, slots::N_STATE - slots::STATE_ITERS);
        self.ctx.write_buffer(
            &self.buf.state,
            4 * at as u64,
            &vec![0u8; 4 * words as usize],
        );
    }

    /// Whether a status shows that `prepare` could not factor the aggregates' E on the
    /// device while the run used E⁺ (`co`): then E⁺ has come from the host
    /// ([`DeviceCg::upload_aggregate_einv`]) and the state is reset for the start to run
    /// again, fresh.
    pub(super) fn coarse_fallback(
        &mut self,
        st: &ChunkStatus,
        frames: &DeviceFrames,
        co: Co,
    ) -> Result<bool, GpuError> {
        if !(st.coarse_failed && co == Co::Aggregates) {
            return Ok(false);
        }
        self.upload_aggregate_einv(frames)?;
        self.clear_state();
        let acc = self.ty.acc;
        self.ctx.write_buffer(
            &self.buf.scal,
            acc.size() * slots::SCAL_PSCALE as u64,
            &acc.bytes(&[0.0]),
        );
        Ok(true)
    }

    /// Submits a run's start as `record` records it and reads its status, answering a
    /// failed coarse factorization ([`DeviceCg::coarse_fallback`]) by running it again: a
    /// resumed direction was rescaled in place by the first (no resume follows a prepare
    /// before a fresh start has met the flag).
    pub(super) fn start_status(
        &mut self,
        frames: &DeviceFrames,
        co: Co,
        what: &str,
        record: &dyn Fn(&DeviceCg) -> wgpu::CommandEncoder,
    ) -> Result<ChunkStatus, GpuError> {
        let (st, _) = self.submit_and_read(record(self), &[], what)?;
        if !self.coarse_fallback(&st, frames, co)? {
            return Ok(st);
        }
        Ok(self.submit_and_read(record(self), &[], what)?.0)
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
