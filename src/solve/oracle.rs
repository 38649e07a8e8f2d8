//! The CPU oracle: faer sparse Cholesky (LLᵀ) of the assembled eliminated system.
//!
//! Analysis and factorization are split as in faer: [`CholeskyOracle::analyze`] builds
//! the structure of Ĥ (free components of H's block pattern plus the constrained
//! diagonal) and its symbolic factorization; [`CholeskyOracle::solve`] factors numerically
//! and solves, reusing the analysis while the block pattern and the masks are unchanged
//! (and re-analysing by itself when they change).
//!
//! The fill-reducing ordering is faer's AMD or nested dissection of the node graph
//! ([`crate::solve::ordering`]), chosen by [`CholeskyOrdering`] and passed to faer as a custom
//! symmetric ordering.

use crate::core::elimination::Eliminated;
use crate::error::SolveError;
use crate::solve::ordering::{self, CholeskyOrdering, NodeGraph};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltError as PivotError;
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::perm::PermRef;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, simplicial, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymbolicCholeskyRaw, SymmetricOrdering,
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
    /// The ordering the analysis used: "amd" or "nested-dissection" (never "auto").
    pub ordering: CholeskyOrdering,
    /// Seconds computing that ordering (part of `symbolic_seconds`; 0 when reused).
    pub ordering_seconds: f64,
    /// Stored entries of the lower triangle of Ĥ and of the factor L. faer's supernodal
    /// storage holds each supernode's diagonal block in full and the zeros that merging
    /// supernodes adds, so `factor_nnz` exceeds the structural count below.
    pub matrix_nnz: usize,
    pub factor_nnz: usize,
    /// Structural nonzeros of L (on and below the diagonal) for the ordering used: the
    /// elimination tree's column counts, comparable with other solvers' nnz(L).
    pub factor_nnz_exact: usize,
    /// ‖b̂ − Ĥy‖/‖b̂‖ recomputed in f64 (matrix-free).
    pub relative_residual: f64,
    /// ‖D(b̂ − Ĥy)‖/‖Db̂‖, the residual of the system the factor is of (D: the powers of
    /// two nearest Ĥ_kk^(−½)); the bound [`CHOLESKY_MAX_RESIDUAL`] applies to it. It
    /// equals the relative residual when Ĥ's diagonal is uniform, and stays meaningful
    /// when the diagonal spans the f64 range (where Ĥy cancels to far below its terms
    /// and the plain residual cannot be computed in f64).
    pub scaled_residual: f64,
    /// Steps of iterative refinement on the factor (0 unless the first solve's scaled
    /// residual was above [`CHOLESKY_MAX_RESIDUAL`]).
    pub refinements: usize,
    /// κ(DĤD) estimated on the factor (‖DĤD‖∞ times an inverse-iteration estimate of
    /// ‖(DĤD)⁻¹‖₂), computed only when the refined residual stayed above the bound.
    pub condition_estimate: Option<f64>,
}

/// The residual ‖D(b̂ − Ĥy)‖/‖Db̂‖ a Cholesky solve aims for. Above it the solve refines
/// (up to [`MAX_REFINEMENTS`] steps on the same factor, residuals in double-double). A
/// result still above it is accepted only while κ(DĤD) stays below [`SINGULAR_KAPPA`]:
/// no f64 y has a residual much below κε‖b̂‖, so an ill-conditioned Ĥ (κ = 1e10, say)
/// misses the bound with the best answer f64 holds; past that κ, Ĥ is singular to
/// working precision and the solve fails ([`SolveError::Singular`]).
pub const CHOLESKY_MAX_RESIDUAL: f64 = 1e-8;
/// κ(DĤD) from which Ĥ counts as singular to working precision: 1/(64ε) ≈ 7.0e13 (the
/// LAPACK test rcond < ε, with a margin of 64 for the estimate). At κε = 1/64 a
/// backward-stable solve can already be off by a few per cent.
pub const SINGULAR_KAPPA: f64 = 1.0 / (64.0 * f64::EPSILON);
/// Refinement steps at most; refinement also stops when a step does not lower the
/// residual, or once it is at the level of rounding (a scaled residual of 1e-14).
pub const MAX_REFINEMENTS: usize = 10;
/// Where refinement stops: a residual at the level of rounding.
const REFINED: f64 = 1e-14;

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

/// ‖D(b̂ − Ĥy)‖/‖Db̂‖ with its vector D(b̂ − Ĥy), for one system and scaling. The
/// residual is summed in double-double ([`crate::core::sparse::BlockCsr::residual_dd`]):
/// accurate however much b̂ and Ĥy cancel, where an f64 residual would stall at
/// ε‖Ĥ‖‖y‖ (≈ κε‖b̂‖), so refinement converges while κ(Ĥ)·ε < 1 and the check measures
/// the solve, not its own rounding.
struct ScaledResidual<'e> {
    hat: &'e crate::core::sparse::BlockCsr,
    rhs: &'e [f64],
    scale: &'e [f64],
    db_norm: f64,
}

