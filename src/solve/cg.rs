//! Preconditioned conjugate gradients in f64 on the eliminated operator, matrix-free.
//!
//! CG never reports convergence it did not reach: when the recurrence residual meets the
//! tolerance, the true residual ‖b̂ − Ĥy‖/‖b̂‖ is recomputed; if it misses, CG restarts
//! from the current iterate (a few times) and otherwise reports [`CgError::Stagnation`].
//! Non-positive curvature pᵀĤp ≤ 0 (Ĥ not positive definite on the free subspace) and
//! the iteration limit are errors too.
//!
//! Rounding makes the recurrence residual drift from the true one (loss of orthogonality
//! on ill-conditioned systems). Every [`CgParams::check_every`] iterations the true
//! residual is recomputed; a recurrence more than 2× optimistic is replaced by the true
//! residual (residual replacement, keeping the search direction). Stagnation (no new best
//! residual for [`CgParams::stagnation_window`] iterations) restarts from the true
//! residual while restarts are left, and is reported with the residual reached otherwise.
//! Every error carries the true residual of the iterate reached.

use crate::core::constraints::Frames;
use crate::core::elimination::Eliminated;
use crate::core::linalg::norm2;
use crate::core::sparse::BlockCsr;
use crate::solve::cg_fused::Fused;
use crate::solve::coarse::CoarseSpace;
pub use crate::solve::options::Preconditioner;
pub use crate::solve::precond::{diagonal_blocks, BuiltPreconditioner};

/// Symmetric diagonal equilibration of Ĥ before CG: solve (SĤS) z = S b̂, y = S z.
///
/// S is constant within a node (s_i = 2^round(−½ log₂(tr H_ii / d))), so it commutes with
/// the node's rotation V_i: the scaled system is again an eliminated system on the same
/// frames (any solver, the GPU's included, can take it), and powers of two make the
/// scaling itself exact. What it buys: with [`Preconditioner::None`] it is the difference
/// between converging and not on stiffness contrasts (1e8); with Jacobi or block-Jacobi
/// PCG it changes nothing but rounding (those preconditioners already are a symmetric
/// diagonal scaling), so it is off by default. The stopping test stays on the unscaled
/// residual ‖b̂ − Ĥy‖/‖b̂‖. STABILITY.md has the measurements.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scaling {
    /// Solve Ĥ as given.
    #[default]
    None,
    /// Per-node power-of-two scaling from the trace of H's diagonal blocks.
    NodeDiagonal,
}

/// The default stagnation window of every CG (CPU, GPU, the device PCG): iterations
/// without a new smallest recurrence residual before the run is declared stagnant.
pub const STAGNATION_WINDOW: usize = 1_000;

/// Parameters of a CG solve.
#[derive(Debug, Clone, PartialEq)]
pub struct CgParams {
    /// Stop when ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol (checked on the true residual).
    pub tol: f64,
    /// Iteration limit (all restarts together).
    pub max_iters: usize,
    pub preconditioner: Preconditioner,
    /// Stagnation: the best recurrence residual has not improved for this many iterations.
    pub stagnation_window: usize,
    /// Restarts allowed when the true residual misses the tolerance at recurrence
    /// convergence, or when CG stagnates (a restart from the true residual is tried
    /// before giving up).
    pub max_restarts: usize,
    /// Every this many iterations the true residual is recomputed (one extra product);
    /// when the recurrence residual has drifted below it by more than 2× (rounding, loss
    /// of orthogonality), the recurrence residual is replaced by the true one. 0: only
    /// at convergence.
    pub check_every: usize,
    /// Diagonal equilibration (off by default; see [`Scaling`]).
    pub scaling: Scaling,
    /// Coarse correction added to the preconditioner (see [`crate::solve::coarse`]).
    pub coarse: CoarseSpace,
}

