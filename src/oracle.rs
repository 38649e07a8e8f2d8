//! The CPU oracle: faer sparse Cholesky (LLᵀ) of the assembled eliminated system.
//!
//! Analysis and factorization are split as in faer: [`CholeskyOracle::analyze`] builds
//! the structure of Ĥ (free components of H's block pattern plus the constrained
//! diagonal) and its symbolic factorization; [`CholeskyOracle::solve`] factors numerically
//! and solves, reusing the analysis while the block pattern and the masks are unchanged
//! (and re-analysing by itself when they change).

use crate::elimination::Eliminated;
use crate::error::SolveError;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltError as PivotError;
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Side};
use std::time::Instant;

/// Timings and sizes of one oracle solve.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OracleInfo {
    /// Seconds in the symbolic analysis (0 when it was reused).
    pub symbolic_seconds: f64,
    pub numeric_seconds: f64,
    pub solve_seconds: f64,
    /// True when this solve reused an earlier analysis.
    pub reused_symbolic: bool,
    /// Stored entries of the lower triangle of Ĥ and of the factor L.
    pub matrix_nnz: usize,
    pub factor_nnz: usize,
    /// ‖b̂ − Ĥy‖/‖b̂‖ recomputed in f64 (matrix-free).
    pub relative_residual: f64,
}

/// Structure of the lower triangle of Ĥ in CSC, with a map from each stored entry back
/// to its place in H's block values.
#[derive(Debug, Clone)]
struct Structure {
    dim: usize,
    row_ptr: Vec<usize>,
    col_idx: Vec<usize>,
    mask: Vec<u8>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// For each stored entry: the index into Ĥ's block values (assembled BlockCsr).
    src: Vec<usize>,
}

