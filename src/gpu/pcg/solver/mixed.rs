//! Mixed precision on the device PCG, in three stages, each entered only when the one
//! before cannot go on:
//! 1. f32 segments with reliable updates: the f32 level (2^s Ĥ in f32, f64 sums, the
//!    difference form where chosen) solves Ĥd = r/‖r‖ until its recurrence residual has
//!    dropped by δ = `inner_tol` ([`DeviceCg::segment`]); y += 2^s‖r‖d in f64 on the
//!    host; r = b̂ − Ĥy in f64 (the product on the f64 level, or on the host where that
//!    level does not fit); the next segment resumes the last one's search direction;
//! 2. f64 CG (the f64 level, else the CPU CG), warm-started from y, when f32 meets
//!    non-positive curvature, breaks down, a segment reduces the f64 residual less than
//!    2×, or the f32 CG's condition estimate is too large for f32 (`policy.rs`);
//! 3. extended-precision refinement when f64 CG stagnates on its residual's rounding
//!    floor (and, with `error_tol`, after success, until the error estimate is met).
//!
//! [`DeviceCg::segment`]: crate::gpu::pcg::DeviceCg::segment

use super::{PcgSolver, Tally};
use crate::core::elimination::norm2;
use crate::gpu::pcg::policy::{resume_scales, MixedPolicy, Stop};
use crate::gpu::pcg::{DeviceCg, DeviceCgParams, SegmentEnd, SegmentStart, LANCZOS_HIST};
use crate::gpu::{GpuError, SolveOutcome};
use crate::solve::cg::{lanczos_condition, CgError};
use std::time::Instant;

/// Counts of a mixed solve so far.
#[derive(Default)]
struct Count {
    iterations: usize,
    recorded: usize,
    reads: usize,
    restarts: usize,
    outer: usize,
    download: f64,
    kappa: Option<f64>,
}

impl Count {
    fn kappa(&mut self, k: Option<f64>) {
        if let Some(k) = k {
            self.kappa = Some(self.kappa.map_or(k, |c: f64| c.max(k)));
        }
    }
}

/// The f32 segments' Lanczos coefficients as one sequence across reliable updates: a
/// resumed segment continues it, joined by its link β (ρ of its start over the rescaled
/// ρ_prev); a fresh start, or a segment whose history was cut at [`LANCZOS_HIST`], closes
/// it. κ̃ is the largest estimate over the sequences.
#[derive(Default)]
struct Lanczos {
    alphas: Vec<f64>,
    betas: Vec<f64>,
    closed: Option<f64>,
}

impl Lanczos {
    fn close(&mut self) {
        let k = lanczos_condition(&self.alphas, &self.betas);
        self.closed = max_opt(self.closed, k);
        self.alphas.clear();
        self.betas.clear();
    }

    /// κ̃ with a segment's coefficients so far (`link`: its joining β, when resumed).
    fn estimate_with(&self, a: &[f64], b: &[f64], link: Option<f64>) -> Option<f64> {
        match link {
            Some(l) if !self.alphas.is_empty() => {
                let aa: Vec<f64> = self.alphas.iter().chain(a).copied().collect();
                let bb: Vec<f64> = (self.betas.iter().copied())
                    .chain(std::iter::once(l))
                    .chain(b.iter().copied())
                    .collect();
                max_opt(lanczos_condition(&aa, &bb), self.closed)
            }
            _ => [
                lanczos_condition(a, b),
                lanczos_condition(&self.alphas, &self.betas),
                self.closed,
            ]
            .into_iter()
            .fold(None, max_opt),
        }
    }

    /// Appends a finished segment's coefficients (of `iterations`, `link` as above).
    fn collect(&mut self, a: Vec<f64>, b: Vec<f64>, link: Option<f64>, iterations: usize) {
        match link {
            Some(l) if !self.alphas.is_empty() => self.betas.push(l),
            _ => self.close(),
        }
        self.alphas.extend(a);
        self.betas.extend(b);
        if iterations > LANCZOS_HIST as usize {
            // Cut: the next segment cannot continue this sequence.
            self.close();
        }
    }

    fn kappa(&self) -> Option<f64> {
        max_opt(lanczos_condition(&self.alphas, &self.betas), self.closed)
    }
}

fn max_opt(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(x), Some(y)) => Some(x.max(y)),
        (x, y) => x.or(y),
    }
}

