//! The device-resident CG driver: starting and resuming a run, recording chunks of
//! iterations, the status read-back, chunk sizing and the Lanczos condition estimate.

use super::levels::{LANCZOS_HIST, N_SCAL, N_STATE, SCAL_LEN};
use super::state::Outcome;
use super::GpuSolver;
use crate::gpu::kernels::slots;
use crate::gpu::schedule::{late_rate, next_chunk, state_words, ChunkStatus};
use crate::gpu::GpuError;

impl GpuSolver {
    /// Resets the CG scalars: ρ_prev, the convergence threshold, the direction scale kept
    /// by `init` (0: p = 0), flags cleared.
    fn reset_scalars(&self, thresh: f64, rho_prev: f64, pscale: f64) {
        let l = &self.dev.level;
        let mut s = vec![0.0f64; N_SCAL];
        s[slots::SCAL_RHO_PREV as usize] = rho_prev;
        s[slots::SCAL_THRESH as usize] = thresh;
        s[slots::SCAL_PSCALE as usize] = pscale;
        self.ctx.write_buffer(&l.buf.scal, 0, &l.acc.bytes(&s));
        self.ctx.write_buffer(&l.buf.state, 0, &[0u8; 4 * N_STATE]);
    }

    pub(super) fn dispatch(&mut self, pass: &mut wgpu::ComputePass<'_>, which: Which, groups: u32) {
        let (k, bg) = match which {
            Which::UpdateP => (&self.dev.level.k.update_p, &self.dev.level.k.cg_group),
            Which::UpdateXrz => (&self.dev.level.k.update_xrz, &self.dev.level.k.cg_group),
            Which::Init => (&self.dev.level.k.init, &self.dev.level.k.cg_group),
            Which::MatvecP | Which::MatvecX => {
                let l = &self.dev.level;
                let bgs = if matches!(which, Which::MatvecP) {
                    &l.k.matvec_p
                } else {
                    &l.k.matvec_x
                };
                l.op.dispatch(pass, bgs, groups, &self.ctx.launch(), self.dev.wg);
                let name = l.op.matvec.name;
                self.record(name);
                return;
            }
            Which::Restrict | Which::CoarseSolve => {
                let Some(agg) = &self.dev.level.k.agg else {
                    return;
                };
                let (kr, ks, bg) = (&agg.restrict, &agg.solve, &agg.group);
                let (k, groups) = if matches!(which, Which::Restrict) {
                    (kr, groups.min(self.dev.consts.agg))
                } else {
                    let rows = self.dev.dim as u32 * self.dev.consts.agg;
                    (ks, groups.min(rows.div_ceil(self.dev.wg)))
                };
                pass.set_pipeline(&k.pipeline);
                pass.set_bind_group(0, bg, &[]);
                // One aggregate (restrict) or row (solve) per item: any layout.
                self.ctx
                    .launch()
                    .groups(groups.max(1) as u64, self.dev.wg)
                    .dispatch(pass);
                let name = k.name;
                self.record(name);
                return;
            }
        };
        pass.set_pipeline(&k.pipeline);
        pass.set_bind_group(0, bg, &[]);
        // Reductions: exactly `groups` workgroups, one partial each.
        self.ctx
            .launch()
            .reduction(groups, self.dev.wg)
            .dispatch(pass);
        let name = k.name;
        self.record(name);
    }

    /// Starts CG at the current x (zeroed first unless `keep_x`): q = Ĥx, r = b − q,
    /// z = M⁻¹r, then the first update_p (p = z).
    pub(super) fn start(&mut self, keep_x: bool, thresh: f64) -> Result<(), GpuError> {
        self.begin(thresh, Begin::Restart { keep_x })
    }

    /// Mixed precision's reliable update: CG goes on from the new right-hand side b (the
    /// true residual, renormalized) with x = 0, r = b, and the search direction kept,
    /// rescaled by `pscale` (= ‖r_old‖/‖r_new‖, the ratio of the two normalizations);
    /// `rho_prev` is ρ_prev in the new normalization. Restarting instead (p = 0) throws the
    /// Krylov space away and costs mixed 40% more iterations than f64 CG (64k nodes).
    pub(super) fn resume(
        &mut self,
        thresh: f64,
        rho_prev: f64,
        pscale: f64,
    ) -> Result<(), GpuError> {
        self.begin(thresh, Begin::Resume { rho_prev, pscale })
    }