impl<'e> ScaledResidual<'e> {
    fn new(hat: &'e crate::core::sparse::BlockCsr, rhs: &'e [f64], scale: &'e [f64]) -> Self {
        let db: Vec<f64> = rhs.iter().zip(scale).map(|(b, s)| b * s).collect();
        ScaledResidual {
            hat,
            rhs,
            scale,
            db_norm: crate::core::linalg::norm2(&db),
        }
    }

    /// D(b̂ − Ĥy) and its norm over ‖Db̂‖ (0 when both vanish, 1 when only b̂ does).
    fn of(&self, y: &[f64]) -> (Vec<f64>, f64) {
        let mut dr = self.hat.residual_dd(self.rhs, y);
        dr.iter_mut().zip(self.scale).for_each(|(r, s)| *r *= s);
        let rn = crate::core::linalg::norm2(&dr);
        let ratio = match (self.db_norm == 0.0, rn == 0.0) {
            (true, true) => 0.0,
            (true, false) => 1.0,
            _ => rn / self.db_norm,
        };
        (dr, ratio)
    }
}

/// ‖A⁻¹‖₂ estimated by 8 steps of inverse iteration from a fixed vector (`solve`
/// overwrites its argument with A⁻¹ times it): ‖A⁻¹v_k‖ for unit v_k, a lower bound that
/// approaches ‖A⁻¹‖₂ as the smallest eigenvalue separates.
fn inverse_norm_estimate(n: usize, mut solve: impl FnMut(&mut [f64])) -> f64 {
    // A fixed, irregular start (golden-ratio sequence): no eigenvector of a structured
    // matrix is orthogonal to it by accident.
    let mut v: Vec<f64> = (0..n)
        .map(|k| 0.5 + (k as f64 * 0.618_033_988_749_895).fract())
        .collect();
    let mut est = 0.0;
    for _ in 0..8 {
        let nv = crate::core::linalg::norm2(&v);
        if !(nv > 0.0 && nv.is_finite()) {
            return f64::INFINITY;
        }
        v.iter_mut().for_each(|x| *x /= nv);
        solve(&mut v);
        est = crate::core::linalg::norm2(&v);
    }
    est
}

/// y ← D y.
fn unscale(y: &mut [f64], scale: &[f64]) {
    for (v, s) in y.iter_mut().zip(scale) {
        *v *= s;
    }
}

impl Structure {
    /// Scales the lower triangle's values to D Ĥ D in place and returns D: per DOF the
    /// power of two nearest Ĥ_kk^(−½) (1 where Ĥ_kk is not a positive finite number).
    /// Powers of two scale every operation of the factorization exactly, so this changes
    /// no bits unless Ĥ's entries approach the ends of the f64 range.
    fn scale(&self, values: &mut [f64]) -> Vec<f64> {
        let nd = self.col_ptr.len() - 1;
        let mut scale = vec![1.0; nd];
        for (c, s) in scale.iter_mut().enumerate() {
            let range = self.col_ptr[c]..self.col_ptr[c + 1];
            if let Some(k) = range.clone().find(|&k| self.row_idx[k] == c) {
                let d = values[k];
                if d > 0.0 && d.is_finite() {
                    *s = crate::core::linalg::power_of_two(-0.5 * d.log2());
                }
            }
        }
        for c in 0..nd {
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                values[k] *= scale[self.row_idx[k]] * scale[c];
            }
        }
        scale
    }

    /// ‖A‖∞ of the symmetric matrix whose lower triangle `values` holds.
    fn norm_inf(&self, values: &[f64]) -> f64 {
        let nd = self.col_ptr.len() - 1;
        let mut rows = vec![0.0f64; nd];
        for c in 0..nd {
            let range = self.col_ptr[c]..self.col_ptr[c + 1];
            for (&r, v) in self.row_idx[range.clone()].iter().zip(&values[range]) {
                rows[r] += v.abs();
                if r != c {
                    rows[c] += v.abs();
                }
            }
        }
        rows.into_iter().fold(0.0, f64::max)
    }

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
    /// What was asked for (a re-analysis asks again) and what ran.
    requested: CholeskyOrdering,
    ordering: CholeskyOrdering,
    ordering_seconds: f64,
    factor_nnz_exact: usize,
    used: bool,
}

