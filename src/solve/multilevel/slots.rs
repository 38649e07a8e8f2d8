//! The CPU V-cycle's vectors in the smoother's own layout: each level's values cluster by
//! cluster, a cluster's items in order, each cluster padded with zeros to whole tiles
//! ([`tiled_side`]). The cluster smoothing then reads and writes each cluster's values
//! where they lie, with no gather into cluster order and no scatter back (about half of
//! a smoothing's time in node order); the level products, the restriction and the
//! prolongation read and write the same slots instead of item positions. Every sum runs
//! in the order of the node-order passes, so the V-cycle's values are the same bits.

use super::dense::{apply_tiled, tiled_side};
use super::level::{split_at_starts, split_rows, Factors, Level};
use super::smoothed::SmoothPattern;
use rayon::prelude::*;

/// One level's slot layout and its matrix's rows in that order (pattern only).
#[derive(Debug, Clone)]
pub(super) struct Slots {
    /// Item i's first value.
    pub(super) at: Vec<u32>,
    /// Cluster c's values: `start[c]..start[c + 1]` (its items' values, then zeros).
    pub(super) start: Vec<usize>,
    /// The level matrix's rows in cluster order (row t is item `items[t]`): blocks
    /// `ptr[t]..ptr[t + 1]`, their columns' slots `col` and their indices in the level's
    /// pattern `src`.
    ptr: Vec<usize>,
    col: Vec<u32>,
    src: Vec<usize>,
    /// Rows per cluster: `lev.ptr` (the items of cluster c are rows `rows[c]..rows[c + 1]`).
    rows: Vec<usize>,
}

impl Slots {
    pub(super) fn new(lev: &Level, d: usize) -> Self {
        let nc = lev.clusters();
        let mut start = Vec::with_capacity(nc + 1);
        let mut total = 0usize;
        for c in 0..nc {
            start.push(total);
            total += tiled_side((lev.ptr[c + 1] - lev.ptr[c]) * d);
        }
        start.push(total);
        let at: Vec<u32> = (0..lev.n)
            .map(|i| (start[lev.of[i] as usize] + lev.pos[i] as usize * d) as u32)
            .collect();
        let (mut ptr, mut col, mut src) = (vec![0usize], Vec::new(), Vec::new());
        for &i in &lev.items {
            let i = i as usize;
            for k in lev.row_ptr[i]..lev.row_ptr[i + 1] {
                col.push(at[lev.col_idx[k]]);
                src.push(k);
            }
            ptr.push(col.len());
        }
        Slots {
            at,
            start,
            ptr,
            col,
            src,
            rows: lev.ptr.clone(),
        }
    }

    /// Values in the layout.
    pub(super) fn len(&self) -> usize {
        *self.start.last().unwrap_or(&0)
    }

    /// out (slots) = v (item order); padding left as it is (zero).
    pub(super) fn gather(&self, d: usize, v: &[f64], out: &mut [f64]) {
        for (i, &a) in self.at.iter().enumerate() {
            let a = a as usize;
            out[a..a + d].copy_from_slice(&v[i * d..(i + 1) * d]);
        }
    }

    /// out (item order) = v (slots).
    pub(super) fn scatter(&self, d: usize, v: &[f64], out: &mut [f64]) {
        out.par_chunks_mut(d)
            .with_min_len(256)
            .zip(self.at.par_iter())
            .for_each(|(o, &a)| o.copy_from_slice(&v[a as usize..a as usize + d]));
    }