    /// The common start of a CG run: scalars, then init and the first update_p. A restart
    /// computes q = Ĥx; a resume has x = 0, so it clears q instead of a product.
    fn begin(&mut self, thresh: f64, how: Begin) -> Result<(), GpuError> {
        let (label, what) = match how {
            Begin::Restart { .. } => ("cg start", "starting CG"),
            Begin::Resume { .. } => ("cg reliable update", "reliable update"),
        };
        let mut enc = self.encoder(label);
        match how {
            Begin::Restart { keep_x } => {
                self.reset_scalars(thresh, 1.0, 0.0);
                self.run.lz_resumed = false;
                if !keep_x {
                    enc.clear_buffer(&self.dev.level.buf.x, 0, None);
                }
            }
            Begin::Resume { rho_prev, pscale } => {
                self.reset_scalars(thresh, rho_prev, pscale);
                self.run.lz_resumed = true;
                enc.clear_buffer(&self.dev.level.buf.x, 0, None);
                enc.clear_buffer(&self.dev.level.buf.q, 0, None);
            }
        }
        {
            let mut pass = enc
                .begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(label),
                    timestamp_writes: None,
                })
                .forget_lifetime();
            let g = self.dev.n_partials;
            if matches!(how, Begin::Restart { .. }) {
                self.dispatch(&mut pass, Which::MatvecX, g);
            }
            self.dispatch(&mut pass, Which::Init, g);
            self.dispatch(&mut pass, Which::Restrict, g);
            self.dispatch(&mut pass, Which::CoarseSolve, g);
            self.dispatch(&mut pass, Which::UpdateP, g);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check(what)
    }

    /// Records `k` iterations in one submit, then reads the status back.
    pub(super) fn chunk(&mut self, k: usize) -> Result<ChunkStatus, GpuError> {
        self.tel.recorded += k;
        let mut enc = self.encoder("cg chunk");
        {
            let tw = self
                .dev
                .timestamps
                .as_ref()
                .map(|t| wgpu::ComputePassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: Some(0),
                    end_of_pass_write_index: Some(1),
                });
            let mut pass = enc
                .begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("cg chunk pass"),
                    timestamp_writes: tw,
                })
                .forget_lifetime();
            let g = self.dev.n_partials;
            for _ in 0..k {
                self.dispatch(&mut pass, Which::MatvecP, g);
                self.dispatch(&mut pass, Which::UpdateXrz, g);
                self.dispatch(&mut pass, Which::Restrict, g);
                self.dispatch(&mut pass, Which::CoarseSolve, g);
                self.dispatch(&mut pass, Which::UpdateP, g);
            }
        }
        let l = &self.dev.level;
        // The scalars and the coefficient history (16 KiB in f64: no extra read-back).
        let sb = l.acc.size() * SCAL_LEN as u64;
        enc.copy_buffer_to_buffer(&l.buf.scal, 0, &l.buf.status_staging, 0, sb);
        enc.copy_buffer_to_buffer(
            &l.buf.state,
            0,
            &l.buf.status_staging,
            sb,
            4 * N_STATE as u64,
        );
        if let Some(t) = &self.dev.timestamps {
            enc.resolve_query_set(&t.set, 0..2, &t.resolve, 0);
            enc.copy_buffer_to_buffer(
                &t.resolve,
                0,
                &l.buf.status_staging,
                sb + 4 * N_STATE as u64,
                16,
            );
        }
        self.ctx.queue.submit([enc.finish()]);
        let total = sb + 4 * N_STATE as u64 + 16;
        let staging = self.dev.level.buf.status_staging.clone();
        let bytes = self.read(&staging, total)?;
        let scal = self.dev.level.acc.values(&bytes[..sb as usize]);
        let st = state_words(&bytes[sb as usize..sb as usize + 4 * N_STATE]);
        if let Some(t) = &self.dev.timestamps {
            let o = sb as usize + 4 * N_STATE;
            let t0 = u64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
            let t1 = u64::from_le_bytes(bytes[o + 8..o + 16].try_into().expect("8 bytes"));
            self.tel.gpu_seconds += t1.saturating_sub(t0) as f64 * t.period_ns * 1e-9;
        }
        self.run.last_rho_prev = scal[slots::SCAL_RHO_PREV as usize];
        let st_out = ChunkStatus::read(&scal, &st);
        self.run.last_scal = scal;
        Ok(st_out)
    }

    /// Appends the Lanczos coefficients of the run that just ended (from the last status
    /// read) to the current sequence: continued across a reliable update (joined by the
    /// β of its first update_p), else after closing the previous sequence.
    fn lanczos_collect(&mut self, iterations: usize) {
        let resumed = std::mem::take(&mut self.run.lz_resumed);
        if !resumed || self.run.lz_alphas.is_empty() {
            self.lanczos_close();
        } else {
            let beta0 = self.run.last_scal[slots::SCAL_BETA0 as usize];
            self.run.lz_betas.push(beta0);
        }
        let n = iterations.min(LANCZOS_HIST);
        let h = &self.run.last_scal[N_SCAL..];
        self.run.lz_alphas.extend((0..n).map(|j| h[2 * j]));
        self.run
            .lz_betas
            .extend((0..n.saturating_sub(1)).map(|j| h[2 * j + 1]));
        if iterations > LANCZOS_HIST {
            // Truncated: the next run cannot continue this sequence.
            self.lanczos_close();
        }
    }

    /// Ends the current coefficient sequence, keeping the largest estimate so far.
    pub(super) fn lanczos_close(&mut self) {
        if let Some(k) =
            crate::solve::cg::lanczos_condition(&self.run.lz_alphas, &self.run.lz_betas)
        {
            self.run.kappa_est = Some(self.run.kappa_est.map_or(k, |c: f64| c.max(k)));
        }
        self.run.lz_alphas.clear();
        self.run.lz_betas.clear();
    }

    /// κ̃(M⁻¹Ĥ) during a run, after `iters` iterations: the closed sequences, the open
    /// one, and this run's coefficients so far (joined to the open one when the run
    /// resumed it, as `lanczos_collect` will join them).
    fn kappa_in_run(&self, iters: usize) -> Option<f64> {
        let n = iters.min(LANCZOS_HIST);
        let h = &self.run.last_scal[N_SCAL..];
        let run_a = (0..n).map(|j| h[2 * j]);
        let run_b = (0..n.saturating_sub(1)).map(|j| h[2 * j + 1]);
        let (a, b, earlier): (Vec<f64>, Vec<f64>, Option<f64>) = if self.run.lz_resumed
            && !self.run.lz_alphas.is_empty()
        {
            let a = self.run.lz_alphas.iter().copied().chain(run_a).collect();
            let b = self
                .run
                .lz_betas
                .iter()
                .copied()
                .chain(std::iter::once(
                    self.run.last_scal[slots::SCAL_BETA0 as usize],
                ))
                .chain(run_b)
                .collect();
            (a, b, None)
        } else {
            let open = crate::solve::cg::lanczos_condition(&self.run.lz_alphas, &self.run.lz_betas);
            (run_a.collect(), run_b.collect(), open)
        };
        [
            crate::solve::cg::lanczos_condition(&a, &b),
            earlier,
            self.run.kappa_est,
        ]
        .into_iter()
        .flatten()
        .reduce(f64::max)
    }

    /// κ̃(M⁻¹Ĥ) of the current sequence and the earlier ones.
    pub(super) fn kappa_now(&self) -> Option<f64> {
        let cur = crate::solve::cg::lanczos_condition(&self.run.lz_alphas, &self.run.lz_betas);
        match (cur, self.run.kappa_est) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        }
    }

    /// Runs CG from the state `start` left until the recurrence residual² ≤ `thresh`,
    /// the budget, or stagnation. Returns the outcome and the iterations done.
    ///
    /// Chunk sizing: the first chunks double from `first_chunk` (or start at 3/4 of
    /// `chunk_hint`); once two status reads exist, the next chunk is the number of
    /// iterations predicted to reach `thresh` at the residual reduction rate observed over
    /// the later half of the run so far (3/4 of it when it exceeds 8: CG speeds up),
    /// clamped to [first_chunk/4, min(2·previous, max_chunk)]. Iterations recorded past
    /// convergence are then at most about one prediction error (or first_chunk/4), not
    /// half the run.
    pub(super) fn run_cg(
        &mut self,
        budget: usize,
        done_before: usize,
        thresh: f64,
    ) -> Result<(Outcome, usize), GpuError> {
        let res = self.run_cg_chunks(budget, done_before, thresh);
        if let Ok((_, it)) = &res {
            self.lanczos_collect(*it);
        } else {
            self.run.lz_resumed = false;
        }
        res
    }

    fn run_cg_chunks(
        &mut self,
        budget: usize,
        done_before: usize,
        thresh: f64,
    ) -> Result<(Outcome, usize), GpuError> {
        let cap = self.params.max_chunk;
        // An iteration recorded past convergence is not free (on lavapipe it costs a third
        // of a real one), while a status read costs less than an iteration there and a few
        // on a discrete GPU. So once the rate is known, chunks follow the prediction down
        // to `first_chunk / 4`. A hint (mixed: the previous segment's length) is a guess,
        // and segments shorten as the Krylov space kept across reliable updates grows: the
        // first chunk takes 3/4 of it.
        let floor = self.params.first_chunk.div_ceil(4);
        let mut k = match self.run.chunk_hint.take() {
            Some(h) => (3 * h).div_ceil(4).clamp(1, cap),
            None => self.params.first_chunk.min(cap),
        };
        let mut best = f64::INFINITY;
        let mut best_at = 0usize;
        let mut iters = 0usize;
        // (iterations, ln r·r) at each status read.
        let mut hist: Vec<(usize, f64)> = Vec::new();
        if let Some(rr0) = self
            .run
            .start_rr
            .take()
            .filter(|v| *v > 0.0 && v.is_finite())
        {
            hist.push((0, rr0.ln()));
        }
        loop {
            let kk = k.min(budget.saturating_sub(iters));
            if kk == 0 {
                return Ok((Outcome::MaxIters, iters));
            }
            let st = self.chunk(kk)?;
            iters = st.iterations;
            st.error(done_before)?;
            if st.converged {
                if st.rr > 0.0 && st.rr.is_finite() {
                    hist.push((iters, st.rr.ln()));
                }
                self.run.last_rate = late_rate(&hist);
                return Ok((Outcome::Converged, iters));
            }
            if let Some((policy, outer)) = self.run.kappa_watch {
                if let Some(why) = policy.kappa_verdict(outer, self.kappa_in_run(iters)) {
                    return Ok((Outcome::LeaveF32(why), iters));
                }
            }
            if st.rr < best {
                best = st.rr;
                best_at = iters;
            } else if iters - best_at >= self.params.stagnation_window {
                return Ok((Outcome::Stagnated, iters));
            }
            if st.rr > 0.0 && st.rr.is_finite() {
                hist.push((iters, st.rr.ln()));
            }
            k = next_chunk(&hist, thresh, kk, floor, cap);
        }
    }
}

/// How `GpuSolver::begin` starts a CG run.
#[derive(Clone, Copy)]
enum Begin {
    /// From the current x (or zero), p = 0.
    Restart { keep_x: bool },
    /// Mixed's reliable update: x = 0, p kept and rescaled.
    Resume { rho_prev: f64, pscale: f64 },
}

#[derive(Clone, Copy)]
pub(super) enum Which {
    UpdateP,
    UpdateXrz,
    Init,
    MatvecP,
    MatvecX,
    /// Aggregate coarse correction: w = Zᵀr, then c = E⁺w (no-ops without aggregates).
    Restrict,
    CoarseSolve,
}
