//! The driver of a solve: chunks of iterations recorded many per submit, each ending in
//! its verification, one status read per chunk, restarts from the true residual.
//!
//! A solve's first submit holds its start, a first chunk as long as the last solve took
//! (a quarter more; a first solve's, as many iterations as 160 dispatches make:
//! [`schedule::first_chunk`]), that chunk's verification and Δx's recovery, and what the caller
//! wants done once the solve has succeeded ([`Tail`]); the tolerance, where it depends on
//! ‖b̂‖, is evaluated on the device at the start ([`ToleranceRule`]). So a solve that
//! converges within its first chunk waits on the device once. Iterations recorded past
//! the stop are no-ops that still cost their dispatches.

use super::*;
use crate::gpu::pcg::multilevel::Step;
use crate::gpu::schedule::{self, ChunkStatus};
use crate::solve::cg::CgError;
use crate::solve::tolerance::ToleranceRule;

impl DeviceCg {
    /// Records the status copies (`scal`, `state` into `status`) after the work of `enc`,
    /// submits, and reads the status back with `extra` (one wait).
    pub(super) fn submit_and_read(
        &self,
        mut enc: wgpu::CommandEncoder,
        extra: &[ReadRange],
        what: &str,
    ) -> Result<(ChunkStatus, TailBytes), GpuError> {
        let acc = self.ty.acc;
        let sb = acc.size() * slots::STATUS_SCAL as u64;
        enc.copy_buffer_to_buffer(&self.buf.scal, 0, &self.buf.status, 0, sb);
        enc.copy_buffer_to_buffer(
            &self.buf.state,
            0,
            &self.buf.status,
            sb,
            4 * slots::N_STATE as u64,
        );
        self.ctx.submit(enc);
        self.ctx.check(what)?;
        let mut ranges = vec![ReadRange {
            buffer: &self.buf.status,
            offset: 0,
            bytes: status_bytes(acc),
        }];
        ranges.extend_from_slice(extra);
        let mut bytes = self.ctx.download_many(&ranges, what)?;
        let tail = bytes.split_off(1);
        let status = &bytes[0];
        self.reads.set(self.reads.get() + 1);
        let scal = acc.values(&status[..sb as usize]);
        let st = ChunkStatus::read(&scal, &schedule::state_words(&status[sb as usize..]));
        Ok((st, tail))
    }

    /// Clears the stop flags (the iteration count stays): the next CG dispatches run.
    pub(super) fn clear_flags(&self) {
        self.ctx
            .write_buffer(&self.buf.state, 0, &[0u8; 4 * slots::STATE_FLAGS as usize]);
    }

    /// The tolerance the last solve ran to (`None` before a solve's first status).
    pub fn last_tolerance(&self) -> Option<f64> {
        self.last_eta
    }

    /// The device's status words (flags and counts at `gpu::kernels::slots`), for a
    /// [`Tail`]'s kernels to gate on.
    pub fn state_buffer(&self) -> &wgpu::Buffer {
        &self.buf.state
    }

