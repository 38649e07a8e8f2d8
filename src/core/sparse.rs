//! Block-sparse symmetric matrices with d×d blocks (d = 2 or 3), node-major DOF order.
//!
//! Both triangles are stored: the GPU and CPU products are then row-parallel without
//! atomics, and a block row holds everything a node needs.

use crate::error::InputError;

/// Block compressed sparse rows. Block (i, j) couples node i to node j; its d×d values
/// are stored row-major at `values[k*d*d ..]` for `col_idx[k] == j`, `row_ptr[i] <= k < row_ptr[i+1]`.
#[derive(Debug, Clone, PartialEq)]
pub struct BlockCsr {
    pub dim: usize,
    pub n: usize,
    pub row_ptr: Vec<usize>,
    pub col_idx: Vec<usize>,
    pub values: Vec<f64>,
}

/// Relative tolerance of the symmetry check on H: |H_ij − H_ji| ≤ SYMMETRY_RTOL · max|H|.
/// Assembled Hessians are symmetric up to round-off of a few operations per entry, so
/// 1e-10 of the largest entry accepts them and still rejects any real asymmetry.
pub const SYMMETRY_RTOL: f64 = 1e-10;

impl BlockCsr {
    /// Number of scalar rows (d·n).
    pub fn ndof(&self) -> usize {
        self.dim * self.n
    }

    /// Number of stored blocks.
    pub fn nnz_blocks(&self) -> usize {
        self.col_idx.len()
    }

    /// Builds the block pattern from scalar triplets (0-based), summing duplicates.
    /// `symmetric_lower`: the triplets hold one triangle only (Matrix Market `symmetric`),
    /// so every off-diagonal entry is mirrored.
    pub fn from_triplets(
        dim: usize,
        ndof: usize,
        triplets: &[(usize, usize, f64)],
        symmetric_half: bool,
    ) -> Self {
        match Self::try_from_triplets(dim, ndof, triplets, symmetric_half) {
            Ok(m) => m,
            Err(e) => panic!("from_triplets: {e}"),
        }
    }

    /// [`BlockCsr::from_triplets`] with every buffer allocated fallibly: a matrix read
    /// from a file that does not fit in memory (or under `ulimit -v`) is an error for the
    /// reader to report, not an abort.
    pub fn try_from_triplets(
        dim: usize,
        ndof: usize,
        triplets: &[(usize, usize, f64)],
        symmetric_half: bool,
    ) -> Result<Self, std::collections::TryReserveError> {
        assert!(dim == 2 || dim == 3, "block size must be 2 or 3");
        assert!(ndof % dim == 0, "ndof must be a multiple of dim");
        let n = ndof / dim;
        let bb = dim * dim;
        // Collect block coordinates, then sort and deduplicate per row.
        let mut coords: Vec<(usize, usize)> = Vec::new();
        coords.try_reserve_exact(triplets.len() * if symmetric_half { 2 } else { 1 })?;
        for &(r, c, _) in triplets {
            coords.push((r / dim, c / dim));
            if symmetric_half && r != c {
                coords.push((c / dim, r / dim));
            }
        }
        coords.sort_unstable();
        coords.dedup();
        let mut row_ptr: Vec<usize> = Vec::new();
        row_ptr.try_reserve_exact(n + 1)?;
        row_ptr.resize(n + 1, 0);
        for &(i, _) in &coords {
            row_ptr[i + 1] += 1;
        }
        for i in 0..n {
            row_ptr[i + 1] += row_ptr[i];
        }
        let mut col_idx: Vec<usize> = Vec::new();
        col_idx.try_reserve_exact(coords.len())?;
        col_idx.extend(coords.iter().map(|&(_, j)| j));
        let mut values: Vec<f64> = Vec::new();
        values.try_reserve_exact(coords.len() * bb)?;
        values.resize(coords.len() * bb, 0.0);
        drop(coords);
        let mut m = BlockCsr {
            dim,
            n,
            row_ptr,
            col_idx,
            values,
        };
        for &(r, c, v) in triplets {
            m.add(r, c, v);
            if symmetric_half && r != c {
                m.add(c, r, v);
            }
        }
        Ok(m)
    }

    /// Builds a block matrix from a symmetric block pattern given as per-row sorted
    /// neighbour lists (each list must contain the row itself). Values start at zero.
    pub fn from_pattern(dim: usize, rows: &[Vec<usize>]) -> Self {
        let n = rows.len();
        let mut row_ptr = Vec::with_capacity(n + 1);
        row_ptr.push(0);
        let mut col_idx = Vec::new();
        for r in rows {
            col_idx.extend_from_slice(r);
            row_ptr.push(col_idx.len());
        }
        let nb = col_idx.len();
        BlockCsr {
            dim,
            n,
            row_ptr,
            col_idx,
            values: vec![0.0; nb * dim * dim],
        }
    }

