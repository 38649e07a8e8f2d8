//! The relative residual tolerance of an iterative solve as a rule of ‖b̂‖, evaluated
//! where ‖b̂‖ is first known: on the host for the CPU CG, on the device for the device
//! PCG (shaders/pcg_update.wgsl, `rule_tolerance`, does the operations of
//! [`ToleranceRule::eval`] in the same order), so that a device solve needs no round trip
//! between forming b̂ and iterating.

/// A tolerance as a function of ‖b̂‖.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ToleranceRule {
    /// The same tolerance whatever ‖b̂‖.
    Fixed(f64),
    /// Eisenstat and Walker's second choice against the previous system of a sequence:
    /// η = γ (‖b̂‖/‖b̂_prev‖)², raised to `guard` when `guard` > 0, `hi` when that is not
    /// a number (‖b̂‖ = ‖b̂_prev‖ = 0), else clamped to [`lo`, `hi`].
    Ratio {
        prev_norm: f64,
        gamma: f64,
        guard: f64,
        lo: f64,
        hi: f64,
    },
}

impl ToleranceRule {
    /// The tolerance for a right-hand side of norm `rhs_norm`.
    pub fn eval(&self, rhs_norm: f64) -> f64 {
        match *self {
            ToleranceRule::Fixed(t) => t,
            ToleranceRule::Ratio {
                prev_norm,
                gamma,
                guard,
                lo,
                hi,
            } => {
                let ratio = rhs_norm / prev_norm;
                let mut eta = gamma * (ratio * ratio);
                // A NaN η takes the guard too (as f64::max does).
                if guard > 0.0 && (eta.is_nan() || eta < guard) {
                    eta = guard;
                }
                if eta.is_nan() || eta < 0.0 {
                    hi
                } else if eta < lo {
                    lo
                } else if eta > hi {
                    hi
                } else {
                    eta
                }
            }
        }
    }

    /// Whether the rule needs ‖b̂‖.
    pub fn depends_on_the_rhs(&self) -> bool {
        matches!(self, ToleranceRule::Ratio { .. })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ratio_rule_squares_the_fall_guards_and_clamps() {
        let rule = |prev_norm: f64, guard: f64| ToleranceRule::Ratio {
            prev_norm,
            gamma: 0.9,
            guard,
            lo: 1e-6,
            hi: 1e-2,
        };
        let r = rule(1.0, 0.0);
        assert_eq!(r.eval(0.01), 0.9 * (0.01 * 0.01));
        assert_eq!(r.eval(1.0), 1e-2);
        assert_eq!(r.eval(1e-6), 1e-6);
        assert_eq!(r.eval(f64::INFINITY), 1e-2);
        assert_eq!(rule(0.0, 0.0).eval(0.0), 1e-2);
        let guarded = rule(1.0, 5e-3);
        assert_eq!(guarded.eval(1e-3), 5e-3);
        assert_eq!(ToleranceRule::Fixed(1e-8).eval(f64::NAN), 1e-8);
        assert!(r.depends_on_the_rhs() && !ToleranceRule::Fixed(1.0).depends_on_the_rhs());
    }
}
