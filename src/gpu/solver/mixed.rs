//! Mixed precision: f32 CG with reliable updates and an f64 outer residual, the f64
//! fallback (GPU or CPU), extended-precision refinement and the f32 operator's scale.

use super::builder::{Builder, Real};
use super::host::HostOp;
use super::levels::{build_level, build_operator};
use super::plan::{self, binding_limit, memory_limit, DOES_NOT_FIT};
use super::policy::{resume_scales, MixedPolicy, Stop};
use super::state::Outcome;
use super::{GpuSolver, Solved};
use crate::core::elimination::{norm2, Eliminated};
use crate::core::sparse::BlockCsr;
use crate::gpu::GpuError;
use crate::solve::cg::CgError;
use std::time::Instant;

impl GpuSolver {
    /// Mixed precision, in three stages, each entered only when the one before cannot go on:
    /// 1. f32 CG with reliable updates (f64 accumulation of y, f64 true residuals);
    /// 2. f64 CG (GPU, else CPU), warm-started from y, when f32 meets non-positive
    ///    curvature, breaks down, a segment reduces the true residual less than 2×, or
    ///    the f32 CG's condition estimate is too large for f32 (`policy.rs`);
    /// 3. extended-precision refinement when f64 CG stagnates on its residual's rounding
    ///    floor (and, with `error_tol`, after success, until the error estimate is met).
    pub(super) fn solve_mixed(
        &mut self,
        bnorm: f64,
        notes: &mut Vec<String>,
    ) -> Result<Solved, GpuError> {
        let tol = self.params.tol;
        let t0 = Instant::now();
        let mut total = 0usize;
        let mut dl = 0.0;
        if self.dev.refine.as_ref().is_some_and(|r| r.op.is_none()) {
            notes.push(
                "mixed: the f64 blocks exceed the adapter's buffer size limit; only the f32 \
                 blocks live on the device and the outer f64 residual is computed on the host"
                    .into(),
            );
        }
        if self.mixed.inner_scale != 1.0 {
            notes.push(format!(
                "mixed: Ĥ's diagonal is extreme; the f32 operator holds 2^{} Ĥ (exact) and the \
                 corrections are scaled back in f64",
                self.mixed.inner_scale.log2()
            ));
        }
        self.clear_y64();
        let policy = MixedPolicy::new(&self.params);
        let mut outer = 0usize;
        let mut prev = f64::INFINITY;
        // (ρ_prev, ‖r‖) of a converged f32 segment: the next one resumes from its direction.
        let mut keep: Option<(f64, f64)> = None;
        let mut seg_hint: Option<usize> = None;
        let reason: String = loop {
            let rel = self.outer_residual()? / bnorm;
            if policy.converged(rel) {
                let td = Instant::now();
                let (y, dx) = self.download_solution()?;
                dl += td.elapsed().as_secs_f64();
                let true_rel = self.host.relative_residual(&y);
                if policy.converged(true_rel) {
                    let (total, y, dx) = self.certify(total, &mut dl, notes, y, dx)?;
                    return Ok(Solved {
                        iterations: total,
                        outer,
                        restarts: 0,
                        solve_seconds: t0.elapsed().as_secs_f64() - dl,
                        download_seconds: dl,
                        y,
                        dx,
                    });
                }
                notes.push(format!(
                    "device f64 residual {rel:e} but host residual {true_rel:e}; refining further"
                ));
            }
            match policy.before_segment(outer, total, rel, prev) {
                None => {}
                Some(Stop::Fallback(why)) => {
                    if !rel.is_finite() {
                        self.clear_y64();
                    }
                    break why;
                }
                Some(stop) => {
                    let (y, _) = self.download_solution()?;
                    let true_rel = self.host.relative_residual(&y);
                    return Err(if stop == Stop::MaxIterations {
                        CgError::MaxIterations {
                            iterations: total,
                            relative_residual: true_rel,
                            tol,
                        }
                    } else {
                        CgError::Stagnation {
                            iterations: total,
                            relative_residual: true_rel,
                            tol,
                        }
                    }
                    .into());
                }
            }
            prev = rel;
            // f32 CG on 2^s Ĥ d̃ = r/‖r‖ (unit right-hand side) until its recurrence residual
            // has dropped by δ = inner_tol; then y += 2^s‖r‖d̃ in f64, the true residual is
            // recomputed in f64 and replaces the f32 one (a reliable update, as in QUDA's
            // mixed-precision CG), and CG goes on with its search direction kept. Only
            // after an f32 segment that did not converge (stagnation, budget) does the next
            // segment restart from p = 0.
            let rn = rel * bnorm;
            let thresh = policy.inner_threshold();
            match keep
                .take()
                .and_then(|(rho, rn_prev)| resume_scales(rho, rn_prev, rn))
            {
                Some((rho_prev, ps)) => self.resume(thresh, rho_prev, ps)?,
                None => self.start(false, thresh)?,
            }
            self.run.chunk_hint = seg_hint;
            self.run.start_rr = Some(1.0);
            // The condition estimate is watched at every status read of the segment.
            self.run.kappa_watch = Some((policy, outer + 1));
            let run = self.run_cg(self.params.max_iters - total, total, thresh);
            self.run.kappa_watch = None;
            match run {
                Ok((out, it)) => {
                    total += it;
                    outer += 1;
                    self.accumulate();
                    match out {
                        Outcome::Converged => {
                            keep = Some((self.run.last_rho_prev, rn));
                            seg_hint = Some(policy.segment_hint(it, self.run.last_rate));
                        }
                        Outcome::LeaveF32(why) => break why,
                        Outcome::MaxIters | Outcome::Stagnated => {}
                    }
                    if let Some(why) = policy.kappa_verdict(outer, self.kappa_now()) {
                        break why;
                    }
                }
                Err(GpuError::Cg(CgError::NonPositiveCurvature {
                    iteration,
                    curvature,
                })) => {
                    total = total.max(iteration.saturating_sub(1));
                    outer += 1;
                    // x is the last iterate before the rejected step: keep its progress.
                    self.accumulate();
                    break format!(
                        "outer step {outer}: the f32 inner CG met non-positive curvature \
                         pᵀĤp = {curvature:e} at iteration {iteration} (f32 rounding; f64 CG \
                         checks Ĥ again)"
                    );
                }
                Err(GpuError::Cg(CgError::Breakdown { iteration })) => {
                    total = total.max(iteration);
                    outer += 1;
                    break format!(
                        "outer step {outer}: the f32 inner CG broke down (non-finite value) at \
                         iteration {iteration}"
                    );
                }
                Err(e) => return Err(e),
            }
        };
        // Fallback: f64 CG for the rest of the solve, warm-started from the f64 iterate.
        let on_gpu = self.dev.refine.as_ref().is_some_and(|r| r.op.is_some())
            && !self.mixed.force_cpu_fallback
            && match self.ensure_fallback_level() {
                Ok(()) => true,
                Err(e @ GpuError::BufferTooLarge { .. }) => {
                    notes.push(format!("f64 fallback level does not fit on the GPU: {e}"));
                    false
                }
                Err(GpuError::Device(m)) if m.contains(DOES_NOT_FIT) => {
                    notes.push(format!("f64 fallback level: {m}"));
                    false
                }
                Err(e) => return Err(e),
            };
        let place = if on_gpu {
            "f64 CG on the GPU"
        } else {
            "f64 CG on the CPU (src/solve/cg.rs)"
        };
        let msg = format!("{reason}; finished by {place}, warm-started from the f64 iterate");
        notes.push(format!("mixed fell back to f64: {msg}"));
        self.mixed.last_fallback = Some(msg);
        let fb = if on_gpu {
            self.fallback_gpu(total, &mut dl)
        } else {
            self.fallback_cpu(total, &mut dl)
        };
        let (all, restarts, y, dx) = match fb {
            Ok((it, restarts, y, dx)) => {
                let (all, y, dx) = self.certify(total + it, &mut dl, notes, y, dx)?;
                (all, restarts, y, dx)
            }
            Err(GpuError::Cg(CgError::Stagnation {
                iterations,
                relative_residual,
                ..
            })) if on_gpu && matches!(self.host.op, HostOp::Blocks(_)) => {
                notes.push(format!(
                    "f64 CG stagnated at relative residual {relative_residual:.3e} (its \
                     rounding floor); extended-precision refinement (double-double residuals \
                     on the host, f64 CG corrections on the GPU) goes on"
                ));
                // The residual cannot show tol: the error estimate must be ≤ tol instead
                // (and ≤ error_tol when that is asked for too).
                let target = self
                    .params
                    .error_tol
                    .map_or(self.params.tol, |et| et.min(self.params.tol));
                let (it, y, dx) = self.refine_extended(iterations, &mut dl, notes, target)?;
                (iterations + it, 0, y, dx)
            }
            Err(e) => return Err(e),
        };
        Ok(Solved {
            iterations: all,
            outer,
            restarts,
            solve_seconds: t0.elapsed().as_secs_f64() - dl,
            download_seconds: dl,
            y,
            dx,
        })
    }