impl Default for CgParams {
    fn default() -> Self {
        CgParams {
            tol: 1e-8,
            max_iters: 10_000,
            preconditioner: Preconditioner::Jacobi,
            stagnation_window: STAGNATION_WINDOW,
            max_restarts: 3,
            check_every: 64,
            scaling: Scaling::None,
            coarse: CoarseSpace::default(),
        }
    }
}

/// What a successful CG solve did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CgInfo {
    pub iterations: usize,
    /// The true relative residual ‖b̂ − Ĥy‖/‖b̂‖, recomputed in f64 at the end.
    pub relative_residual: f64,
    pub restarts: usize,
    /// Times the recurrence residual was replaced by the true residual.
    pub residual_replacements: usize,
    /// Lanczos estimate of κ(M⁻¹Ĥ) from the CG coefficients of the last cycle (extreme
    /// Ritz values; a lower bound on the true κ that tightens with iterations). None
    /// when CG ran fewer than 2 iterations.
    pub condition_estimate: Option<f64>,
    /// Largest loss of local conjugacy |p_kᵀĤp_{k−1}|/√(p_kᵀĤp_k · p_{k−1}ᵀĤp_{k−1})
    /// seen (≈ ε when CG is healthy; near 1 means the recurrences lost orthogonality).
    pub conjugacy_loss: f64,
    /// Whether the solve ran on the equilibrated system.
    pub scaled: bool,
}

impl CgInfo {
    /// Nothing done yet: no iteration, no restart, no estimate.
    fn zero() -> Self {
        CgInfo {
            iterations: 0,
            relative_residual: 0.0,
            restarts: 0,
            residual_replacements: 0,
            condition_estimate: None,
            conjugacy_loss: 0.0,
            scaled: false,
        }
    }
}
pub use crate::error::CgError;

/// Refuses a system whose Ĥ is singular by a rigid translation that nothing pins (see
/// [`crate::solve::coarse::unpinned_translation`]); every CG entry point calls it first.
pub fn check_pinned(e: &Eliminated) -> Result<(), CgError> {
    match crate::solve::coarse::unpinned_translation(e.h, e.frames) {
        Some(u) => Err(CgError::Unpinned(u)),
        None => Ok(()),
    }
}

/// Solves Ĥ y = b̂ by PCG from y = 0.
pub fn solve(e: &Eliminated, params: &CgParams) -> Result<(Vec<f64>, CgInfo), CgError> {
    check_pinned(e)?;
    if params.scaling == Scaling::NodeDiagonal {
        // The equilibrated solve builds its own preconditioner on SĤS.
        return solve_equilibrated(e, None, params);
    }
    let pre =
        BuiltPreconditioner::new(e, params.preconditioner).with_coarse(e, params.coarse, None);
    solve_with(e, &pre, None, params)
}

/// Solves Ĥ y = b̂ by PCG with a prebuilt preconditioner, from `y0` (or zero). With
/// [`Scaling::NodeDiagonal`] a preconditioner of the same kind is built on the scaled
/// system instead of `pre`.
pub fn solve_with(
    e: &Eliminated,
    pre: &BuiltPreconditioner,
    y0: Option<&[f64]>,
    params: &CgParams,
) -> Result<(Vec<f64>, CgInfo), CgError> {
    match params.scaling {
        Scaling::None => pcg(e, pre, y0, params),
        Scaling::NodeDiagonal => solve_equilibrated(e, y0, params),
    }
}

/// The equilibrated system S Ĥ S, S b̂ (see [`Scaling`]); `node_scale` holds s_i.
#[derive(Debug, Clone)]
pub struct Equilibrated {
    pub h: BlockCsr,
    pub rhs: Vec<f64>,
    pub diag: Vec<f64>,
    pub node_scale: Vec<f64>,
}

impl Equilibrated {
    /// The scaled system as an eliminated system on the same frames.
    pub fn eliminated<'a>(&'a self, frames: &'a Frames) -> Eliminated<'a> {
        Eliminated {
            h: &self.h,
            frames,
            rhs: self.rhs.clone(),
            diag: self.diag.clone(),
        }
    }