/// `e` with its iteration count moved on by `done` (an error of a later stage reports the
/// whole solve's iterations).
fn offset(e: GpuError, done: usize) -> GpuError {
    let c = match e {
        GpuError::Cg(c) => c,
        other => return other,
    };
    GpuError::Cg(match c {
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
    })
}

/// The error of a mixed solve stopped by its policy at `iterations` with the host's
/// `relative_residual`: the iteration limit, or stagnation.
fn stopped(stop: Stop, iterations: usize, relative_residual: f64, tol: f64) -> GpuError {
    if stop == Stop::MaxIterations {
        CgError::MaxIterations {
            iterations,
            relative_residual,
            tol,
        }
    } else {
        CgError::Stagnation {
            iterations,
            relative_residual,
            tol,
        }
    }
    .into()
}

impl PcgSolver {
    fn seg_params(&self, tol: f64, done: usize) -> DeviceCgParams {
        DeviceCgParams {
            tol,
            max_iterations: self.params.max_iters.saturating_sub(done),
            preconditioner: self.params.preconditioner,
            coarse: self.params.coarse,
            stagnation_window: self.params.stagnation_window,
        }
    }

    /// Clears the last fallback and returns the f32 operator's scale with the notes that
    /// say how this solve is set up (no f64 level, a scaled operator).
    fn start_mixed(&mut self) -> (f64, Vec<String>) {
        let mut notes = Vec::new();
        let (scale, missing) = {
            let side = self.side_mut();
            side.last_fallback = None;
            (side.inner_scale, side.missing.clone())
        };
        if let Some(why) = missing {
            notes.push(format!(
                "mixed: the f64 level does not fit beside the f32 one ({why}); the f64 \
                 residual is formed on the host and a fallback would run on the CPU"
            ));
        }
        if scale != 1.0 {
            notes.push(format!(
                "mixed: Ĥ's diagonal is extreme; the f32 operator holds 2^{} Ĥ (exact) and the \
                 corrections are scaled back in f64",
                scale.log2()
            ));
        }
        (scale, notes)
    }

