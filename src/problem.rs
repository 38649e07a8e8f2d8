//! [`Problem`]: one constrained Newton system, min ½ΔxᵀHΔx + gᵀΔx subject to per-node
//! constraints, checked and prepared for the solvers (frames, masks and lift built once).
#![deny(missing_docs)]

use crate::constraints::{Constraint, Frames};
use crate::error::{Error, InputError};
use crate::solver::LayoutKey;
use crate::sparse::{BlockCsr, SYMMETRY_RTOL};

/// A constrained Newton system: H (dn × dn, symmetric, node-major DOFs), g (length dn)
/// and the per-node constraints, with the per-node frames they imply.
///
/// Build it with [`Problem::from_triplets`]; for the next Newton iteration call
/// [`Problem::update_values`]. A problem whose sparsity pattern and constraints are
/// unchanged keeps its [`LayoutKey`], and a [`crate::Solver`] that solved it before reuses
/// its Cholesky analysis or GPU buffers.
#[derive(Debug, Clone)]
pub struct Problem {
    h: BlockCsr,
    g: Vec<f64>,
    constraints: Vec<Constraint>,
    frames: Frames,
    layout: LayoutKey,
}

impl Problem {
    /// Builds a problem from H's entries as `(row, col, value)` triplets (0-based; both
    /// triangles; duplicates are summed, as finite-element assembly produces them), the
    /// gradient `g` (length `dim · n_nodes`) and the constraints (any order; several on
    /// one node combine by rank).
    ///
    /// Errors ([`Error::Input`]) name the faulty entry: a dimension other than 2 or 3, a
    /// triplet out of range or not finite, an asymmetric H (beyond a relative
    /// [`SYMMETRY_RTOL`] of max |H|), a wrong-length or non-finite g, and any constraint
    /// the model cannot accept (node out of range, zero or non-finite normal,
    /// contradictory rows on one node), named `constraints[k]`.
    pub fn from_triplets(
        dim: usize,
        n_nodes: usize,
        triplets: &[(usize, usize, f64)],
        g: &[f64],
        constraints: &[Constraint],
    ) -> Result<Self, Error> {
        let ndof = check_size(dim, n_nodes)?;
        let h = assemble(dim, ndof, triplets)?;
        Self::from_blocks(h, g.to_vec(), constraints)
    }

    /// Builds a problem from an assembled block-sparse H (both triangles stored), for
    /// callers that assemble into [`BlockCsr`] themselves. Checks as
    /// [`Problem::from_triplets`].
    pub fn from_blocks(
        h: BlockCsr,
        g: Vec<f64>,
        constraints: &[Constraint],
    ) -> Result<Self, Error> {
        check_size(h.dim, h.n)?;
        check_values(&h)?;
        check_gradient(h.ndof(), &g)?;
        let constraints = labelled(constraints);
        let frames = Frames::build(h.dim, h.n, &constraints)
            .map_err(|e| InputError::new("constraints", e.label, e.problem))?;
        Ok(Problem {
            h,
            g,
            constraints,
            frames,
            layout: LayoutKey::fresh(),
        })
    }

    /// A problem whose parts were read and checked elsewhere (the command line's readers,
    /// which name the files in their messages).
    #[cfg(feature = "cli")]
    pub(crate) fn from_checked_parts(
        h: BlockCsr,
        g: Vec<f64>,
        constraints: Vec<Constraint>,
        frames: Frames,
    ) -> Self {
        Problem {
            h,
            g,
            constraints,
            frames,
            layout: LayoutKey::fresh(),
        }
    }

    /// Replaces H's values and g for the next Newton iteration; the constraints stay.
    /// When the triplets produce the same block pattern as before the problem keeps its
    /// [`LayoutKey`] (a solver reuses its analysis and device buffers); a different
    /// pattern is accepted and gets a new key. Checks as [`Problem::from_triplets`]; on
    /// an error the problem is unchanged.
    pub fn update_values(
        &mut self,
        triplets: &[(usize, usize, f64)],
        g: &[f64],
    ) -> Result<(), Error> {
        let h = assemble(self.h.dim, self.h.ndof(), triplets)?;
        check_values(&h)?;
        check_gradient(h.ndof(), g)?;
        if h.row_ptr != self.h.row_ptr || h.col_idx != self.h.col_idx {
            self.layout = LayoutKey::fresh();
        }
        self.h = h;
        self.g.clear();
        self.g.extend_from_slice(g);
        Ok(())
    }