    /// The level matrix `a` (d×d row-major blocks on the level's pattern, both
    /// triangles) rounded to f32 in this order of rows, each block stored by columns,
    /// from the upper triangle's values (so exactly symmetric; `mirror[k]`: the index of
    /// block k's transposed partner), with one zero after the last block (the product
    /// reads a column as four values).
    pub(super) fn fill(
        &self,
        d: usize,
        lev: &Level,
        mirror: &[u32],
        a: &[f64],
        out: &mut Vec<f32>,
    ) {
        let dd = d * d;
        let nb = self.src.len();
        out.resize(nb * dd + 1, 0.0);
        out[nb * dd] = 0.0;
        let rows = split_rows(&mut out[..nb * dd], &self.ptr, dd);
        rows.into_par_iter()
            .zip(lev.items.par_iter())
            .enumerate()
            .for_each(|(t, (o, &i))| {
                let i = i as usize;
                for (&k, ob) in self.src[self.ptr[t]..self.ptr[t + 1]]
                    .iter()
                    .zip(o.chunks_exact_mut(dd))
                {
                    let j = lev.col_idx[k];
                    let own = &a[k * dd..(k + 1) * dd];
                    let m = mirror[k] as usize;
                    let other = &a[m * dd..(m + 1) * dd];
                    for r in 0..d {
                        for c in 0..d {
                            // An off-diagonal block without a stored partner keeps its own.
                            let upper = i < j || (i == j && r <= c) || (i != j && m == k);
                            let v = if upper {
                                own[r * d + c]
                            } else {
                                other[c * d + r]
                            };
                            ob[c * d + r] = v as f32;
                        }
                    }
                }
            });
    }

    /// y = A x, or y = b − A x with `b`, all in slots, for `a` from [`Slots::fill`];
    /// every product and sum in f64 and in the order of the node-order product: row i
    /// sums each column c of its blocks times x_j[c] into its own accumulator, in block
    /// order, then adds them as (acc_0 + acc_1) + acc_2.
    pub(super) fn product(&self, d: usize, a: &[f32], b: Option<&[f64]>, x: &[f64], y: &mut [f64]) {
        assert!(a.len() > self.src.len() * d * d, "the trailing zero");
        let parts = split_at_starts(y, &self.start);
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each(|(c, ys)| {
                let base = self.start[c];
                #[cfg(target_arch = "x86_64")]
                if d == 3 && std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2, checked just above; `a` ends in the zero
                    // asserted above.
                    unsafe { self.rows3_avx2(c, a, b, x, base, ys) };
                    return;
                }
                match d {
                    2 => self.rows::<2, 4>(c, a, b, x, base, ys),
                    _ => self.rows::<3, 9>(c, a, b, x, base, ys),
                }
            });
    }

    /// Cluster c's rows of [`Slots::product`] into its slice `ys` (slot `base` first).
    fn rows<const D: usize, const DD: usize>(
        &self,
        c: usize,
        a: &[f32],
        b: Option<&[f64]>,
        x: &[f64],
        base: usize,
        ys: &mut [f64],
    ) {
        for (p, t) in (self.rows[c]..self.rows[c + 1]).enumerate() {
            let mut acc = [[0.0f64; D]; D];
            let (rs, re) = (self.ptr[t], self.ptr[t + 1]);
            for (blk, &j) in a[rs * DD..re * DD].chunks_exact(DD).zip(&self.col[rs..re]) {
                let j = j as usize;
                for (cc, ac) in acc.iter_mut().enumerate() {
                    let xc = x[j + cc];
                    for r in 0..D {
                        ac[r] += f64::from(blk[cc * D + r]) * xc;
                    }
                }
            }
            for (r, y) in ys[p * D..(p + 1) * D].iter_mut().enumerate() {
                let mut s = acc[0][r] + acc[1][r];
                if D == 3 {
                    s += acc[2][r];
                }
                *y = match b {
                    Some(b) => b[base + p * D + r] - s,
                    None => s,
                };
            }
        }
    }

    /// [`Slots::rows`] for d = 3 in AVX2: a block column's three values (and the next
    /// one, whose lane is dropped) in four f64 lanes; the same products and sums in the
    /// same order, so the same bits.
    ///
    /// # Safety
    /// The CPU must have AVX2, and `a` hold one value past the last block.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn rows3_avx2(
        &self,
        c: usize,
        a: &[f32],
        b: Option<&[f64]>,
        x: &[f64],
        base: usize,
        ys: &mut [f64],
    ) {
        use std::arch::x86_64::*;
        let ap = a.as_ptr();
        for (p, t) in (self.rows[c]..self.rows[c + 1]).enumerate() {
            let mut acc = [_mm256_setzero_pd(); 3];
            let (rs, re) = (self.ptr[t], self.ptr[t + 1]);
            for (k, &j) in (rs..re).zip(&self.col[rs..re]) {
                let xj: &[f64; 3] = x[j as usize..j as usize + 3].try_into().expect("3 values");
                for (cc, ac) in acc.iter_mut().enumerate() {
                    // SAFETY: block k's column cc is a[9k + 3cc..9k + 3cc + 3], and the
                    // fourth value read is within a (the trailing zero at the latest).
                    let col = _mm256_cvtps_pd(_mm_loadu_ps(ap.add(9 * k + 3 * cc)));
                    *ac = _mm256_add_pd(*ac, _mm256_mul_pd(col, _mm256_set1_pd(xj[cc])));
                }
            }
            let s = _mm256_add_pd(_mm256_add_pd(acc[0], acc[1]), acc[2]);
            let mut sv = [0.0f64; 4];
            _mm256_storeu_pd(sv.as_mut_ptr(), s);
            for (r, (y, v)) in ys[p * 3..p * 3 + 3].iter_mut().zip(sv).enumerate() {
                *y = match b {
                    Some(b) => b[base + p * 3 + r] - v,
                    None => v,
                };
            }
        }
    }

    /// out = scale·B⁺src (or out += with `add`), all in slots, each cluster's block
    /// applied where its values lie ([`apply_tiled`], G in `f`).
    pub(super) fn smooth(&self, f: &Factors, scale: f64, add: bool, src: &[f64], out: &mut [f64]) {
        let parts = split_at_starts(out, &self.start);
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each_init(Vec::new, |z, (c, o)| {
                let r = &src[self.start[c]..self.start[c + 1]];
                z.resize(r.len(), 0.0);
                apply_tiled(&f.g[f.g_start[c]..f.g_start[c + 1]], r, z);
                if add {
                    o.iter_mut()
                        .zip(z.iter())
                        .for_each(|(v, w)| *v += scale * w);
                } else {
                    o.iter_mut().zip(z.iter()).for_each(|(v, w)| *v = scale * w);
                }
            });
    }
}

