//! The coarse spaces' host side: E of the translations (read with every status, its
//! pseudo-inverse for the translations' correction, the check of an unpinned body), the
//! aggregates' E⁺, and the multilevel preconditioner's levels.

use super::{DeviceCg, DeviceFrames, Galerkin, Scalars};
use crate::core::constraints::Frames;
use crate::gpu::kernels::slots;
use crate::gpu::schedule::ChunkStatus;
use crate::gpu::{GpuError, TrafficCount};
use crate::solve::cg::CgError;
use crate::solve::multilevel::Multilevel;

use super::super::multilevel::{DeviceMultilevel, Finest};

impl DeviceCg {
    /// E⁺ of the aggregates written from the host for the iterations of the current
    /// `prepare`, in place of the device's (whose failure flag it clears).
    pub(super) fn write_aggregate_einv(&mut self, frames: &DeviceFrames, einv: &[f64]) {
        let Some(a) = &frames.agg else { return };
        let acc = self.ty.acc;
        self.ctx.write_buffer(
            &frames.coarse_buf,
            acc.size() * a.einv_at as u64,
            &acc.bytes(einv),
        );
        self.ctx.write_buffer(
            &self.buf.state,
            4 * slots::STATE_COARSE_FAILED as u64,
            &[0u8; 4],
        );
        self.coarse_traffic.host_to_device_bytes += acc.size() * einv.len() as u64;
    }
    /// The multilevel preconditioner of the system just prepared (built on the host from
    /// the same H and constraints `frames` were built from: [`Multilevel::new`]),
    /// uploaded for the iterations with `Preconditioner::Multilevel`; call after every
    /// `prepare`. A hierarchy met before keeps its buffers and only the values move; the
    /// same generation of levels ([`Multilevel::generation`]: kept levels refreshed) moves
    /// only its smoothing weights.
    ///
    /// The cluster inverses go in buffers of consecutive clusters under the adapter's
    /// binding limit, lowered to `binding_limit` where given (tests of the split path): the
    /// smoothings run once per buffer, with the same sums as one buffer.
    pub fn set_multilevel(
        &mut self,
        ml: &Multilevel,
        frames: &Frames,
        binding_limit: Option<u64>,
    ) -> Result<(), GpuError> {
        if frames.n_nodes != self.n_nodes {
            return Err(GpuError::Mismatch(format!(
                "the constraints have {} nodes, the device PCG {}",
                frames.n_nodes, self.n_nodes
            )));
        }
        if self.ty != Scalars::F64 {
            return Err(GpuError::Unsupported(
                "the multilevel preconditioner runs in f64 only".into(),
            ));
        }
        if self.ml.is_none() {
            self.ml = Some(DeviceMultilevel::new(&self.ctx, self.dim)?);
        }
        let finest = Finest {
            r: &self.buf.r,
            z: &self.buf.z,
            q: &self.buf.q,
            state: &self.buf.state,
        };
        if let Some(dm) = self.ml.as_mut() {
            dm.set(ml, frames, finest, binding_limit)?;
        }
        self.ml_ready = true;
        Ok(())
    }
    /// Clusters per level of the multilevel preconditioner on the device, finest first
    /// (empty before [`DeviceCg::set_multilevel`]).
    pub fn multilevel_clusters(&self) -> Vec<usize> {
        self.ml
            .as_ref()
            .map(DeviceMultilevel::cluster_counts)
            .unwrap_or_default()
    }
    /// Buffers of cluster inverses per level of the multilevel preconditioner on the
    /// device, finest first (empty before [`DeviceCg::set_multilevel`]).
    pub fn multilevel_inverse_buffers(&self) -> Vec<usize> {
        self.ml
            .as_ref()
            .map(DeviceMultilevel::inverse_chunk_counts)
            .unwrap_or_default()
    }
    /// The fallback where `prepare` could not factor E of the aggregates on the device:
    /// E read back, pseudo-inverted on the host as the CPU does
    /// ([`crate::solve::coarse::aggregates_einv_from_galerkin`], whose fallback is the
    /// eigen pseudo-inverse of the whole of E) and E⁺ written back (zero where E has no
    /// usable part: no correction then).
    pub(super) fn upload_aggregate_einv(&mut self, frames: &DeviceFrames) -> Result<(), GpuError> {
        let Some(a) = frames.agg.as_ref() else {
            return Ok(());
        };
        let e = self.read_coarse(
            frames,
            a.e_at,
            a.k * a.k,
            "reading back the aggregates' coarse matrix E = ZᵀĤZ",
        )?;
        let einv =
            crate::solve::coarse::aggregates_einv_from_galerkin(self.dim, a.count, e, &a.gram)
                .unwrap_or_else(|| vec![0.0; a.k * a.k]);
        self.coarse_traffic.device_to_host_bytes += self.ty.acc.size() * (a.k * a.k) as u64;
        self.write_aggregate_einv(frames, &einv);
        Ok(())
    }
    /// The aggregates' E and E⁺ moved between host and device so far (part of the
    /// context's `GpuContext::traffic`).
    pub fn coarse_traffic(&self) -> TrafficCount {
        self.coarse_traffic
    }
    /// E of the last `prepare` read back and pseudo-inverted, with its rows' absolute sums
    /// (once per `prepare`): a read of its own, for the translations' correction, whose
    /// E⁺ goes in before the start.
    pub(super) fn read_galerkin(&mut self) -> Result<(), GpuError> {
        if let Galerkin::Read { .. } = self.galerkin {
            return Ok(());
        }
        let len = (slots::SCAL_EABS - slots::SCAL_E) as usize + self.dim;
        let acc = self.ty.acc;
        let bytes = self.ctx.download(
            &self.buf.scal,
            acc.size() * slots::SCAL_E as u64,
            acc.size() * len as u64,
            "reading back the coarse matrix E = ZᵀĤZ",
        )?;
        let mut v = [0.0; 12];
        v[..len].copy_from_slice(&acc.values(&bytes));
        self.set_galerkin(&v);
        Ok(())
    }