    /// Mixed with `error_tol`: after the residual criterion is met, extended-precision
    /// refinement goes on until the estimated relative error is ≤ error_tol. Without it,
    /// returns its inputs.
    fn certify(
        &mut self,
        total: usize,
        dl: &mut f64,
        notes: &mut Vec<String>,
        y: Vec<f64>,
        dx: Vec<f64>,
    ) -> Result<(usize, Vec<f64>, Vec<f64>), GpuError> {
        let Some(target) = self.params.error_tol else {
            return Ok((total, y, dx));
        };
        if !matches!(self.host.op, HostOp::Blocks(_)) {
            return Err(GpuError::Unsupported(
                "error_tol needs an assembled Hessian (not a mass-spring operator)".into(),
            ));
        }
        if self.dev.refine.as_ref().is_some_and(|r| r.op.is_none()) {
            return Err(GpuError::Unsupported(
                "error_tol needs the f64 operator on the GPU, and its blocks exceed the \
                 adapter's buffer size limit"
                    .into(),
            ));
        }
        self.ensure_fallback_level()?;
        notes.push(format!(
            "error_tol {target:e}: extended-precision refinement estimates and reduces the error"
        ));
        let (it, y, dx) = self.refine_extended(total, dl, notes, target)?;
        Ok((total + it, y, dx))
    }