    /// CG from y = 0 on the b̂ and preconditioner of the last [`DeviceCg::prepare`] with
    /// these frames, until the true residual ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol, then Δx = V P y into
    /// [`DeviceCg::dx_buffer`].
    ///
    /// The recurrence residual decides when to look: once it meets the tolerance, the true
    /// residual is computed in f64 on the device (q = Ĥy, r = b̂ − q), by the chunk's
    /// verification in the same submit; if it misses, CG restarts from y with that
    /// residual. Iterations are recorded in chunks, one status read-back each (the first
    /// as long as the last solve or sized by an iteration's dispatches, then as many as
    /// the residual's rate of fall predicts, at least 2, at most double the last and 256:
    /// [`schedule::next_chunk`]).
    pub fn iterate(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<DeviceCgInfo, GpuError> {
        let rule = ToleranceRule::Fixed(params.tol);
        Ok(self.run(frames, params, rule, None, false)?.0)
    }

    /// [`DeviceCg::iterate`] to the tolerance `rule` gives for ‖b̂‖ (evaluated on the
    /// device at the start: [`DeviceCgInfo::tolerance`] is its value), with `tail` recorded
    /// after every chunk; its bytes come back from the status read that ended the solve
    /// when that chunk's verification recovered Δx (else `None`: the tail did not run on
    /// the answer, and the caller does that work itself).
    pub fn iterate_with(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        rule: ToleranceRule,
        tail: Option<&Tail>,
    ) -> Result<(DeviceCgInfo, Option<TailBytes>), GpuError> {
        self.run(frames, params, rule, tail, false)
    }

    /// [`DeviceCg::iterate`] from the y the last iterate left (a restart: r = b̂ − Ĥy),
    /// for a caller whose own check of y missed the tolerance.
    pub fn iterate_from_current(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<DeviceCgInfo, GpuError> {
        let rule = ToleranceRule::Fixed(params.tol);
        Ok(self.run(frames, params, rule, None, true)?.0)
    }

    /// What every run checks and sets up before its start: the frames, the tolerance, the
    /// preconditioner's state (E⁺ of the translations or the aggregates on the device),
    /// and the scalars it starts from (written by the caller).
    pub(super) fn begin(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<Begun, GpuError> {
        self.own(frames)?;
        self.check_prepared(frames)?;
        let tol = check_tol(params.tol)?;
        let (pre, co) = overrides(params, frames);
        if pre != Pre::Multilevel
            && params.coarse == CoarseSpace::Aggregates
            && frames.coarse != CoarseSpace::Aggregates
        {
            return Err(GpuError::Mismatch(
                "the device CG's aggregates need frames built for them (DeviceCg::frames)".into(),
            ));
        }
        if pre == Pre::Multilevel
            && !(self.ml_ready && self.ml.as_ref().is_some_and(DeviceMultilevel::is_set))
        {
            return Err(GpuError::Mismatch(
                "the multilevel preconditioner was not set for this system (call \
                 set_multilevel after prepare)"
                    .into(),
            ));
        }
        self.recorded.set(0);
        self.reads.set(0);
        // Every slot before E: the scalars, c and E⁺ (zero without the correction, or
        // when every translation is constrained: then c = 0 and so is the correction).
        let mut scal = [0.0f64; slots::SCAL_E as usize];
        scal[slots::SCAL_TOL2 as usize] = tol * tol;
        scal[slots::SCAL_ETA as usize] = tol;
        if co == Co::Translations {
            // E⁺ goes in before the start: the one coarse space whose pseudo-inverse
            // needs E on the host first (a D×D eigen-decomposition, as the CPU's).
            self.read_galerkin()?;
            if let Galerkin::Read {
                einv: Some(einv), ..
            } = &self.galerkin
            {
                let at = slots::SCAL_EINV as usize;
                scal[at..at + einv.len()].copy_from_slice(einv);
            }
        }
        Ok(Begun { tol, pre, co, scal })
    }

    /// The scalars a run starts from, with the tolerance `rule` where it depends on ‖b̂‖
    /// (then the start evaluates it).
    pub(super) fn write_start(&self, scal: &mut [f64], rule: ToleranceRule) {
        let acc = self.ty.acc;
        if let ToleranceRule::Ratio {
            prev_norm,
            gamma,
            guard,
            lo,
            hi,
        } = rule
        {
            scal[slots::SCAL_RULE_ON as usize] = 1.0;
            self.ctx.write_buffer(
                &self.buf.scal,
                acc.size() * slots::SCAL_RULE_PREV as u64,
                &acc.bytes(&[prev_norm, gamma, guard, lo, hi]),
            );
        }
        self.ctx.write_buffer(&self.buf.scal, 0, &acc.bytes(scal));
        self.clear_state();
    }

    /// The first chunk of a solve of `dispatches` dispatches per iteration
    /// ([`schedule::first_chunk`]): as long as the longest of the last few solves took, a
    /// quarter more, or for a PCG's first solve as many iterations as
    /// [`schedule::FIRST_SOLVE_DISPATCHES`] pays for, at most [`FIRST_CHUNK_SOLVE`]. A loose
    /// solve says little about the tight one after it; an iteration recorded past the stop
    /// costs its dispatches as no-ops, a chunk too short a round trip.
    pub(super) fn first_chunk(&self, max: usize, dispatches: usize) -> usize {
        let bounds = (FIRST_CHUNK, FIRST_CHUNK_SOLVE, MAX_CHUNK);
        schedule::first_chunk(self.recent.iter().max().copied(), dispatches, bounds, max)
    }

    pub(super) fn run(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        rule: ToleranceRule,
        tail: Option<&Tail>,
        from_current: bool,
    ) -> Result<(DeviceCgInfo, Option<TailBytes>), GpuError> {
        let mut begun = self.begin(frames, params)?;
        self.last_eta = None;
        let (pre, co) = (begun.pre, begun.co);
        let max = params.max_iterations;
        let rule = if rule.depends_on_the_rhs() {
            rule
        } else {
            ToleranceRule::Fixed(check_tol(rule.eval(0.0))?)
        };
        if let ToleranceRule::Fixed(t) = rule {
            begun.scal[slots::SCAL_TOL2 as usize] = t * t;
            begun.scal[slots::SCAL_ETA as usize] = t;
        }
        self.write_start(&mut begun.scal, rule);

        // Start (from y = 0, so q = Ĥy = 0 without a product, or from the current y) and
        // the first chunk, in one submit; again where the status shows that E⁺ of the
        // aggregates had to come from the host.
        let first = self.first_chunk(max, self.iteration(frames, pre, co).len());
        let (mut st, mut bytes) =
            self.start_and_chunk(frames, (pre, co), first, tail, from_current)?;
        if self.coarse_fallback(&st, frames, co)? {
            self.write_start(&mut begun.scal, rule);
            (st, bytes) = self.start_and_chunk(frames, (pre, co), first, tail, from_current)?;
        }
        self.galerkin_from_status(&st);
        self.check_pinned(frames)?;
        st.error(0)?;
        self.run_starts = vec![0];
        let bb = st.bb;
        let rhs_norm = bb.sqrt();
        // The device's tolerance: the rule evaluated where ‖b̂‖ was formed.
        let tol = check_tol(st.eta)?;
        self.last_eta = Some(tol);
        let relative = |rr: f64| {
            if bb == 0.0 {
                if rr == 0.0 {
                    0.0
                } else {
                    1.0
                }
            } else {
                rr.sqrt() / rhs_norm
            }
        };
        // The run the first chunk began, from y = 0 (r·r = ‖b̂‖²) or the current y.
        let mut track = RunTrack::new(0, if from_current { f64::NAN } else { bb });
        let thresh = tol * tol * bb;
        let window = params.stagnation_window.max(1);
        // The first chunk's status, seen as `chunks` sees every later one.
        let mut check_now = false;
        if !st.converged {
            check_now = track.stagnated(&st, window);
            track.observe(&st, first, thresh);
        }
        // The smallest true residual so far: a check that does not improve on it ends the
        // solve in stagnation (the recurrence residual of f64 CG goes on falling long
        // after the true one has stopped at its rounding floor).
        let mut best_true = f64::INFINITY;
        let mut ended = Chunked::Stopped;
        loop {
            if check_now {
                ended = Chunked::Check;
                check_now = false;
            } else if !st.converged {
                ended = self.chunks(
                    frames,
                    (pre, co),
                    params,
                    thresh,
                    &mut st,
                    tail,
                    &mut bytes,
                    &mut track,
                    None,
                )?;
            }
            if !st.verified {
                // The run stopped without a verification (the window or the limit): the
                // true residual at y.
                (st, bytes) = self.true_residual(frames, (pre, co))?;
            }
            let rel = relative(st.rr);
            // A run that ends on no better a true residual than the best before it is at
            // the rounding floor, whether its recurrence met the tolerance or the
            // stagnation window ended it: another restart would only repeat it. A run
            // whose recurrence met the tolerance must also halve the best: away from the
            // floor the true residual falls with the recurrence, at the floor it only
            // creeps while the recurrence falls on past it. (A start that met the
            // tolerance on the device but not by the host's quotient began no run.)
            let ran = st.iterations > track.start;
            if ran {
                let gain = match ended {
                    Chunked::Stopped if st.iterations < max => MIN_RESTART_GAIN,
                    _ => 1.0,
                };
                if rel > tol && rel >= gain * best_true {
                    return Err(CgError::Stagnation {
                        iterations: st.iterations,
                        relative_residual: rel,
                        tol,
                    }
                    .into());
                }
                best_true = best_true.min(rel);
            }
            if rel <= tol {
                break;
            }
            if st.iterations >= max {
                return Err(CgError::MaxIterations {
                    iterations: st.iterations,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            if ran {
                self.run_starts.push(st.iterations);
            }
            // The next run goes on from the restart state the true residual left.
            self.clear_flags();
            (st.converged, st.verified, st.true_ok) = (false, false, false);
            track = RunTrack::new(st.iterations, st.rr);
        }
        let answered = self.finish(frames, &st)?;
        Ok((
            DeviceCgInfo {
                iterations: st.iterations,
                restarts: self.run_starts.len() - 1,
                recorded_iterations: self.recorded.get(),
                status_reads: self.reads.get(),
                relative_residual: relative(st.rr),
                rhs_norm,
                tolerance: tol,
            },
            (answered && tail.is_some()).then_some(bytes),
        ))
    }

    /// The true residual at y (q = Ĥy, then a restart's kernels), read with the status.
    fn true_residual(
        &self,
        frames: &DeviceFrames,
        (pre, co): (Pre, Co),
    ) -> Result<(ChunkStatus, TailBytes), GpuError> {
        self.clear_flags();
        let mut enc = self.encoder("pcg true residual");
        let mut kernels = self.product_of_y(frames, Mode::Iterate);
        kernels.extend(self.start(frames, pre, co, Mode::Iterate));
        self.pass(&mut enc, "pcg true residual", Phase::Cg, &kernels);
        let (st, bytes) = self.submit_and_read(enc, &[], "the device PCG's true residual")?;
        st.error(0)?;
        Ok((st, bytes))
    }

    /// A solve that met its tolerance with the status `st`: its iterations remembered for
    /// the next first chunk, and Δx recovered where the chunk's verification did not
    /// (the host's quotient met the tolerance where the device's missed it by rounding).
    /// Whether the verification had recovered it (and the tail run on it).
    fn finish(&mut self, frames: &DeviceFrames, st: &ChunkStatus) -> Result<bool, GpuError> {
        self.last_iterations = st.iterations;
        if self.recent.len() == RECENT_SOLVES {
            self.recent.pop_front();
        }
        self.recent.push_back(st.iterations);
        if !st.true_ok && !self.given_rhs {
            let mut enc = self.encoder("pcg recovery");
            let recover = self.kernels.product.recover(&self.ctx, Mode::Iterate);
            self.pass(
                &mut enc,
                "pcg recovery",
                Phase::Cg,
                &[(recover, self.launches.nodes, &frames.groups[0])],
            );
            self.ctx.submit(enc);
            self.ctx.check("recovering the device Newton step")?;
        }
        Ok(st.true_ok)
    }

    /// The start of a run and its first chunk of `k` iterations, in one submit (one
    /// wait).
    fn start_and_chunk(
        &self,
        frames: &DeviceFrames,
        (pre, co): (Pre, Co),
        k: usize,
        tail: Option<&Tail>,
        from_current: bool,
    ) -> Result<(ChunkStatus, TailBytes), GpuError> {
        let mut enc = self.encoder("pcg start");
        let mut kernels: Vec<Kernel> = Vec::new();
        if from_current {
            kernels.extend(self.product_of_y(frames, Mode::Iterate));
        } else {
            enc.clear_buffer(&self.buf.y, 0, None);
            enc.clear_buffer(&self.buf.q, 0, None);
        }
        kernels.extend(self.start(frames, pre, co, Mode::Iterate));
        self.pass(&mut enc, "pcg start", Phase::Cg, &kernels);
        self.chunk_submit(enc, frames, (pre, co), k, tail, true)
    }

    /// Records `k` iterations after the work in `enc`, the chunk's verification (with
    /// `verify`), Δx's recovery where it met the tolerance and the `tail`, then submits
    /// and reads the status (one wait).
    pub(super) fn chunk_submit(
        &self,
        mut enc: wgpu::CommandEncoder,
        frames: &DeviceFrames,
        (pre, co): (Pre, Co),
        k: usize,
        tail: Option<&Tail>,
        verify: bool,
    ) -> Result<(ChunkStatus, TailBytes), GpuError> {
        let one = self.iteration(frames, pre, co);
        let mut kernels: Vec<Kernel> = Vec::with_capacity(k * one.len() + 16);
        for _ in 0..k {
            kernels.extend(one.iter().map(|(_, kern)| kern.clone()));
        }
        self.recorded.set(self.recorded.get() + k);
        if verify {
            kernels.extend(self.product_of_y(frames, Mode::Verify));
            kernels.extend(self.start(frames, pre, co, Mode::Verify));
            let up = &self.kernels.update;
            kernels.push((up.verified(&self.ctx), ONE, &frames.groups[0]));
            if !self.given_rhs {
                let recover = self.kernels.product.recover(&self.ctx, Mode::Verify);
                kernels.push((recover, self.launches.nodes, &frames.groups[0]));
            }
        }
        self.pass(&mut enc, "pcg chunk", Phase::Cg, &kernels);
        let reads: &[ReadRange] = match tail {
            Some(t) => {
                (t.record)(&mut enc)?;
                t.read
            }
            None => &[],
        };
        self.submit_and_read(enc, reads, "a device PCG chunk")
    }

    /// q = Ĥx for a given x (frame coordinates, n·d) with these frames, read back: the
    /// product every iteration runs, for tests of the operator. Overwrites y (an
    /// `iterate` starts afresh from y = 0).
    pub fn apply(&mut self, frames: &DeviceFrames, x: &[f64]) -> Result<Vec<f64>, GpuError> {
        self.own(frames)?;
        if x.len() != self.n_nodes * self.dim {
            return Err(GpuError::Mismatch(format!(
                "x has {} entries, the system {}",
                x.len(),
                self.n_nodes * self.dim
            )));
        }
        self.ctx
            .write_buffer(&self.buf.y, 0, &self.ty.real.bytes(x));
        // No stop flag: the product runs.
        self.clear_state();
        let mut enc = self.encoder("pcg product");
        let kernels = self.product_of_y(frames, Mode::Iterate);
        self.pass(&mut enc, "pcg product", Phase::Cg, &kernels);
        self.ctx.submit(enc);
        self.ctx.check("the device PCG's product")?;
        self.read_vector(&self.buf.q, "reading back the product")
    }

    /// Compiles the pipelines a solve with these frames and parameters records (each is
    /// compiled the first time a solve asks for it), for a caller that counts compiling
    /// as setup rather than as its first solve's time.
    pub fn compile_solve_pipelines(&self, frames: &DeviceFrames, params: &DeviceCgParams) {
        let (pre, co) = overrides(params, frames);
        let _ = self.iteration(frames, pre, co);
        for mode in [Mode::Iterate, Mode::Verify] {
            let _ = self.start(frames, pre, co, mode);
            let _ = self.product_of_y(frames, mode);
        }
        let _ = self.kernels.update.verified(&self.ctx);
        let _ = self.kernels.product.recover(&self.ctx, Mode::Verify);
    }

    /// q = Ĥy: p = y and pw = V P y, then the product (`Verify`: only while verifying).
    pub(super) fn product_of_y<'a>(
        &'a self,
        frames: &'a DeviceFrames,
        mode: Mode,
    ) -> Vec<Kernel<'a>> {
        let pr = &self.kernels.product;
        let dev = &self.ctx;
        let mut k = vec![(
            pr.world_y(dev, mode),
            self.launches.nodes,
            &frames.groups[0],
        )];
        k.extend(Self::per_chunk(
            pr.matvec(dev, mode),
            &self.launches.chunk_segments,
            frames,
        ));
        k
    }

    /// The kernels of a (re)start from the q = Ĥy in `q`: r, z, p, ρ and the true r·r; with
    /// the coarse correction `start_p` (β = 0) then completes p = z + Z E⁺Zᵀr.
    pub(super) fn start<'a>(
        &'a self,
        frames: &'a DeviceFrames,
        pre: Pre,
        co: Co,
        mode: Mode,
    ) -> Vec<Kernel<'a>> {
        let up = &self.kernels.update;
        let dev = &self.ctx;
        let g0 = &frames.groups[0];
        let l = &self.launches;
        if pre == Pre::Multilevel {
            let mut k = vec![(up.init(dev, pre, Co::None, mode), l.segments, g0)];
            k.extend(self.vcycle(frames, mode).into_iter().map(|(_, k)| k));
            k.push((up.ml_start(dev, mode), l.segments, g0));
            k.push((up.scalar_start(dev, Co::None, mode), ONE, g0));
            return k;
        }
        let mut k = vec![(up.init(dev, pre, co, mode), l.segments, g0)];
        k.extend(self.aggregate_correction(frames, co, mode));
        k.push((up.scalar_start(dev, co, mode), ONE, g0));
        if co != Co::None {
            k.push((up.start_p(dev, co, mode), l.fused, g0));
        }
        k
    }

    /// With the aggregates: w = Zᵀr (a workgroup per aggregate) and c = E⁺w (a workgroup
    /// per coarse row).
    pub(super) fn aggregate_correction<'a>(
        &'a self,
        frames: &'a DeviceFrames,
        co: Co,
        mode: Mode,
    ) -> Vec<Kernel<'a>> {
        let (cp, limits) = (&self.kernels.coarse, self.ctx.launch());
        let dev = &self.ctx;
        // A workgroup per aggregate (coarse row) on a GPU; a CPU adapter's few loop over
        // them, each still summed by one workgroup in the same order.
        let policy = self.ctx.segments();
        match (&frames.agg, co) {
            (Some(a), Co::Aggregates) => vec![
                (
                    cp.agg_restrict(dev, mode),
                    policy.launch(&limits, a.count as u64, WORKGROUP),
                    &frames.groups[0],
                ),
                (
                    cp.agg_solve(dev, mode),
                    policy.launch(&limits, a.k as u64, WORKGROUP),
                    &frames.groups[0],
                ),
            ],
            _ => Vec::new(),
        }
    }