/// The smoothed prolongation's transfers between two levels' slots: P's rows in the fine
/// level's cluster order and Pᵀ's lists in the coarse level's, so that both passes read
/// their blocks as one stream and write their slots in order.
#[derive(Debug, Clone)]
pub(super) struct TransferSlots {
    /// P's blocks by fine row in cluster order (row t: `p_ptr[t]..p_ptr[t + 1]`), each's
    /// index in `SmoothPattern`'s P (`p_src`) and its coarse column's slot (`p_at`).
    p_ptr: Vec<usize>,
    p_src: Vec<u32>,
    p_at: Vec<u32>,
    /// Each P block's place in that order.
    pub(super) p_pos: Vec<u32>,
    /// Pᵀ's lists by coarse item in cluster order (`pt_ptr[t]..pt_ptr[t + 1]`), each
    /// entry's index in `SmoothPattern::pt` (`pt_src`) and its fine row's slot (`pt_at`).
    pt_ptr: Vec<usize>,
    pt_src: Vec<u32>,
    pt_at: Vec<u32>,
    /// Each entry of `SmoothPattern::pt`'s place in that order.
    pub(super) pt_pos: Vec<u32>,
}

impl TransferSlots {
    pub(super) fn new(
        sp: &SmoothPattern,
        fine_lev: &Level,
        fine: &Slots,
        coarse_lev: &Level,
        coarse: &Slots,
    ) -> Self {
        let (mut p_ptr, mut p_src, mut p_at) = (vec![0usize], Vec::new(), Vec::new());
        let mut p_pos = vec![0u32; sp.p_col.len()];
        for &i in &fine_lev.items {
            let blocks = sp.p_ptr[i as usize]..sp.p_ptr[i as usize + 1];
            for (pk, &c) in blocks.clone().zip(&sp.p_col[blocks]) {
                p_pos[pk] = p_src.len() as u32;
                p_src.push(pk as u32);
                p_at.push(coarse.at[c as usize]);
            }
            p_ptr.push(p_src.len());
        }
        let (mut pt_ptr, mut pt_src, mut pt_at) = (vec![0usize], Vec::new(), Vec::new());
        let mut pt_pos = vec![0u32; sp.pt.len()];
        for &c in &coarse_lev.items {
            let list = sp.pt_ptr[c as usize]..sp.pt_ptr[c as usize + 1];
            for (t, &(i, _)) in list.clone().zip(&sp.pt[list]) {
                pt_pos[t] = pt_src.len() as u32;
                pt_src.push(t as u32);
                pt_at.push(fine.at[i as usize]);
            }
            pt_ptr.push(pt_src.len());
        }
        TransferSlots {
            p_ptr,
            p_src,
            p_at,
            p_pos,
            pt_ptr,
            pt_src,
            pt_at,
            pt_pos,
        }
    }

