//! Mixed precision's decisions, as plain CPU code without a device: when the f32 inner CG
//! is given up for f64 CG, when the solve has run out of budget, how the next f32 segment
//! is sized and started, and the f32 operator's scale. `mixed.rs` carries them out.

use crate::gpu::GpuParams;

/// f32 CG is given up for f64 once κ̃(M⁻¹Ĥ)·ε_f32 exceeds this. There f32 CG's loss of
/// orthogonality costs more iterations than f32 saves (kappa-1e6, κ̃ε = 0.09: 2.3× f64's
/// count; needles, 0.014: 1.6×; see STABILITY.md).
pub(crate) const F32_KAPPA_LIMIT: f64 = 0.05;

/// An f32 segment must reduce the f64 residual by at least this factor (2×); less, and
/// the f32 operator no longer represents Ĥ well enough to make progress.
const MIN_REDUCTION: f64 = 0.5;

/// Why the f32 phase of a mixed solve ends without convergence.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Stop {
    /// Hand the rest of the solve to f64 CG, warm-started from the f64 iterate; the
    /// reason is reported.
    Fallback(String),
    /// The iteration budget is spent.
    MaxIterations,
    /// The outer steps are spent while the budget is not.
    MaxOuter,
}

/// The thresholds of a mixed solve (`GpuParams`: tol, inner_tol, max_outer, max_iters).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MixedPolicy {
    tol: f64,
    inner_tol: f64,
    max_outer: usize,
    max_iters: usize,
}

impl MixedPolicy {
    pub(crate) fn new(p: &GpuParams) -> Self {
        MixedPolicy {
            tol: p.tol,
            inner_tol: p.inner_tol,
            max_outer: p.max_outer,
            max_iters: p.max_iters,
        }
    }

    /// Whether the relative f64 residual meets the tolerance.
    pub(crate) fn converged(&self, rel: f64) -> bool {
        rel <= self.tol
    }

    /// Whether the f32 phase stops before outer step `outer + 1`, given the relative f64
    /// residual `rel` now and `prev` before the last segment, after `total` iterations.
    pub(crate) fn before_segment(
        &self,
        outer: usize,
        total: usize,
        rel: f64,
        prev: f64,
    ) -> Option<Stop> {
        if !rel.is_finite() {
            return Some(Stop::Fallback(format!(
                "the f64 residual is not finite after outer step {outer}"
            )));
        }
        if outer > 0 && rel > MIN_REDUCTION * prev {
            return Some(Stop::Fallback(format!(
                "outer step {outer}: the f32 inner solve reduced the f64 residual only from \
                 {prev:.3e} to {rel:.3e} (less than 2×)"
            )));
        }
        if total >= self.max_iters {
            return Some(Stop::MaxIterations);
        }
        if outer >= self.max_outer {
            return Some(Stop::MaxOuter);
        }
        None
    }

    /// The reason to give up f32 CG when its condition estimate κ̃(M⁻¹Ĥ) (from the
    /// Lanczos coefficients of its runs so far, during or after outer step `outer`) says
    /// that f32 CG costs more iterations than it saves; None while it does not.
    ///
    /// Checked at every status read of an f32 segment, not only at its end: a segment runs
    /// until its recurrence residual has dropped by δ, and on an ill-conditioned system
    /// that can take thousands of iterations (24 DOFs, κ = 1e8: f64 CG 143, a first f32
    /// segment 1,700 to 2,350). The estimate of a prefix of the coefficients never exceeds
    /// that of the whole (the extreme eigenvalues of a tridiagonal's leading submatrices
    /// interlace), so the earlier check gives up f32 only where the check at the segment's
    /// end would have, and sooner.
    pub(crate) fn kappa_verdict(&self, outer: usize, kappa: Option<f64>) -> Option<String> {
        let k = kappa?;
        let ke = k * f64::from(f32::EPSILON);
        (ke > F32_KAPPA_LIMIT).then(|| {
            format!(
                "outer step {outer}: κ̃(M⁻¹Ĥ) ≈ {k:.2e} from the f32 CG's Lanczos \
                 coefficients; κ̃·ε_f32 = {ke:.2} > {F32_KAPPA_LIMIT}, where f32 CG loses \
                 orthogonality and costs more iterations than it saves"
            )
        })
    }
}

/// How a converged segment's CG goes on in the next one (a reliable update): its search
/// direction is rescaled by `pscale` = ‖r_prev‖/‖r‖ (the ratio of the two unit
/// normalizations of the right-hand side) and ρ_prev by pscale². None when the new
/// residual is zero (nothing to continue).
pub(crate) fn resume_scales(rho_prev: f64, rn_prev: f64, rn: f64) -> Option<(f64, f64)> {
    (rn > 0.0).then(|| {
        let ps = rn_prev / rn;
        (rho_prev * ps * ps, ps)
    })
}