    /// Index of block (i, j) in `col_idx`, if stored.
    pub fn find(&self, i: usize, j: usize) -> Option<usize> {
        let s = self.row_ptr[i];
        let e = self.row_ptr[i + 1];
        self.col_idx[s..e].binary_search(&j).ok().map(|k| s + k)
    }

    /// Adds `v` to scalar entry (r, c). Panics if the block is not in the pattern
    /// (an internal invariant: callers build the pattern first).
    pub fn add(&mut self, r: usize, c: usize, v: f64) {
        let d = self.dim;
        let k = self
            .find(r / d, c / d)
            .expect("entry outside the block pattern");
        self.values[k * d * d + (r % d) * d + (c % d)] += v;
    }

    /// Scalar entry (r, c), zero when outside the pattern.
    pub fn get(&self, r: usize, c: usize) -> f64 {
        let d = self.dim;
        match self.find(r / d, c / d) {
            Some(k) => self.values[k * d * d + (r % d) * d + (c % d)],
            None => 0.0,
        }
    }

    /// The d×d block at storage index k, row-major.
    pub fn block(&self, k: usize) -> &[f64] {
        let bb = self.dim * self.dim;
        &self.values[k * bb..(k + 1) * bb]
    }

    /// Storage index of the diagonal block of row i (every row of a Hessian has one).
    pub fn diag_index(&self, i: usize) -> Option<usize> {
        self.find(i, i)
    }

    /// y = H x.
    pub fn matvec(&self, x: &[f64], y: &mut [f64]) {
        match self.dim {
            2 => self.matvec_d::<2>(x, y),
            3 => self.matvec_d::<3>(x, y),
            _ => unreachable!("block size is 2 or 3"),
        }
    }