impl Structure {
    fn new(e: &Eliminated) -> Self {
        let h = e.h;
        let d = h.dim;
        let f = e.frames;
        let nd = h.ndof();
        let mut col_ptr = Vec::with_capacity(nd + 1);
        col_ptr.push(0);
        let mut row_idx = Vec::new();
        let mut src = Vec::new();
        // Column c = (node j, comp b) of the lower triangle equals row c of the upper one:
        // block row j, blocks (j, i) with i ≥ j, entry (b, a) with (i, a) ≥ (j, b).
        for j in 0..h.n {
            for b in 0..d {
                let c = j * d + b;
                let col_free = f.is_free(j, b);
                for k in h.row_ptr[j]..h.row_ptr[j + 1] {
                    let i = h.col_idx[k];
                    if i < j {
                        continue;
                    }
                    for a in 0..d {
                        let r = i * d + a;
                        if r < c {
                            continue;
                        }
                        let keep = if r == c {
                            true
                        } else {
                            col_free && f.is_free(i, a)
                        };
                        if keep {
                            row_idx.push(r);
                            src.push(k * d * d + b * d + a);
                        }
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        Structure {
            dim: d,
            row_ptr: h.row_ptr.clone(),
            col_idx: h.col_idx.clone(),
            mask: f.mask.clone(),
            col_ptr,
            row_idx,
            src,
        }
    }

    fn matches(&self, e: &Eliminated) -> bool {
        self.dim == e.h.dim
            && self.row_ptr == e.h.row_ptr
            && self.col_idx == e.h.col_idx
            && self.mask == e.frames.mask
    }
}

/// Sparse Cholesky of Ĥ with a reusable symbolic analysis.
pub struct CholeskyOracle {
    structure: Structure,
    symbolic: SymbolicCholesky<usize>,
    symbolic_seconds: f64,
    used: bool,
}

impl CholeskyOracle {
    /// Analyses the pattern of Ĥ (AMD ordering, elimination tree, supernodes).
    pub fn analyze(e: &Eliminated) -> Result<Self, SolveError> {
        let t = Instant::now();
        let structure = Structure::new(e);
        let nd = e.h.ndof();
        let sym = SymbolicSparseColMatRef::new_checked(
            nd,
            nd,
            &structure.col_ptr,
            None,
            &structure.row_idx,
        );
        let symbolic = factorize_symbolic_cholesky(
            sym,
            Side::Lower,
            SymmetricOrdering::Amd,
            CholeskySymbolicParams::default(),
        )
        .map_err(|err| SolveError::Factorization(format!("{err:?}")))?;
        Ok(CholeskyOracle {
            structure,
            symbolic,
            symbolic_seconds: t.elapsed().as_secs_f64(),
            used: false,
        })
    }

    /// Whether the stored analysis fits `e` (same block pattern and masks).
    pub fn fits(&self, e: &Eliminated) -> bool {
        self.structure.matches(e)
    }

    /// Factors Ĥ and solves Ĥ y = b̂; re-analyses first if the pattern or masks changed.
    pub fn solve(&mut self, e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
        let mut reused = self.used;
        if !self.fits(e) {
            *self = CholeskyOracle::analyze(e)?;
            reused = false;
        }
        let symbolic_seconds = if reused { 0.0 } else { self.symbolic_seconds };
        self.used = true;
        let nd = e.h.ndof();
        let t = Instant::now();
        // Values of the lower triangle of Ĥ, gathered from the assembled blocks.
        let hat = e.assemble();
        let values: Vec<f64> = self.structure.src.iter().map(|&s| hat.values[s]).collect();
        let sym = SymbolicSparseColMatRef::new_checked(
            nd,
            nd,
            &self.structure.col_ptr,
            None,
            &self.structure.row_idx,
        );
        let a = SparseColMatRef::new(sym, &values);
        let mut l_values = vec![0.0f64; self.symbolic.len_val()];
        // faer's global setting: all cores through rayon unless the caller changed it.
        let par = faer::get_global_parallelism();
        let mut mem = MemBuffer::try_new(
            self.symbolic
                .factorize_numeric_llt_scratch::<f64>(par, Default::default()),
        )
        .map_err(|err| SolveError::Factorization(format!("out of memory: {err:?}")))?;
        let result = self.symbolic.factorize_numeric_llt::<f64>(
            &mut l_values,
            a,
            Side::Lower,
            LltRegularization::default(),
            par,
            MemStack::new(&mut mem),
            Default::default(),
        );
        let llt: LltRef<'_, usize, f64> = match result {
            Ok(l) => l,
            Err(PivotError::NonPositivePivot { index }) => {
                // The pivot index is in the permuted order; map it back to a DOF.
                let dof = match self.symbolic.perm() {
                    Some(p) => p.arrays().0[index.min(nd - 1)],
                    None => index,
                };
                let d = e.h.dim;
                return Err(SolveError::NotPositiveDefinite {
                    node: dof / d,
                    component: dof % d,
                });
            }
        };
        let numeric_seconds = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut y = e.rhs.clone();
        let mut mem = MemBuffer::try_new(self.symbolic.solve_in_place_scratch::<f64>(1, par))
            .map_err(|err| SolveError::Factorization(format!("out of memory: {err:?}")))?;
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(&mut y, nd, 1),
            par,
            MemStack::new(&mut mem),
        );
        let solve_seconds = t.elapsed().as_secs_f64();
        let relative_residual = e.relative_residual(&y);
        Ok((
            y,
            OracleInfo {
                symbolic_seconds,
                numeric_seconds,
                solve_seconds,
                reused_symbolic: reused,
                matrix_nnz: values.len(),
                factor_nnz: self.symbolic.len_val(),
                relative_residual,
            },
        ))
    }
}

/// One-shot: analyse, factor and solve.
pub fn solve(e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
    CholeskyOracle::analyze(e)?.solve(e)
}

/// Cholesky of the equilibrated system S Ĥ S (see [`crate::cg::Scaling`]), unscaled
/// after. With power-of-two scaling, Cholesky's rounding is unchanged (scaling commutes
/// with every floating-point operation short of over/underflow), so this helps only when
/// entries approach the ends of the f64 range; the plain [`solve`] stays the default.
/// The residual reported is the unscaled one.
pub fn solve_equilibrated(e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
    let eq = crate::cg::equilibrate(e);
    let es = eq.eliminated(e.frames);
    let (z, mut info) = solve(&es)?;
    let y = eq.unscale(&z);
    info.relative_residual = e.relative_residual(&y);
    Ok((y, info))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elimination::ConstrainedDiagonal;
    use crate::generate::{random_system, SystemSpec};

    #[test]
    fn symbolic_reuse_gives_the_same_answer() {
        let mut s = random_system(&SystemSpec::small(3, 21));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let mut oracle = CholeskyOracle::analyze(&e).unwrap();
        let (y1, i1) = oracle.solve(&e).unwrap();
        assert!(!i1.reused_symbolic);
        // A new Newton iterate: same pattern, new values.
        for v in s.h.values.iter_mut() {
            *v *= 1.5;
        }
        for v in s.g.iter_mut() {
            *v *= 1.5;
        }
        let e2 = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let (y2, i2) = oracle.solve(&e2).unwrap();
        assert!(i2.reused_symbolic);
        let (y3, _) = solve(&e2).unwrap();
        for k in 0..y1.len() {
            // Scaling H and g alike leaves the free solution unchanged up to the lift.
            assert!((y2[k] - y3[k]).abs() <= 1e-12 * (1.0 + y3[k].abs()));
        }
        assert!(i1.relative_residual < 1e-12 && i2.relative_residual < 1e-12);
    }

    #[test]
    fn indefinite_system_names_a_node() {
        let mut s = random_system(&SystemSpec::small(2, 4));
        s.frames = crate::constraints::Frames::unconstrained(2, s.h.n);
        let k = s.h.diag_index(3).unwrap();
        s.h.values[k * 4 + 3] = -1e4;
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        match solve(&e) {
            Err(SolveError::NotPositiveDefinite { node, .. }) => assert!(node < s.h.n),
            other => panic!("expected NotPositiveDefinite, got {other:?}"),
        }
    }
}