    /// y = S z.
    pub fn unscale(&self, z: &[f64]) -> Vec<f64> {
        let d = self.h.dim;
        z.iter()
            .enumerate()
            .map(|(k, v)| v * self.node_scale[k / d])
            .collect()
    }

    /// z = S⁻¹ y.
    pub fn scale(&self, y: &[f64]) -> Vec<f64> {
        let d = self.h.dim;
        y.iter()
            .enumerate()
            .map(|(k, v)| v / self.node_scale[k / d])
            .collect()
    }
}

/// Builds S Ĥ S with s_i = 2^round(−½ log₂(tr H_ii / d)) (1 where the trace is not a
/// positive finite number). The trace is invariant under the node's rotation.
pub fn equilibrate(e: &Eliminated) -> Equilibrated {
    let h = e.h;
    let d = h.dim;
    let s: Vec<f64> = (0..h.n)
        .map(|i| {
            let t = h.diag_index(i).map_or(0.0, |k| {
                (0..d).map(|a| h.values[k * d * d + a * d + a]).sum::<f64>() / d as f64
            });
            if t > 0.0 && t.is_finite() {
                crate::core::linalg::power_of_two(-0.5 * t.log2())
            } else {
                1.0
            }
        })
        .collect();
    let mut hs = h.clone();
    for i in 0..h.n {
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            let f = s[i] * s[h.col_idx[k]];
            for v in &mut hs.values[k * d * d..(k + 1) * d * d] {
                *v *= f;
            }
        }
    }
    let rhs = e
        .rhs
        .iter()
        .enumerate()
        .map(|(k, v)| v * s[k / d])
        .collect();
    let diag = e
        .diag
        .iter()
        .enumerate()
        .map(|(k, v)| v * s[k / d] * s[k / d])
        .collect();
    Equilibrated {
        h: hs,
        rhs,
        diag,
        node_scale: s,
    }
}

/// PCG on the equilibrated system; the tolerance is met on the unscaled residual. When
/// the scaled solve converges but the unscaled residual misses, the scaled tolerance is
/// tightened by the ratio and CG continues from where it is (at most `max_restarts` times).
fn solve_equilibrated(
    e: &Eliminated,
    y0: Option<&[f64]>,
    params: &CgParams,
) -> Result<(Vec<f64>, CgInfo), CgError> {
    let eq = equilibrate(e);
    let es = eq.eliminated(e.frames);
    let pre = BuiltPreconditioner::new(&es, params.preconditioner).with_coarse(
        &es,
        params.coarse,
        Some(&eq.node_scale),
    );
    let mut z = y0.map(|y| eq.scale(y));
    let mut p = params.clone();
    p.scaling = Scaling::None;
    let mut used = 0usize;
    let mut restarts = 0usize;
    loop {
        p.max_iters = params.max_iters.saturating_sub(used);
        let (zs, res) = pcg_core(&es, &pre, z.as_deref(), &p);
        let y = eq.unscale(&zs);
        match res {
            Ok(mut info) => {
                used += info.iterations;
                let rel = e.relative_residual(&y);
                if rel <= params.tol {
                    info.iterations = used;
                    info.relative_residual = rel;
                    info.restarts += restarts;
                    info.scaled = true;
                    return Ok((y, info));
                }
                if restarts >= params.max_restarts || used >= params.max_iters {
                    return Err(CgError::Stagnation {
                        iterations: used,
                        relative_residual: rel,
                        tol: params.tol,
                    });
                }
                // Tighten the scaled tolerance by how far the unscaled residual missed.
                p.tol = (p.tol * 0.5 * params.tol / rel).max(f64::MIN_POSITIVE);
                restarts += 1;
                z = Some(zs);
            }
            // Errors carry the unscaled residual of the iterate reached, and the total
            // iteration count.
            Err(CgError::Stagnation { iterations, .. }) => {
                return Err(CgError::Stagnation {
                    iterations: used + iterations,
                    relative_residual: e.relative_residual(&y),
                    tol: params.tol,
                })
            }
            Err(CgError::MaxIterations { iterations, .. }) => {
                return Err(CgError::MaxIterations {
                    iterations: used + iterations,
                    relative_residual: e.relative_residual(&y),
                    tol: params.tol,
                })
            }
            Err(other) => return Err(other),
        }
    }
}