    /// Replaces g only (H and the constraints stay).
    pub fn update_gradient(&mut self, g: &[f64]) -> Result<(), Error> {
        check_gradient(self.h.ndof(), g)?;
        self.g.clear();
        self.g.extend_from_slice(g);
        Ok(())
    }

    /// The spatial dimension d (2 or 3).
    pub fn dim(&self) -> usize {
        self.h.dim
    }

    /// The number of nodes n.
    pub fn n_nodes(&self) -> usize {
        self.h.n
    }

    /// The number of unknowns d·n.
    pub fn ndof(&self) -> usize {
        self.h.ndof()
    }

    /// H, block-sparse with both triangles stored.
    pub fn hessian(&self) -> &BlockCsr {
        &self.h
    }

    /// g.
    pub fn gradient(&self) -> &[f64] {
        &self.g
    }

    /// The constraints, labelled `constraints[k]` where they came without a label.
    pub fn constraints(&self) -> &[Constraint] {
        &self.constraints
    }

    /// The per-node frames, masks and lift the constraints imply.
    pub fn frames(&self) -> &Frames {
        &self.frames
    }

    /// Unknowns left free by the constraints.
    pub fn free_dofs(&self) -> usize {
        self.frames.free_dofs()
    }

    /// Unknowns the constraints fix.
    pub fn constrained_dofs(&self) -> usize {
        self.frames.constrained_dofs()
    }

    /// The identity of this problem's sparsity pattern and constraint set.
    pub fn layout(&self) -> LayoutKey {
        self.layout
    }
}

/// d·n, or an error when d is not 2 or 3, n is 0, or d·n overflows.
fn check_size(dim: usize, n_nodes: usize) -> Result<usize, Error> {
    if dim != 2 && dim != 3 {
        return Err(InputError::new("problem", "dim", format!("must be 2 or 3, got {dim}")).into());
    }
    if n_nodes == 0 {
        return Err(InputError::new("problem", "n_nodes", "the system has no nodes").into());
    }
    dim.checked_mul(n_nodes)
        .filter(|&nd| nd <= u32::MAX as usize)
        .ok_or_else(|| {
            InputError::new(
                "problem",
                "n_nodes",
                format!("{n_nodes} nodes × {dim} is more unknowns than supported (2³² − 1)"),
            )
            .into()
        })
}

/// H from triplets, each checked for range and finiteness first.
fn assemble(dim: usize, ndof: usize, triplets: &[(usize, usize, f64)]) -> Result<BlockCsr, Error> {
    for (k, &(r, c, v)) in triplets.iter().enumerate() {
        if r >= ndof || c >= ndof {
            return Err(InputError::new(
                "H",
                format!("triplet {k} ({r}, {c})"),
                format!("index out of range: H is {ndof} × {ndof} (indices from 0)"),
            )
            .into());
        }
        if !v.is_finite() {
            return Err(InputError::new(
                "H",
                format!("triplet {k} ({r}, {c})"),
                format!("value {v} is not finite"),
            )
            .into());
        }
    }
    Ok(BlockCsr::from_triplets(dim, ndof, triplets, false))
}

/// Finite sums (duplicates can overflow) and symmetry, named in 0-based entries.
fn check_values(h: &BlockCsr) -> Result<(), Error> {
    let d = h.dim;
    if h.row_ptr.len() != h.n + 1 || h.values.len() != h.col_idx.len() * d * d {
        return Err(InputError::new("H", "", "the block arrays disagree in length").into());
    }
    for i in 0..h.n {
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            let j = h.col_idx[k];
            if j >= h.n {
                return Err(InputError::new(
                    "H",
                    format!("block ({i}, {j})"),
                    format!("column out of range ({} nodes)", h.n),
                )
                .into());
            }
            for (a, v) in h.block(k).iter().enumerate() {
                if !v.is_finite() {
                    return Err(InputError::new(
                        "H",
                        format!("entry ({}, {})", i * d + a / d, j * d + a % d),
                        format!("summed value {v} is not finite"),
                    )
                    .into());
                }
            }
        }
    }
    if let Err((r, c, v, vt)) = h.check_symmetric() {
        return Err(InputError::new(
            "H",
            format!("entry ({r}, {c})"),
            format!(
                "H is not symmetric: H({r}, {c}) = {v:e} but H({c}, {r}) = {vt:e} \
                 (relative tolerance {SYMMETRY_RTOL:e} of max |H|)"
            ),
        )
        .into());
    }
    Ok(())
}