    fn matvec_d<const D: usize>(&self, x: &[f64], y: &mut [f64]) {
        debug_assert_eq!(x.len(), self.ndof());
        debug_assert_eq!(y.len(), self.ndof());
        for i in 0..self.n {
            let mut acc = [0.0f64; D];
            for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                let j = self.col_idx[k];
                let b = &self.values[k * D * D..(k + 1) * D * D];
                let xj = &x[j * D..j * D + D];
                for r in 0..D {
                    let mut s = 0.0;
                    for c in 0..D {
                        s += b[r * D + c] * xj[c];
                    }
                    acc[r] += s;
                }
            }
            y[i * D..i * D + D].copy_from_slice(&acc);
        }
    }

    /// Largest absolute entry (0 for an empty matrix).
    pub fn max_abs(&self) -> f64 {
        self.values.iter().fold(0.0f64, |m, v| m.max(v.abs()))
    }

    /// Checks |H_ij − H_ji| ≤ SYMMETRY_RTOL·max|H| for all stored entries.
    /// Returns the worst offending scalar entry (0-based) on failure.
    pub fn check_symmetric(&self) -> Result<(), (usize, usize, f64, f64)> {
        let d = self.dim;
        let tol = SYMMETRY_RTOL * self.max_abs();
        for i in 0..self.n {
            for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                let j = self.col_idx[k];
                let kt = self.find(j, i);
                for r in 0..d {
                    for c in 0..d {
                        let v = self.values[k * d * d + r * d + c];
                        let vt = match kt {
                            Some(kt) => self.values[kt * d * d + c * d + r],
                            None => 0.0,
                        };
                        if (v - vt).abs() > tol {
                            return Err((i * d + r, j * d + c, v, vt));
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Dense copy (tests and small problems only).
    pub fn to_dense(&self) -> nalgebra::DMatrix<f64> {
        let nd = self.ndof();
        let d = self.dim;
        let mut m = nalgebra::DMatrix::zeros(nd, nd);
        for i in 0..self.n {
            for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                let j = self.col_idx[k];
                for r in 0..d {
                    for c in 0..d {
                        m[(i * d + r, j * d + c)] = self.values[k * d * d + r * d + c];
                    }
                }
            }
        }
        m
    }

    /// Validates a Hessian read from `file`: finite entries and symmetry.
    pub fn validate(&self, file: &str) -> Result<(), InputError> {
        let d = self.dim;
        for i in 0..self.n {
            for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                let j = self.col_idx[k];
                for r in 0..d {
                    for c in 0..d {
                        let v = self.values[k * d * d + r * d + c];
                        if !v.is_finite() {
                            return Err(InputError::new(
                                file,
                                format!("entry ({}, {})", i * d + r + 1, j * d + c + 1),
                                format!("value {v} is not finite"),
                            ));
                        }
                    }
                }
            }
        }
        if let Err((r, c, v, vt)) = self.check_symmetric() {
            return Err(InputError::new(
                file,
                format!("entry ({}, {})", r + 1, c + 1),
                format!(
                    "matrix is not symmetric: H({}, {}) = {v:e} but H({}, {}) = {vt:e} (relative tolerance {SYMMETRY_RTOL:e} of max |H|)",
                    r + 1,
                    c + 1,
                    c + 1,
                    r + 1
                ),
            ));
        }
        Ok(())
    }
}

/// s + e = a + b exactly (Knuth's two-sum).
fn two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    let bb = s - a;
    (s, (a - (s - bb)) + (b - bb))
}

impl BlockCsr {
    /// b − A y with every product (exact by FMA) and sum carried in double-double, then
    /// rounded (Ogita–Rump–Oishi Dot2): accurate to about ε relative to the residual itself,
    /// however much b and A y cancel. Iterative refinement with this residual converges to
    /// the solution of the f64 matrix A while κ(A)·ε < 1, where an f64 residual stalls at
    /// ε·‖A‖‖y‖.
    pub fn residual_dd(&self, b: &[f64], y: &[f64]) -> Vec<f64> {
        let d = self.dim;
        let mut out = vec![0.0; b.len()];
        for i in 0..self.n {
            for r in 0..d {
                let (mut hi, mut lo) = (b[i * d + r], 0.0f64);
                for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                    let j = self.col_idx[k];
                    for c in 0..d {
                        let av = self.values[k * d * d + r * d + c];
                        let p = -av * y[j * d + c];
                        let pe = (-av).mul_add(y[j * d + c], -p);
                        let (s, e) = two_sum(hi, p);
                        hi = s;
                        lo += e + pe;
                    }
                }
                out[i * d + r] = hi + lo;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn residual_dd_is_exact_where_the_f64_residual_cancels() {
        // One 2×2 block: a·y = p + e exactly (FMA), and b = p, so b − a·y = −e, far below
        // the f64 residual's rounding (which returns 0 or noise of size ulp(p)).
        let a0 = 1.0 + 2f64.powi(-30);
        let y0 = 1.0 - 2f64.powi(-29);
        let p = a0 * y0;
        let e = a0.mul_add(y0, -p);
        assert!(e != 0.0, "the example must round");
        let m = BlockCsr {
            dim: 2,
            n: 1,
            row_ptr: vec![0, 1],
            col_idx: vec![0],
            values: vec![a0, 0.0, 0.0, 3.0],
        };
        let r = m.residual_dd(&[p, 7.0], &[y0, 2.0]);
        assert_eq!(r, vec![-e, 1.0]);
        // Cancellation across terms of a row: 1e16 + 1 − 1e16 in double-double is 1.
        let m = BlockCsr {
            dim: 2,
            n: 1,
            row_ptr: vec![0, 1],
            col_idx: vec![0],
            values: vec![1e16, -1e16, 0.0, 1.0],
        };
        let r = m.residual_dd(&[1.0, 0.0], &[1.0, 1.0]);
        assert_eq!(r, vec![1.0, -1.0]);
    }

    #[test]
    fn triplets_symmetric_half_mirror_and_sum_duplicates() {
        // 2 nodes, d = 2; lower triangle with a duplicate entry.
        let t = vec![
            (0, 0, 2.0),
            (1, 1, 3.0),
            (2, 0, -1.0),
            (2, 0, -0.5),
            (2, 2, 4.0),
            (3, 3, 5.0),
        ];
        let m = BlockCsr::from_triplets(2, 4, &t, true);
        assert_eq!(m.get(2, 0), -1.5);
        assert_eq!(m.get(0, 2), -1.5);
        assert!(m.check_symmetric().is_ok());
        let x = [1.0, 2.0, 3.0, 4.0];
        let mut y = [0.0; 4];
        m.matvec(&x, &mut y);
        let dense = m.to_dense();
        let yd = &dense * nalgebra::DVector::from_column_slice(&x);
        for i in 0..4 {
            assert_eq!(y[i], yd[i]);
        }
    }

    #[test]
    fn asymmetry_is_found() {
        let t = vec![(0, 0, 1.0), (1, 1, 1.0), (0, 1, 0.5), (1, 0, 0.4)];
        let m = BlockCsr::from_triplets(2, 2, &t, false);
        assert!(m.check_symmetric().is_err());
    }
}
