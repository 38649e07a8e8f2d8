//! One level of the hierarchy: its clusters, its matrix's pattern and the operations on
//! them (the product, the cluster blocks' inverses and their application, the Galerkin
//! sum into the next level).

use super::dense::{
    cholesky_dropping, explicit_inverse, factor_inverse, pack_lower, pack_tiled_f32, packed_len,
    tiled_index, tiled_len,
};
use crate::core::elimination::{rotate_block, Eliminated};
use rayon::prelude::*;

/// Power-iteration steps of the smoother's estimate of λmax(B_l⁺A_l).
pub const LAMBDA_STEPS: usize = 4;

/// A partition of one level's items (nodes, or the clusters of the level below) into
/// clusters, with the pattern of the level's matrix.
#[derive(Debug, Clone)]
pub(super) struct Level {
    /// Items of this level.
    pub(super) n: usize,
    /// Cluster of each item.
    pub(super) of: Vec<u32>,
    /// Position of each item in its cluster.
    pub(super) pos: Vec<u32>,
    /// Items of cluster c: `items[ptr[c]..ptr[c + 1]]`, ascending.
    pub(super) ptr: Vec<usize>,
    pub(super) items: Vec<u32>,
    /// The matrix of this level's items (level 0: H's own pattern).
    pub(super) row_ptr: Vec<usize>,
    pub(super) col_idx: Vec<usize>,
    /// `col_idx` in u32: what the products read (half the index bytes).
    pub(super) col32: Vec<u32>,
}

impl Level {
    pub(super) fn clusters(&self) -> usize {
        self.ptr.len() - 1
    }

    /// The stored block (i, i), if any (columns are sorted in every row).
    pub(super) fn diag_index(&self, i: usize) -> Option<usize> {
        let row = &self.col_idx[self.row_ptr[i]..self.row_ptr[i + 1]];
        row.binary_search(&i).ok().map(|k| self.row_ptr[i] + k)
    }
}

/// λmax(M⁻¹A) estimated by `steps` power steps from a fixed start ([`power_start`]), as
/// the Rayleigh quotient in the A inner product (a lower bound); `step(x, ax, y)` sets
/// ax = A x and y = M⁻¹ ax. 0 when a step meets a non-positive xᵀAx or a vanishing y.
pub(super) fn power_estimate(
    n: usize,
    steps: usize,
    step: impl FnMut(&[f64], &mut [f64], &mut [f64]),
) -> f64 {
    power_estimate_from(power_start(n), steps, step)
}

/// The power steps' start: every component non-zero, the same on every run.
pub(super) fn power_start(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| 1.0 + ((k * 7919) % 13) as f64 / 13.0)
        .collect()
}

/// [`power_estimate`] from the start `x` (any layout the step works in: zeros where it
/// holds no values stay zero).
pub(super) fn power_estimate_from(
    mut x: Vec<f64>,
    steps: usize,
    mut step: impl FnMut(&[f64], &mut [f64], &mut [f64]),
) -> f64 {
    use crate::core::linalg::{dot, norm2};
    let n = x.len();
    let (mut ax, mut y) = (vec![0.0; n], vec![0.0; n]);
    let mut lam = 0.0;
    for _ in 0..steps {
        step(&x, &mut ax, &mut y);
        let xax = dot(&x, &ax);
        let nrm = norm2(&y);
        if xax.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || nrm.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || !nrm.is_finite()
        {
            break;
        }
        lam = dot(&y, &ax) / xax;
        x.iter_mut().zip(&y).for_each(|(a, b)| *a = b / nrm);
    }
    lam
}