impl CholeskyOracle {
    /// Analyses the pattern of Ĥ (ordering, elimination tree, supernodes) with the
    /// [`CholeskyOrdering::Auto`] choice of ordering.
    pub fn analyze(e: &Eliminated) -> Result<Self, SolveError> {
        Self::analyze_with(e, CholeskyOrdering::Auto)
    }

    /// Analyses the pattern of Ĥ with the given ordering.
    pub fn analyze_with(e: &Eliminated, requested: CholeskyOrdering) -> Result<Self, SolveError> {
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
        let t_order = Instant::now();
        let graph = || NodeGraph::new(e.h.dim, &e.h.row_ptr, &e.h.col_idx, &e.frames.mask);
        let chosen = match requested {
            CholeskyOrdering::Amd => Candidate::amd(sym)?.counted(&structure)?,
            CholeskyOrdering::NestedDissection => {
                let g = graph().map_err(SolveError::Factorization)?;
                Candidate::nested_dissection(&structure, &g, e)?
            }
            CholeskyOrdering::Auto => {
                // AMD's flops are its own estimate (no column-count pass unless it wins).
                let amd = Candidate::amd(sym)?;
                // A graph METIS cannot index keeps AMD.
                let nest = match graph() {
                    Ok(g) if ordering::auto_tries_nested_dissection(&g) => {
                        Some(Candidate::nested_dissection(&structure, &g, e)?)
                    }
                    _ => None,
                };
                match nest {
                    Some(n) if n.flops < amd.flops => n,
                    _ => amd.counted(&structure)?,
                }
            }
        };
        let ordering_seconds = t_order.elapsed().as_secs_f64();
        let symbolic = factorize_symbolic_cholesky(
            sym,
            Side::Lower,
            SymmetricOrdering::Custom(PermRef::new_checked(&chosen.fwd, &chosen.inv, nd)),
            CholeskySymbolicParams::default(),
        )
        .map_err(|err| SolveError::Factorization(format!("{err:?}")))?;
        Ok(CholeskyOracle {
            structure,
            symbolic,
            symbolic_seconds: t.elapsed().as_secs_f64(),
            requested,
            ordering: chosen.ordering,
            ordering_seconds,
            factor_nnz_exact: chosen.nnz,
            used: false,
        })
    }

    /// The ordering the analysis used ([`CholeskyOrdering::Amd`] or
    /// [`CholeskyOrdering::NestedDissection`]).
    pub fn ordering(&self) -> CholeskyOrdering {
        self.ordering
    }

