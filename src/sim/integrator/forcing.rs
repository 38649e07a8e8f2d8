//! Inexact Newton: the CG tolerance of each Newton system.
//!
//! Newton needs a direction good enough to keep its convergence rate, not the exact one.
//! With `[solver] cg_tolerance = "adaptive"` the tolerance η_k of iteration k of a sequence
//! follows Eisenstat and Walker's second choice (1996) on F_k = b̂_k (the eliminated
//! gradient), within [η_min, η_max] = [`CgTolerance::ADAPTIVE_TIGHTEST`,
//! `CgTolerance::ADAPTIVE_LOOSEST`]:
//!
//! ```text
//! η_1 = min(η_max, τ / (2 ‖Δx_1‖∞ of the previous sequence))      (η_max for the first)
//! η_k = γ (‖b̂_k‖ / ‖b̂_{k−1}‖)^2   (γ = 0.9)
//!       safeguard: η_k ← max(η_k, γ η_{k−1}^2) when γ η_{k−1}^2 > 0.1
//! η_k ← clamp(η_k, η_min, η_max)
//! ```
//!
//! τ is the Newton test's bound on ‖Δx‖∞. Far from the solution ‖b̂‖ falls slowly and η
//! stays near η_max; near it Newton converges fast and η falls with ‖b̂‖². A sequence's
//! first direction does most of a step's work, and an error of η‖Δx_1‖ left by it costs
//! Newton an iteration more once it exceeds τ: it is solved to what the previous
//! sequence's first direction says that takes. η never goes below η_min, which is also the
//! tolerance of the direction on which a step may be declared converged (the Newton loop
//! solves a system again when its loosely solved direction passes the test), so the Newton
//! test ‖Δx‖∞/h < tol is always judged on a direction solved to η_min, whatever the
//! sequence did before.
//!
//! A sequence restarts at the start of every step and whenever the system changes other
//! than by a Newton step: a moving node snapped and eliminated, or the penalty updated. A
//! fixed `cg_tolerance` solves every system to it.

use crate::sim::scene::CgTolerance;
use crate::solve::tolerance::ToleranceRule;

/// γ of the forcing sequence.
const GAMMA: f64 = 0.9;
/// The safeguard applies when γ η_{k−1}^2 exceeds this.
const SAFEGUARD: f64 = 0.1;

/// The forcing sequence of one Newton loop (kept across steps).
#[derive(Debug, Clone)]
pub struct Forcing {
    policy: CgTolerance,
    /// The Newton test's bound on ‖Δx‖∞.
    test: f64,
    /// ‖b̂‖ and η of the previous system of this sequence.
    previous: Option<(f64, f64)>,
    /// ‖Δx‖∞ of the first direction of the current sequence, once solved.
    first_step: Option<f64>,
    /// The same of the previous sequence.
    last_first_step: Option<f64>,
}

impl Forcing {
    /// `test`: the Newton test's bound on ‖Δx‖∞ (newton_tol·h).
    pub fn new(policy: CgTolerance, test: f64) -> Self {
        Forcing {
            policy,
            test,
            previous: None,
            first_step: None,
            last_first_step: None,
        }
    }

    /// The next system starts a new sequence.
    pub fn restart(&mut self) {
        self.previous = None;
        if let Some(s) = self.first_step.take() {
            self.last_first_step = Some(s);
        }
    }

    /// What the next step's sequence starts from (a checkpoint keeps it).
    pub fn carried(&self) -> Option<f64> {
        self.first_step.or(self.last_first_step)
    }

    /// Continues from what [`Forcing::carried`] returned: the state between two steps.
    pub fn resume(&mut self, carried: Option<f64>) {
        self.previous = None;
        self.first_step = None;
        self.last_first_step = carried;
    }

    /// ‖Δx‖∞ of the direction of the last system.
    pub fn step_taken(&mut self, dmax: f64) {
        if self.first_step.is_none() && dmax.is_finite() {
            self.first_step = Some(dmax);
        }
    }

    /// The tolerance of a system whose right-hand side has norm `rhs_norm`; the sequence
    /// remembers it for the next.
    pub fn tolerance(&mut self, rhs_norm: f64) -> f64 {
        let eta = self.rule().eval(rhs_norm);
        self.record(rhs_norm, eta);
        eta
    }

