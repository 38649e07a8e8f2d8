//! The smoothed prolongation from one level to the next: P = (I − ω D⁻¹A) T, T the
//! tentative prolongation (a cluster's world translation seen by each of its items: in
//! the node frames at level 0, T_i = P_i V_iᵀ, and T_i = I deeper) and D the item blocks
//! of the level's matrix A. A piecewise-constant T alone interpolates smooth modes with
//! an energy that grows as the mesh is refined, and the V-cycle's iterations with it; one
//! Jacobi smoothing step of T is smoothed aggregation's answer. The next level's matrix
//! is the Galerkin product Pᵀ A P = Pᵀ Q, Q = A P.
//!
//! The patterns of P, Q and PᵀAP depend on the level's pattern and clusters only
//! ([`SmoothPattern`], once per mesh); the values are rebuilt for every system.

use super::dense::{block9, cholesky_dropping, inverse_from_factor};
use super::level::{block_matvec, group, power_estimate, split_rows, Level, LAMBDA_STEPS};
use crate::core::elimination::Eliminated;
use rayon::prelude::*;

/// Block patterns (CSR over rows, sorted columns) of P (items × clusters), Q = A P (items ×
/// clusters) and Pᵀ Q (clusters × clusters), and Pᵀ's lists.
#[derive(Debug, Clone)]
pub(super) struct SmoothPattern {
    pub p_ptr: Vec<usize>,
    pub p_col: Vec<u32>,
    pub q_ptr: Vec<usize>,
    pub q_col: Vec<u32>,
    /// For cluster c: the P blocks in its column, as (row i, block index in P), by i.
    pub pt_ptr: Vec<usize>,
    pub pt: Vec<(u32, u32)>,
    pub a_ptr: Vec<usize>,
    pub a_col: Vec<usize>,
}

/// Sorted unique values of an iterator into `out` (cleared first).
fn unique(out: &mut Vec<u32>, it: impl Iterator<Item = u32>) {
    out.clear();
    out.extend(it);
    out.sort_unstable();
    out.dedup();
}

impl SmoothPattern {
    /// From a level's pattern (both triangles) and each item's cluster (`nc` clusters).
    pub fn new(row_ptr: &[usize], col_idx: &[usize], of: &[u32], nc: usize) -> Self {
        let n = of.len();
        let mut tmp = Vec::new();
        let (mut p_ptr, mut p_col) = (vec![0usize], Vec::new());
        for i in 0..n {
            unique(
                &mut tmp,
                col_idx[row_ptr[i]..row_ptr[i + 1]].iter().map(|&j| of[j]),
            );
            p_col.extend_from_slice(&tmp);
            p_ptr.push(p_col.len());
        }
        let (mut q_ptr, mut q_col) = (vec![0usize], Vec::new());
        for i in 0..n {
            unique(
                &mut tmp,
                col_idx[row_ptr[i]..row_ptr[i + 1]]
                    .iter()
                    .flat_map(|&j| p_col[p_ptr[j]..p_ptr[j + 1]].iter().copied()),
            );
            q_col.extend_from_slice(&tmp);
            q_ptr.push(q_col.len());
        }
        // Pᵀ: each cluster's blocks, by row (blocks are stored row by row).
        let mut row = vec![0u32; p_col.len()];
        for i in 0..n {
            row[p_ptr[i]..p_ptr[i + 1]].fill(i as u32);
        }
        let (pt_ptr, blocks) = group(&p_col, nc);
        let pt: Vec<(u32, u32)> = blocks.iter().map(|&k| (row[k as usize], k)).collect();
        let (mut a_ptr, mut a_col) = (vec![0usize], Vec::new());
        for c in 0..nc {
            unique(
                &mut tmp,
                pt[pt_ptr[c]..pt_ptr[c + 1]].iter().flat_map(|&(i, _)| {
                    let i = i as usize;
                    q_col[q_ptr[i]..q_ptr[i + 1]].iter().copied()
                }),
            );
            a_col.extend(tmp.iter().map(|&c| c as usize));
            a_ptr.push(a_col.len());
        }
        SmoothPattern {
            p_ptr,
            p_col,
            q_ptr,
            q_col,
            pt_ptr,
            pt,
            a_ptr,
            a_col,
        }
    }

