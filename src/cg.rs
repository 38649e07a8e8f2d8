//! Preconditioned conjugate gradients in f64 on the eliminated operator, matrix-free.
//!
//! CG never reports convergence it did not reach: when the recurrence residual meets the
//! tolerance, the true residual ‖b̂ − Ĥy‖/‖b̂‖ is recomputed; if it misses, CG restarts
//! from the current iterate (a few times) and otherwise reports [`CgError::Stagnation`].
//! Non-positive curvature pᵀĤp ≤ 0 (Ĥ not positive definite on the free subspace) and
//! the iteration limit are errors too.

use crate::elimination::{norm2, rotate_block, Eliminated};

/// Preconditioner built on the free components of Ĥ (constrained components get 1/D).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preconditioner {
    /// No preconditioning.
    None,
    /// The inverse of diag(Ĥ).
    #[default]
    Jacobi,
    /// The inverse of each node's d×d diagonal block of Ĥ (in the node's frame, masked).
    BlockJacobi,
}

impl std::str::FromStr for Preconditioner {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(Preconditioner::None),
            "jacobi" => Ok(Preconditioner::Jacobi),
            "block-jacobi" => Ok(Preconditioner::BlockJacobi),
            _ => Err(format!(
                "unknown preconditioner '{s}' (expected none, jacobi or block-jacobi)"
            )),
        }
    }
}

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
    /// Restarts allowed when the true residual misses the tolerance at recurrence convergence.
    pub max_restarts: usize,
}

impl Default for CgParams {
    fn default() -> Self {
        CgParams {
            tol: 1e-8,
            max_iters: 10_000,
            preconditioner: Preconditioner::Jacobi,
            stagnation_window: 1_000,
            max_restarts: 3,
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
}

/// Why CG stopped without reaching its tolerance.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CgError {
    #[error("CG met non-positive curvature pᵀĤp = {curvature:e} at iteration {iteration}: the Hessian is not positive definite on the free subspace")]
    NonPositiveCurvature { iteration: usize, curvature: f64 },
    #[error("CG stagnated at iteration {iterations} with relative residual {relative_residual:e} (tolerance {tol:e})")]
    Stagnation {
        iterations: usize,
        relative_residual: f64,
        tol: f64,
    },
    #[error("CG reached the iteration limit {iterations} with relative residual {relative_residual:e} (tolerance {tol:e})")]
    MaxIterations {
        iterations: usize,
        relative_residual: f64,
        tol: f64,
    },
    #[error("CG broke down at iteration {iteration}: a non-finite value appeared")]
    Breakdown { iteration: usize },
}

impl CgError {
    /// The residual reached when the solver gave up (None for breakdowns).
    pub fn reached_residual(&self) -> Option<f64> {
        match self {
            CgError::Stagnation {
                relative_residual, ..
            }
            | CgError::MaxIterations {
                relative_residual, ..
            } => Some(*relative_residual),
            _ => None,
        }
    }
}

/// A preconditioner applied as z = M⁻¹ r.
#[derive(Debug, Clone)]
pub struct BuiltPreconditioner {
    kind: Preconditioner,
    dim: usize,
    /// Jacobi: 1/diag (length dn). BlockJacobi: d·d inverse blocks per node.
    data: Vec<f64>,
}

impl BuiltPreconditioner {
    /// Builds the preconditioner from the diagonal blocks of Ĥ.
    pub fn new(e: &Eliminated, kind: Preconditioner) -> Self {
        let d = e.h.dim;
        let n = e.h.n;
        let blocks = diagonal_blocks(e);
        let data = match kind {
            Preconditioner::None => Vec::new(),
            Preconditioner::Jacobi => (0..n * d)
                .map(|k| {
                    let (i, a) = (k / d, k % d);
                    let v = blocks[i * d * d + a * d + a];
                    if v > 0.0 && v.is_finite() {
                        1.0 / v
                    } else {
                        1.0
                    }
                })
                .collect(),
            Preconditioner::BlockJacobi => {
                let mut out = vec![0.0; n * d * d];
                for i in 0..n {
                    let b = &blocks[i * d * d..(i + 1) * d * d];
                    let inv = invert_spd(d, b).unwrap_or_else(|| {
                        // Not SPD (H indefinite there): fall back to the diagonal so CG
                        // can still detect the negative curvature itself.
                        let mut m = [0.0; 9];
                        for a in 0..d {
                            let v = b[a * d + a];
                            m[a * d + a] = if v > 0.0 { 1.0 / v } else { 1.0 };
                        }
                        m
                    });
                    out[i * d * d..(i + 1) * d * d].copy_from_slice(&inv[..d * d]);
                }
                out
            }
        };
        BuiltPreconditioner {
            kind,
            dim: d,
            data,
        }
    }