    /// E of the last `prepare` as a status read brought it (E and its sums ride with every
    /// status), where it was not read yet.
    pub(super) fn galerkin_from_status(&mut self, st: &ChunkStatus) {
        if let Galerkin::OnDevice = self.galerkin {
            self.set_galerkin(&st.coarse);
        }
    }

    /// E (D² values unsymmetrized, then from entry 9 the D absolute row sums), symmetrized
    /// as src/solve/coarse.rs does, with its pseudo-inverse.
    pub(super) fn set_galerkin(&mut self, v: &[f64; 12]) {
        let d = self.dim;
        let mut e = v[..d * d].to_vec();
        let abs = v[9..9 + d].to_vec();
        for a in 0..d {
            for b in 0..a {
                let m = 0.5 * (e[a * d + b] + e[b * d + a]);
                e[a * d + b] = m;
                e[b * d + a] = m;
            }
        }
        let einv = crate::solve::coarse::pseudo_inverse(d, &e);
        self.galerkin = Galerkin::Read { e, abs, einv };
    }

    /// The coarse matrix E = ZᵀĤZ of the last `prepare` computed on the host in f64 from
    /// `h` (the values this PCG holds, before rounding) and the frames `f` these frames
    /// were built from, in place of the device's reduction: an f32 PCG sums blocks rounded
    /// to f32, whose rounding (ε_f32‖H‖ per row) swamps a free body's mass term, the very
    /// part of E the correction is for. The translations' absolute row sums (the check of
    /// a pinned body) stay the device's. Call after every `prepare`.
    pub fn set_galerkin_from_host(
        &mut self,
        frames: &DeviceFrames,
        h: &crate::core::sparse::BlockCsr,
        f: &crate::core::constraints::Frames,
    ) -> Result<(), GpuError> {
        self.own(frames)?;
        self.check_prepared(frames)?;
        let d = self.dim;
        self.read_galerkin()?;
        if let Galerkin::Read { e, einv, .. } = &mut self.galerkin {
            let (host_e, _) = crate::solve::coarse::translations_galerkin_from_blocks(h, f);
            *einv = crate::solve::coarse::pseudo_inverse(d, &host_e);
            *e = host_e;
        }
        if let Some(a) = &frames.agg {
            let (row_ptr, col_idx) = self.usize_pattern();
            let agg = crate::solve::coarse::Aggregation::from_pattern(&row_ptr, &col_idx);
            let einv = crate::solve::coarse::aggregates_einv_from_blocks(h, f, &agg)
                .unwrap_or_else(|| vec![0.0; a.k * a.k]);
            self.write_aggregate_einv(frames, &einv);
        }
        Ok(())
    }
    /// Refuses a system that a rigid translation of the free nodes leaves singular to
    /// working precision, by the CPU CG's test ([`crate::solve::coarse::is_unpinned`]),
    /// with every free node as one group (the CPU tests each connected group).
    pub(super) fn check_pinned(&mut self, frames: &DeviceFrames) -> Result<(), GpuError> {
        let gram = &frames.gram;
        if gram.count == 0 {
            return Ok(());
        }
        if let Galerkin::Read { e, abs, .. } = &self.galerkin {
            let t = crate::solve::coarse::group_translation(
                self.dim, e, &gram.g, abs, gram.first, gram.count,
            );
            if let Some(t) = t.filter(crate::solve::coarse::is_unpinned) {
                return Err(CgError::Unpinned(t).into());
            }
        }
        Ok(())
    }
    /// E = ZᵀĤZ of the translations (D², row-major, symmetrized) and its pseudo-inverse
    /// (`None`: no correction) as the last `iterate` read them (every solve reads E for
    /// its check of the translations); `None` before one. For tests and diagnostics.
    pub fn coarse_matrix(&self) -> Option<(&[f64], Option<&[f64]>)> {
        match &self.galerkin {
            Galerkin::Read { e, einv, .. } => Some((e, einv.as_deref())),
            Galerkin::OnDevice => None,
        }
    }
    /// Whether the last `iterate` found no usable E of the translations (every translation
    /// constrained, or E not finite): the translations' correction then adds nothing.
    pub fn translations_inactive(&self) -> bool {
        matches!(self.galerkin, Galerkin::Read { einv: None, .. })
    }
    /// E⁺ of the aggregates (K×K, row-major) as the last `iterate` with them wrote it;
    /// `None` for frames without aggregates. For tests and diagnostics (a read-back).
    pub fn aggregate_einv(&self, frames: &DeviceFrames) -> Result<Option<Vec<f64>>, GpuError> {
        self.own(frames)?;
        let Some(a) = &frames.agg else {
            return Ok(None);
        };
        let einv = self.read_coarse(
            frames,
            a.einv_at,
            a.k * a.k,
            "reading back the aggregates' E⁺",
        )?;
        Ok(Some(einv))
    }
    /// `len` values of the frames' coarse buffer (`acc`) from index `at`.
    pub(super) fn read_coarse(
        &self,
        frames: &DeviceFrames,
        at: usize,
        len: usize,
        what: &str,
    ) -> Result<Vec<f64>, GpuError> {
        let acc = self.ty.acc;
        let bytes = self.ctx.download(
            &frames.coarse_buf,
            acc.size() * at as u64,
            acc.size() * len as u64,
            what,
        )?;
        Ok(acc.values(&bytes))
    }
}
