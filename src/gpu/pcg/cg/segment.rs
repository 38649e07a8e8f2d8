//! Segments: runs of the device PCG from y = 0 that stop once the recurrence residual
//! meets the tolerance, with no true-residual check, and keep p and ρ for the next one.
//! They are the inner solves of reliable updates (as in QUDA's mixed-precision CG): the
//! caller forms the true residual r in a higher precision, gives r/‖r‖ as the next b̂
//! ([`DeviceCg::set_rhs`]) and resumes, so CG goes on along its search direction instead
//! of restarting from p = z.

use super::run::RunTrack;
use super::{
    Begun, ChunkWatch, Chunked, Co, DeviceCg, DeviceCgParams, DeviceFrames, Mode, Pre, SegmentEnd,
    SegmentInfo, SegmentStart, Watch,
};
use crate::gpu::kernels::slots;
use crate::gpu::{GpuError, Phase};

impl DeviceCg {
    /// Writes b̂ (frame coordinates, zero in the constrained components, n·d) for the next
    /// [`DeviceCg::segment`], keeping the preconditioner of the last
    /// [`DeviceCg::prepare_with_rhs`] with these frames.
    pub fn set_rhs(&mut self, frames: &DeviceFrames, rhs: &[f64]) -> Result<(), GpuError> {
        self.own(frames)?;
        self.check_prepared(frames)?;
        self.write_rhs(frames, rhs)
    }

    /// CG from y = 0 on the current b̂ until the recurrence residual √(r·r)/‖b̂‖ meets
    /// `params.tol`, the iteration limit, or no improvement over a stagnation window; y
    /// is then [`DeviceCg::read_y`]'s, and after `Converged` p and ρ (in the returned
    /// info) are those a [`SegmentStart::Resume`] goes on from. Non-positive curvature and
    /// breakdowns are errors, as in [`DeviceCg::iterate`]. The multilevel preconditioner
    /// does not resume (its V-cycle forms p itself). `watch`, where given, looks at the run
    /// after every status read (with the iterations so far) and may stop it
    /// (`SegmentEnd::Watched`).
    pub fn segment(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        start: SegmentStart,
        watch: Option<&mut Watch>,
    ) -> Result<SegmentInfo, GpuError> {
        let Begun {
            tol,
            pre,
            co,
            mut scal,
        } = self.begin(frames, params)?;
        let resume = match start {
            SegmentStart::Fresh => false,
            SegmentStart::Resume { rho_prev, pscale } => {
                if pre == Pre::Multilevel {
                    return Err(GpuError::Unsupported(
                        "a device PCG segment resumes under Jacobi or block Jacobi, not the \
                         multilevel preconditioner"
                            .into(),
                    ));
                }
                let fine = |v: f64| v > 0.0 && v.is_finite();
                if !(fine(rho_prev) && fine(pscale)) {
                    return Err(GpuError::Unsupported(format!(
                        "a resumed segment needs a positive, finite ρ_prev and scale, not \
                         {rho_prev:e} and {pscale:e}"
                    )));
                }
                scal[slots::SCAL_RHO_PREV as usize] = rho_prev;
                scal[slots::SCAL_PSCALE as usize] = pscale;
                true
            }
        };
        let acc = self.ty.acc;
        self.ctx.write_buffer(&self.buf.scal, 0, &acc.bytes(&scal));
        self.clear_state();
        let record = |cg: &DeviceCg| {
            let mut enc = cg.encoder("pcg segment start");
            enc.clear_buffer(&cg.buf.y, 0, None);
            enc.clear_buffer(&cg.buf.q, 0, None);
            let mut kernels = cg.start(frames, pre, co, Mode::Iterate);
            // With the coarse correction `start` already ends in start_p; without it,
            // init left p alone and start_p forms p = z + βp here.
            if resume && co == Co::None {
                let sp = cg.kernels.update.start_p(&cg.ctx, co, Mode::Iterate);
                kernels.push((sp, cg.launches.fused, &frames.groups[0]));
            }
            cg.pass(&mut enc, "pcg segment start", Phase::Cg, &kernels);
            enc
        };
        let mut st = self.start_status(frames, co, "starting a device PCG segment", &record)?;
        self.galerkin_from_status(&st);
        self.check_pinned(frames)?;
        st.error(0)?;
        // Only the start resumes: no later init of this PCG may take p as kept.
        self.ctx.write_buffer(
            &self.buf.scal,
            acc.size() * slots::SCAL_PSCALE as u64,
            &acc.bytes(&[0.0]),
        );
        self.run_starts = vec![0];
        let start_rho = st.rho;
        let bb = st.bb;
        let mut end = SegmentEnd::Converged;
        // The recurrence r·r at the last window's end: a window without a fall below it
        // is stagnation.
        let mut last_check = st.rr;
        let mut inner = watch.map(|w| move |cg: &DeviceCg, it: usize| w(cg, it, start_rho));
        let mut bytes = Vec::new();
        while !st.converged {
            let mut track = RunTrack::new(st.iterations, st.rr);
            track.verify = false;
            match self.chunks(
                frames,
                (pre, co),
                params,
                tol * tol * bb,
                &mut st,
                None,
                &mut bytes,
                &mut track,
                inner.as_mut().map(|w| w as &mut ChunkWatch),
            )? {
                Chunked::Watched => {
                    end = SegmentEnd::Watched;
                    break;
                }
                Chunked::Stopped if st.converged => {}
                Chunked::Stopped => {
                    end = SegmentEnd::MaxIterations;
                    break;
                }
                Chunked::Check if st.rr < last_check => last_check = st.rr,
                Chunked::Check => {
                    end = SegmentEnd::Stagnated;
                    break;
                }
            }
        }
        self.last_iterations = st.iterations;
        let rhs_norm = bb.sqrt();
        Ok(SegmentInfo {
            end,
            iterations: st.iterations,
            recorded_iterations: self.recorded.get(),
            status_reads: self.reads.get(),
            recurrence_residual: if bb == 0.0 {
                0.0
            } else {
                st.rr.sqrt() / rhs_norm
            },
            rho: st.rho,
            start_rho,
            rhs_norm,
        })
    }
}