    /// P's values: row i's blocks (d×d, row-major) δ_{c,c(i)} T_i − ω Σ_{j: c(j)=c} S_ij T_j
    /// with S_ij = D_i⁻¹ A_ij; `hblock(k)` is the level matrix's stored block k,
    /// `dinv[i]` is D_i⁻¹ and `t[i]` is T_i, `None` where T_i is the identity: A_ij T_j
    /// is then A_ij itself (most items of a mesh; for finite values the product with I
    /// would give S_ij T_j the same bits).
    #[allow(clippy::too_many_arguments)]
    pub fn p_values(
        &self,
        d: usize,
        row_ptr: &[usize],
        col_idx: &[usize],
        of: &[u32],
        omega: f64,
        hblock: impl Fn(usize) -> [f64; 9] + Sync,
        dinv: &[[f64; 9]],
        t: &[Option<[f64; 9]>],
    ) -> Vec<f64> {
        let dd = d * d;
        let mut out = vec![0.0; self.p_col.len() * dd];
        split_rows(&mut out, &self.p_ptr, dd)
            .into_par_iter()
            .with_min_len(64)
            .enumerate()
            .for_each(|(i, v)| {
                let cols = &self.p_col[self.p_ptr[i]..self.p_ptr[i + 1]];
                let di = &dinv[i];
                let (rs, re) = (row_ptr[i], row_ptr[i + 1]);
                for (k, &j) in (rs..re).zip(&col_idx[rs..re]) {
                    // S_ij T_j = D_i⁻¹ (A_ij T_j)
                    let h = hblock(k);
                    let st = match &t[j] {
                        None => mul(d, di, &h),
                        Some(tj) => mul(d, di, &mul(d, &h, tj)),
                    };
                    let s = cols.binary_search(&of[j]).unwrap_or(0) * dd;
                    for (o, x) in v[s..s + dd].iter_mut().zip(&st[..dd]) {
                        *o -= omega * x;
                    }
                }
                let s = cols.binary_search(&of[i]).unwrap_or(0) * dd;
                let ti = t[i].unwrap_or_else(|| identity(d));
                for (o, x) in v[s..s + dd].iter_mut().zip(&ti[..dd]) {
                    *o += x;
                }
            });
        out
    }

    /// Pᵀ (A P) on `a_ptr`/`a_col` for the level matrix `a` (d×d row-major blocks on
    /// `row_ptr`/`col_idx`), summed in a fixed order (row c: its P blocks by item, each
    /// item's Q row by column).
    pub fn galerkin(
        &self,
        d: usize,
        row_ptr: &[usize],
        col_idx: &[usize],
        p: &[f64],
        a: &[f64],
    ) -> Vec<f64> {
        match d {
            2 => self.galerkin_d::<2, 4>(row_ptr, col_idx, p, a),
            _ => self.galerkin_d::<3, 9>(row_ptr, col_idx, p, a),
        }
    }