    /// Stored entries of the factor L (faer's supernodal storage).
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.len_val()
    }

    /// Supernodes of the factor (None when faer chose the simplicial factorization).
    pub fn supernodes(&self) -> Option<usize> {
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(s) => Some(s.n_supernodes()),
            SymbolicCholeskyRaw::Simplicial(_) => None,
        }
    }

    /// Structural nonzeros of L for the ordering used.
    pub fn factor_nnz_exact(&self) -> usize {
        self.factor_nnz_exact
    }

    /// Seconds of the analysis, and of the ordering within it.
    pub fn analysis_seconds(&self) -> (f64, f64) {
        (self.symbolic_seconds, self.ordering_seconds)
    }

    /// Whether the stored analysis fits `e` (same block pattern and masks).
    pub fn fits(&self, e: &Eliminated) -> bool {
        self.structure.matches(e)
    }

    /// Factors Ĥ and solves Ĥ y = b̂; re-analyses first if the pattern or masks changed.
    /// The factor is of D Ĥ D with D the powers of two nearest Ĥ's diagonal to the −½
    /// (exact: the same bits as Ĥ's own factor wherever that stays inside the f64 range,
    /// and a factor where Ĥ's entries span it). A residual above [`CHOLESKY_MAX_RESIDUAL`]
    /// is refined on the factor; if it still misses the bound and DĤD is singular to
    /// working precision ([`SINGULAR_KAPPA`]) the solve fails ([`SolveError::Singular`],
    /// or [`SolveError::NotFinite`] for an overflow).
    pub fn solve(&mut self, e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
        let (y, info) = self.solve_refined(e)?;
        let r = info.scaled_residual;
        if r.is_nan() || r.is_infinite() {
            return Err(SolveError::NotFinite(format!(
                "the Cholesky solve's relative residual is {r}: the system overflows f64 \
                 (check the magnitudes of H, g and the prescribed values)"
            )));
        }
        if let Some(kappa) = info.condition_estimate {
            if kappa >= SINGULAR_KAPPA || kappa.is_nan() {
                return Err(SolveError::Singular {
                    condition_estimate: kappa,
                    scaled_residual: r,
                    refinements: info.refinements,
                });
            }
        }
        Ok((y, info))
    }

    /// One factorization and solve, refined while the residual is above the bound.
    fn solve_refined(&mut self, e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
        let mut reused = self.used;
        if !self.fits(e) {
            *self = CholeskyOracle::analyze_with(e, self.requested)?;
            reused = false;
        }
        let symbolic_seconds = if reused { 0.0 } else { self.symbolic_seconds };
        self.used = true;
        let nd = e.h.ndof();
        let t = Instant::now();
        // Values of the lower triangle of Ĥ, gathered from the assembled blocks.
        let hat = e.assemble();
        let mut values: Vec<f64> = self.structure.src.iter().map(|&s| hat.values[s]).collect();
        let scale = self.structure.scale(&mut values);
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
                // The pivot index is in the permuted order; map it back to a DOF. faer's
                // simplicial factorization reports it one-based, the supernodal zero-based.
                let index = match self.symbolic.raw() {
                    SymbolicCholeskyRaw::Simplicial(_) => index.saturating_sub(1),
                    SymbolicCholeskyRaw::Supernodal(_) => index,
                };
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
        let mut y: Vec<f64> = e.rhs.iter().zip(&scale).map(|(b, s)| b * s).collect();
        let mut mem = MemBuffer::try_new(self.symbolic.solve_in_place_scratch::<f64>(1, par))
            .map_err(|err| SolveError::Factorization(format!("out of memory: {err:?}")))?;
        // v ← (DĤD)⁻¹v on the factor.
        let mut solve_in_place = |v: &mut [f64]| {
            llt.solve_in_place_with_conj(
                Conj::No,
                MatMut::from_column_major_slice_mut(v, nd, 1),
                par,
                MemStack::new(&mut mem),
            )
        };
        solve_in_place(&mut y);
        unscale(&mut y, &scale);
        let scaled = ScaledResidual::new(&hat, &e.rhs, &scale);
        let (mut dr, mut scaled_residual) = scaled.of(&y);
        let mut refinements = 0;
        if scaled_residual > CHOLESKY_MAX_RESIDUAL && scaled_residual.is_finite() {
            while refinements < MAX_REFINEMENTS && scaled_residual > REFINED {
                // y + D (DĤD)⁻¹ D(b̂ − Ĥy) on the same factor (the residual in
                // double-double), kept only if it lowers the residual.
                let mut d = dr;
                solve_in_place(&mut d);
                unscale(&mut d, &scale);
                let next: Vec<f64> = y.iter().zip(&d).map(|(a, b)| a + b).collect();
                let (next_dr, r) = scaled.of(&next);
                if r >= scaled_residual || r.is_nan() {
                    break;
                }
                (y, dr, scaled_residual) = (next, next_dr, r);
                refinements += 1;
            }
        }
        // Above the bound after refinement: is DĤD singular to working precision, or is
        // this the residual f64 allows for its condition (an f64 y cannot do better than
        // ‖b̂ − Ĥy‖ ≈ κε‖b̂‖)? Estimated on the same factor.
        let condition_estimate = (scaled_residual > CHOLESKY_MAX_RESIDUAL).then(|| {
            let norm_inf = self.structure.norm_inf(&values);
            norm_inf * inverse_norm_estimate(nd, &mut solve_in_place)
        });
        let relative_residual = e.relative_residual(&y);
        let solve_seconds = t.elapsed().as_secs_f64();
        Ok((
            y,
            OracleInfo {
                symbolic_seconds,
                numeric_seconds,
                solve_seconds,
                reused_symbolic: reused,
                ordering: self.ordering,
                ordering_seconds: if reused { 0.0 } else { self.ordering_seconds },
                matrix_nnz: values.len(),
                factor_nnz: self.symbolic.len_val(),
                factor_nnz_exact: self.factor_nnz_exact,
                relative_residual,
                scaled_residual,
                refinements,
                condition_estimate,
            },
        ))
    }
}

/// One fill-reducing permutation with its factor's size.
struct Candidate {
    ordering: CholeskyOrdering,
    /// `fwd[new] = old` DOF, `inv[old] = new`.
    fwd: Vec<usize>,
    inv: Vec<usize>,
    /// Structural nnz(L), and the flops counted as AMD counts them ([`ldl_flops`]).
    nnz: usize,
    flops: f64,
}