/// Indices 0..keys.len() grouped by key (`groups` keys): group g holds
/// `members[ptr[g]..ptr[g + 1]]`, ascending.
pub(super) fn group(keys: &[u32], groups: usize) -> (Vec<usize>, Vec<u32>) {
    let mut ptr = vec![0usize; groups + 1];
    for &k in keys {
        ptr[k as usize + 1] += 1;
    }
    for g in 0..groups {
        ptr[g + 1] += ptr[g];
    }
    let mut fill = ptr.clone();
    let mut members = vec![0u32; keys.len()];
    for (i, &k) in keys.iter().enumerate() {
        members[fill[k as usize]] = i as u32;
        fill[k as usize] += 1;
    }
    (ptr, members)
}

impl Level {
    pub(super) fn new(n: usize, of: Vec<u32>, row_ptr: Vec<usize>, col_idx: Vec<usize>) -> Self {
        let nc = of.iter().map(|&c| c as usize + 1).max().unwrap_or(0);
        let (ptr, items) = group(&of, nc);
        let mut pos = vec![0u32; n];
        for c in 0..nc {
            for (p, &i) in items[ptr[c]..ptr[c + 1]].iter().enumerate() {
                pos[i as usize] = p as u32;
            }
        }
        let col32 = col_idx.iter().map(|&j| j as u32).collect();
        Level {
            n,
            of,
            pos,
            ptr,
            items,
            row_ptr,
            col_idx,
            col32,
        }
    }
}

/// One level's cluster blocks, in two forms. The V-cycle of the CPU CG applies cluster
/// c's G = L⁺ (the inverse of its dropping Cholesky factor, lower triangular, rounded to
/// f32, in 4×4 tiles at `g[g_start[c]..]`, [`pack_tiled_f32`]) as GᵀG: about a quarter
/// of an f64 explicit inverse's bytes, run four lanes wide, and semidefinite whatever
/// the rounding ([`apply_tiled`]). The same X = L⁺ in f64, packed by rows at
/// `x[x_start[c]..]`, is what the explicit (L Lᵀ)⁺ = XᵀX the device V-cycle holds is
/// computed from, only when asked ([`Factors::inverses`]): a CPU solve never reads it.
#[derive(Debug, Clone)]
pub(super) struct Factors {
    pub(super) g_start: Vec<usize>,
    pub(super) g: Vec<f32>,
    x_start: Vec<usize>,
    x: Vec<f64>,
}

/// One level's explicit cluster inverses (L Lᵀ)⁺ = XᵀX in f64: cluster c's m×m symmetric
/// block (m = d·|c|, row-major) at `inv[start[c]..start[c + 1]]`.
#[derive(Debug, Clone)]
pub(super) struct Inverses {
    pub(super) start: Vec<usize>,
    pub(super) inv: Vec<f64>,
}

impl Factors {
    /// The explicit inverses XᵀX of every cluster from the f64 factor inverses X
    /// ([`explicit_inverse`]'s arithmetic on the build's X, so the same bits whenever
    /// asked).
    pub(super) fn inverses(&self, lev: &Level, d: usize) -> Inverses {
        let nc = lev.clusters();
        let mut start = Vec::with_capacity(nc + 1);
        let mut total = 0;
        for c in 0..nc {
            start.push(total);
            let m = (lev.ptr[c + 1] - lev.ptr[c]) * d;
            total += m * m;
        }
        start.push(total);
        let mut inv = vec![0.0; total];
        split_rows(&mut inv, &start, 1)
            .into_par_iter()
            .enumerate()
            .for_each(|(c, out)| {
                let m = (lev.ptr[c + 1] - lev.ptr[c]) * d;
                let mut x = vec![0.0; m * m];
                unpack_lower(m, &self.x[self.x_start[c]..self.x_start[c + 1]], &mut x);
                out.copy_from_slice(&explicit_inverse(m, &x));
            });
        Inverses { start, inv }
    }