    /// The next system's tolerance as a rule of its ‖b̂‖ ([`Forcing::tolerance`] is its
    /// value, remembered): what a device solve evaluates where ‖b̂‖ is formed.
    pub fn rule(&self) -> ToleranceRule {
        let (lo, hi) = (self.policy.tightest(), self.policy.loosest());
        match (self.policy, self.previous) {
            (CgTolerance::Fixed(t), _) => ToleranceRule::Fixed(t),
            (CgTolerance::Adaptive, None) => ToleranceRule::Fixed(match self.last_first_step {
                // A NaN (a zero first step) keeps η_max through `clamp`'s NaN check below.
                Some(s) if s > 0.0 => (0.5 * self.test / s).clamp(lo, hi),
                _ => hi,
            }),
            (CgTolerance::Adaptive, Some((prev_norm, prev_eta))) => {
                let guard = GAMMA * (prev_eta * prev_eta);
                ToleranceRule::Ratio {
                    prev_norm,
                    gamma: GAMMA,
                    guard: if guard > SAFEGUARD { guard } else { 0.0 },
                    lo,
                    hi,
                }
            }
        }
    }

    /// Remembers the system just solved: its ‖b̂‖ and the tolerance it was solved to
    /// (the value of [`Forcing::rule`] at it).
    pub fn record(&mut self, rhs_norm: f64, eta: f64) {
        self.previous = Some((rhs_norm, eta));
    }

    /// The tolerance a direction must have been solved to for the step to be declared
    /// converged on it.
    pub fn converged_tolerance(&self) -> f64 {
        self.policy.tightest()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HI: f64 = CgTolerance::ADAPTIVE_LOOSEST;
    const LO: f64 = CgTolerance::ADAPTIVE_TIGHTEST;

    #[test]
    fn fixed_tolerance_is_every_systems() {
        let mut f = Forcing::new(CgTolerance::Fixed(1e-9), 1e-8);
        for norm in [1.0, 1e-3, 5.0, 0.0] {
            assert_eq!(f.tolerance(norm), 1e-9);
        }
        assert_eq!(f.converged_tolerance(), 1e-9);
    }

    #[test]
    fn adaptive_starts_loose_and_tightens_with_the_square_of_the_fall() {
        let mut f = Forcing::new(CgTolerance::Adaptive, 1e-8);
        assert_eq!(f.tolerance(1.0), HI);
        // ‖b̂‖ fell 100×: γ·1e-4 = 9e-5, below η_max; the safeguard (γ·1e-8) does not apply.
        let eta = f.tolerance(0.01);
        assert!((eta - GAMMA * 1e-4).abs() <= 1e-15 * eta, "{eta}");
        // Quadratic convergence: 1e-4 fall → γ·1e-8, floored at η_min.
        assert_eq!(f.tolerance(1e-6), LO);
        assert_eq!(f.converged_tolerance(), LO);
    }

    #[test]
    fn a_sequence_starts_from_what_the_last_first_direction_needed() {
        let mut f = Forcing::new(CgTolerance::Adaptive, 1e-8);
        assert_eq!(f.tolerance(1.0), HI);
        f.step_taken(2e-4);
        f.step_taken(1e-6);
        f.restart();
        // τ/(2·2e-4) = 2.5e-5.
        let eta = f.tolerance(1.0);
        assert!((eta - 2.5e-5).abs() <= 1e-15 * eta, "{eta}");
        // A first direction far larger: floored at η_min; far smaller: capped at η_max.
        f.step_taken(1.0);
        f.restart();
        assert_eq!(f.tolerance(1.0), LO);
        f.step_taken(1e-9);
        f.restart();
        assert_eq!(f.tolerance(1.0), HI);
    }

    #[test]
    fn a_slow_fall_keeps_the_loosest() {
        let mut f = Forcing::new(CgTolerance::Adaptive, 1e-8);
        f.tolerance(1.0);
        // ‖b̂‖ grew (a line search far from the solution): capped at η_max.
        assert_eq!(f.tolerance(3.0), HI);
    }

    #[test]
    fn zero_and_nan_norms_never_leave_the_range() {
        let mut f = Forcing::new(CgTolerance::Adaptive, 1e-8);
        f.tolerance(0.0);
        f.step_taken(f64::NAN);
        f.step_taken(0.0);
        f.restart();
        for norm in [0.0, f64::NAN, 1.0, f64::INFINITY] {
            let eta = f.tolerance(norm);
            assert!((LO..=HI).contains(&eta), "{norm}: {eta}");
        }
    }
}
