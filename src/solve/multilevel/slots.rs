//! The CPU V-cycle's vectors in the smoother's own layout: each level's values cluster by
//! cluster, a cluster's items in order, each cluster padded with zeros to whole tiles
//! ([`tiled_side`]). The cluster smoothing then reads and writes each cluster's values
//! where they lie, with no gather into cluster order and no scatter back (about half of
//! a smoothing's time in node order); the level products, the restriction and the
//! prolongation read and write the same slots instead of item positions. Every sum runs
//! in the order of the node-order passes, so the V-cycle's values are the same bits.

use super::dense::{apply_tiled, tiled_side};
use super::level::{split_rows, Factors, Level};
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
        }
    }

    /// Values in the layout.
    pub(super) fn len(&self) -> usize {
        *self.start.last().unwrap_or(&0)
    }

    /// out (slots) = v (item order), for the level `lev` of these slots, cluster by
    /// cluster in parallel; padding left as it is (zero).
    pub(super) fn gather(&self, d: usize, lev: &Level, v: &[f64], out: &mut [f64]) {
        split_rows(out, &self.start, 1)
            .into_par_iter()
            .enumerate()
            .with_min_len(64)
            .for_each(|(c, o)| {
                for (oi, &i) in o
                    .chunks_exact_mut(d)
                    .zip(&lev.items[lev.ptr[c]..lev.ptr[c + 1]])
                {
                    let i = i as usize;
                    oi.copy_from_slice(&v[i * d..(i + 1) * d]);
                }
            });
    }

    /// out (item order) = v (slots).
    pub(super) fn scatter(&self, d: usize, v: &[f64], out: &mut [f64]) {
        out.par_chunks_mut(d)
            .with_min_len(256)
            .zip(self.at.par_iter())
            .for_each(|(o, &a)| o.copy_from_slice(&v[a as usize..a as usize + d]));
    }

    /// The level matrix `a` (d×d row-major blocks on the level's pattern, both
    /// triangles) rounded to f32 in this order of rows ([`Slots::fill_with`]).
    pub(super) fn fill(
        &self,
        d: usize,
        lev: &Level,
        mirror: &[u32],
        a: &[f64],
        out: &mut Vec<f32>,
    ) {
        let dd = d * d;
        self.fill_with(
            d,
            lev,
            mirror,
            |_, k, _, o| {
                o.copy_from_slice(&a[k * dd..(k + 1) * dd]);
            },
            out,
        );
    }

    /// The level matrix rounded to f32 in this order of rows, each block stored by
    /// columns, from the upper triangle's values (so exactly symmetric; `mirror[k]`: the
    /// index of block k's transposed partner), with one zero after the last block (the
    /// product reads a column as four values). `block(i, k, j, out)` gives stored block
    /// k = (i, j) as d×d row-major f64 values: the level's values, or Ĥ's blocks rotated
    /// into the node frames as they are needed (a refresh, with no f64 copy of the level).
    pub(super) fn fill_with(
        &self,
        d: usize,
        lev: &Level,
        mirror: &[u32],
        block: impl Fn(usize, usize, usize, &mut [f64]) + Sync,
        out: &mut Vec<f32>,
    ) {
        let dd = d * d;
        let nb = self.src.len();
        out.resize(nb * dd + 1, 0.0);
        out[nb * dd] = 0.0;
        let rows = split_rows(&mut out[..nb * dd], &self.ptr, dd);
        let fill = |t: usize, o: &mut [f32], i: usize| match d {
            2 => self.fill_row::<2, 4>(t, o, i, lev, mirror, &block),
            _ => self.fill_row::<3, 9>(t, o, i, lev, mirror, &block),
        };
        rows.into_par_iter()
            .zip(lev.items.par_iter())
            .enumerate()
            .with_min_len(64)
            .for_each(|(t, (o, &i))| fill(t, o, i as usize));
    }

    /// Row t (item i) of [`Slots::fill_with`] into its blocks `o`.
    #[inline(always)]
    fn fill_row<const D: usize, const DD: usize>(
        &self,
        t: usize,
        o: &mut [f32],
        i: usize,
        lev: &Level,
        mirror: &[u32],
        block: &(impl Fn(usize, usize, usize, &mut [f64]) + Sync),
    ) {
        let mut v = [0.0f64; DD];
        for (&k, ob) in self.src[self.ptr[t]..self.ptr[t + 1]]
            .iter()
            .zip(o.chunks_exact_mut(DD))
        {
            let j = lev.col_idx[k];
            let m = mirror[k] as usize;
            if i > j && m != k {
                // The lower triangle: the partner (j, i) by columns is (i, j)'s transpose
                // by rows, value for value.
                block(j, m, i, &mut v);
                ob.iter_mut().zip(&v).for_each(|(o, &x)| *o = x as f32);
                continue;
            }
            block(i, k, j, &mut v);
            for r in 0..D {
                for c in 0..D {
                    // A diagonal block is read from its upper triangle; an off-diagonal
                    // block above the diagonal, or without a stored partner, keeps its
                    // own values.
                    let x = if i == j && r > c {
                        v[c * D + r]
                    } else {
                        v[r * D + c]
                    };
                    ob[c * D + r] = x as f32;
                }
            }
        }
    }

    /// y = A x, or y = b − A x with `b`, all in slots, for `a` from [`Slots::fill`] (`lev`
    /// the level of these slots: cluster c's rows are `lev.ptr[c]..lev.ptr[c + 1]`);
    /// every product and sum in f64 and in the order of the node-order product: row i
    /// sums each column c of its blocks times x_j[c] into its own accumulator, in block
    /// order, then adds them as (acc_0 + acc_1) + acc_2.
    pub(super) fn product(
        &self,
        d: usize,
        lev: &Level,
        a: &[f32],
        b: Option<&[f64]>,
        x: &[f64],
        y: &mut [f64],
    ) {
        assert!(a.len() > self.src.len() * d * d, "the trailing zero");
        let parts = split_rows(y, &self.start, 1);
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each(|(c, ys)| {
                let (base, rows) = (self.start[c], lev.ptr[c]..lev.ptr[c + 1]);
                #[cfg(target_arch = "x86_64")]
                if d == 3 && std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2, checked just above; `a` ends in the zero
                    // asserted above.
                    unsafe { self.rows3_avx2(rows, a, b, x, base, ys) };
                    return;
                }
                match d {
                    2 => self.rows::<2, 4>(rows, a, b, x, base, ys),
                    _ => self.rows::<3, 9>(rows, a, b, x, base, ys),
                }
            });
    }

    /// One cluster's rows of [`Slots::product`] into its slice `ys` (slot `base` first).
    fn rows<const D: usize, const DD: usize>(
        &self,
        rows: std::ops::Range<usize>,
        a: &[f32],
        b: Option<&[f64]>,
        x: &[f64],
        base: usize,
        ys: &mut [f64],
    ) {
        for (p, t) in rows.clone().enumerate() {
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
        rows: std::ops::Range<usize>,
        a: &[f32],
        b: Option<&[f64]>,
        x: &[f64],
        base: usize,
        ys: &mut [f64],
    ) {
        use std::arch::x86_64::*;
        let ap = a.as_ptr();
        for (p, t) in rows.clone().enumerate() {
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
        let parts = split_rows(out, &self.start, 1);
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

/// A block matrix between two levels' slots with its rows in the cluster order of the
/// slots it writes, so that a pass reads its blocks as one stream and writes its slots
/// in order: P (fine rows, coarse columns) or Pᵀ (coarse rows, fine columns).
#[derive(Debug, Clone)]
pub(super) struct SlotBlocks {
    /// Row t's blocks (rows in cluster order): `ptr[t]..ptr[t + 1]`, each's index in the
    /// pattern it comes from (`src`) and its column's slot (`at`).
    ptr: Vec<usize>,
    src: Vec<u32>,
    at: Vec<u32>,
    /// Each block of the source pattern's place in this order.
    pub(super) pos: Vec<u32>,
}

impl SlotBlocks {
    /// Row by row over `rows` (items in cluster order), `row_blocks(i)` giving item i's
    /// blocks as (index in the source pattern, column item) among `blocks` in all.
    fn new<I: Iterator<Item = (usize, u32)>>(
        rows: &[u32],
        blocks: usize,
        columns: &Slots,
        row_blocks: impl Fn(usize) -> I,
    ) -> Self {
        let (mut ptr, mut src, mut at) = (vec![0usize], Vec::new(), Vec::new());
        let mut pos = vec![0u32; blocks];
        for &i in rows {
            for (k, j) in row_blocks(i as usize) {
                pos[k] = src.len() as u32;
                src.push(k as u32);
                at.push(columns.at[j as usize]);
            }
            ptr.push(src.len());
        }
        SlotBlocks { ptr, src, at, pos }
    }

    /// The blocks of `v` (in the source pattern's order, d×d row-major values each) in
    /// this order, rounded to f32, each block stored by columns, with one zero after the
    /// last block (the AVX2 pass reads a column as four values).
    pub(super) fn f32_values(&self, d: usize, v: &[f64]) -> Vec<f32> {
        let dd = d * d;
        let mut out = vec![0.0f32; self.src.len() * dd + 1];
        out[..self.src.len() * dd]
            .par_chunks_mut(dd)
            .zip(self.src.par_iter())
            .for_each(|(o, &k)| {
                let b = &v[k as usize * dd..(k as usize + 1) * dd];
                for r in 0..d {
                    for c in 0..d {
                        o[c * d + r] = b[r * d + c] as f32;
                    }
                }
            });
        out
    }

    /// out = M x, or out += M x with `add` (x and out in slots, `rows` the levels the
    /// rows and the output belong to), `m` from [`SlotBlocks::f32_values`]; each row's
    /// sum in block order, starting from out's value with `add`.
    pub(super) fn apply(
        &self,
        d: usize,
        rows: (&Level, &Slots),
        m: &[f32],
        x: &[f64],
        add: bool,
        out: &mut [f64],
    ) {
        let (lev, slots) = rows;
        assert!(m.len() > self.src.len() * d * d, "the trailing zero");
        split_rows(out, &slots.start, 1)
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each(|(cl, o)| {
                let rows = lev.ptr[cl]..lev.ptr[cl + 1];
                #[cfg(target_arch = "x86_64")]
                if d == 3 && std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2, checked just above; `m` ends in the zero
                    // asserted above.
                    unsafe { self.rows3_avx2(rows, m, x, add, o) };
                    return;
                }
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2, checked just above.
                    unsafe { self.rows_avx2(d, rows, m, x, add, o) };
                    return;
                }
                self.rows(d, rows, m, x, add, o);
            });
    }

    /// [`SlotBlocks::rows`] compiled for AVX2 (d = 2): the same operations in the same
    /// order, so the same bits.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn rows_avx2(
        &self,
        d: usize,
        rows: std::ops::Range<usize>,
        m: &[f32],
        x: &[f64],
        add: bool,
        o: &mut [f64],
    ) {
        self.rows(d, rows, m, x, add, o);
    }

    /// [`SlotBlocks::rows`] for d = 3 in AVX2: a block column's three values (and the
    /// next one, whose lane is dropped) in four f64 lanes, so a block is three products
    /// and sums across the row's three outputs at once; the same products and sums in
    /// the same order as [`SlotBlocks::rows`], so the same bits.
    ///
    /// # Safety
    /// The CPU must have AVX2, and `m` hold one value past the last block.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn rows3_avx2(
        &self,
        rows: std::ops::Range<usize>,
        m: &[f32],
        x: &[f64],
        add: bool,
        o: &mut [f64],
    ) {
        use std::arch::x86_64::*;
        let mp = m.as_ptr();
        for (q, row) in rows.enumerate() {
            let oi: &mut [f64; 3] = (&mut o[q * 3..q * 3 + 3]).try_into().expect("3 values");
            let mut acc = if add {
                _mm256_setr_pd(oi[0], oi[1], oi[2], 0.0)
            } else {
                _mm256_setzero_pd()
            };
            for k in self.ptr[row]..self.ptr[row + 1] {
                let at = self.at[k] as usize;
                let xc: &[f64; 3] = x[at..at + 3].try_into().expect("3 values");
                // SAFETY: block k's column c is m[9k + 3c..9k + 3c + 3], and the fourth
                // value read is within m (the trailing zero at the latest).
                let col =
                    |c: usize| unsafe { _mm256_cvtps_pd(_mm_loadu_ps(mp.add(9 * k + 3 * c))) };
                let mut s = _mm256_mul_pd(col(0), _mm256_set1_pd(xc[0]));
                s = _mm256_add_pd(s, _mm256_mul_pd(col(1), _mm256_set1_pd(xc[1])));
                s = _mm256_add_pd(s, _mm256_mul_pd(col(2), _mm256_set1_pd(xc[2])));
                acc = _mm256_add_pd(acc, s);
            }
            let mut sv = [0.0f64; 4];
            _mm256_storeu_pd(sv.as_mut_ptr(), acc);
            oi.copy_from_slice(&sv[..3]);
        }
    }

    #[inline(always)]
    fn rows(
        &self,
        d: usize,
        rows: std::ops::Range<usize>,
        m: &[f32],
        x: &[f64],
        add: bool,
        o: &mut [f64],
    ) {
        // `add` as a constant: the fill below leaves the loop without a branch.
        match (d, add) {
            (2, false) => self.rows_d::<2, 4, false>(rows, m, x, o),
            (2, true) => self.rows_d::<2, 4, true>(rows, m, x, o),
            (_, false) => self.rows_d::<3, 9, false>(rows, m, x, o),
            (_, true) => self.rows_d::<3, 9, true>(rows, m, x, o),
        }
    }

    /// One cluster's rows of [`SlotBlocks::apply`] into its slice `o`.
    #[inline(always)]
    fn rows_d<const D: usize, const DD: usize, const ADD: bool>(
        &self,
        rows: std::ops::Range<usize>,
        m: &[f32],
        x: &[f64],
        o: &mut [f64],
    ) {
        for (q, row) in rows.enumerate() {
            let oi = &mut o[q * D..(q + 1) * D];
            if !ADD {
                oi.fill(0.0);
            }
            for k in self.ptr[row]..self.ptr[row + 1] {
                let b: &[f32; DD] = m[k * DD..(k + 1) * DD].try_into().expect("D·D values");
                let at = self.at[k] as usize;
                let xc: &[f64; D] = x[at..at + D].try_into().expect("D values");
                for a in 0..D {
                    let mut s = 0.0;
                    for c in 0..D {
                        s += f64::from(b[c * D + a]) * xc[c];
                    }
                    oi[a] += s;
                }
            }
        }
    }
}