    /// The dispatches of z = M⁻¹r with the multilevel preconditioner (r and z the PCG's),
    /// named: the V-cycle's, with level 0's product the PCG's own (pw = V P z, then q = Ĥz).
    pub(super) fn vcycle<'a>(
        &'a self,
        frames: &'a DeviceFrames,
        mode: Mode,
    ) -> Vec<(&'static str, Kernel<'a>)> {
        let Some(ml) = &self.ml else {
            return Vec::new();
        };
        let pr = &self.kernels.product;
        let dev = &self.ctx;
        let mut out = Vec::new();
        for step in ml.steps(mode == Mode::Verify) {
            match step {
                Step::Kernel(name, pipe, launch, group) => {
                    out.push((name, (pipe.clone(), launch, group)))
                }
                Step::FinestProduct => {
                    out.push((
                        "ml world_z",
                        (
                            pr.world_z(dev, mode),
                            self.launches.nodes,
                            &frames.groups[0],
                        ),
                    ));
                    out.extend(
                        Self::per_chunk(
                            pr.matvec(dev, mode),
                            &self.launches.chunk_segments,
                            frames,
                        )
                        .map(|k| ("ml matvec", k)),
                    );
                }
            }
        }
        out
    }

    /// The dispatches of one CG iteration, named.
    pub(super) fn iteration<'a>(
        &'a self,
        frames: &'a DeviceFrames,
        pre: Pre,
        co: Co,
    ) -> Vec<(&'static str, Kernel<'a>)> {
        let (pr, up) = (&self.kernels.product, &self.kernels.update);
        let dev = &self.ctx;
        let l = &self.launches;
        let g0 = &frames.groups[0];
        let mut one: Vec<(&'static str, Kernel)> =
            Self::per_chunk(pr.matvec(dev, Mode::Iterate), &l.chunk_segments, frames)
                .map(|k| ("matvec", k))
                .collect();
        one.push(("update_yr", (up.update_yr(dev, pre, co), l.fused, g0)));
        if pre == Pre::Multilevel {
            one.extend(self.vcycle(frames, Mode::Iterate));
            one.push(("ml_dot", (up.ml_dot(dev), l.segments, g0)));
        }
        let agg = self.aggregate_correction(frames, co, Mode::Iterate);
        one.extend(["agg_restrict", "agg_solve"].into_iter().zip(agg));
        one.push(("update_p", (up.update_p(dev, co), l.fused, g0)));
        one
    }

    /// CG iterations in chunks from the current state until the recurrence residual meets
    /// `thresh` (on r·r; then the chunk's verification has computed the true residual),
    /// `params.max_iterations` are done in all, or the stagnation window asks for the true
    /// residual; `st` is the last status, `bytes` the tail's bytes read with it and
    /// `track` the run so far.
    /// A `watch` may stop the run after any status read.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn chunks(
        &self,
        frames: &DeviceFrames,
        (pre, co): (Pre, Co),
        params: &DeviceCgParams,
        thresh: f64,
        st: &mut ChunkStatus,
        tail: Option<&Tail>,
        bytes: &mut TailBytes,
        track: &mut RunTrack,
        mut watch: Option<&mut ChunkWatch>,
    ) -> Result<Chunked, GpuError> {
        let max = params.max_iterations;
        let window = params.stagnation_window.max(1);
        loop {
            let kk = track.next.min(max.saturating_sub(st.iterations));
            if kk == 0 {
                return Ok(Chunked::Stopped);
            }
            if st.iterations - track.start >= window {
                return Ok(Chunked::Check);
            }
            let kk = kk.min(window - (st.iterations - track.start));
            let enc = self.encoder("pcg chunk");
            (*st, *bytes) = self.chunk_submit(enc, frames, (pre, co), kk, tail, track.verify)?;
            st.error(0)?;
            if st.converged {
                return Ok(Chunked::Stopped);
            }
            if let Some(w) = watch.as_deref_mut() {
                if w(self, st.iterations)? {
                    return Ok(Chunked::Watched);
                }
            }
            if track.stagnated(st, window) {
                return Ok(Chunked::Check);
            }
            track.observe(st, kk, thresh);
        }
    }
}