    pub(super) fn solve_mixed(&mut self) -> Result<SolveOutcome, GpuError> {
        let t0 = Instant::now();
        let tol = self.params.tol;
        let bn = norm2(&self.host.rhs);
        let nd = self.host.ndof();
        let (scale, mut notes) = self.start_mixed();
        let policy = MixedPolicy::new(&self.params);
        let mut c = Count::default();
        // y on the host where the f64 level is missing; else in that level's y.
        let mut y = vec![0.0; nd];
        if bn == 0.0 {
            notes.push("b̂ = 0: y = 0 without iterating".into());
            return self.finish(t0, c, y, None, None, notes);
        }
        let rhs = self.host.rhs.clone();
        if let Some(l) = &mut self.side_mut().level {
            l.cg.write_y(&l.frames, &y)?;
            if !l.holds_rhs {
                let b: Vec<f64> = rhs.iter().map(|v| v * l.rhs_scale).collect();
                l.cg.set_rhs(&l.frames, &b)?;
                l.holds_rhs = true;
            }
        }
        let mut prev = f64::INFINITY;
        // (ρ of the last α, ‖r‖) of a converged segment: the next one resumes from them.
        let mut keep: Option<(f64, f64)> = None;
        let mut lz = Lanczos::default();
        let reason: String = loop {
            let (rn, rel) = self.outer_residual(&y, scale, &mut c)?;
            if policy.converged(rel) {
                let y = self.outer_y(&y, &mut c)?;
                let true_rel = self.host.relative_residual(&y);
                if policy.converged(true_rel) {
                    return self.certify_and_finish(t0, c, y, None, notes);
                }
                notes.push(format!(
                    "device f64 residual {rel:e} but host residual {true_rel:e}; refining further"
                ));
            }
            match policy.before_segment(c.outer, c.iterations, rel, prev) {
                None => {}
                Some(Stop::Fallback(why)) => {
                    y = self.outer_y(&y, &mut c)?;
                    if !rel.is_finite() {
                        y.fill(0.0);
                    }
                    break why;
                }
                Some(stop) => {
                    let y = self.outer_y(&y, &mut c)?;
                    let relative_residual = self.host.relative_residual(&y);
                    return Err(stopped(stop, c.iterations, relative_residual, tol));
                }
            }
            prev = rel;
            let start = keep
                .take()
                .and_then(|(rho, rn_prev)| resume_scales(rho, rn_prev, rn))
                .map_or(SegmentStart::Fresh, |(rho_prev, pscale)| {
                    SegmentStart::Resume { rho_prev, pscale }
                });
            let params = self.seg_params(self.params.inner_tol, c.iterations);
            let rho_prev = match start {
                SegmentStart::Resume { rho_prev, .. } => Some(rho_prev),
                SegmentStart::Fresh => None,
            };
            let link = |start_rho: f64| rho_prev.map(|r| start_rho / r);
            // κ̃ is watched at every status read of the segment, not only at its end: on
            // an ill-conditioned system a segment can run thousands of iterations before
            // its residual drops by δ, and the estimate of a prefix of the coefficients
            // never exceeds that of the whole (interlacing), so stopping early stops
            // only where the end would have.
            let step = c.outer + 1;
            let mut watched: Option<String> = None;
            let mut watch = |cg: &DeviceCg, it: usize, start_rho: f64| {
                let (a, b) = cg.lanczos_history(it)?;
                let k = lz.estimate_with(&a, &b, link(start_rho));
                watched = policy.kappa_verdict(step, k);
                Ok(watched.is_some())
            };
            let run = self
                .cg
                .segment(&self.frames, &params, start, Some(&mut watch));
            match run {
                Ok(info) => {
                    c.iterations += info.iterations;
                    c.recorded += info.recorded_iterations;
                    c.reads += info.status_reads;
                    c.outer += 1;
                    self.accumulate(&mut y, scale * rn, &mut c)?;
                    if info.end == SegmentEnd::Converged {
                        keep = Some((info.rho, rn));
                    }
                    let (a, b) = self.cg.lanczos_history(info.iterations)?;
                    lz.collect(a, b, link(info.start_rho), info.iterations);
                    c.kappa(lz.kappa());
                    if let Some(why) = watched.or_else(|| policy.kappa_verdict(c.outer, lz.kappa()))
                    {
                        y = self.outer_y(&y, &mut c)?;
                        break why;
                    }
                }
                Err(GpuError::Cg(CgError::NonPositiveCurvature {
                    iteration,
                    curvature,
                })) => {
                    c.iterations += iteration.saturating_sub(1);
                    c.outer += 1;
                    // y is the last iterate before the rejected step: keep its progress.
                    self.accumulate(&mut y, scale * rn, &mut c)?;
                    y = self.outer_y(&y, &mut c)?;
                    break format!(
                        "outer step {}: the f32 inner CG met non-positive curvature pᵀĤp = \
                         {curvature:e} at iteration {} (f32 rounding; f64 CG checks Ĥ again)",
                        c.outer,
                        c.iterations + 1
                    );
                }
                Err(GpuError::Cg(CgError::Breakdown { iteration })) => {
                    c.iterations += iteration;
                    c.outer += 1;
                    y = self.outer_y(&y, &mut c)?;
                    break format!(
                        "outer step {}: the f32 inner CG broke down (non-finite value) at \
                         iteration {}",
                        c.outer, c.iterations
                    );
                }
                Err(e) => return Err(e),
            }
        };
        self.fall_back(t0, c, y, reason, notes)
    }

    fn side_mut(&mut self) -> &mut super::MixedSide {
        self.mixed.as_mut().expect("a mixed-precision solver")
    }

    fn side(&self) -> &super::MixedSide {
        self.mixed.as_ref().expect("a mixed-precision solver")
    }

    /// Stage 1's residual r = b̂ − Ĥy in f64 and the next segment's right-hand side
    /// r/‖r‖ (with the factor 2^s‖r‖ of the next `accumulate`): on the device, from the
    /// f64 level's y, where that level exists (two scalars move); else on the host from
    /// `y`. Returns ‖r‖ (scaled by the f64 level's σ on the device) and ‖r‖/‖b̂‖.
    fn outer_residual(
        &mut self,
        y: &[f64],
        scale: f64,
        c: &mut Count,
    ) -> Result<(f64, f64), GpuError> {
        let params = self.seg_params(self.params.tol, 0);
        if let Some(m) = &mut self.mixed {
            if let (Some(l), Some(refine)) = (&mut m.level, &m.refine) {
                let (rr, bb) = l.cg.residual_norm(&l.frames, &params)?;
                c.reads += 1;
                let rn = rr.max(0.0).sqrt();
                let rel = if bb > 0.0 { rn / bb.sqrt() } else { 0.0 };
                refine.scale_rhs(rn, scale)?;
                return Ok((rn, rel));
            }
        }
        let mut r = vec![0.0; y.len()];
        self.host.apply(y, &mut r);
        for (rk, bk) in r.iter_mut().zip(&self.host.rhs) {
            *rk = bk - *rk;
        }
        let rn = norm2(&r);
        let unit: Vec<f64> = r.iter().map(|v| v / rn).collect();
        self.cg.set_rhs(&self.frames, &unit)?;
        Ok((rn, rn / norm2(&self.host.rhs)))
    }