impl Candidate {
    /// AMD's order with AMD's estimate of the flops (from its approximate degrees, upper
    /// bounds of the exact ones); `nnz` is 0 until [`Candidate::counted`].
    fn amd(sym: SymbolicSparseColMatRef<'_, usize>) -> Result<Self, SolveError> {
        let nd = sym.nrows();
        let mut fwd = vec![0usize; nd];
        let mut inv = vec![0usize; nd];
        let mut mem = MemBuffer::try_new(amd::order_maybe_unsorted_scratch::<usize>(
            nd,
            sym.compute_nnz(),
        ))
        .map_err(|err| SolveError::Factorization(format!("out of memory: {err:?}")))?;
        let est = amd::order_maybe_unsorted(
            &mut fwd,
            &mut inv,
            sym,
            amd::Control::default(),
            MemStack::new(&mut mem),
        )
        .map_err(|err| SolveError::Factorization(format!("AMD: {err:?}")))?;
        Ok(Candidate {
            ordering: CholeskyOrdering::Amd,
            fwd,
            inv,
            nnz: 0,
            flops: est.n_div + est.n_mult_subs_ldl,
        })
    }

    fn nested_dissection(s: &Structure, g: &NodeGraph, e: &Eliminated) -> Result<Self, SolveError> {
        let fwd =
            ordering::nested_dissection(g, e.h.dim, e.h.n).map_err(SolveError::Factorization)?;
        let inv = ordering::inverse(&fwd).ok_or_else(|| {
            SolveError::Factorization("nested dissection: not a permutation".into())
        })?;
        Candidate {
            ordering: CholeskyOrdering::NestedDissection,
            fwd,
            inv,
            nnz: 0,
            flops: 0.0,
        }
        .counted(s)
    }

    /// Exact column counts: nnz(L), the flops, and the order postordered.
    fn counted(self, s: &Structure) -> Result<Self, SolveError> {
        let Candidate {
            ordering, fwd, inv, ..
        } = self;
        let (counts, etree) = column_counts(s, &inv)?;
        // Postorder the elimination tree (fill unchanged): each subtree's columns become
        // consecutive, so faer finds whole supernodes. AMD's order already is one;
        // METIS's is not.
        let post = postorder(&etree);
        let fwd: Vec<usize> = post.iter().map(|&k| fwd[k]).collect();
        let inv = ordering::inverse(&fwd)
            .ok_or_else(|| SolveError::Factorization("postorder: not a permutation".into()))?;
        Ok(Candidate {
            ordering,
            nnz: counts.iter().sum(),
            flops: counts.iter().map(|&c| ldl_flops(c)).sum(),
            fwd,
            inv,
        })
    }
}

/// Flops of one column of L with `c` entries (diagonal included), as AMD counts them: d
/// divisions and d(d + 1)/2 multiply-subtracts for its d = c − 1 off-diagonal entries.
fn ldl_flops(c: usize) -> f64 {
    let d = c.saturating_sub(1) as f64;
    d + d * (d + 1.0) / 2.0
}

/// Column counts (diagonal included) of the Cholesky factor of the lower-triangle
/// pattern in `s` permuted by `inv` (`inv[old] = new`): faer's elimination-tree pass,
/// O(nnz(L)). Their sum is the structural nnz(L). Also the elimination tree (parent of
/// each column, negative at a root).
fn column_counts(s: &Structure, inv: &[usize]) -> Result<(Vec<usize>, Vec<isize>), SolveError> {
    let nd = s.col_ptr.len() - 1;
    // Upper triangle of P Ĥ Pᵀ in CSC (faer's pass reads the upper part; it needs no
    // order within a column).
    let mut col_ptr = vec![0usize; nd + 1];
    for c in 0..nd {
        for &r in &s.row_idx[s.col_ptr[c]..s.col_ptr[c + 1]] {
            col_ptr[inv[r].max(inv[c]) + 1] += 1;
        }
    }
    for k in 0..nd {
        col_ptr[k + 1] += col_ptr[k];
    }
    let mut next = col_ptr.clone();
    let mut row_idx = vec![0usize; s.row_idx.len()];
    for c in 0..nd {
        for &r in &s.row_idx[s.col_ptr[c]..s.col_ptr[c + 1]] {
            let (a, b) = (inv[r], inv[c]);
            let col = a.max(b);
            row_idx[next[col]] = a.min(b);
            next[col] += 1;
        }
    }
    let upper = SymbolicSparseColMatRef::new_unsorted_checked(nd, nd, &col_ptr, None, &row_idx);
    let mut etree = vec![0isize; nd];
    let mut counts = vec![0usize; nd];
    let mut mem = MemBuffer::try_new(simplicial::prefactorize_symbolic_cholesky_scratch::<usize>(
        nd,
        row_idx.len(),
    ))
    .map_err(|err| SolveError::Factorization(format!("out of memory: {err:?}")))?;
    simplicial::prefactorize_symbolic_cholesky(
        &mut etree,
        &mut counts,
        upper,
        MemStack::new(&mut mem),
    );
    Ok((counts, etree))
}