impl DeviceCg {
    /// Writes y (frame coordinates, n·d): the start of a following
    /// [`DeviceCg::iterate_from_current`] (a warm start from an iterate formed elsewhere).
    pub fn write_y(&mut self, frames: &DeviceFrames, y: &[f64]) -> Result<(), GpuError> {
        self.own(frames)?;
        if y.len() != self.n_nodes * self.dim {
            return Err(GpuError::Mismatch(format!(
                "y has {} entries, the system {}",
                y.len(),
                self.n_nodes * self.dim
            )));
        }
        self.ctx
            .write_buffer(&self.buf.y, 0, &self.ty.real.bytes(y));
        Ok(())
    }
}

impl DeviceCg {
    /// The true residual r = b̂ − Ĥy of the current y, formed in this PCG's precision by
    /// the kernels of a restart (left in r, with z and p as a restart leaves them):
    /// (r·r, ‖b̂‖²) read back with the status. y is unchanged.
    pub fn residual_norm(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<(f64, f64), GpuError> {
        let Begun { pre, co, scal, .. } = self.begin(frames, params)?;
        let acc = self.ty.acc;
        self.ctx.write_buffer(&self.buf.scal, 0, &acc.bytes(&scal));
        self.clear_state();
        let record = |cg: &DeviceCg| {
            let mut enc = cg.encoder("pcg residual");
            let mut kernels = cg.product_of_y(frames, Mode::Iterate);
            kernels.extend(cg.start(frames, pre, co, Mode::Iterate));
            cg.pass(&mut enc, "pcg residual", Phase::Cg, &kernels);
            enc
        };
        let st = self.start_status(frames, co, "the device PCG's residual", &record)?;
        self.galerkin_from_status(&st);
        self.check_pinned(frames)?;
        st.error(0)?;
        Ok((st.rr, st.bb))
    }

    /// Unknowns (n·d).
    pub fn n_dofs(&self) -> u64 {
        (self.n_nodes * self.dim) as u64
    }

    /// r, b̂ and y on the device (`real`, n·d): for kernels that move vectors between two
    /// PCGs (mixed precision's refinement, `gpu::pcg::refine`).
    pub(crate) fn residual_buffer(&self) -> &wgpu::Buffer {
        &self.buf.r
    }

    pub(crate) fn rhs_buffer(&self) -> &wgpu::Buffer {
        &self.buf.b
    }

    pub(crate) fn y_buffer(&self) -> &wgpu::Buffer {
        &self.buf.y
    }
}