    /// P's f32 blocks in this order, from `p` in `SmoothPattern`'s (d×d each).
    pub(super) fn p_f32(&self, dd: usize, p: &[f64]) -> Vec<f32> {
        permuted_f32(dd, &self.p_src, p)
    }

    /// Pᵀ's f32 blocks in this order, from `pt` in `SmoothPattern::pt`'s.
    pub(super) fn pt_f32(&self, dd: usize, pt: &[f64]) -> Vec<f32> {
        permuted_f32(dd, &self.pt_src, pt)
    }

    /// out (coarse slots) = Pᵀ r (r in fine slots), `pt_values` from
    /// [`TransferSlots::pt_f32`]; each coarse item's sum in the order of its list.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn restrict(
        &self,
        d: usize,
        coarse: &Slots,
        coarse_lev: &Level,
        pt_values: &[f32],
        r: &[f64],
        out: &mut [f64],
    ) {
        let parts = split_at_starts(out, &coarse.start);
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each(|(cl, o)| {
                let rows = coarse_lev.ptr[cl]..coarse_lev.ptr[cl + 1];
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2, checked just above.
                    unsafe { self.restrict_avx2(d, rows, pt_values, r, o) };
                    return;
                }
                self.restrict_items(d, rows, pt_values, r, o);
            });
    }

    /// [`TransferSlots::restrict_items`] compiled for AVX2: the same operations in the
    /// same order, so the same bits.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn restrict_avx2(
        &self,
        d: usize,
        rows: std::ops::Range<usize>,
        pt_values: &[f32],
        r: &[f64],
        o: &mut [f64],
    ) {
        self.restrict_items(d, rows, pt_values, r, o);
    }

    #[inline(always)]
    fn restrict_items(
        &self,
        d: usize,
        rows: std::ops::Range<usize>,
        pt_values: &[f32],
        r: &[f64],
        o: &mut [f64],
    ) {
        match d {
            2 => self.restrict_d::<2, 4>(rows, pt_values, r, o),
            _ => self.restrict_d::<3, 9>(rows, pt_values, r, o),
        }
    }

    /// A coarse cluster's items of [`TransferSlots::restrict`] into its slice `o`.
    #[inline(always)]
    fn restrict_d<const D: usize, const DD: usize>(
        &self,
        rows: std::ops::Range<usize>,
        pt_values: &[f32],
        r: &[f64],
        o: &mut [f64],
    ) {
        for (p, row) in rows.enumerate() {
            let mut acc = [0.0f64; D];
            for t in self.pt_ptr[row]..self.pt_ptr[row + 1] {
                let at = self.pt_at[t] as usize;
                let ri: &[f64; D] = r[at..at + D].try_into().expect("D values");
                let pb: &[f32; DD] = pt_values[t * DD..(t + 1) * DD]
                    .try_into()
                    .expect("D·D values");
                for a in 0..D {
                    let mut s = 0.0;
                    for k in 0..D {
                        s += f64::from(pb[a * D + k]) * ri[k];
                    }
                    acc[a] += s;
                }
            }
            o[p * D..(p + 1) * D].copy_from_slice(&acc);
        }
    }

    /// z (fine slots) += P x (x in coarse slots), `p` from [`TransferSlots::p_f32`]; each
    /// fine item's sum in the order of its row.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn prolong_add(
        &self,
        d: usize,
        fine: &Slots,
        fine_lev: &Level,
        p: &[f32],
        x: &[f64],
        z: &mut [f64],
    ) {
        let parts = split_at_starts(z, &fine.start);
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each(|(cl, zs)| {
                let rows = fine_lev.ptr[cl]..fine_lev.ptr[cl + 1];
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2, checked just above.
                    unsafe { self.prolong_avx2(d, rows, p, x, zs) };
                    return;
                }
                self.prolong_items(d, rows, p, x, zs);
            });
    }

    /// [`TransferSlots::prolong_items`] compiled for AVX2: the same operations in the
    /// same order, so the same bits.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn prolong_avx2(
        &self,
        d: usize,
        rows: std::ops::Range<usize>,
        p: &[f32],
        x: &[f64],
        zs: &mut [f64],
    ) {
        self.prolong_items(d, rows, p, x, zs);
    }

    #[inline(always)]
    fn prolong_items(
        &self,
        d: usize,
        rows: std::ops::Range<usize>,
        p: &[f32],
        x: &[f64],
        zs: &mut [f64],
    ) {
        match d {
            2 => self.prolong_d::<2, 4>(rows, p, x, zs),
            _ => self.prolong_d::<3, 9>(rows, p, x, zs),
        }
    }

    /// A fine cluster's items of [`TransferSlots::prolong_add`], added into its slice.
    #[inline(always)]
    fn prolong_d<const D: usize, const DD: usize>(
        &self,
        rows: std::ops::Range<usize>,
        p: &[f32],
        x: &[f64],
        zs: &mut [f64],
    ) {
        for (q, row) in rows.enumerate() {
            let zi = &mut zs[q * D..(q + 1) * D];
            for pk in self.p_ptr[row]..self.p_ptr[row + 1] {
                let pb: &[f32; DD] = p[pk * DD..(pk + 1) * DD].try_into().expect("D·D values");
                let at = self.p_at[pk] as usize;
                let xc: &[f64; D] = x[at..at + D].try_into().expect("D values");
                for a in 0..D {
                    let mut s = 0.0;
                    for k in 0..D {
                        s += f64::from(pb[a * D + k]) * xc[k];
                    }
                    zi[a] += s;
                }
            }
        }
    }
}