/// A postorder of the forest `parent` (negative: a root): `post[k]` is the k-th column
/// visited, children in increasing order, every subtree consecutive.
fn postorder(parent: &[isize]) -> Vec<usize> {
    let n = parent.len();
    // Children lists in increasing order (built backwards, so pushes come out ascending).
    let mut head = vec![usize::MAX; n];
    let mut next = vec![usize::MAX; n];
    let mut roots = Vec::new();
    for j in (0..n).rev() {
        match usize::try_from(parent[j]) {
            Ok(p) if p < n => {
                next[j] = head[p];
                head[p] = j;
            }
            _ => roots.push(j),
        }
    }
    let mut post = Vec::with_capacity(n);
    let mut stack: Vec<usize> = Vec::new();
    // Roots were collected backwards; take them ascending.
    for &r in roots.iter().rev() {
        stack.push(r);
        while let Some(&j) = stack.last() {
            let c = head[j];
            if c == usize::MAX {
                post.push(j);
                stack.pop();
            } else {
                // Detach the first child and descend into it.
                head[j] = next[c];
                stack.push(c);
            }
        }
    }
    post
}

/// One-shot: analyse, factor and solve.
pub fn solve(e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
    CholeskyOracle::analyze(e)?.solve(e)
}

/// Cholesky of the node-wise equilibrated system S Ĥ S (see [`crate::solve::cg::Scaling`]),
/// unscaled after: the CG's scaling, for comparison. [`solve`] already scales per DOF
/// by powers of two, which changes no bits short of over/underflow, so the two agree
/// except at the ends of the f64 range. The residual reported is the unscaled one.
pub fn solve_equilibrated(e: &Eliminated) -> Result<(Vec<f64>, OracleInfo), SolveError> {
    let eq = crate::solve::cg::equilibrate(e);
    let es = eq.eliminated(e.frames);
    let (z, mut info) = solve(&es)?;
    let y = eq.unscale(&z);
    info.relative_residual = e.relative_residual(&y);
    Ok((y, info))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cases::generate::{random_system, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

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
        s.frames = crate::core::constraints::Frames::unconstrained(2, s.h.n);
        let k = s.h.diag_index(3).unwrap();
        s.h.values[k * 4 + 3] = -1e4;
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        match solve(&e) {
            Err(SolveError::NotPositiveDefinite { node, .. }) => assert!(node < s.h.n),
            other => panic!("expected NotPositiveDefinite, got {other:?}"),
        }
    }
}

#[cfg(test)]
mod pivot_tests {
    use super::*;
    use crate::cases::generate::{random_system, GeneratedSystem, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    /// A diagonal Ĥ with one zero entry: the error names that DOF, under both orderings.
    #[test]
    fn a_zero_pivot_names_its_own_dof() {
        for dim in [2usize, 3] {
            for seed in 0..5u64 {
                let s = random_system(&SystemSpec::small(dim, 40 + seed));
                zero_pivot_case(&s, (seed as usize * 7 + 3) % s.h.ndof());
            }
        }
    }

    /// The same on grids large enough for faer's supernodal factorization.
    #[test]
    fn a_zero_pivot_names_its_own_dof_in_a_supernodal_factor() {
        let mut supernodal = 0;
        for (dim, grid) in [(2usize, [40usize, 40, 1]), (3, [12, 12, 12])] {
            let mut spec = SystemSpec::small(dim, 7);
            spec.grid = grid;
            let s = random_system(&spec);
            let n = s.h.ndof();
            for dof in [0, 1, n / 2 + 1, n - 1] {
                supernodal += zero_pivot_case(&s, dof);
            }
        }
        assert!(supernodal > 0, "no case used the supernodal factorization");
    }

    /// Ĥ = 2I on the system's pattern (no constraints) with a zero at `dof`: the error
    /// names `dof` under AMD and nested dissection. Returns how many of the two
    /// factorizations were supernodal.
    fn zero_pivot_case(s: &GeneratedSystem, dof: usize) -> usize {
        let (dim, d2) = (s.h.dim, s.h.dim * s.h.dim);
        let mut h = s.h.clone();
        for i in 0..h.n {
            for k in h.row_ptr[i]..h.row_ptr[i + 1] {
                for a in 0..d2 {
                    let diag = h.col_idx[k] == i && a % (dim + 1) == 0;
                    h.values[k * d2 + a] = if diag { 2.0 } else { 0.0 };
                }
            }
        }
        let k = h.diag_index(dof / dim).unwrap();
        h.values[k * d2 + (dof % dim) * (dim + 1)] = 0.0;
        let frames = crate::core::constraints::Frames::unconstrained(dim, h.n);
        let e = Eliminated::new(&h, &s.g, &frames, ConstrainedDiagonal::Identity);
        let mut supernodal = 0;
        for ordering in [CholeskyOrdering::Amd, CholeskyOrdering::NestedDissection] {
            let mut oracle = CholeskyOracle::analyze_with(&e, ordering).unwrap();
            supernodal += oracle.supernodes().is_some() as usize;
            match oracle.solve(&e) {
                Err(SolveError::NotPositiveDefinite { node, component }) => assert_eq!(
                    (node, component),
                    (dof / dim, dof % dim),
                    "{dim}D DOF {dof} {ordering:?}"
                ),
                other => panic!("{dim}D DOF {dof} {ordering:?}: {other:?}"),
            }
        }
        supernodal
    }
}

#[cfg(test)]
mod ordering_tests {
    use super::*;
    use crate::cases::generate::{random_system, ConstraintMix, GeneratedSystem, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    /// A seeded system of about `nodes` nodes with every kind of constraint mixed in
    /// (rotated slip nodes, sticky nodes, lines, prescribed values).
    fn mixed(dim: usize, nodes: usize, seed: u64) -> GeneratedSystem {
        let mut spec = SystemSpec::with_nodes(dim, nodes, seed);
        spec.mix = ConstraintMix::Random;
        let s = random_system(&spec);
        assert!(!s.frames.rot_nodes.is_empty(), "no rotated slip nodes");
        s
    }

    fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
        let den: f64 = b.iter().map(|y| y * y).sum();
        (num / den).sqrt()
    }