/// Plain PCG on `e` (no scaling); the iterate is returned with errors too.
fn pcg(
    e: &Eliminated,
    pre: &BuiltPreconditioner,
    y0: Option<&[f64]>,
    params: &CgParams,
) -> Result<(Vec<f64>, CgInfo), CgError> {
    let (y, res) = pcg_core(e, pre, y0, params);
    res.map(|info| (y, info))
}

/// κ of M⁻¹Ĥ estimated from the CG coefficients of one uninterrupted run: the extreme
/// eigenvalues of the Lanczos tridiagonal T (diagonal 1/α_j + β_j/α_{j−1}, off-diagonal
/// √β_{j+1}/α_j), `betas[j]` being the β computed after α_j. An underestimate that tightens
/// as CG runs. None with fewer than 2 coefficients or a non-positive λ_min.
pub fn lanczos_condition(alphas: &[f64], betas: &[f64]) -> Option<f64> {
    let k = alphas.len();
    if k < 2 || betas.len() + 1 < k {
        return None;
    }
    let mut da = vec![0.0; k];
    let mut ob = vec![0.0; k - 1];
    for j in 0..k {
        da[j] = 1.0 / alphas[j]
            + if j > 0 {
                betas[j - 1] / alphas[j - 1]
            } else {
                0.0
            };
        if j + 1 < k {
            ob[j] = betas[j].sqrt() / alphas[j];
        }
    }
    let (lo, hi) = tridiagonal_extremes(&da, &ob)?;
    (lo > 0.0).then(|| hi / lo)
}

/// Extreme eigenvalues of the symmetric tridiagonal (diag a, off-diagonal b) by Sturm
/// bisection: (λ_min, λ_max).
fn tridiagonal_extremes(a: &[f64], b: &[f64]) -> Option<(f64, f64)> {
    let k = a.len();
    if k == 0 || a.iter().chain(b).any(|v| !v.is_finite()) {
        return None;
    }
    // Gershgorin interval.
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for i in 0..k {
        let r = if i > 0 { b[i - 1].abs() } else { 0.0 } + if i + 1 < k { b[i].abs() } else { 0.0 };
        lo = lo.min(a[i] - r);
        hi = hi.max(a[i] + r);
    }
    // Number of eigenvalues < x (negative pivots of the LDLᵀ of T − xI).
    let count = |x: f64| -> usize {
        let mut c = 0;
        let mut q = 1.0f64;
        for i in 0..k {
            let bb = if i > 0 { b[i - 1] * b[i - 1] } else { 0.0 };
            q = a[i] - x - if i > 0 { bb / q } else { 0.0 };
            if q == 0.0 {
                q = f64::MIN_POSITIVE;
            }
            if q < 0.0 {
                c += 1;
            }
        }
        c
    };
    let bisect = |target: usize| -> f64 {
        // Smallest x with count(x) > target, i.e. the (target+1)-th eigenvalue.
        let (mut l, mut h) = (lo, hi);
        for _ in 0..200 {
            let m = 0.5 * (l + h);
            if m <= l || m >= h {
                break;
            }
            if count(m) > target {
                h = m;
            } else {
                l = m;
            }
        }
        0.5 * (l + h)
    };
    Some((bisect(0), bisect(k - 1)))
}