    /// Mixed precision's last stage, after f64 CG stagnated above `tol`: iterative
    /// refinement y ← y + d with r = b̂ − Ĥy in double-double on the host
    /// ([`BlockCsr::residual_dd`]) and Ĥd = r solved by f64 CG on the GPU. Each step
    /// contracts the error by the inner solve's relative error η (≈ κε), so y converges to
    /// the solution of the f64 Ĥ while κε < 1, past the f64 residual's rounding floor.
    /// Success is claimed when the estimated error ‖d‖/‖y‖·ρ/(1 − ρ) (ρ the observed
    /// contraction of consecutive corrections) is ≤ tol; a contraction ρ ≥ 1/2 ends it with
    /// `Stagnation`. Returns the iterations of its inner solves, y and Δx.
    fn refine_extended(
        &mut self,
        done: usize,
        dl: &mut f64,
        notes: &mut Vec<String>,
        target: f64,
    ) -> Result<(usize, Vec<f64>, Vec<f64>), GpuError> {
        let nd = self.host.ndof();
        let y64 = self.y64();
        let mut y = self.download_y64(nd, dl)?;
        if self.mixed.assembled.is_none() {
            let HostOp::Blocks(h) = &self.host.op else {
                return Err(GpuError::Unsupported(
                    "extended-precision refinement needs an assembled Hessian".into(),
                ));
            };
            let e = Eliminated {
                h,
                frames: &self.host.frames,
                rhs: Vec::new(),
                diag: self.host.diag.clone(),
            };
            self.mixed.assembled = Some(e.assemble());
        }
        let a = self.mixed.assembled.take().expect("assembled above");
        let res =
            self.on_fallback_level(|s| s.refine_extended_run(&a, &mut y, done, notes, target));
        self.mixed.assembled = Some(a);
        let (its, est) = res?;
        self.mixed.last_error_estimate = Some(est);
        self.ctx.write_buffer(&y64, 0, &Real::F64.bytes(&y));
        let td = Instant::now();
        let (y, dx) = self.download_solution()?;
        *dl += td.elapsed().as_secs_f64();
        Ok((its, y, dx))
    }