    /// Cluster c's G with component `row` (of m) masked: row and column zeroed, `1/√D`
    /// on the diagonal (`sqrt_inv`), as a build gives a component whose block row is D
    /// alone. X stays the build's: the explicit inverse is masked on its own
    /// ([`mask_inverse`]), its other entries the build's.
    pub(super) fn mask(&mut self, c: usize, m: usize, row: usize, sqrt_inv: f64) {
        let g = &mut self.g[self.g_start[c]..self.g_start[c + 1]];
        for j in 0..row {
            g[tiled_index(row, j)] = 0.0;
        }
        for k in row + 1..m {
            g[tiled_index(k, row)] = 0.0;
        }
        g[tiled_index(row, row)] = sqrt_inv as f32;
    }
}

/// The m×m row-major lower-triangular matrix packed row by row in `packed` into `out`
/// (its upper part left as it is: [`explicit_inverse`] reads the lower one only).
fn unpack_lower(m: usize, packed: &[f64], out: &mut [f64]) {
    let mut at = 0;
    for k in 0..m {
        out[k * m..k * m + k + 1].copy_from_slice(&packed[at..at + k + 1]);
        at += k + 1;
    }
}

/// Cluster block `inv` (m×m) with component `row` masked: row and column zeroed, `diag`
/// on the diagonal.
pub(super) fn mask_inverse(inv: &mut [f64], m: usize, row: usize, diag: f64) {
    for k in 0..m {
        inv[row * m + k] = 0.0;
        inv[k * m + row] = 0.0;
    }
    inv[row * m + row] = diag;
}

/// Ĥ's stored blocks in the node frames ([`frame_block`]), on H's pattern.
pub(super) fn frame_values(e: &Eliminated) -> Vec<f64> {
    let mut v = Vec::new();
    frame_values_into(e, &mut v);
    v
}

/// [`frame_values`] into `v` (resized; its allocation kept, as kept levels refresh it for
/// every system).
pub(super) fn frame_values_into(e: &Eliminated, v: &mut Vec<f64>) {
    let h = e.h;
    let dd = h.dim * h.dim;
    v.resize(h.values.len(), 0.0);
    let rows: Vec<&mut [f64]> = split_rows(v, &h.row_ptr, dd);
    rows.into_par_iter().enumerate().for_each(|(i, out)| {
        for (k, o) in (h.row_ptr[i]..h.row_ptr[i + 1]).zip(out.chunks_exact_mut(dd)) {
            frame_block(e, i, k, h.col_idx[k], o);
        }
    });
}

/// `v` split at the rows of a block pattern (`per` values per stored block).
pub(super) fn split_rows<'v, T>(
    mut v: &'v mut [T],
    row_ptr: &[usize],
    per: usize,
) -> Vec<&'v mut [T]> {
    let mut out = Vec::with_capacity(row_ptr.len().saturating_sub(1));
    for w in row_ptr.windows(2) {
        let (a, rest) = std::mem::take(&mut v).split_at_mut((w[1] - w[0]) * per);
        out.push(a);
        v = rest;
    }
    out
}

/// y = A x for a level's matrix (d×d row-major blocks on the level's pattern, in f64 or
/// f32), every sum in f64.
pub(super) fn block_matvec<T: Copy + Into<f64> + Sync>(
    d: usize,
    lev: &Level,
    a: &[T],
    x: &[f64],
    y: &mut [f64],
) {
    match d {
        2 => block_matvec_d::<T, 2, 4>(lev, a, x, y),
        _ => block_matvec_d::<T, 3, 9>(lev, a, x, y),
    }
}

/// y = A x for d = D.
fn block_matvec_d<T: Copy + Into<f64> + Sync, const D: usize, const DD: usize>(
    lev: &Level,
    a: &[T],
    x: &[f64],
    y: &mut [f64],
) {
    y.par_chunks_mut(D * 64)
        .enumerate()
        .for_each(|(chunk, ys)| {
            block_rows::<T, D, DD>(lev, a, x, chunk * 64, ys);
        });
}