/// Blocks `src[t]` of `v` (dd values each), in order, rounded to f32.
fn permuted_f32(dd: usize, src: &[u32], v: &[f64]) -> Vec<f32> {
    let mut out = vec![0.0f32; src.len() * dd];
    out.par_chunks_mut(dd)
        .zip(src.par_iter())
        .for_each(|(o, &k)| {
            let b = &v[k as usize * dd..(k as usize + 1) * dd];
            o.iter_mut().zip(b).for_each(|(o, &x)| *o = x as f32);
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::multilevel::level::mirror_blocks;

    /// A level of `n` items in clusters of 5 (the last one shorter), each item joined to
    /// the items up to 3 away and to one far item.
    fn level(n: usize) -> Level {
        let (mut row_ptr, mut col_idx) = (vec![0usize], Vec::new());
        for i in 0..n {
            let mut cols: Vec<usize> = (i.saturating_sub(3)..(i + 4).min(n)).collect();
            cols.push((i * 37 + 11) % n);
            cols.extend((0..n).filter(|&k| (k * 37 + 11) % n == i));
            cols.sort_unstable();
            cols.dedup();
            col_idx.extend(cols);
            row_ptr.push(col_idx.len());
        }
        // Clusters that interleave the items, so that slots and items differ in order.
        let of = (0..n).map(|i| ((i * 7) % n / 5) as u32).collect();
        Level::new(n, of, row_ptr, col_idx)
    }

    /// The product in slots is the item-order product of the same f32 values (the same
    /// sums in the same order: the same bits), and its AVX2 rows are its portable rows.
    #[test]
    fn the_slot_product_is_the_item_order_product_in_every_build() {
        for d in [2usize, 3] {
            let n = 201;
            let lev = level(n);
            let dd = d * d;
            let nnz = lev.row_ptr[n];
            let a: Vec<f64> = (0..nnz * dd)
                .map(|k| ((k * 2654435761) % 2001) as f64 / 1000.0 - 1.0)
                .collect();
            let sl = Slots::new(&lev, d);
            let mut vals = Vec::new();
            sl.fill(d, &lev, &mirror_blocks(&lev), &a, &mut vals);
            let x: Vec<f64> = (0..n * d)
                .map(|k| ((k * 7919) % 23) as f64 / 7.0 - 1.3)
                .collect();
            let b: Vec<f64> = (0..n * d).map(|k| (k % 5) as f64 * 0.1).collect();
            let (mut xs, mut bs, mut ys) = (
                vec![0.0; sl.len()],
                vec![0.0; sl.len()],
                vec![0.0; sl.len()],
            );
            sl.gather(d, &x, &mut xs);
            sl.gather(d, &b, &mut bs);
            sl.product(d, &vals, Some(&bs), &xs, &mut ys);
            let mut y = vec![0.0; n * d];
            sl.scatter(d, &ys, &mut y);
            // Item order, block by block in the pattern's order, each column into its own
            // accumulator: the order the slot rows keep.
            let mut portable = vec![0.0; sl.len()];
            for c in 0..lev.clusters() {
                let (s, e) = (sl.start[c], sl.start[c + 1]);
                match d {
                    2 => sl.rows::<2, 4>(c, &vals, Some(&bs), &xs, s, &mut portable[s..e]),
                    _ => sl.rows::<3, 9>(c, &vals, Some(&bs), &xs, s, &mut portable[s..e]),
                }
            }
            assert!(
                ys.iter()
                    .zip(&portable)
                    .all(|(p, q)| p.to_bits() == q.to_bits()),
                "d = {d}: dispatched and portable rows"
            );
            for i in 0..n {
                let mut acc = vec![vec![0.0f64; d]; d];
                for k in lev.row_ptr[i]..lev.row_ptr[i + 1] {
                    let j = lev.col_idx[k];
                    // The stored f32 block of (i, j), by columns, as `fill` wrote it.
                    let row = lev
                        .items
                        .iter()
                        .position(|&q| q as usize == i)
                        .expect("item");
                    let at = (sl.ptr[row]..sl.ptr[row + 1])
                        .find(|&q| sl.src[q] == k)
                        .expect("block");
                    for (cc, ac) in acc.iter_mut().enumerate() {
                        for r in 0..d {
                            ac[r] += f64::from(vals[at * dd + cc * d + r]) * x[j * d + cc];
                        }
                    }
                }
                for r in 0..d {
                    let mut s = acc[0][r] + acc[1][r];
                    if d == 3 {
                        s += acc[2][r];
                    }
                    let want = b[i * d + r] - s;
                    assert_eq!(y[i * d + r].to_bits(), want.to_bits(), "d = {d}, item {i}");
                }
            }
        }
    }
}