fn check_gradient(ndof: usize, g: &[f64]) -> Result<(), Error> {
    if g.len() != ndof {
        return Err(InputError::new(
            "g",
            "",
            format!("has {} entries, expected {ndof} (dim × nodes)", g.len()),
        )
        .into());
    }
    if let Some(k) = g.iter().position(|v| !v.is_finite()) {
        return Err(InputError::new(
            "g",
            format!("entry {k}"),
            format!("value {} is not finite", g[k]),
        )
        .into());
    }
    Ok(())
}

/// The constraints with `constraints[k]` as the label of those that came without one.
fn labelled(constraints: &[Constraint]) -> Vec<Constraint> {
    constraints
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let mut c = c.clone();
            if c.label.is_empty() {
                c.label = format!("constraints[{k}]");
            }
            c
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chain(n: usize) -> Vec<(usize, usize, f64)> {
        let mut t = Vec::new();
        for i in 0..3 * n {
            t.push((i, i, 2.0));
        }
        for i in 0..3 * (n - 1) {
            t.push((i, i + 3, -0.5));
            t.push((i + 3, i, -0.5));
        }
        t
    }

    #[test]
    fn bad_input_is_an_error_naming_the_entry() {
        let t = chain(4);
        let g = vec![0.0; 12];
        let msg = |r: Result<Problem, Error>| r.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(msg(Problem::from_triplets(4, 4, &t, &g, &[])).contains("dim"));
        assert!(
            msg(Problem::from_triplets(3, 4, &t, &g[..11], &[])).starts_with("g: has 11 entries")
        );
        let mut nan = t.clone();
        nan[3].2 = f64::NAN;
        assert!(msg(Problem::from_triplets(3, 4, &nan, &g, &[])).contains("triplet 3"));
        let mut out = t.clone();
        out.push((12, 0, 1.0));
        assert!(msg(Problem::from_triplets(3, 4, &out, &g, &[])).contains("out of range"));
        let mut asym = t.clone();
        asym.push((0, 3, 1.0));
        assert!(msg(Problem::from_triplets(3, 4, &asym, &g, &[])).contains("not symmetric"));
        let c = [
            Constraint::sticky(0),
            Constraint::plane(9, &[0.0, 1.0, 0.0]),
        ];
        let m = msg(Problem::from_triplets(3, 4, &t, &g, &c));
        assert!(
            m.starts_with("constraints: constraints[1]: node 9 is out of range"),
            "{m}"
        );
        let c = [Constraint::plane(1, &[0.0, 0.0, 0.0])];
        assert!(msg(Problem::from_triplets(3, 4, &t, &g, &c)).contains("normal is zero"));
    }

    #[test]
    fn same_pattern_keeps_the_layout_and_a_new_one_changes_it() {
        let t = chain(4);
        let g = vec![1.0; 12];
        let mut p = Problem::from_triplets(3, 4, &t, &g, &[Constraint::sticky(0)]).expect("valid");
        let key = p.layout();
        let scaled: Vec<_> = t.iter().map(|&(r, c, v)| (r, c, 3.0 * v)).collect();
        p.update_values(&scaled, &g).expect("valid");
        assert_eq!(p.layout(), key);
        assert_eq!(p.hessian().get(0, 0), 6.0);
        let mut wider = t.clone();
        wider.extend([(0, 9, 0.1), (9, 0, 0.1)]);
        p.update_values(&wider, &g).expect("valid");
        assert_ne!(p.layout(), key);
        // A failed update leaves the problem as it was.
        let before = p.hessian().clone();
        assert!(p.update_values(&t, &g[..3]).is_err());
        assert_eq!(p.hessian(), &before);
    }
}
