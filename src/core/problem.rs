//! [`Problem`]: one constrained Newton system, min ½ΔxᵀHΔx + gᵀΔx subject to per-node
//! constraints, checked and prepared for the solvers (frames, masks and lift built once).
#![deny(missing_docs)]

use crate::core::constraints::{Constraint, Frames};
use crate::core::sparse::{BlockCsr, SYMMETRY_RTOL};
use crate::error::{Error, InputError};

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

    /// Builds a problem from H in compressed sparse rows (0-based, both triangles, scalar
    /// entries): `indptr` (length `dim · n_nodes + 1`), `indices` and `data` as SciPy's
    /// `csr_matrix` holds them, read in place (no triplet list). Column indices need not
    /// be sorted within a row and duplicates are summed. The index type is any integer
    /// (SciPy uses `i32` or `i64`). Checks as [`Problem::from_triplets`], naming entries
    /// as `entry (row, col)`, plus the shape of the three arrays.
    pub fn from_csr<I>(
        dim: usize,
        n_nodes: usize,
        indptr: &[I],
        indices: &[I],
        data: &[f64],
        g: &[f64],
        constraints: &[Constraint],
    ) -> Result<Self, Error>
    where
        I: Copy + TryInto<usize> + std::fmt::Display,
    {
        let ndof = check_size(dim, n_nodes)?;
        let h = assemble_csr(dim, ndof, indptr, indices, data)?;
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
        self.replace(h, g)
    }

    /// [`Problem::update_values`] with H in compressed sparse rows, as
    /// [`Problem::from_csr`] takes it.
    pub fn update_csr_values<I>(
        &mut self,
        indptr: &[I],
        indices: &[I],
        data: &[f64],
        g: &[f64],
    ) -> Result<(), Error>
    where
        I: Copy + TryInto<usize> + std::fmt::Display,
    {
        let h = assemble_csr(self.h.dim, self.h.ndof(), indptr, indices, data)?;
        self.replace(h, g)
    }

    /// [`Problem::update_values`] with an assembled block-sparse H of the same dimension
    /// and node count.
    pub fn update_blocks(&mut self, h: BlockCsr, g: &[f64]) -> Result<(), Error> {
        if h.dim != self.h.dim || h.n != self.h.n {
            return Err(InputError::new(
                "H",
                "",
                format!(
                    "has {} nodes of dimension {}, expected {} of dimension {} (the problem's)",
                    h.n, h.dim, self.h.n, self.h.dim
                ),
            )
            .into());
        }
        self.replace(h, g)
    }

    /// Checks the new H and g, then puts them in place; the layout key changes only with
    /// the block pattern.
    fn replace(&mut self, h: BlockCsr, g: &[f64]) -> Result<(), Error> {
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

/// H from scalar CSR arrays: shapes, index ranges and finiteness checked first, then
/// each block row's pattern from the columns of its d scalar rows.
fn assemble_csr<I>(
    dim: usize,
    ndof: usize,
    indptr: &[I],
    indices: &[I],
    data: &[f64],
) -> Result<BlockCsr, Error>
where
    I: Copy + TryInto<usize> + std::fmt::Display,
{
    let bad =
        |entry: String, problem: String| -> Error { InputError::new("H", entry, problem).into() };
    if indptr.len() != ndof + 1 {
        return Err(bad(
            "indptr".into(),
            format!(
                "has {} entries, expected {} (rows + 1)",
                indptr.len(),
                ndof + 1
            ),
        ));
    }
    if indices.len() != data.len() {
        return Err(bad(
            "indices".into(),
            format!("has {} entries but data has {}", indices.len(), data.len()),
        ));
    }
    let ptr = |k: usize| -> Result<usize, Error> {
        let p = indptr[k];
        p.try_into()
            .ok()
            .filter(|&p| p <= indices.len())
            .ok_or_else(|| {
                bad(
                    format!("indptr[{k}]"),
                    format!("{p} is outside 0..={} (the stored entries)", indices.len()),
                )
            })
    };
    let mut start = ptr(0)?;
    if start != 0 {
        return Err(bad("indptr[0]".into(), format!("is {start}, expected 0")));
    }
    let mut rows = Vec::with_capacity(ndof + 1);
    rows.push(0);
    for r in 0..ndof {
        let end = ptr(r + 1)?;
        if end < start {
            return Err(bad(
                format!("indptr[{}]", r + 1),
                format!("{end} is less than indptr[{r}] = {start}"),
            ));
        }
        for k in start..end {
            let c = indices[k];
            let col = c.try_into().ok().filter(|&c| c < ndof).ok_or_else(|| {
                bad(
                    format!("entry ({r}, {c})"),
                    format!("column out of range: H is {ndof} × {ndof} (indices from 0)"),
                )
            })?;
            let v = data[k];
            if !v.is_finite() {
                return Err(bad(
                    format!("entry ({r}, {col})"),
                    format!("value {v} is not finite"),
                ));
            }
        }
        rows.push(end);
        start = end;
    }
    if start != indices.len() {
        return Err(bad(
            format!("indptr[{ndof}]"),
            format!(
                "is {start}, expected {} (the stored entries)",
                indices.len()
            ),
        ));
    }
    // Every index was checked above, so the conversions below cannot fail.
    let col = |k: usize| indices[k].try_into().unwrap_or(0);
    let n = ndof / dim;
    let bb = dim * dim;
    let mut row_ptr = Vec::with_capacity(n + 1);
    row_ptr.push(0);
    let mut col_idx: Vec<usize> = Vec::new();
    for i in 0..n {
        let s = col_idx.len();
        for k in rows[i * dim]..rows[(i + 1) * dim] {
            col_idx.push(col(k) / dim);
        }
        col_idx[s..].sort_unstable();
        let mut w = s;
        for k in s..col_idx.len() {
            if w == s || col_idx[k] != col_idx[w - 1] {
                col_idx[w] = col_idx[k];
                w += 1;
            }
        }
        col_idx.truncate(w);
        row_ptr.push(w);
    }
    let mut h = BlockCsr {
        dim,
        n,
        row_ptr,
        values: vec![0.0; col_idx.len() * bb],
        col_idx,
    };
    for (r, w) in rows.windows(2).enumerate() {
        let i = r / dim;
        let (s, e) = (h.row_ptr[i], h.row_ptr[i + 1]);
        for (&c, &v) in indices[w[0]..w[1]].iter().zip(&data[w[0]..w[1]]) {
            let c = c.try_into().unwrap_or(0);
            if let Ok(b) = h.col_idx[s..e].binary_search(&(c / dim)) {
                h.values[(s + b) * bb + (r % dim) * dim + c % dim] += v;
            }
        }
    }
    Ok(h)
}

/// Finite sums (duplicates can overflow) and symmetry, named in 0-based entries.
fn check_values(h: &BlockCsr) -> Result<(), Error> {
    let d = h.dim;
    if h.row_ptr.len() != h.n + 1
        || h.values.len() != h.col_idx.len() * d * d
        || h.row_ptr.first() != Some(&0)
        || h.row_ptr.last() != Some(&h.col_idx.len())
        || h.row_ptr.windows(2).any(|w| w[1] < w[0])
    {
        return Err(InputError::new(
            "H",
            "",
            "the block arrays disagree: row_ptr must have n + 1 entries rising from 0 to the \
             number of blocks, and values d·d per block",
        )
        .into());
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
            // Blocks are found by binary search: each row's columns must increase.
            if k > h.row_ptr[i] && h.col_idx[k - 1] >= j {
                return Err(InputError::new(
                    "H",
                    format!("block ({i}, {j})"),
                    format!(
                        "block columns of row {i} are not strictly increasing ({} then {j}): \
                         sort them and sum duplicates",
                        h.col_idx[k - 1]
                    ),
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

    /// `t` as CSR arrays with each row's entries in reverse column order and its first
    /// entry split in two halves (unsorted, with duplicates: what from_csr must accept).
    fn to_csr(ndof: usize, t: &[(usize, usize, f64)]) -> (Vec<i32>, Vec<i32>, Vec<f64>) {
        let mut rows = vec![Vec::new(); ndof];
        for &(r, c, v) in t {
            rows[r].push((c, v));
        }
        let (mut ptr, mut idx, mut val) = (vec![0i32], Vec::new(), Vec::new());
        for row in &mut rows {
            row.sort_by_key(|e| std::cmp::Reverse(e.0));
            for (k, &(c, v)) in row.iter().enumerate() {
                if k == 0 {
                    idx.extend([c as i32, c as i32]);
                    val.extend([0.5 * v, 0.5 * v]);
                } else {
                    idx.push(c as i32);
                    val.push(v);
                }
            }
            ptr.push(idx.len() as i32);
        }
        (ptr, idx, val)
    }

    #[test]
    fn csr_arrays_give_the_triplets_problem() {
        let mut t = chain(5);
        t.extend([(1, 13, 0.25), (13, 1, 0.25), (2, 2, 1.0)]);
        let g: Vec<f64> = (0..15).map(|k| k as f64).collect();
        let c = [
            Constraint::sticky(0),
            Constraint::plane(3, &[1.0, 1.0, 0.0]),
        ];
        let a = Problem::from_triplets(3, 5, &t, &g, &c).expect("valid");
        let (ptr, idx, val) = to_csr(15, &t);
        let mut b = Problem::from_csr(3, 5, &ptr, &idx, &val, &g, &c).expect("valid");
        // Halving and re-adding an entry rounds exactly (powers of two), so the blocks
        // are equal, not merely close.
        assert_eq!(a.hessian(), b.hessian());
        assert_eq!(a.gradient(), b.gradient());
        assert_eq!(a.constraints(), b.constraints());
        let key = b.layout();
        let scaled: Vec<f64> = val.iter().map(|v| 2.0 * v).collect();
        b.update_csr_values(&ptr, &idx, &scaled, &g).expect("valid");
        assert_eq!(b.layout(), key);
        assert_eq!(b.hessian().get(13, 1), 0.5);
        // i64 indices read the same.
        let ptr64: Vec<i64> = ptr.iter().map(|&p| p as i64).collect();
        let idx64: Vec<i64> = idx.iter().map(|&p| p as i64).collect();
        let c64 = Problem::from_csr(3, 5, &ptr64, &idx64, &val, &g, &c).expect("valid");
        assert_eq!(c64.hessian(), a.hessian());
    }

    #[test]
    fn bad_csr_arrays_are_errors_naming_the_entry() {
        let t = chain(2);
        let g = vec![0.0; 6];
        let (ptr, idx, val) = to_csr(6, &t);
        let msg = |p: &[i32], i: &[i32], v: &[f64]| {
            Problem::from_csr(3, 2, p, i, v, &g, &[])
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default()
        };
        assert!(msg(&ptr[..6], &idx, &val).starts_with("H: indptr: has 6 entries, expected 7"));
        assert!(msg(&ptr, &idx[1..], &val).starts_with("H: indices: has"));
        let mut p = ptr.clone();
        p[3] = p[2] - 1;
        assert!(
            msg(&p, &idx, &val).starts_with("H: indptr[3]:"),
            "{}",
            msg(&p, &idx, &val)
        );
        let mut p = ptr.clone();
        p[6] += 1;
        assert!(msg(&p, &idx, &val).starts_with("H: indptr[6]:"));
        let mut i = idx.clone();
        i[0] = -1;
        assert_eq!(
            msg(&ptr, &i, &val),
            "H: entry (0, -1): column out of range: H is 6 × 6 (indices from 0)"
        );
        let mut v = val.clone();
        let k = ptr[4] as usize;
        v[k] = f64::NAN;
        assert_eq!(
            msg(&ptr, &idx, &v),
            format!("H: entry (4, {}): value NaN is not finite", idx[k])
        );
    }

    #[test]
    fn blocks_out_of_order_are_an_error_and_update_blocks_keeps_the_layout() {
        let t = chain(3);
        let g = vec![0.0; 9];
        let good = Problem::from_triplets(3, 3, &t, &g, &[]).expect("valid");
        let mut h = good.hessian().clone();
        let (s, e) = (h.row_ptr[1], h.row_ptr[2]);
        h.col_idx[s..e].reverse();
        let m = Problem::from_blocks(h, g.clone(), &[])
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(m.contains("not strictly increasing"), "{m}");
        let mut p = good.clone();
        let key = p.layout();
        let mut h2 = good.hessian().clone();
        h2.values.iter_mut().for_each(|v| *v *= 3.0);
        p.update_blocks(h2.clone(), &g).expect("valid");
        assert_eq!(p.layout(), key);
        assert_eq!(p.hessian(), &h2);
        let mut short = h2.clone();
        short.row_ptr[3] += 1;
        assert!(p.update_blocks(short, &g).is_err());
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

/// The identity of a sparsity pattern and constraint set: a [`crate::Solver`] keeps the analysis
/// and device buffers of the last few layouts it solved, keyed by this.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct LayoutKey(u64);

impl LayoutKey {
    /// A key no other layout has.
    pub fn fresh() -> Self {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        LayoutKey(NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed))
    }
}