    /// [`Self::galerkin`] for d = D. Each row's blocks find their slot in a per-thread
    /// map from column to position in the row (set from the row's sorted columns before
    /// use; every column looked up is one of them).
    fn galerkin_d<const D: usize, const DD: usize>(
        &self,
        row_ptr: &[usize],
        col_idx: &[usize],
        p: &[f64],
        a: &[f64],
    ) -> Vec<f64> {
        let nc = self.a_ptr.len() - 1;
        let block = |v: &[f64], k: usize| -> [f64; DD] {
            v[k * DD..(k + 1) * DD].try_into().expect("D·D values")
        };
        // Q = A P, row by row.
        let mut q = vec![0.0; self.q_col.len() * DD];
        split_rows(&mut q, &self.q_ptr, DD)
            .into_par_iter()
            .with_min_len(64)
            .enumerate()
            .for_each_init(
                || vec![0u32; nc],
                |slot, (i, v)| {
                    let cols = &self.q_col[self.q_ptr[i]..self.q_ptr[i + 1]];
                    for (s, &c) in cols.iter().enumerate() {
                        slot[c as usize] = s as u32;
                    }
                    let (rs, re) = (row_ptr[i], row_ptr[i + 1]);
                    for (k, &j) in (rs..re).zip(&col_idx[rs..re]) {
                        let h = block(a, k);
                        for pk in self.p_ptr[j]..self.p_ptr[j + 1] {
                            let pb = block(p, pk);
                            let s = slot[self.p_col[pk] as usize] as usize * DD;
                            let o = &mut v[s..s + DD];
                            for r in 0..D {
                                for c in 0..D {
                                    let mut acc = 0.0;
                                    for t in 0..D {
                                        acc += h[r * D + t] * pb[t * D + c];
                                    }
                                    o[r * D + c] += acc;
                                }
                            }
                        }
                    }
                },
            );
        let mut out = vec![0.0; self.a_col.len() * DD];
        split_rows(&mut out, &self.a_ptr, DD)
            .into_par_iter()
            .enumerate()
            .for_each_init(
                || vec![0u32; nc],
                |slot, (c, v)| {
                    let cols = &self.a_col[self.a_ptr[c]..self.a_ptr[c + 1]];
                    for (s, &k) in cols.iter().enumerate() {
                        slot[k] = s as u32;
                    }
                    for &(i, pk) in &self.pt[self.pt_ptr[c]..self.pt_ptr[c + 1]] {
                        let (i, pk) = (i as usize, pk as usize);
                        let pb = block(p, pk);
                        for qk in self.q_ptr[i]..self.q_ptr[i + 1] {
                            let qb = block(&q, qk);
                            let s = slot[self.q_col[qk] as usize] as usize * DD;
                            let o = &mut v[s..s + DD];
                            // Pᵀ block times Q block.
                            for r in 0..D {
                                for cc in 0..D {
                                    let mut acc = 0.0;
                                    for k in 0..D {
                                        acc += pb[k * D + r] * qb[k * D + cc];
                                    }
                                    o[r * D + cc] += acc;
                                }
                            }
                        }
                    }
                },
            );
        out
    }

    /// P's blocks in `pt`'s order (cluster by cluster), each transposed: what the
    /// restriction reads, in the order it reads it.
    pub fn transpose(&self, d: usize, p: &[f64]) -> Vec<f64> {
        let dd = d * d;
        let mut out = vec![0.0; p.len()];
        out.par_chunks_mut(dd)
            .zip(self.pt.par_iter())
            .for_each(|(o, &(_, pk))| {
                let b = &p[pk as usize * dd..(pk as usize + 1) * dd];
                for r in 0..d {
                    for c in 0..d {
                        o[r * d + c] = b[c * d + r];
                    }
                }
            });
        out
    }
}

/// The smoothed prolongation's values from level `lev` (matrix `a` on its pattern) to
/// the next, with ω = 4 / (3 λ̂), λ̂ a power estimate of λmax(D⁻¹A) with D the item
/// blocks of A, and `t(i)` the tentative block T_i of item i.
pub(super) fn smoothed_p(
    d: usize,
    lev: &Level,
    sp: &SmoothPattern,
    a: &[f64],
    t: &(dyn Fn(usize) -> [f64; 9] + Sync),
) -> Vec<f64> {
    let dd = d * d;
    let n = lev.n;
    // D_i⁻¹ (the diagonal's inverse where the block is not SPD).
    let dinv: Vec<[f64; 9]> = (0..n)
        .into_par_iter()
        .map(|i| {
            let b = match lev.diag_index(i) {
                Some(k) => block9(d, &a[k * dd..(k + 1) * dd]),
                None => [0.0; 9],
            };
            let mut l = b;
            let mut o = [0.0; 9];
            if cholesky_dropping(d, &mut l[..dd]) == 0 {
                o[..dd].copy_from_slice(&inverse_from_factor(d, &l[..dd]));
            } else {
                for a in 0..d {
                    let v = b[a * d + a];
                    o[a * d + a] = if v > 0.0 { 1.0 / v } else { 1.0 };
                }
            }
            o
        })
        .collect();
    // λmax(D⁻¹A) by a few power steps.
    let lam = power_estimate(n * d, LAMBDA_STEPS, |x, ax, y| {
        block_matvec(d, lev, a, x, ax);
        y.par_chunks_mut(d).enumerate().for_each(|(i, yi)| {
            for r in 0..d {
                yi[r] = (0..d).map(|c| dinv[i][r * d + c] * ax[i * d + c]).sum();
            }
        });
    });
    let omega = if lam > 0.0 && lam.is_finite() {
        4.0 / (3.0 * lam)
    } else {
        0.0
    };
    let hb = |k: usize| block9(d, &a[k * dd..(k + 1) * dd]);
    let id = identity(d);
    let tv: Vec<Option<[f64; 9]>> = (0..n)
        .into_par_iter()
        .map(|i| Some(t(i)).filter(|ti| *ti != id))
        .collect();
    sp.p_values(
        d,
        &lev.row_ptr,
        &lev.col_idx,
        &lev.of,
        omega,
        hb,
        &dinv,
        &tv,
    )
}