/// Rows `first..` of y = A x into `ys`, compiled for AVX2 where the CPU has
/// it ([`block_rows_body`]).
fn block_rows<T: Copy + Into<f64>, const D: usize, const DD: usize>(
    lev: &Level,
    a: &[T],
    x: &[f64],
    first: usize,
    ys: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        unsafe { block_rows_avx2::<T, D, DD>(lev, a, x, first, ys) };
        return;
    }
    block_rows_body::<T, D, DD>(lev, a, x, first, ys);
}

/// [`block_rows_body`] compiled for AVX2 (wider f32 → f64 conversions); the same
/// operations in the same order, so the same bits.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn block_rows_avx2<T: Copy + Into<f64>, const D: usize, const DD: usize>(
    lev: &Level,
    a: &[T],
    x: &[f64],
    first: usize,
    ys: &mut [f64],
) {
    block_rows_body::<T, D, DD>(lev, a, x, first, ys);
}

/// Rows `first..` of y = A x into `ys`.
#[inline(always)]
fn block_rows_body<T: Copy + Into<f64>, const D: usize, const DD: usize>(
    lev: &Level,
    a: &[T],
    x: &[f64],
    first: usize,
    ys: &mut [f64],
) {
    let (row_ptr, col_idx) = (&lev.row_ptr, &lev.col32);
    for (r0, yi) in ys.chunks_exact_mut(D).enumerate() {
        let i = first + r0;
        let mut acc = [0.0f64; D];
        let (rs, re) = (row_ptr[i], row_ptr[i + 1]);
        for (blk, &j) in a[rs * DD..re * DD].chunks_exact(DD).zip(&col_idx[rs..re]) {
            let j = j as usize;
            let xj: &[f64; D] = x[j * D..j * D + D].try_into().expect("D values");
            let blk: &[T; DD] = blk.try_into().expect("D·D values");
            for r in 0..D {
                let mut s = blk[r * D].into() * xj[0];
                for c in 1..D {
                    s += blk[r * D + c].into() * xj[c];
                }
                acc[r] += s;
            }
        }
        yi.copy_from_slice(&acc);
    }
}

/// For each stored block k = (i, j) of a level's pattern (both triangles stored), the
/// index of block (j, i).
pub(super) fn mirror_blocks(lev: &Level) -> Vec<u32> {
    (0..lev.n)
        .into_par_iter()
        .flat_map_iter(|i| {
            (lev.row_ptr[i]..lev.row_ptr[i + 1]).map(move |k| {
                let j = lev.col_idx[k];
                let row = &lev.col_idx[lev.row_ptr[j]..lev.row_ptr[j + 1]];
                // Every level's pattern is symmetric (both triangles stored); k itself
                // where (j, i) is missing.
                row.binary_search(&i).map_or(k, |t| lev.row_ptr[j] + t) as u32
            })
        })
        .collect()
}

/// Ĥ_ij for stored block k = (i, j): P_i V_iᵀ H_ij V_j P_j, with D on the constrained
/// diagonal.
pub(super) fn frame_block(e: &Eliminated, i: usize, k: usize, j: usize, out: &mut [f64]) {
    let d = e.h.dim;
    let f = e.frames;
    match (f.rotation(i), f.rotation(j)) {
        // Most nodes keep the world frame: the block as it is (what the rotation gives).
        (None, None) => out.copy_from_slice(e.h.block(k)),
        (vi, vj) => rotate_block(d, e.h.block(k), vi, vj, out),
    }
    let (mi, mj) = (f.mask[i], f.mask[j]);
    if mi | mj == 0 {
        return;
    }
    for r in 0..d {
        for c in 0..d {
            if mi & (1 << r) != 0 || mj & (1 << c) != 0 {
                out[r * d + c] = 0.0;
            }
        }
        if i == j && mi & (1 << r) != 0 {
            out[r * d + r] = e.diag[i * d + r];
        }
    }
}

