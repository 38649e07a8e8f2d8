//! `run --dump-systems`: the Newton systems of chosen steps, handed to the caller (the
//! driver writes them as `solve`'s input files) so that a slow or failed solve can be
//! replayed and the solvers benchmarked on the systems a simulation really produces.

use crate::core::constraints::Constraint;
use crate::core::sparse::BlockCsr;
use std::collections::BTreeSet;

/// Which steps' systems to dump: `all`, or a comma-separated list of step numbers (from 1).
/// A checkpoint holds it, so that a resumed run dumps the steps its first part was asked to.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StepSelection {
    All,
    Steps(BTreeSet<usize>),
}

impl StepSelection {
    pub fn contains(&self, step: usize) -> bool {
        match self {
            StepSelection::All => true,
            StepSelection::Steps(s) => s.contains(&step),
        }
    }

    /// Refuses a step past the run's last (`steps`).
    pub fn check(&self, steps: usize) -> Result<(), String> {
        match self {
            StepSelection::Steps(s) => match s.iter().next_back() {
                Some(&last) if last > steps => {
                    Err(format!("step {last} is past the run's last step ({steps})"))
                }
                _ => Ok(()),
            },
            StepSelection::All => Ok(()),
        }
    }
}

impl std::str::FromStr for StepSelection {
    type Err = String;
    /// `all`, or step numbers from 1 separated by commas (`1,10`).
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "all" {
            return Ok(StepSelection::All);
        }
        let mut steps = BTreeSet::new();
        for part in s.split(',') {
            let part = part.trim();
            match part.parse::<usize>() {
                Ok(k) if k >= 1 => {
                    steps.insert(k);
                }
                _ => {
                    return Err(format!(
                        "expected \"all\" or step numbers from 1 separated by commas (1,10), \
                         got \"{part}\""
                    ))
                }
            }
        }
        Ok(StepSelection::Steps(steps))
    }
}

/// One Newton system of a step, as the loop solved it.
#[derive(Debug, Clone)]
pub struct NewtonSystem {
    pub step: usize,
    /// Newton iteration (from 1).
    pub iteration: usize,
    pub dim: usize,
    /// ∇²E (PSD-projected, with the moving penalty), both triangles.
    pub h: BlockCsr,
    /// ∇E.
    pub g: Vec<f64>,
    /// The iterate the system was taken at.
    pub x: Vec<f64>,
    /// The Newton direction the loop used.
    pub dx: Vec<f64>,
    /// The step's homogeneous constraints (static and snapped moving conditions).
    pub constraints: Vec<Constraint>,
    /// The relative residual tolerance Δx was solved to; None for a direct solve.
    pub tolerance: Option<f64>,
    /// CG iterations (1 for a direct solve).
    pub iterations: usize,
}

/// Where [`super::Stepper::step_with`] hands each system of a dumped step.
pub type SystemSink<'a> = &'a mut dyn FnMut(NewtonSystem) -> Result<(), String>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selections_parse_and_refuse_in_one_line() {
        assert_eq!("all".parse::<StepSelection>(), Ok(StepSelection::All));
        let s: StepSelection = "10,1, 3".parse().expect("list");
        assert!(s.contains(1) && s.contains(3) && s.contains(10) && !s.contains(2));
        assert!(s.check(10).is_ok());
        let e = s.check(9).expect_err("past the end");
        assert!(e.contains("step 10") && e.contains("(9)"), "{e}");
        for bad in ["", "0", "1,,2", "x", "-1", "1.5", "ALL"] {
            let e = bad.parse::<StepSelection>().expect_err(bad);
            assert!(
                !e.contains('\n') && e.contains("step numbers"),
                "{bad}: {e}"
            );
        }
    }
}