/// T_i = P_i V_iᵀ of the nodes (level 0): row a is column a of V_i, zero where a is
/// constrained. Deeper levels take T_i = I (their unknowns are world translations).
pub(super) fn node_translation(e: &Eliminated, i: usize) -> [f64; 9] {
    let d = e.h.dim;
    let mut o = [0.0; 9];
    let m = e.frames.mask[i];
    let v = e.frames.rotation(i);
    for a in 0..d {
        if m & (1 << a) != 0 {
            continue;
        }
        for b in 0..d {
            o[a * d + b] = match v {
                None => f64::from(u8::from(a == b)),
                Some(v) => v[b * d + a],
            };
        }
    }
    o
}

/// T_i = I (d×d in the first d² of 9).
pub(super) fn identity(d: usize) -> [f64; 9] {
    let mut o = [0.0; 9];
    for a in 0..d {
        o[a * d + a] = 1.0;
    }
    o
}

/// a·b for d×d row-major blocks (in the first d² of 9).
fn mul(d: usize, a: &[f64; 9], b: &[f64; 9]) -> [f64; 9] {
    let mut o = [0.0f64; 9];
    for r in 0..d {
        for c in 0..d {
            let mut s = 0.0;
            for k in 0..d {
                s += a[r * d + k] * b[k * d + c];
            }
            o[r * d + c] = s;
        }
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    /// T_j left out where it is the identity gives P the same bits as the product with I,
    /// with zeros of either sign among the level's values.
    #[test]
    fn an_identity_translation_left_out_gives_the_same_bits() {
        for d in [2usize, 3] {
            let dd = d * d;
            let n = 40;
            let (mut row_ptr, mut col_idx) = (vec![0usize], Vec::new());
            for i in 0..n {
                let mut cols = vec![
                    i,
                    (i + 1) % n,
                    (i + n - 1) % n,
                    (i + 5) % n,
                    (i + n - 5) % n,
                ];
                cols.sort_unstable();
                cols.dedup();
                col_idx.extend(cols);
                row_ptr.push(col_idx.len());
            }
            let of: Vec<u32> = (0..n).map(|i| ((i * 7) % n / 4) as u32).collect();
            let sp = SmoothPattern::new(&row_ptr, &col_idx, &of, n / 4);
            let a: Vec<f64> = (0..col_idx.len() * dd)
                .map(|k| match k % 11 {
                    3 => -0.0,
                    7 => 0.0,
                    _ => ((k * 2654435761) % 1999) as f64 / 999.0 - 1.0,
                })
                .collect();
            let dinv: Vec<[f64; 9]> = (0..n)
                .map(|i| {
                    let mut b = [0.0; 9];
                    for (k, v) in b[..dd].iter_mut().enumerate() {
                        *v = ((i * 31 + k * 7) % 13) as f64 / 13.0 - 0.4;
                    }
                    b
                })
                .collect();
            let id = identity(d);
            // Every third item has its first component masked (T_i's first row zero).
            let left_out: Vec<Option<[f64; 9]>> = (0..n)
                .map(|i| {
                    (i % 3 == 0).then(|| {
                        let mut t = id;
                        t[..d].fill(0.0);
                        t
                    })
                })
                .collect();
            let given: Vec<Option<[f64; 9]>> =
                left_out.iter().map(|t| Some(t.unwrap_or(id))).collect();
            let hb = |k: usize| block9(d, &a[k * dd..(k + 1) * dd]);
            let p1 = sp.p_values(d, &row_ptr, &col_idx, &of, 0.7, hb, &dinv, &left_out);
            let p2 = sp.p_values(d, &row_ptr, &col_idx, &of, 0.7, hb, &dinv, &given);
            assert_eq!(p1.len(), sp.p_col.len() * dd);
            assert!(
                p1.iter().zip(&p2).all(|(x, y)| x.to_bits() == y.to_bits()),
                "d = {d}"
            );
        }
    }
}