/// Factors every cluster block of a level's matrix, `block(i, k, j, out)` giving stored
/// block k = (i, j). Returns the factors and the pivots dropped.
pub(super) fn factor_level(
    lev: &Level,
    d: usize,
    block: impl Fn(usize, usize, usize, &mut [f64]) + Sync,
) -> (Factors, usize) {
    let nc = lev.clusters();
    let offsets = |len: &dyn Fn(usize) -> usize| {
        let mut start = Vec::with_capacity(nc + 1);
        let mut total = 0;
        for c in 0..nc {
            start.push(total);
            total += len((lev.ptr[c + 1] - lev.ptr[c]) * d);
        }
        start.push(total);
        start
    };
    let g_start = offsets(&tiled_len);
    let x_start = offsets(&packed_len);
    let mut g = vec![0.0f32; g_start[nc]];
    let mut x64 = vec![0.0f64; x_start[nc]];
    let g_parts = split_rows(&mut g, &g_start, 1);
    let x_parts = split_rows(&mut x64, &x_start, 1);
    let dropped: usize = g_parts
        .into_par_iter()
        .zip(x_parts)
        .enumerate()
        .map(|(c, (gc, xc))| {
            let items = &lev.items[lev.ptr[c]..lev.ptr[c + 1]];
            let m = items.len() * d;
            let mut a = vec![0.0f64; m * m];
            let mut b = [0.0f64; 9];
            for (p, &i) in items.iter().enumerate() {
                let i = i as usize;
                for k in lev.row_ptr[i]..lev.row_ptr[i + 1] {
                    let j = lev.col_idx[k];
                    if lev.of[j] as usize != c {
                        continue;
                    }
                    let q = lev.pos[j] as usize;
                    block(i, k, j, &mut b[..d * d]);
                    for r in 0..d {
                        for s in 0..d {
                            a[(p * d + r) * m + q * d + s] = b[r * d + s];
                        }
                    }
                }
            }
            let dropped = cholesky_dropping(m, &mut a);
            let x = factor_inverse(m, &a);
            pack_tiled_f32(m, &x, gc);
            pack_lower(m, &x, xc);
            dropped
        })
        .sum();
    (
        Factors {
            g_start,
            g,
            x_start,
            x: x64,
        },
        dropped,
    )
}

/// out = B⁺ src over a level's clusters (their explicit inverses): each cluster's items gathered into its own
/// slice of a cluster-ordered copy and solved there, then scattered back.
/// `tmp` holds the cluster-ordered copy (resized to the level's length).
pub(super) fn solve_level(
    lev: &Level,
    d: usize,
    f: &Inverses,
    src: &[f64],
    out: &mut [f64],
    tmp: &mut Vec<f64>,
) {
    tmp.resize(lev.n * d, 0.0);
    let parts = split_rows(tmp, &lev.ptr, d);
    parts
        .into_par_iter()
        .with_min_len(8)
        .enumerate()
        .for_each(|(c, x)| {
            let items = &lev.items[lev.ptr[c]..lev.ptr[c + 1]];
            let inv = &f.inv[f.start[c]..f.start[c + 1]];
            let m = x.len();
            x.iter_mut().for_each(|v| *v = 0.0);
            // x = Σ_k inv[:, k] b_k (inv is symmetric: its rows are its columns), in a
            // fixed order, column by column: each step is a streaming, vectorised axpy.
            for (p, &i) in items.iter().enumerate() {
                let i = i as usize;
                for a in 0..d {
                    let bk = src[i * d + a];
                    let col = &inv[(p * d + a) * m..(p * d + a + 1) * m];
                    for (xv, cv) in x.iter_mut().zip(col) {
                        *xv += cv * bk;
                    }
                }
            }
        });
    out.par_chunks_mut(d)
        .with_min_len(256)
        .enumerate()
        .for_each(|(i, o)| {
            let at = (lev.ptr[lev.of[i] as usize] + lev.pos[i] as usize) * d;
            o.copy_from_slice(&tmp[at..at + d]);
        });
}