    fn refine_extended_run(
        &mut self,
        a: &BlockCsr,
        y: &mut [f64],
        done: usize,
        notes: &mut Vec<String>,
        target: f64,
    ) -> Result<(usize, f64), GpuError> {
        // Corrections within a few ulps of y are rounding: y is then the f64 Ĥ's solution
        // to working precision.
        const ROUNDING: f64 = 8.0 * f64::EPSILON;
        const MAX_STEPS: usize = 10;
        // The inner CG's recurrence target: far below the f64 residual floor, so the
        // correction is as accurate as f64 CG makes it.
        const INNER_TOL: f64 = 1e-12;
        let tol = self.params.tol;
        let nd = y.len();
        let bnorm = norm2(&self.host.rhs);
        let mut its = 0usize;
        let mut prev: Option<f64> = None;
        for step in 1..=MAX_STEPS {
            let r = a.residual_dd(&self.host.rhs, y);
            let rn = norm2(&r);
            let rel = rn / bnorm;
            if rn == 0.0 {
                notes.push(format!(
                    "extended step {step}: the residual is exactly zero"
                ));
                return Ok((its, 0.0));
            }
            let scaled: Vec<f64> = r.iter().map(|v| v / rn).collect();
            self.ctx
                .write_buffer(&self.dev.level.buf.b, 0, &Real::F64.bytes(&scaled));
            self.start(false, INNER_TOL * INNER_TOL)?;
            let budget = self.params.max_iters.saturating_sub(done + its);
            let (out, it) = self.run_cg(budget, done + its, INNER_TOL * INNER_TOL)?;
            its += it;
            // A correction from a stagnated inner CG is still used (it is the best f64 CG
            // reaches), but it may underestimate the error: no claim on its step.
            let inner_converged = matches!(out, Outcome::Converged);
            if matches!(out, Outcome::MaxIters) {
                return Err(CgError::MaxIterations {
                    iterations: done + its,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            let x_buf = self.dev.level.buf.x.clone();
            let x = self.download(self.encoder("download correction"), &x_buf, Real::F64, nd)?;
            let mut d2 = 0.0f64;
            for (v, xk) in y.iter_mut().zip(&x) {
                let d = rn * xk;
                *v += d;
                d2 += d * d;
            }
            let yn = norm2(y);
            if !(d2.is_finite() && yn.is_finite()) {
                return Err(CgError::Breakdown {
                    iteration: done + its,
                }
                .into());
            }
            let eta = if yn > 0.0 { d2.sqrt() / yn } else { 0.0 };
            let (rho, est) = match prev {
                _ if !inner_converged => (f64::NAN, f64::INFINITY),
                // Rounding-level corrections count only after one observed contraction.
                Some(_) if eta <= ROUNDING => (0.0, ROUNDING),
                Some(pe) if pe > 0.0 => {
                    let rho = eta / pe;
                    // Floored at the rounding of y itself: no f64 vector is closer than that.
                    let est = eta * rho / (1.0 - rho).max(f64::MIN_POSITIVE);
                    (rho, est.max(ROUNDING))
                }
                _ => (f64::NAN, f64::INFINITY),
            };
            notes.push(format!(
                "extended step {step}: residual (double-double) {rel:.3e}, correction \
                 ‖d‖/‖y‖ {eta:.3e}, contraction {rho:.2e}, error estimate {est:.2e} \
                 ({it} f64 CG iterations)"
            ));
            if est <= target {
                return Ok((its, est));
            }
            if rho >= 0.5 {
                break;
            }
            prev = Some(eta);
        }
        // The residual of the iterate that is returned.
        let rel = norm2(&a.residual_dd(&self.host.rhs, y)) / bnorm;
        Err(CgError::Stagnation {
            iterations: done + its,
            relative_residual: rel,
            tol,
        }
        .into())
    }

    /// The f64 iterate y of mixed precision (a handle to its device buffer).
    fn y64(&self) -> wgpu::Buffer {
        self.dev
            .refine
            .as_ref()
            .expect("mixed has a refinement level")
            .y64
            .clone()
    }

    /// Downloads the f64 iterate y (`nd` values), adding the time to `dl`.
    fn download_y64(&mut self, nd: usize, dl: &mut f64) -> Result<Vec<f64>, GpuError> {
        let y64 = self.y64();
        let td = Instant::now();
        let y = self.download(self.encoder("download y"), &y64, Real::F64, nd)?;
        *dl += td.elapsed().as_secs_f64();
        Ok(y)
    }

    fn clear_y64(&mut self) {
        let rf = self
            .dev
            .refine
            .as_ref()
            .expect("mixed has a refinement level");
        let mut enc = self.encoder("mixed reset");
        enc.clear_buffer(&rf.y64, 0, None);
        self.ctx.queue.submit([enc.finish()]);
    }

    /// y64 += 2^s·‖r‖·x32 (the factors written by `outer_residual`).
    fn accumulate(&mut self) {
        let rf = self
            .dev
            .refine
            .as_ref()
            .expect("mixed has a refinement level");
        let mut enc = self.encoder("mixed accumulate");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("accumulate pass"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&rf.k_accumulate.pipeline);
            pass.set_bind_group(0, &rf.bg_refine, &[]);
            self.ctx
                .launch()
                .grid((self.dev.n_nodes * self.dev.dim) as u64, self.dev.wg)
                .dispatch(&mut pass);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.record("accumulate");
    }

    /// Builds the f64 CG level of the fallback (once; kept across solves and updates).
    fn ensure_fallback_level(&mut self) -> Result<(), GpuError> {
        if self.dev.fallback_level.is_some() {
            return Ok(());
        }
        let ctx = self.ctx.clone();
        let acc = self.dev.level.acc;
        if let Some(mem) = memory_limit(&ctx, &self.params) {
            let c = &self.dev.consts;
            let need = plan::level_bytes(&ctx, &self.host, &self.params, c, Real::F64, acc)?;
            let used = self.tel.resources().total_bytes();
            ctx.check_fits(used + need, Some(mem))?;
        }
        let mut bld = Builder::new(&ctx, binding_limit(&ctx, &self.params));
        let op = build_operator(
            &mut bld,
            &self.dev.shared,
            &self.host,
            Real::F64,
            acc,
            &self.dev.consts,
        )?;
        let level = build_level(
            &mut bld,
            &self.dev.shared,
            op,
            &self.host,
            acc,
            &self.dev.consts,
            self.params.preconditioner,
        )?;
        ctx.check("allocating the f64 fallback level")?;
        self.tel.extend("fallback_", bld.buffers, bld.kernels);
        self.dev.fallback_level = Some(level);
        if let Some(fl) = &self.dev.fallback_level {
            self.write_operator(&fl.op, 1.0);
            self.write_coarse(fl, 1.0);
        }
        self.setup_levels(false, true)
    }

    /// Runs `f` with the f64 fallback level in the CG's place, then puts both back.
    fn on_fallback_level<T>(
        &mut self,
        f: impl FnOnce(&mut Self) -> Result<T, GpuError>,
    ) -> Result<T, GpuError> {
        let Some(mut fb) = self.dev.fallback_level.take() else {
            return Err(GpuError::Device("the f64 fallback level is missing".into()));
        };
        std::mem::swap(&mut self.dev.level, &mut fb);
        let r = f(self);
        std::mem::swap(&mut self.dev.level, &mut fb);
        self.dev.fallback_level = Some(fb);
        r
    }

    /// The fallback on the GPU: the f64 level takes the CG's place for the run.
    fn fallback_gpu(
        &mut self,
        done: usize,
        dl: &mut f64,
    ) -> Result<(usize, usize, Vec<f64>, Vec<f64>), GpuError> {
        self.on_fallback_level(|s| s.fallback_gpu_run(done, dl))
    }

    fn fallback_gpu_run(
        &mut self,
        done: usize,
        dl: &mut f64,
    ) -> Result<(usize, usize, Vec<f64>, Vec<f64>), GpuError> {
        let tol = self.params.tol;
        let thresh = (tol * norm2(&self.host.rhs)).powi(2);
        let nd = self.host.ndof() as u64;
        let y64 = self.y64();
        self.ctx
            .write_buffer(&self.dev.level.buf.b, 0, &Real::F64.bytes(&self.host.rhs));
        let mut enc = self.encoder("fallback warm start");
        enc.copy_buffer_to_buffer(&y64, 0, &self.dev.level.buf.x, 0, nd * 8);
        self.ctx.queue.submit([enc.finish()]);
        let mut total = 0usize;
        let mut restarts = 0usize;
        loop {
            self.start(true, thresh)?;
            let budget = self.params.max_iters.saturating_sub(done + total);
            let (out, it) = self.run_cg(budget, done + total, thresh)?;
            total += it;
            let mut enc = self.encoder("fallback result");
            enc.copy_buffer_to_buffer(&self.dev.level.buf.x, 0, &y64, 0, nd * 8);
            self.ctx.queue.submit([enc.finish()]);
            let td = Instant::now();
            let (y, dx) = self.download_solution()?;
            *dl += td.elapsed().as_secs_f64();
            let rel = self.host.relative_residual(&y);
            match out {
                Outcome::Converged if rel <= tol => return Ok((total, restarts, y, dx)),
                Outcome::Converged
                    if restarts < self.params.max_restarts
                        && done + total < self.params.max_iters =>
                {
                    restarts += 1;
                }
                Outcome::MaxIters => {
                    return Err(CgError::MaxIterations {
                        iterations: done + total,
                        relative_residual: rel,
                        tol,
                    }
                    .into())
                }
                _ => {
                    return Err(CgError::Stagnation {
                        iterations: done + total,
                        relative_residual: rel,
                        tol,
                    }
                    .into())
                }
            }
        }
    }

    /// The fallback on the CPU: `cg::solve_with` from the downloaded f64 iterate.
    fn fallback_cpu(
        &mut self,
        done: usize,
        dl: &mut f64,
    ) -> Result<(usize, usize, Vec<f64>, Vec<f64>), GpuError> {
        let nd = self.host.ndof();
        let y64 = self.y64();
        let y0 = self.download_y64(nd, dl)?;
        let HostOp::Blocks(h) = &self.host.op else {
            return Err(GpuError::Unsupported(
                "the CPU fallback of mixed precision needs an assembled Hessian".into(),
            ));
        };
        let e = Eliminated {
            h,
            frames: &self.host.frames,
            rhs: self.host.rhs.clone(),
            diag: self.host.diag.clone(),
        };
        let pc = self.params.preconditioner;
        let pre = crate::solve::cg::BuiltPreconditioner::new(&e, pc).with_coarse(
            &e,
            self.params.coarse,
            None,
        );
        let cp = crate::solve::cg::CgParams {
            tol: self.params.tol,
            max_iters: self.params.max_iters.saturating_sub(done),
            preconditioner: pc,
            coarse: self.params.coarse,
            stagnation_window: self.params.stagnation_window,
            max_restarts: self.params.max_restarts,
            ..Default::default()
        };
        let warm = y0.iter().all(|v| v.is_finite()).then_some(&y0[..]);
        let (y, info) =
            crate::solve::cg::solve_with(&e, &pre, warm, &cp).map_err(|err| match err {
                CgError::NonPositiveCurvature {
                    iteration,
                    curvature,
                } => CgError::NonPositiveCurvature {
                    iteration: iteration + done,
                    curvature,
                },
                CgError::Stagnation {
                    iterations,
                    relative_residual,
                    tol,
                } => CgError::Stagnation {
                    iterations: iterations + done,
                    relative_residual,
                    tol,
                },
                CgError::MaxIterations {
                    iterations,
                    relative_residual,
                    tol,
                } => CgError::MaxIterations {
                    iterations: iterations + done,
                    relative_residual,
                    tol,
                },
                CgError::Breakdown { iteration } => CgError::Breakdown {
                    iteration: iteration + done,
                },
                u @ CgError::Unpinned(_) => u,
            })?;
        self.ctx.write_buffer(&y64, 0, &Real::F64.bytes(&y));
        let td = Instant::now();
        let (_, dx) = self.download_solution()?;
        *dl += td.elapsed().as_secs_f64();
        Ok((info.iterations, info.restarts, y, dx))
    }

    /// ‖b̂ − Ĥy‖ in f64 (on the device, or on the host when the f64 blocks do not fit);
    /// also sets the inner CG's right-hand side to r/‖r‖ and the factors
    /// [1/‖r‖, 2^s·‖r‖] of the refinement kernels.
    fn outer_residual(&mut self) -> Result<f64, GpuError> {
        let g = self.dev.n_partials;
        let nd = self.host.ndof();
        let scale = self.mixed.inner_scale;
        let factors = |rn: f64| -> Vec<u8> {
            let inv = if rn > 0.0 && (1.0 / rn).is_finite() {
                1.0 / rn
            } else {
                1.0
            };
            Real::F64.bytes(&[inv, scale / inv]).into_owned()
        };
        let rf = self
            .dev
            .refine
            .as_ref()
            .expect("mixed has a refinement level");
        let (Some(op), Some(bg_mv)) = (&rf.op, &rf.bg_mv) else {
            // Host path: download y (f64), r = b̂ − Ĥy in f64, upload f32(r/‖r‖).
            let y64 = rf.y64.clone();
            let fb = rf.factors.clone();
            let y = self.download(self.encoder("download y"), &y64, Real::F64, nd)?;
            let mut r = vec![0.0; nd];
            self.host.apply(&y, &mut r);
            // r = b̂ − Ĥy in place.
            for (v, b) in r.iter_mut().zip(&self.host.rhs) {
                *v = b - *v;
            }
            let rn = norm2(&r);
            let f = factors(rn);
            let inv = Real::F64.values(&f)[0];
            r.iter_mut().for_each(|v| *v *= inv);
            self.ctx
                .write_buffer(&self.dev.level.buf.b, 0, &Real::F32.bytes(&r));
            self.ctx.write_buffer(&fb, 0, &f);
            return Ok(rn);
        };
        let mut enc = self.encoder("mixed residual");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("residual pass"),
                timestamp_writes: None,
            });
            let launch = self.ctx.launch();
            op.dispatch(&mut pass, bg_mv, g, &launch, self.dev.wg);
            pass.set_pipeline(&rf.k_residual.pipeline);
            pass.set_bind_group(0, &rf.bg_refine, &[]);
            launch.reduction(g, self.dev.wg).dispatch(&mut pass);
        }
        enc.copy_buffer_to_buffer(&rf.partials64, 0, &rf.staging, 0, 8 * g as u64);
        self.ctx.queue.submit([enc.finish()]);
        let name = op.matvec.name;
        let staging = rf.staging.clone();
        self.record(name);
        self.record("residual");
        let bytes = self.read(&staging, 8 * g as u64)?;
        // Fixed-order sum of the per-workgroup partials: deterministic.
        let s: f64 = Real::F64.values(&bytes).iter().sum();
        let rn = s.max(0.0).sqrt();
        let rf = self
            .dev
            .refine
            .as_ref()
            .expect("mixed has a refinement level");
        self.ctx.write_buffer(&rf.factors, 0, &factors(rn));
        let mut enc = self.encoder("mixed scale rhs");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("scale rhs pass"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&rf.k_scale_rhs.pipeline);
            pass.set_bind_group(0, &rf.bg_refine, &[]);
            self.ctx
                .launch()
                .grid(nd as u64, self.dev.wg)
                .dispatch(&mut pass);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.record("scale_rhs");
        Ok(rn)
    }
}