    /// AMD and nested dissection factor the same SPD matrix in different orders; each
    /// solve is backward stable, so the two solutions differ by at most about κ·ε. The
    /// generated systems have κ below 1e5 (mass 0.01 against unit springs), so 1e-9 —
    /// the oracle's accuracy bound against a dense KKT solve (tests/kkt.rs) — leaves
    /// room; a misapplied permutation gives O(1) differences.
    #[test]
    fn nested_dissection_and_amd_agree_on_random_systems() {
        for (dim, nodes, seed) in [(2, 900, 1), (2, 2500, 2), (3, 512, 3), (3, 2744, 4)] {
            let s = mixed(dim, nodes, seed);
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
            let mut amd = CholeskyOracle::analyze_with(&e, CholeskyOrdering::Amd).unwrap();
            let mut nd =
                CholeskyOracle::analyze_with(&e, CholeskyOrdering::NestedDissection).unwrap();
            assert_eq!(amd.ordering(), CholeskyOrdering::Amd);
            assert_eq!(nd.ordering(), CholeskyOrdering::NestedDissection);
            let (ya, ia) = amd.solve(&e).unwrap();
            let (yn, i_n) = nd.solve(&e).unwrap();
            assert_eq!(ia.ordering, CholeskyOrdering::Amd);
            assert_eq!(i_n.ordering, CholeskyOrdering::NestedDissection);
            assert!(ia.relative_residual < 1e-12 && i_n.relative_residual < 1e-12);
            let d = rel_diff(&yn, &ya);
            assert!(d <= 1e-9, "{dim}D {nodes}: ‖y_nd − y_amd‖/‖y_amd‖ = {d:e}");
        }
    }

    /// The analysis with nested dissection is reused across new values of the same
    /// pattern, and a changed constraint set re-analyses with the ordering asked for.
    #[test]
    fn nested_dissection_analysis_is_reused() {
        let mut s = mixed(3, 343, 7);
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let mut oracle =
            CholeskyOracle::analyze_with(&e, CholeskyOrdering::NestedDissection).unwrap();
        let (_, i1) = oracle.solve(&e).unwrap();
        assert!(!i1.reused_symbolic);
        for v in s.h.values.iter_mut() {
            *v *= 1.5;
        }
        let e2 = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let (y2, i2) = oracle.solve(&e2).unwrap();
        assert!(i2.reused_symbolic);
        assert_eq!(i2.ordering, CholeskyOrdering::NestedDissection);
        assert_eq!(i2.ordering_seconds, 0.0);
        let (y3, _) = CholeskyOracle::analyze_with(&e2, CholeskyOrdering::Amd)
            .unwrap()
            .solve(&e2)
            .unwrap();
        assert!(rel_diff(&y2, &y3) <= 1e-9);
        // Free one constrained node: another mask, so a new analysis.
        let k = s.frames.mask.iter().position(|&m| m != 0).unwrap();
        s.frames.mask[k] = 0;
        let e3 = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let (_, i3) = oracle.solve(&e3).unwrap();
        assert!(!i3.reused_symbolic);
        assert_eq!(i3.ordering, CholeskyOrdering::NestedDissection);
    }