/// The power of two 2^s that brings H's largest diagonal entry to [1, 2) when it lies
/// outside [2^-20, 2^20] (else 1): the f32 operator of mixed precision holds 2^s·Ĥ, which
/// is exact in floating point and keeps f32 far from underflow and overflow.
pub(crate) fn inner_scale(diag_max: f64) -> f64 {
    if !(diag_max > 0.0 && diag_max.is_finite()) {
        return 1.0;
    }
    let e = diag_max.log2().floor();
    if e.abs() <= 20.0 {
        1.0
    } else {
        (-e).exp2()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::Precision;

    fn policy() -> MixedPolicy {
        MixedPolicy::new(&GpuParams {
            precision: Precision::Mixed,
            tol: 1e-8,
            max_iters: 2_000,
            max_outer: 10,
            ..Default::default()
        })
    }

    /// The Lanczos coefficients (α_j, β_j) of `k` CG iterations on the diagonal matrix
    /// `lam` with right-hand side all ones, in f64, as the GPU CG records them.
    fn cg_coefficients(lam: &[f64], k: usize) -> (Vec<f64>, Vec<f64>) {
        let n = lam.len();
        let mut x = vec![0.0; n];
        let mut r = vec![1.0; n];
        let mut p = r.clone();
        let mut rho: f64 = r.iter().map(|v| v * v).sum();
        let (mut alphas, mut betas) = (Vec::new(), Vec::new());
        for _ in 0..k {
            let q: Vec<f64> = p.iter().zip(lam).map(|(a, l)| a * l).collect();
            let pq: f64 = p.iter().zip(&q).map(|(a, b)| a * b).sum();
            let alpha = rho / pq;
            for j in 0..n {
                x[j] += alpha * p[j];
                r[j] -= alpha * q[j];
            }
            let rho_new: f64 = r.iter().map(|v| v * v).sum();
            let beta = rho_new / rho;
            alphas.push(alpha);
            betas.push(beta);
            rho = rho_new;
            for j in 0..n {
                p[j] = r[j] + beta * p[j];
            }
        }
        betas.pop();
        (alphas, betas)
    }

    #[test]
    fn a_24_dof_system_with_kappa_1e8_leaves_f32_within_three_status_reads() {
        // Eigenvalues log-spaced over [1, 1e8] (24 DOFs; Jacobi leaves such a spectrum
        // about where it is when the eigenvectors are spread over every DOF). The status
        // reads of a segment come after chunks of 8, 16, 32 iterations (the first chunk,
        // doubling while the rate is unknown): by the third read, 56 iterations, the
        // estimate shows κ̃·ε_f32 above the limit, so f32 is given up there, not after the
        // segment's 1,700 or more iterations.
        let lam: Vec<f64> = (0..24).map(|k| 1e8f64.powf(k as f64 / 23.0)).collect();
        let first = super::super::cg::FIRST_CHUNK;
        let reads = [first, 3 * first, 7 * first];
        let verdicts: Vec<Option<String>> = reads
            .iter()
            .map(|&k| {
                let (a, b) = cg_coefficients(&lam, k);
                let kappa = crate::solve::cg::lanczos_condition(&a, &b);
                let est = kappa.expect("an estimate");
                assert!(est <= 1e8 * (1.0 + 1e-6), "never above κ: {est:e}");
                policy().kappa_verdict(1, kappa)
            })
            .collect();
        let at = verdicts.iter().position(Option::is_some);
        assert!(at.is_some(), "no verdict by {} iterations", reads[2]);
        let why = verdicts.into_iter().flatten().next().expect("a verdict");
        assert!(why.contains("outer step 1") && why.contains("κ̃"), "{why}");
        // A well-conditioned spectrum (κ = 1e4, κε = 1.2e-3) stays in f32 after as many
        // iterations as it has eigenvalues.
        let lam: Vec<f64> = (0..24).map(|k| 1e4f64.powf(k as f64 / 23.0)).collect();
        let (a, b) = cg_coefficients(&lam, 24);
        assert_eq!(
            policy().kappa_verdict(1, crate::solve::cg::lanczos_condition(&a, &b)),
            None
        );
    }

    #[test]
    fn the_condition_limit_sits_at_kappa_eps_f32_of_one_twentieth() {
        let eps = f64::from(f32::EPSILON);
        let at = F32_KAPPA_LIMIT / eps;
        assert_eq!(policy().kappa_verdict(2, Some(0.99 * at)), None);
        assert!(policy().kappa_verdict(2, Some(1.01 * at)).is_some());
        assert_eq!(policy().kappa_verdict(2, None), None);
    }

    #[test]
    fn segments_stop_on_a_bad_residual_or_a_spent_budget() {
        let p = policy();
        assert_eq!(p.before_segment(0, 0, 1.0, f64::INFINITY), None);
        // Halved at least: go on.
        assert_eq!(p.before_segment(1, 40, 0.5, 1.0), None);
        match p.before_segment(1, 40, 0.6, 1.0) {
            Some(Stop::Fallback(why)) => assert!(why.contains("less than 2×"), "{why}"),
            other => panic!("{other:?}"),
        }
        match p.before_segment(3, 40, f64::NAN, 1.0) {
            Some(Stop::Fallback(why)) => assert!(why.contains("not finite"), "{why}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(
            p.before_segment(2, 2_000, 1e-3, 1.0),
            Some(Stop::MaxIterations)
        );
        assert_eq!(p.before_segment(10, 500, 1e-3, 1.0), Some(Stop::MaxOuter));
        assert!(p.converged(1e-8) && !p.converged(1.1e-8));
    }

    #[test]
    fn resuming_rescales_to_the_new_normalization() {
        assert_eq!(resume_scales(2.0, 1.0, 0.5), Some((8.0, 2.0)));
        assert_eq!(resume_scales(2.0, 1.0, 0.0), None);
    }

    #[test]
    fn the_inner_scale_is_a_power_of_two_outside_2_pm20() {
        assert_eq!(inner_scale(1e3), 1.0);
        assert_eq!(inner_scale(0.0), 1.0);
        assert_eq!(inner_scale(f64::NAN), 1.0);
        for v in [1e30, 3e-30, 2f64.powi(21)] {
            let s = inner_scale(v);
            assert_eq!(s.log2().fract(), 0.0);
            assert!((1.0..2.0).contains(&(v * s)), "{v:e}: {}", v * s);
        }
    }
}