/// PCG with true-residual checks (see the module docs); returns the final iterate and
/// the outcome.
/// The power of two nearest 1/‖b̂‖ (1 where ‖b̂‖ is 0 or not finite): CG runs on σb̂,
/// whose scalars (rᵀz ∝ ‖b̂‖², pᵀĤp) stay inside the f64 range for any ‖b̂‖ whose
/// solution does, and unscales y. Powers of two scale every CG operation exactly, so
/// the iterates are the same bits wherever the unscaled run neither over- nor underflows.
pub fn rhs_scale(bnorm: f64) -> f64 {
    if bnorm > 0.0 && bnorm.is_finite() {
        crate::core::linalg::power_of_two(-bnorm.log2())
    } else {
        1.0
    }
}

/// [`pcg_unit`] on σb̂ with σ = [`rhs_scale`]`(‖b̂‖)`, y unscaled after.
fn pcg_core(
    e: &Eliminated,
    pre: &BuiltPreconditioner,
    y0: Option<&[f64]>,
    params: &CgParams,
) -> (Vec<f64>, Result<CgInfo, CgError>) {
    let sigma = rhs_scale(norm2(&e.rhs));
    if sigma == 1.0 {
        return pcg_unit(e, pre, y0, params);
    }
    let es = Eliminated {
        h: e.h,
        frames: e.frames,
        rhs: e.rhs.iter().map(|v| v * sigma).collect(),
        diag: e.diag.clone(),
    };
    let y0s: Option<Vec<f64>> = y0.map(|y| y.iter().map(|v| v * sigma).collect());
    let (mut y, res) = pcg_unit(&es, pre, y0s.as_deref(), params);
    for v in &mut y {
        *v /= sigma;
    }
    (y, res)
}

/// ‖b − Ĥy‖/‖b‖ with Ĥy bitwise equal to Eliminated::apply (through the world copy w
/// of y where the product gathers one); leaves the residual in r.
fn true_relative_residual(
    fz: &Fused,
    world: bool,
    b: &[f64],
    bnorm: f64,
    y: &[f64],
    r: &mut [f64],
    w: &mut [f64],
) -> f64 {
    if world {
        fz.world(y, w);
        fz.product(y, w, None, r);
    } else {
        fz.product(y, y, None, r);
    }
    for (ri, bi) in r.iter_mut().zip(b) {
        *ri = bi - *ri;
    }
    norm2(r) / bnorm
}

/// ‖r‖/‖b‖ from rᵀr where the sum of squares neither overflows nor underflows.
fn recurrence_residual(rr: f64, r: &[f64], bnorm: f64) -> f64 {
    if rr.is_finite() && rr > 1e-200 {
        rr.sqrt() / bnorm
    } else {
        norm2(r) / bnorm
    }
}

/// Why CG must stop at `iteration` with curvature pᵀĤp = `pq` and rᵀz = `rz`: a
/// non-finite value, or non-positive curvature.
fn curvature_fault(pq: f64, rz: f64, iteration: usize) -> Option<CgError> {
    if !pq.is_finite() || !rz.is_finite() {
        return Some(CgError::Breakdown { iteration });
    }
    if pq <= 0.0 {
        return Some(CgError::NonPositiveCurvature {
            iteration,
            curvature: pq,
        });
    }
    None
}

/// The cycle's Lanczos condition estimate (its β's up to one fewer than its α's) merged
/// into `info`'s: the largest of the cycles.
fn merge_condition_estimate(info: &mut CgInfo, alphas: &[f64], betas: &[f64]) {
    if let Some(k) = lanczos_condition(
        alphas,
        &betas[..betas.len().min(alphas.len().saturating_sub(1))],
    ) {
        info.condition_estimate = Some(info.condition_estimate.map_or(k, |c: f64| c.max(k)));
    }
}