/// The smoothed prolongation between two levels' slots: P with its rows in the fine
/// level's cluster order, Pᵀ with its rows (the lists of `SmoothPattern::pt`) in the
/// coarse level's.
#[derive(Debug, Clone)]
pub(super) struct TransferSlots {
    pub(super) p: SlotBlocks,
    pub(super) pt: SlotBlocks,
}

impl TransferSlots {
    pub(super) fn new(
        sp: &SmoothPattern,
        fine_lev: &Level,
        fine: &Slots,
        coarse_lev: &Level,
        coarse: &Slots,
    ) -> Self {
        let p = SlotBlocks::new(&fine_lev.items, sp.p_col.len(), coarse, |i| {
            (sp.p_ptr[i]..sp.p_ptr[i + 1]).map(|k| (k, sp.p_col[k]))
        });
        let pt = SlotBlocks::new(&coarse_lev.items, sp.pt.len(), fine, |c| {
            (sp.pt_ptr[c]..sp.pt_ptr[c + 1]).map(|t| (t, sp.pt[t].0))
        });
        TransferSlots { p, pt }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::multilevel::level::mirror_blocks;

    /// Whether two vectors hold the same bits, value for value.
    fn same_bits(a: &[f64], b: &[f64]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits())
    }

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

    /// A transfer in slots (here the level's own matrix pattern as the block matrix) is
    /// the row-major blocks rounded to f32 times x, each row summed in block order, each
    /// block's products summed column by column; its AVX2 rows are its portable rows.
    #[test]
    fn the_transfer_is_the_row_major_sum_in_every_build() {
        for d in [2usize, 3] {
            let n = 201;
            let lev = level(n);
            let sl = Slots::new(&lev, d);
            let dd = d * d;
            let nnz = lev.row_ptr[n];
            let v: Vec<f64> = (0..nnz * dd)
                .map(|k| ((k * 2654435761) % 2003) as f64 / 997.0 - 1.0)
                .collect();
            let blocks = SlotBlocks::new(&lev.items, nnz, &sl, |i| {
                (lev.row_ptr[i]..lev.row_ptr[i + 1]).map(|k| (k, lev.col_idx[k] as u32))
            });
            let m = blocks.f32_values(d, &v);
            let x: Vec<f64> = (0..n * d)
                .map(|k| ((k * 7919) % 23) as f64 / 7.0 - 1.3)
                .collect();
            let mut xs = vec![0.0; sl.len()];
            sl.gather(d, &lev, &x, &mut xs);
            for add in [false, true] {
                let start: Vec<f64> = (0..sl.len()).map(|k| (k % 3) as f64 * 0.25).collect();
                let mut ys = start.clone();
                blocks.apply(d, (&lev, &sl), &m, &xs, add, &mut ys);
                let mut portable = start.clone();
                for c in 0..lev.clusters() {
                    let (s, e) = (sl.start[c], sl.start[c + 1]);
                    let rows = lev.ptr[c]..lev.ptr[c + 1];
                    blocks.rows(d, rows, &m, &xs, add, &mut portable[s..e]);
                }
                assert!(
                    same_bits(&ys, &portable),
                    "d = {d}, add = {add}: dispatched and portable rows"
                );
                for i in 0..n {
                    let at = sl.at[i] as usize;
                    for r in 0..d {
                        let mut want = if add { start[at + r] } else { 0.0 };
                        for k in lev.row_ptr[i]..lev.row_ptr[i + 1] {
                            let j = lev.col_idx[k];
                            let mut s = 0.0;
                            for c in 0..d {
                                s += f64::from(v[k * dd + r * d + c] as f32) * x[j * d + c];
                            }
                            want += s;
                        }
                        assert_eq!(ys[at + r].to_bits(), want.to_bits(), "d = {d}, item {i}");
                    }
                }
            }
        }
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
            sl.gather(d, &lev, &x, &mut xs);
            sl.gather(d, &lev, &b, &mut bs);
            sl.product(d, &lev, &vals, Some(&bs), &xs, &mut ys);
            let mut y = vec![0.0; n * d];
            sl.scatter(d, &ys, &mut y);
            // Item order, block by block in the pattern's order, each column into its own
            // accumulator: the order the slot rows keep.
            let mut portable = vec![0.0; sl.len()];
            for c in 0..lev.clusters() {
                let (s, e) = (sl.start[c], sl.start[c + 1]);
                let rows = lev.ptr[c]..lev.ptr[c + 1];
                match d {
                    2 => sl.rows::<2, 4>(rows, &vals, Some(&bs), &xs, s, &mut portable[s..e]),
                    _ => sl.rows::<3, 9>(rows, &vals, Some(&bs), &xs, s, &mut portable[s..e]),
                }
            }
            assert!(
                same_bits(&ys, &portable),
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