    /// y += f·d with d the f32 level's segment solution: on the device (the factor
    /// `outer_residual` wrote), or on the host.
    fn accumulate(&mut self, y: &mut [f64], f: f64, c: &mut Count) -> Result<(), GpuError> {
        if let Some(refine) = self.mixed.as_ref().and_then(|m| m.refine.as_ref()) {
            return refine.accumulate();
        }
        let t = Instant::now();
        let d = self.cg.read_y()?;
        c.download += t.elapsed().as_secs_f64();
        for (yk, dk) in y.iter_mut().zip(&d) {
            *yk += f * dk;
        }
        Ok(())
    }

    /// Stage 1's y on the host: read back from the f64 level where it lives there.
    fn outer_y(&mut self, y: &[f64], c: &mut Count) -> Result<Vec<f64>, GpuError> {
        if self.side().refine.is_some() {
            self.f64_iterate(c)
        } else {
            Ok(y.to_vec())
        }
    }

    /// Stages 2 and 3: f64 CG from y, and extended refinement if it stagnates.
    fn fall_back(
        &mut self,
        t0: Instant,
        mut c: Count,
        y: Vec<f64>,
        reason: String,
        mut notes: Vec<String>,
    ) -> Result<SolveOutcome, GpuError> {
        let on_gpu = {
            let side = self.side();
            side.level.is_some() && !side.force_cpu_fallback
        };
        let place = if on_gpu {
            "f64 CG on the GPU"
        } else {
            "f64 CG on the CPU (src/solve/cg.rs)"
        };
        let msg = format!("{reason}; finished by {place}, warm-started from the f64 iterate");
        notes.push(format!("mixed fell back to f64: {msg}"));
        self.side_mut().last_fallback = Some(msg.clone());
        let done = c.iterations;
        let fb = if on_gpu {
            self.fallback_gpu(&y, &mut c)
        } else {
            self.fallback_cpu(&y, &mut c)
        };
        match fb {
            Ok(y) => self.certify_and_finish(t0, c, y, Some(msg), notes),
            Err(GpuError::Cg(CgError::Stagnation {
                iterations,
                relative_residual,
                ..
            })) if on_gpu => {
                notes.push(format!(
                    "f64 CG stagnated at relative residual {relative_residual:.3e} (its \
                     rounding floor); extended-precision refinement (double-double residuals \
                     on the host, f64 CG corrections on the GPU) goes on"
                ));
                c.iterations = iterations.max(done);
                // The residual cannot show tol: the error estimate must be ≤ tol instead
                // (and ≤ error_tol when that is asked for too).
                let target = self
                    .params
                    .error_tol
                    .map_or(self.params.tol, |et| et.min(self.params.tol));
                let y = self.f64_iterate(&mut c)?;
                let (y, est) = self.refine_extended(y, &mut c, &mut notes, target)?;
                self.finish(t0, c, y, Some(msg), Some(est), notes)
            }
            Err(e) => Err(e),
        }
    }

    /// The f64 level's y, unscaled.
    fn f64_iterate(&mut self, c: &mut Count) -> Result<Vec<f64>, GpuError> {
        let Some(l) = &self.side().level else {
            return Err(GpuError::Internal(
                "mixed precision's f64 level is missing".into(),
            ));
        };
        let t = Instant::now();
        let mut y = l.cg.read_y()?;
        c.download += t.elapsed().as_secs_f64();
        y.iter_mut().for_each(|v| *v /= l.rhs_scale);
        Ok(y)
    }