    /// nnz(L) from the column counts equals a dense symbolic elimination of the permuted
    /// pattern, for both orderings.
    #[test]
    fn exact_factor_nnz_matches_a_dense_count() {
        for (dim, seed) in [(2, 11), (3, 12)] {
            let s = mixed(dim, 125, seed);
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
            for ord in [CholeskyOrdering::Amd, CholeskyOrdering::NestedDissection] {
                let oracle = CholeskyOracle::analyze_with(&e, ord).unwrap();
                let st = &oracle.structure;
                let nd = st.col_ptr.len() - 1;
                let perm = oracle.symbolic.perm().unwrap();
                let inv = perm.arrays().1;
                let mut l = vec![false; nd * nd];
                for c in 0..nd {
                    for &r in &st.row_idx[st.col_ptr[c]..st.col_ptr[c + 1]] {
                        let (a, b) = (inv[r], inv[c]);
                        l[a.max(b) * nd + a.min(b)] = true;
                    }
                }
                for k in 0..nd {
                    let rows: Vec<usize> = (k + 1..nd).filter(|&i| l[i * nd + k]).collect();
                    for (x, &i) in rows.iter().enumerate() {
                        for &j in &rows[..=x] {
                            l[i * nd + j] = true;
                        }
                    }
                }
                let dense = l.iter().filter(|&&b| b).count();
                assert_eq!(oracle.factor_nnz_exact(), dense, "{dim}D {ord}");
                assert!(oracle.factor_nnz() >= dense);
            }
        }
    }

    /// Auto: AMD alone below the size; above it, the ordering with fewer flops.
    #[test]
    fn auto_keeps_the_cheaper_ordering() {
        let small = mixed(3, 216, 5);
        let e = Eliminated::new(
            &small.h,
            &small.g,
            &small.frames,
            ConstrainedDiagonal::Identity,
        );
        assert_eq!(
            CholeskyOracle::analyze(&e).unwrap().ordering(),
            CholeskyOrdering::Amd
        );
        for (dim, nodes) in [(2, 4900), (3, 3375)] {
            let s = mixed(dim, nodes, 6);
            assert!(s.h.n >= ordering::AUTO_MIN_NODES);
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
            let st = Structure::new(&e);
            let sym = SymbolicSparseColMatRef::new_checked(
                st.col_ptr.len() - 1,
                st.col_ptr.len() - 1,
                &st.col_ptr,
                None,
                &st.row_idx,
            );
            let amd = Candidate::amd(sym).unwrap();
            let g = NodeGraph::new(dim, &s.h.row_ptr, &s.h.col_idx, &s.frames.mask).unwrap();
            let nest = Candidate::nested_dissection(&st, &g, &e).unwrap();
            let auto = CholeskyOracle::analyze(&e).unwrap();
            let amd_estimate = amd.flops;
            let amd = amd.counted(&st).unwrap();
            // AMD's estimate comes from its approximate degrees, upper bounds of the
            // exact ones; on these meshes it is within 1e-4 of the exact count.
            assert!(amd_estimate >= amd.flops * (1.0 - 1e-12), "{dim}D");
            assert!(amd_estimate <= amd.flops * 1.01, "{dim}D");
            let want = if nest.flops < amd_estimate {
                &nest
            } else {
                &amd
            };
            assert_eq!(auto.ordering(), want.ordering, "{dim}D");
            assert_eq!(auto.factor_nnz_exact(), want.nnz, "{dim}D");
        }
    }

    /// A postorder lists every column once, each after all of its descendants, and each
    /// subtree as one consecutive run.
    #[test]
    fn postorder_keeps_subtrees_together() {
        // Two trees: 5 ← {0, 3}, 3 ← {1, 2}; 6 ← {4}.
        let parent = [5, 3, 3, 5, 6, -1, -1];
        let post = postorder(&parent);
        assert_eq!(post, vec![0, 1, 2, 3, 5, 4, 6]);
        let s = mixed(3, 343, 8);
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let oracle = CholeskyOracle::analyze_with(&e, CholeskyOrdering::NestedDissection).unwrap();
        let inv = oracle.symbolic.perm().unwrap().arrays().1.to_vec();
        let (_, etree) = column_counts(&oracle.structure, &inv).unwrap();
        // Postordered: the subtree of column j (size[j] columns, all ≤ j) is exactly the
        // run [j + 1 − size[j], j], i.e. its smallest column is j + 1 − size[j].
        let n = etree.len();
        let mut size = vec![1usize; n];
        let mut first: Vec<usize> = (0..n).collect();
        for j in 0..n {
            if let Ok(p) = usize::try_from(etree[j]) {
                assert!(p > j, "parent {p} before child {j}");
                size[p] += size[j];
                first[p] = first[p].min(first[j]);
            }
        }
        for j in 0..n {
            assert_eq!(
                first[j] + size[j],
                j + 1,
                "subtree of column {j} is not one run"
            );
        }
    }
}