/// One run of CG between restarts, as its status reads saw it: where it began, its best
/// recurrence r·r and where, the (iterations, ln r·r) history the chunk schedule predicts
/// from, and the next chunk's length.
pub(super) struct RunTrack {
    pub start: usize,
    /// Whether each chunk ends in its verification (not a segment's, which stops on the
    /// recurrence and keeps p for the next).
    pub verify: bool,
    best: f64,
    best_at: usize,
    hist: Vec<(usize, f64)>,
    next: usize,
}

impl RunTrack {
    /// A run beginning at iteration `start` with recurrence r·r `rr` (NaN: unknown).
    pub(super) fn new(start: usize, rr: f64) -> Self {
        let mut hist = Vec::new();
        if rr > 0.0 && rr.is_finite() {
            hist.push((start, rr.ln()));
        }
        RunTrack {
            start,
            verify: true,
            best: if rr.is_nan() { f64::INFINITY } else { rr },
            best_at: start,
            hist,
            next: FIRST_CHUNK,
        }
    }

    /// Whether the recurrence has not improved on its best for `window` iterations.
    pub(super) fn stagnated(&mut self, st: &ChunkStatus, window: usize) -> bool {
        if st.rr < self.best {
            (self.best, self.best_at) = (st.rr, st.iterations);
            false
        } else {
            st.iterations - self.best_at >= window
        }
    }

    /// A status read after a chunk of `k` iterations: its r·r joins the history and the
    /// next chunk is what the schedule predicts to reach `thresh` (on r·r).
    pub(super) fn observe(&mut self, st: &ChunkStatus, k: usize, thresh: f64) {
        if st.rr > 0.0 && st.rr.is_finite() {
            self.hist.push((st.iterations, st.rr.ln()));
        }
        self.next = schedule::next_chunk(&self.hist, thresh, k, MIN_CHUNK, MAX_CHUNK);
    }
}