    pub fn kind(&self) -> Preconditioner {
        self.kind
    }

    /// z = M⁻¹ r.
    pub fn apply(&self, r: &[f64], z: &mut [f64]) {
        match self.kind {
            Preconditioner::None => z.copy_from_slice(r),
            Preconditioner::Jacobi => {
                for ((zi, ri), di) in z.iter_mut().zip(r).zip(&self.data) {
                    *zi = ri * di;
                }
            }
            Preconditioner::BlockJacobi => {
                let d = self.dim;
                for i in 0..r.len() / d {
                    let m = &self.data[i * d * d..(i + 1) * d * d];
                    for a in 0..d {
                        let mut s = 0.0;
                        for b in 0..d {
                            s += m[a * d + b] * r[i * d + b];
                        }
                        z[i * d + a] = s;
                    }
                }
            }
        }
    }

    /// The raw data (1/diag, or inverse blocks), for the GPU upload.
    pub fn data(&self) -> &[f64] {
        &self.data
    }
}

/// The d×d diagonal blocks of Ĥ, row-major, n·d·d values.
pub fn diagonal_blocks(e: &Eliminated) -> Vec<f64> {
    let d = e.h.dim;
    let n = e.h.n;
    let f = e.frames;
    let mut out = vec![0.0; n * d * d];
    for i in 0..n {
        let b = &mut out[i * d * d..(i + 1) * d * d];
        if let Some(k) = e.h.diag_index(i) {
            let v = f.rotation(i);
            rotate_block(d, e.h.block(k), v, v, b);
        }
        let m = f.mask[i];
        if m != 0 {
            for r in 0..d {
                for c in 0..d {
                    if m & (1 << r) != 0 || m & (1 << c) != 0 {
                        b[r * d + c] = 0.0;
                    }
                }
                if m & (1 << r) != 0 {
                    b[r * d + r] = e.diag[i * d + r];
                }
            }
        }
    }
    out
}

/// Inverse of a small SPD matrix through its Cholesky factor; None if not SPD.
fn invert_spd(d: usize, a: &[f64]) -> Option<[f64; 9]> {
    let m = nalgebra::DMatrix::from_row_slice(d, d, a);
    let chol = nalgebra::Cholesky::new(m)?;
    let inv = chol.inverse();
    let mut out = [0.0; 9];
    for r in 0..d {
        for c in 0..d {
            out[r * d + c] = inv[(r, c)];
        }
    }
    Some(out)
}

/// Solves Ĥ y = b̂ by PCG from y = 0.
pub fn solve(e: &Eliminated, params: &CgParams) -> Result<(Vec<f64>, CgInfo), CgError> {
    let pre = BuiltPreconditioner::new(e, params.preconditioner);
    solve_with(e, &pre, None, params)
}

/// Solves Ĥ y = b̂ by PCG with a prebuilt preconditioner, from `y0` (or zero).
pub fn solve_with(
    e: &Eliminated,
    pre: &BuiltPreconditioner,
    y0: Option<&[f64]>,
    params: &CgParams,
) -> Result<(Vec<f64>, CgInfo), CgError> {
    let n = e.ndof();
    let b = &e.rhs;
    let bnorm = norm2(b);
    let mut y = match y0 {
        Some(v) => v.to_vec(),
        None => vec![0.0; n],
    };
    if bnorm == 0.0 {
        // Ĥ is SPD, so the solution is exactly zero.
        return Ok((
            vec![0.0; n],
            CgInfo {
                iterations: 0,
                relative_residual: 0.0,
                restarts: 0,
            },
        ));
    }
    let mut work = vec![0.0; 2 * n];
    let mut r = vec![0.0; n];
    let mut z = vec![0.0; n];
    let mut p = vec![0.0; n];
    let mut q = vec![0.0; n];
    let mut iterations = 0usize;
    let mut restarts = 0usize;
    let true_residual = |y: &[f64], r: &mut [f64], work: &mut [f64]| -> f64 {
        e.apply(y, r, work);
        for (ri, bi) in r.iter_mut().zip(b) {
            *ri = bi - *ri;
        }
        norm2(r) / bnorm
    };
    loop {
        // (Re)start: r = b − Ĥy, z = M⁻¹r, p = z.
        let mut rel = true_residual(&y, &mut r, &mut work);
        if rel <= params.tol {
            return Ok((
                y,
                CgInfo {
                    iterations,
                    relative_residual: rel,
                    restarts,
                },
            ));
        }
        pre.apply(&r, &mut z);
        p.copy_from_slice(&z);
        let mut rz = dot(&r, &z);
        let mut best = rel;
        let mut best_at = iterations;
        loop {
            if iterations >= params.max_iters {
                let rel = true_residual(&y, &mut r, &mut work);
                return Err(CgError::MaxIterations {
                    iterations,
                    relative_residual: rel,
                    tol: params.tol,
                });
            }
            e.apply(&p, &mut q, &mut work);
            let pq = dot(&p, &q);
            iterations += 1;
            if !pq.is_finite() || !rz.is_finite() {
                return Err(CgError::Breakdown {
                    iteration: iterations,
                });
            }
            if pq <= 0.0 {
                return Err(CgError::NonPositiveCurvature {
                    iteration: iterations,
                    curvature: pq,
                });
            }
            let alpha = rz / pq;
            for k in 0..n {
                y[k] += alpha * p[k];
                r[k] -= alpha * q[k];
            }
            rel = norm2(&r) / bnorm;
            if rel <= params.tol {
                break;
            }
            if rel < best {
                best = rel;
                best_at = iterations;
            } else if iterations - best_at >= params.stagnation_window {
                let rel = true_residual(&y, &mut r, &mut work);
                return Err(CgError::Stagnation {
                    iterations,
                    relative_residual: rel,
                    tol: params.tol,
                });
            }
            pre.apply(&r, &mut z);
            let rz_new = dot(&r, &z);
            let beta = rz_new / rz;
            rz = rz_new;
            for k in 0..n {
                p[k] = z[k] + beta * p[k];
            }
        }
        // The recurrence says converged: check the truth.
        let rel_true = true_residual(&y, &mut r, &mut work);
        if rel_true <= params.tol {
            return Ok((
                y,
                CgInfo {
                    iterations,
                    relative_residual: rel_true,
                    restarts,
                },
            ));
        }
        if restarts >= params.max_restarts {
            return Err(CgError::Stagnation {
                iterations,
                relative_residual: rel_true,
                tol: params.tol,
            });
        }
        restarts += 1;
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elimination::ConstrainedDiagonal;
    use crate::generate::{random_system, SystemSpec};

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
            assert!((e.relative_residual(&y) - info.relative_residual).abs() < 1e-15);
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
        s.frames = crate::constraints::Frames::unconstrained(2, s.h.n);
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
}