    /// Stage 2 on the device: the f64 level from y0 on σb̂, its result checked on the
    /// host and restarted from there (a tighter device tolerance) while it misses tol.
    fn fallback_gpu(&mut self, y0: &[f64], c: &mut Count) -> Result<Vec<f64>, GpuError> {
        let tol = self.params.tol;
        let done = c.iterations;
        let mut run = self.seg_params(tol, done);
        let (max_restarts, max_iters) = (self.params.max_restarts, self.params.max_iters);
        let rhs = self.host.rhs.clone();
        let mut its = 0usize;
        let mut restarts = 0usize;
        {
            let Some(l) = &mut self.side_mut().level else {
                return Err(GpuError::Internal(
                    "mixed precision's f64 level is missing".into(),
                ));
            };
            let sigma = l.rhs_scale;
            // Extended refinement may have left another b̂ there.
            let b: Vec<f64> = rhs.iter().map(|v| v * sigma).collect();
            l.cg.set_rhs(&l.frames, &b)?;
            l.holds_rhs = true;
            let y: Vec<f64> = y0.iter().map(|v| v * sigma).collect();
            l.cg.write_y(&l.frames, &y)?;
        }
        loop {
            run.max_iterations = max_iters.saturating_sub(done + its);
            let info = {
                let Some(l) = &mut self.side_mut().level else {
                    return Err(GpuError::Internal(
                        "mixed precision's f64 level is missing".into(),
                    ));
                };
                l.cg.iterate_from_current(&l.frames, &run)
                    .map_err(|e| offset(e, done + its))?
            };
            its += info.iterations;
            restarts += info.restarts;
            c.iterations = done + its;
            c.recorded += info.recorded_iterations;
            c.reads += info.status_reads;
            c.restarts = restarts;
            let y = self.f64_iterate(c)?;
            let rel = self.host.relative_residual(&y);
            if rel <= tol {
                return Ok(y);
            }
            if restarts >= max_restarts || done + its >= max_iters {
                return Err(CgError::Stagnation {
                    iterations: done + its,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            restarts += 1;
            run.tol = (run.tol * 0.5 * tol / rel).max(f64::MIN_POSITIVE);
        }
    }

    /// Stage 2 on the CPU: `cg::solve_with` from y0.
    fn fallback_cpu(&mut self, y0: &[f64], c: &mut Count) -> Result<Vec<f64>, GpuError> {
        let done = c.iterations;
        let e = self.host.eliminated();
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
        let warm = y0.iter().all(|v| v.is_finite()).then_some(y0);
        let (y, info) = crate::solve::cg::solve_with(&e, &pre, warm, &cp)
            .map_err(|err| offset(GpuError::Cg(err), done))?;
        c.iterations = done + info.iterations;
        c.restarts = info.restarts;
        Ok(y)
    }

    /// With `error_tol`, extended refinement after the residual criterion was met, until
    /// the estimated relative error is ≤ error_tol; then the report.
    fn certify_and_finish(
        &mut self,
        t0: Instant,
        mut c: Count,
        y: Vec<f64>,
        fallback: Option<String>,
        mut notes: Vec<String>,
    ) -> Result<SolveOutcome, GpuError> {
        let Some(target) = self.params.error_tol else {
            return self.finish(t0, c, y, fallback, None, notes);
        };
        if self.side().level.is_none() {
            return Err(GpuError::Unsupported(
                "error_tol needs the f64 operator on the GPU, and it does not fit beside the \
                 f32 one"
                    .into(),
            ));
        }
        notes.push(format!(
            "error_tol {target:e}: extended-precision refinement estimates and reduces the error"
        ));
        let (y, est) = self.refine_extended(y, &mut c, &mut notes, target)?;
        self.finish(t0, c, y, fallback, Some(est), notes)
    }

    /// Extended-precision refinement: y ← y + d with r = b̂ − Ĥy in double-double on the
    /// host ([`crate::core::sparse::BlockCsr::residual_dd`]) and Ĥd = r solved by f64 CG
    /// on the f64 level (a segment to a recurrence residual of 1e-12). Each step
    /// contracts the error by the inner solve's relative error η (≈ κε), so y converges to
    /// the solution of the f64 Ĥ while κε < 1, past the f64 residual's rounding floor.
    /// Success is claimed when the estimated error ‖d‖/‖y‖·ρ/(1 − ρ) (ρ the observed
    /// contraction of consecutive corrections) is ≤ `target`; a contraction ρ ≥ 1/2 ends
    /// it with `Stagnation`. Returns y and the error estimate.
    fn refine_extended(
        &mut self,
        mut y: Vec<f64>,
        c: &mut Count,
        notes: &mut Vec<String>,
        target: f64,
    ) -> Result<(Vec<f64>, f64), GpuError> {
        // Corrections within a few ulps of y are rounding: y is then the f64 Ĥ's solution
        // to working precision.
        const ROUNDING: f64 = 8.0 * f64::EPSILON;
        const MAX_STEPS: usize = 10;
        // The inner CG's recurrence target: far below the f64 residual floor, so the
        // correction is as accurate as f64 CG makes it.
        const INNER_TOL: f64 = 1e-12;
        let tol = self.params.tol;
        let bn = norm2(&self.host.rhs);
        if self.side().assembled.is_none() {
            let e = self.host.eliminated();
            let a = e.assemble();
            self.side_mut().assembled = Some(a);
        }
        let mut prev: Option<f64> = None;
        for step in 1..=MAX_STEPS {
            let r = {
                let a = self.side().assembled.as_ref().expect("assembled above");
                a.residual_dd(&self.host.rhs, &y)
            };
            let rn = norm2(&r);
            let rel = rn / bn;
            if rn == 0.0 {
                notes.push(format!(
                    "extended step {step}: the residual is exactly zero"
                ));
                return Ok((y, 0.0));
            }
            let unit: Vec<f64> = r.iter().map(|v| v / rn).collect();
            let params = self.seg_params(INNER_TOL, c.iterations);
            let (info, x) = {
                let Some(l) = &mut self.side_mut().level else {
                    return Err(GpuError::Internal(
                        "mixed precision's f64 level is missing".into(),
                    ));
                };
                l.cg.set_rhs(&l.frames, &unit)?;
                l.holds_rhs = false;
                let info =
                    l.cg.segment(&l.frames, &params, SegmentStart::Fresh, None)
                        .map_err(|e| offset(e, c.iterations))?;
                (info, l.cg.read_y()?)
            };
            c.iterations += info.iterations;
            c.recorded += info.recorded_iterations;
            c.reads += info.status_reads;
            if info.end == SegmentEnd::MaxIterations {
                return Err(CgError::MaxIterations {
                    iterations: c.iterations,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            // A correction from a stagnated inner CG is still used (it is the best f64 CG
            // reaches), but it may underestimate the error: no claim on its step.
            let inner_converged = info.end == SegmentEnd::Converged;
            let mut d2 = 0.0f64;
            for (v, xk) in y.iter_mut().zip(&x) {
                let d = rn * xk;
                *v += d;
                d2 += d * d;
            }
            let yn = norm2(&y);
            if !(d2.is_finite() && yn.is_finite()) {
                return Err(CgError::Breakdown {
                    iteration: c.iterations,
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
                 ({} f64 CG iterations)",
                info.iterations
            ));
            if est <= target {
                return Ok((y, est));
            }
            if rho >= 0.5 {
                break;
            }
            prev = Some(eta);
        }
        // The residual of the iterate reached.
        let a = self.side().assembled.as_ref().expect("assembled above");
        let rel = norm2(&a.residual_dd(&self.host.rhs, &y)) / bn;
        Err(CgError::Stagnation {
            iterations: c.iterations,
            relative_residual: rel,
            tol,
        }
        .into())
    }

    /// The outcome: Δx recovered on the host, the report of the f32 level's iteration.
    fn finish(
        &mut self,
        t0: Instant,
        c: Count,
        y: Vec<f64>,
        fallback: Option<String>,
        error_estimate: Option<f64>,
        notes: Vec<String>,
    ) -> Result<SolveOutcome, GpuError> {
        let rel = self.host.relative_residual(&y);
        let solve_seconds = t0.elapsed().as_secs_f64() - c.download;
        let dx = self.host.recover(&y);
        let params = self.seg_params(self.params.inner_tol, 0);
        let info = self.report(
            &params,
            Tally {
                iterations: c.iterations,
                recorded: c.recorded,
                reads: c.reads,
                restarts: c.restarts,
                outer: c.outer,
                relative_residual: rel,
                solve_seconds,
                download_seconds: c.download,
                condition_estimate: c.kappa,
                fallback,
                error_estimate,
            },
            notes,
        )?;
        Ok(SolveOutcome { y, dx, info })
    }

    /// Tests: the f64 fallback of mixed precision runs on the CPU even where the f64
    /// level is on the device.
    pub fn force_cpu_fallback(&mut self, yes: bool) {
        if let Some(m) = &mut self.mixed {
            m.force_cpu_fallback = yes;
        }
    }

    /// Why the last mixed solve left f32, and where it finished (None: it did not).
    pub fn last_fallback(&self) -> Option<&str> {
        self.mixed.as_ref()?.last_fallback.as_deref()
    }

    /// Whether mixed precision's f64 level is on the device (else its residual is formed
    /// on the host and its fallback runs on the CPU); false in f64 and f32.
    pub fn has_f64_level(&self) -> bool {
        self.mixed.as_ref().is_some_and(|m| m.level.is_some())
    }
}