/// PCG on Ĥ y = b̂ as given (see [`pcg_core`] for the scaling of b̂).
fn pcg_unit(
    e: &Eliminated,
    pre: &BuiltPreconditioner,
    y0: Option<&[f64]>,
    params: &CgParams,
) -> (Vec<f64>, Result<CgInfo, CgError>) {
    let n = e.ndof();
    let b = &e.rhs;
    let bnorm = norm2(b);
    let mut y = match y0 {
        Some(v) => v.to_vec(),
        None => vec![0.0; n],
    };
    let mut info = CgInfo::zero();
    if bnorm == 0.0 {
        // Ĥ is SPD, so the solution is exactly zero.
        return (vec![0.0; n], Ok(info));
    }
    // The fused passes (src/solve/cg_fused.rs): Ĥp with its dot products in one pass over H,
    // then the updates with the preconditioner, then the new direction and its world copy.
    let mut fz = Fused::new(e, pre);
    let world = fz.needs_world();
    let mut r = vec![0.0; n];
    let mut rt = vec![0.0; n];
    let mut p = vec![0.0; n];
    let mut p_prev = vec![0.0; n];
    let mut q = vec![0.0; n];
    // w = V P p (what the product gathers); also scratch for the true residual's V P y.
    let mut w = vec![0.0; if world { n } else { 0 }];
    let mut iterations = 0usize;
    let true_residual = |fz: &Fused, y: &[f64], r: &mut [f64], w: &mut [f64]| -> f64 {
        true_relative_residual(fz, world, b, bnorm, y, r, w)
    };
    let recurrence = |rr: f64, r: &[f64]| recurrence_residual(rr, r, bnorm);
    // Lanczos coefficients of the current cycle (for the condition estimate).
    let mut alphas: Vec<f64> = Vec::new();
    let mut betas: Vec<f64> = Vec::new();
    let estimate = lanczos_condition;
    let mut best_true = f64::INFINITY;
    loop {
        // (Re)start: r = b − Ĥy, z = M⁻¹r, p = z.
        let mut rel = true_residual(&fz, &y, &mut r, &mut w);
        best_true = best_true.min(rel);
        if rel <= params.tol {
            info.iterations = iterations;
            info.relative_residual = rel;
            if let Some(k) = estimate(&alphas, &betas) {
                info.condition_estimate = Some(k);
            }
            return (y, Ok(info));
        }
        alphas.clear();
        betas.clear();
        let (ru, _) = fz.update(None, &mut r);
        let mut rz = ru + fz.coarse_solve();
        fz.direction(None, &r, &p_prev, &mut p, world.then_some(&mut w[..]));
        let mut pq_prev = 0.0f64;
        let mut best = rel;
        let mut best_at = iterations;
        let mut since_check = 0usize;
        loop {
            if iterations >= params.max_iters {
                let rel = true_residual(&fz, &y, &mut r, &mut w);
                return (
                    y,
                    Err(CgError::MaxIterations {
                        iterations,
                        relative_residual: rel,
                        tol: params.tol,
                    }),
                );
            }
            let src: &[f64] = if world { &w } else { &p };
            // p_{k−1}ᵀĤp_k (local conjugacy, zero in exact arithmetic) once there is a p_{k−1}.
            let prev = (pq_prev > 0.0).then_some(&p_prev[..]);
            let (pq, ppq) = fz.product(&p, src, prev, &mut q);
            iterations += 1;
            if let Some(fault) = curvature_fault(pq, rz, iterations) {
                return (y, Err(fault));
            }
            if pq_prev > 0.0 {
                let c = ppq.abs() / (pq * pq_prev).sqrt();
                if c.is_finite() {
                    info.conjugacy_loss = info.conjugacy_loss.max(c);
                }
            }
            let alpha = rz / pq;
            alphas.push(alpha);
            let (mut ru, rr) = fz.update(Some((alpha, &mut y, &p, &q)), &mut r);
            rel = recurrence(rr, &r);
            since_check += 1;
            if params.check_every > 0 && since_check >= params.check_every && rel > params.tol {
                since_check = 0;
                let rel_t = true_residual(&fz, &y, &mut rt, &mut w);
                best_true = best_true.min(rel_t);
                if rel_t <= params.tol {
                    break;
                }
                if rel_t > 2.0 * rel {
                    // The recurrence drifted from the truth: replace it (keeping p, so the
                    // Krylov progress is not thrown away).
                    r.copy_from_slice(&rt);
                    rel = rel_t;
                    info.residual_replacements += 1;
                    ru = fz.update(None, &mut r).0;
                }
            }
            if rel <= params.tol {
                break;
            }
            if rel < best {
                best = rel;
                best_at = iterations;
            } else if iterations - best_at >= params.stagnation_window {
                // Stagnation: check the truth below, restart from it while restarts
                // are left, else report it.
                break;
            }
            // rᵀM⁻¹r = rᵀM_J⁻¹r + (Zᵀr)ᵀE⁺(Zᵀr).
            let rz_new = ru + fz.coarse_solve();
            let beta = rz_new / rz;
            betas.push(beta);
            rz = rz_new;
            pq_prev = pq;
            // The new direction goes into p_prev's storage; the swap makes the old p
            // the previous one.
            fz.direction(Some(beta), &r, &p, &mut p_prev, world.then_some(&mut w[..]));
            std::mem::swap(&mut p, &mut p_prev);
        }
        merge_condition_estimate(&mut info, &alphas, &betas);
        // The recurrence says converged (or stagnated): check the truth.
        let rel_true = true_residual(&fz, &y, &mut r, &mut w);
        if rel_true <= params.tol {
            info.iterations = iterations;
            info.relative_residual = rel_true;
            return (y, Ok(info));
        }
        if info.restarts >= params.max_restarts {
            return (
                y,
                Err(CgError::Stagnation {
                    iterations,
                    relative_residual: rel_true,
                    tol: params.tol,
                }),
            );
        }
        info.restarts += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cases::generate::{random_system, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    /// ‖b̂‖ near either end of the f64 range (rᵀr under- or overflows unscaled): the
    /// solution scaled back by 2^k is the same bits as the unit right-hand side's.
    #[test]
    fn a_right_hand_side_at_the_ends_of_the_range_gives_the_same_bits() {
        let s = crate::cases::generate::random_system(&crate::cases::generate::SystemSpec::small(
            3, 22,
        ));
        let e = Eliminated::new(
            &s.h,
            &s.g,
            &s.frames,
            crate::core::elimination::ConstrainedDiagonal::Identity,
        );
        let params = CgParams {
            tol: 1e-10,
            ..CgParams::default()
        };
        let (unit, ui) = solve(&e, &params).expect("unit");
        for k in [-560i32, 515] {
            let mut es = e.clone();
            es.rhs.iter_mut().for_each(|v| *v *= 2f64.powi(k));
            let (y, info) = solve(&es, &params).unwrap_or_else(|err| panic!("2^{k}: {err}"));
            let back: Vec<f64> = y.iter().map(|v| v * 2f64.powi(-k)).collect();
            assert_eq!(back, unit, "2^{k}");
            assert_eq!(info.iterations, ui.iterations);
        }
    }

    #[test]
    fn all_preconditioners_converge_and_report_the_true_residual() {
        let s = random_system(&SystemSpec::small(3, 5));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        for pc in [
            Preconditioner::None,
            Preconditioner::Jacobi,
            Preconditioner::BlockJacobi,
        ] {
            let params = CgParams {
                tol: 1e-10,
                preconditioner: pc,
                ..Default::default()
            };
            let (y, info) = solve(&e, &params).unwrap();
            assert!(info.relative_residual <= 1e-10);
            // The same computation on the same y: equal to the bit.
            assert_eq!(e.relative_residual(&y), info.relative_residual);
        }
    }

    #[test]
    fn iteration_limit_is_an_error_not_a_success() {
        let s = random_system(&SystemSpec::small(3, 6));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let params = CgParams {
            tol: 1e-14,
            max_iters: 2,
            ..Default::default()
        };
        match solve(&e, &params) {
            Err(CgError::MaxIterations {
                relative_residual, ..
            }) => assert!(relative_residual > 1e-14),
            other => panic!("expected MaxIterations, got {other:?}"),
        }
    }

    #[test]
    fn indefinite_hessian_is_detected() {
        let mut s = random_system(&SystemSpec::small(2, 8));
        s.frames = crate::core::constraints::Frames::unconstrained(2, s.h.n);
        // Make one diagonal entry strongly negative.
        let k = s.h.diag_index(0).unwrap();
        s.h.values[k * 4] = -1e3;
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let params = CgParams {
            preconditioner: Preconditioner::None,
            ..Default::default()
        };
        assert!(matches!(
            solve(&e, &params),
            Err(CgError::NonPositiveCurvature { .. })
        ));
    }

    /// CG refuses a floating body (a chain with no constraint and no mass term) before
    /// iterating, naming the rigid translation that nothing pins.
    #[test]
    fn a_floating_body_is_refused_before_iterating() {
        let n = 12;
        let mut t = Vec::new();
        for i in 0..n - 1 {
            for a in 0..2 {
                let (p, q) = (i * 2 + a, (i + 1) * 2 + a);
                t.extend([(p, p, 1.0), (q, q, 1.0), (p, q, -1.0), (q, p, -1.0)]);
            }
        }
        let h = BlockCsr::from_triplets(2, 2 * n, &t, false);
        let free = Frames::unconstrained(2, n);
        let e = Eliminated::new(&h, &[0.0; 24], &free, ConstrainedDiagonal::Identity);
        let msg = solve(&e, &Default::default()).unwrap_err().to_string();
        assert!(
            msg.starts_with("the eliminated Hessian is not positive definite on the free subspace: the rigid translation along"),
            "{msg}"
        );
    }

    /// Δx of a solve on 1, 2 and 3 threads: bitwise equal, rotated slip nodes and the
    /// coarse spaces included.
    #[test]
    fn solutions_are_bitwise_equal_on_any_thread_count() {
        let pools: Vec<rayon::ThreadPool> = [1, 2, 3]
            .iter()
            .map(|&t| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .expect("thread pool")
            })
            .collect();
        let cases = [
            (
                3,
                8000,
                11u64,
                Preconditioner::Jacobi,
                CoarseSpace::Aggregates,
                Scaling::None,
            ),
            (
                3,
                5000,
                12,
                Preconditioner::BlockJacobi,
                CoarseSpace::Translations,
                Scaling::None,
            ),
            (
                2,
                9000,
                13,
                Preconditioner::Jacobi,
                CoarseSpace::None,
                Scaling::NodeDiagonal,
            ),
        ];
        for (dim, nodes, seed, pc, coarse, scaling) in cases {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            assert!(s.frames.has_rotation(), "the system has rotated slip nodes");
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
            assert!(
                crate::solve::cg_fused::partition(&s.h.row_ptr).len() > 8,
                "many chunks"
            );
            let params = CgParams {
                tol: 1e-10,
                preconditioner: pc,
                coarse,
                scaling,
                check_every: 16,
                ..Default::default()
            };
            let runs: Vec<_> = pools
                .iter()
                .map(|pool| {
                    pool.install(|| {
                        let (y, info) = solve(&e, &params).expect("converges");
                        (e.recover(&y), info)
                    })
                })
                .collect();
            let (dx1, info1) = &runs[0];
            assert!(info1.relative_residual <= 1e-10);
            assert!(info1.iterations > 10);
            for (dx, info) in &runs[1..] {
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
                assert_eq!(bits(dx), bits(dx1), "{dim}D {pc:?} {coarse:?}");
                assert_eq!(info, info1);
            }
        }
    }
}
