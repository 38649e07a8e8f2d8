//! The CPU CG's passes over the eliminated system, fused and run on rayon's threads.
//!
//! One CG iteration is three passes over the node rows: the product q = Ĥp with pᵀq
//! (the only pass that reads H), the y and r updates with the point-wise preconditioner,
//! rᵀM⁻¹r, rᵀr and the coarse restriction Zᵀr, and the new direction p with its world
//! copy w = VPp (what the next product gathers, so no node is rotated twice). The
//! product is the matrix-free one of [`crate::core::elimination::apply_eliminated`], operation
//! for operation, so it equals [`Eliminated::apply`] to the bit. H is read as given: an
//! assembled copy of Ĥ in the node frames costs more to build per solve than its product
//! saves (BENCHMARKS.md, "CPU CG against SciPy's Jacobi CG").
//!
//! The rows are split once per solve into chunks of about [`CHUNK_BLOCKS`] stored blocks
//! (balanced by nonzeros, from the pattern alone). Every reduction is summed within a
//! chunk in row order and the chunk sums are added in chunk order: the chunks do not
//! depend on the thread count, so neither does any bit of the result. Threads take
//! chunks from rayon's pool (the global one, or one the caller installs).

use crate::core::constraints::{Frames, NO_ROTATION};
use crate::core::elimination::Eliminated;
use crate::solve::coarse::Coarse;
use crate::solve::options::Preconditioner;
use crate::solve::precond::BuiltPreconditioner;
use rayon::prelude::*;

/// Stored blocks per chunk: a few hundred nodes, small enough for every thread to get
/// many chunks (rayon balances them), large enough that scheduling them costs little.
pub const CHUNK_BLOCKS: usize = 4096;

/// Column indices in 32 bits where the node count allows (halving their bytes), else
/// the pattern's own.
enum Cols<'a> {
    Narrow(Vec<u32>),
    Wide(&'a [usize]),
}

trait Col: Copy + Send + Sync {
    fn ix(self) -> usize;
}
impl Col for u32 {
    #[inline(always)]
    fn ix(self) -> usize {
        self as usize
    }
}
impl Col for usize {
    #[inline(always)]
    fn ix(self) -> usize {
        self
    }
}

/// The coarse correction's per-chunk buffers: chunk c restricts into
/// `buf[start[c]..start[c] + range[c].len()]`, which holds coarse indices `range[c]`.
struct CoarseChunks<'a> {
    coarse: &'a Coarse,
    range: Vec<std::ops::Range<usize>>,
    start: Vec<usize>,
    buf: Vec<f64>,
    /// Zᵀr, then c = E⁺Zᵀr.
    zr: Vec<f64>,
    c: Vec<f64>,
}

/// One CG step for [`Fused::update`]: (α, y, p, q = Ĥp).
pub(crate) type Step<'s> = (f64, &'s mut [f64], &'s [f64], &'s [f64]);

/// The fused passes of one solve.
pub(crate) struct Fused<'a> {
    e: &'a Eliminated<'a>,
    pre: &'a BuiltPreconditioner,
    d: usize,
    cols: Cols<'a>,
    /// Node boundaries of the chunks (chunk c holds nodes bounds[c]..bounds[c+1]).
    bounds: Vec<usize>,
    /// Rows to rotate or mask (any constraint at all).
    constrained: bool,
    /// Run the chunks on rayon's pool (else in order on this thread: the same bits).
    parallel: bool,
    coarse: Option<CoarseChunks<'a>>,
    /// z = M⁻¹r of the last update, for a preconditioner that is not point-wise, and the
    /// V-cycle's vectors (kept for the whole solve).
    full: Option<(Vec<f64>, crate::solve::multilevel::VcycleWork)>,
}

/// Node boundaries of chunks of about [`CHUNK_BLOCKS`] stored blocks (at least one row
/// each), from the row pointers alone.
pub fn partition(row_ptr: &[usize]) -> Vec<usize> {
    let n = row_ptr.len().saturating_sub(1);
    let mut bounds = vec![0];
    let mut start = row_ptr.first().copied().unwrap_or(0);
    for i in 0..n {
        if row_ptr[i + 1] - start >= CHUNK_BLOCKS {
            bounds.push(i + 1);
            start = row_ptr[i + 1];
        }
    }
    if *bounds.last().unwrap_or(&0) != n || n == 0 {
        bounds.push(n);
    }
    bounds
}

/// Splits `v` into the chunks' slices (`per_node` values per node).
fn split<'v>(mut v: &'v mut [f64], bounds: &[usize], per_node: usize) -> Vec<&'v mut [f64]> {
    let mut out = Vec::with_capacity(bounds.len());
    for w in bounds.windows(2) {
        let (a, rest) = std::mem::take(&mut v).split_at_mut((w[1] - w[0]) * per_node);
        out.push(a);
        v = rest;
    }
    out
}

/// The chunks' results in chunk order, from rayon's pool or from this thread.
fn map_chunks<I: Send, T: Send>(
    parallel: bool,
    items: Vec<I>,
    f: impl Fn(I) -> T + Sync + Send,
) -> Vec<T> {
    if parallel {
        // One task per chunk: a thread that the OS preempts holds back at most the chunk
        // it is in, the others take the rest.
        items.into_par_iter().with_max_len(1).map(f).collect()
    } else {
        items.into_iter().map(f).collect()
    }
}

/// Σ in chunk order.
fn ordered_sum(parts: impl IntoIterator<Item = f64>) -> f64 {
    parts.into_iter().fold(0.0, |a, b| a + b)
}

impl<'a> Fused<'a> {
    pub fn new(e: &'a Eliminated<'a>, pre: &'a BuiltPreconditioner) -> Self {
        let h = e.h;
        let bounds = partition(&h.row_ptr);
        let cols = if h.n <= u32::MAX as usize {
            let mut c = vec![0u32; h.col_idx.len()];
            c.par_chunks_mut(1 << 16)
                .zip(h.col_idx.par_chunks(1 << 16))
                .for_each(|(o, i)| {
                    for (o, i) in o.iter_mut().zip(i) {
                        *o = *i as u32;
                    }
                });
            Cols::Narrow(c)
        } else {
            Cols::Wide(&h.col_idx)
        };
        let coarse = pre.coarse().map(|c| {
            let range: Vec<_> = bounds
                .windows(2)
                .map(|w| c.index_range(w[0], w[1]))
                .collect();
            let mut start = Vec::with_capacity(range.len());
            let mut total = 0;
            for r in &range {
                start.push(total);
                total += r.len();
            }
            CoarseChunks {
                coarse: c,
                range,
                start,
                buf: vec![0.0; total],
                zr: vec![0.0; c.k()],
                c: vec![0.0; c.k()],
            }
        });
        Fused {
            e,
            pre,
            d: h.dim,
            cols,
            parallel: bounds.len() > 2 && rayon::current_num_threads() > 1,
            bounds,
            constrained: e.frames.has_constraints(),
            coarse,
            full: pre
                .multilevel_factors()
                .map(|m| (vec![0.0; h.ndof()], m.workspace())),
        }
    }

    /// Whether the product needs the world copy w = VPp (some node is constrained).
    pub fn needs_world(&self) -> bool {
        self.constrained
    }

    /// w = V P v, node by node (the same operations as `apply_mask` then
    /// `from_frame_in_place`).
    pub fn world(&self, v: &[f64], w: &mut [f64]) {
        if !self.constrained {
            w.copy_from_slice(v);
            return;
        }
        let d = self.d;
        let f = self.e.frames;
        let items: Vec<_> = split(w, &self.bounds, d)
            .into_iter()
            .zip(self.bounds.windows(2))
            .collect();
        map_chunks(self.parallel, items, |(wc, b)| {
            let lo = b[0];
            let vc = &v[lo * d..b[1] * d];
            match d {
                2 => world_chunk::<2>(f, lo, vc, wc),
                _ => world_chunk::<3>(f, lo, vc, wc),
            }
        });
    }

    /// q = Ĥ v from v and its world copy `w` (v itself when nothing is constrained), with
    /// (vᵀq, prevᵀq) when `prev` is given ((vᵀq, 0) otherwise).
    pub fn product(&self, v: &[f64], w: &[f64], prev: Option<&[f64]>, q: &mut [f64]) -> (f64, f64) {
        match (&self.cols, self.d) {
            (Cols::Narrow(c), 2) => self.product_d::<2, 4, u32>(c, v, w, prev, q),
            (Cols::Narrow(c), _) => self.product_d::<3, 9, u32>(c, v, w, prev, q),
            (Cols::Wide(c), 2) => self.product_d::<2, 4, usize>(c, v, w, prev, q),
            (Cols::Wide(c), _) => self.product_d::<3, 9, usize>(c, v, w, prev, q),
        }
    }

    fn product_d<const D: usize, const DD: usize, C: Col>(
        &self,
        cols: &[C],
        v: &[f64],
        w: &[f64],
        prev: Option<&[f64]>,
        q: &mut [f64],
    ) -> (f64, f64) {
        let h = self.e.h;
        let f = self.e.frames;
        let diag = &self.e.diag;
        let constrained = self.constrained;
        let items: Vec<_> = split(q, &self.bounds, D)
            .into_iter()
            .zip(self.bounds.windows(2))
            .collect();
        let parts = map_chunks(self.parallel, items, |(qc, b)| {
            let lo = b[0];
            // One partial sum per component: D short chains instead of one long one.
            let (mut vq, mut pq) = ([0.0f64; D], [0.0f64; D]);
            for (i, qi) in (lo..b[1]).zip(qc.chunks_exact_mut(D)) {
                // The block row, as BlockCsr::matvec sums it.
                let (rs, re) = (h.row_ptr[i], h.row_ptr[i + 1]);
                let mut acc = [0.0f64; D];
                for (bk, j) in h.values[rs * D * D..re * D * D]
                    .chunks_exact(DD)
                    .zip(&cols[rs..re])
                {
                    let j = j.ix() * D;
                    let xj: &[f64; D] = w[j..j + D].try_into().expect("D values");
                    let bk: &[f64; DD] = bk.try_into().expect("D·D values");
                    for r in 0..D {
                        // BlockCsr::matvec starts s at 0.0: 0.0 + b·x differs from b·x
                        // only in the sign of a zero, which acc[r] += s (acc never −0)
                        // cannot see, so the bits stay those of Eliminated::apply.
                        let mut s = bk[r * D] * xj[0];
                        for c in 1..D {
                            s += bk[r * D + c] * xj[c];
                        }
                        acc[r] += s;
                    }
                }
                let vi = &v[i * D..i * D + D];
                if constrained {
                    // out = P Vᵀ acc + (I − P) D v, as apply_eliminated does it.
                    if f.rot_index[i] != NO_ROTATION {
                        let rot = f.rotation(i).unwrap_or(&[]);
                        let t = acc;
                        for c in 0..D {
                            acc[c] = (0..D).map(|k| rot[k * D + c] * t[k]).sum();
                        }
                    }
                    let m = f.mask[i];
                    if m != 0 {
                        for a in 0..D {
                            if m & (1 << a) != 0 {
                                acc[a] = diag[i * D + a] * vi[a];
                            }
                        }
                    }
                }
                qi.copy_from_slice(&acc);
                for a in 0..D {
                    vq[a] += vi[a] * acc[a];
                }
                if let Some(p) = prev {
                    let pi = &p[i * D..i * D + D];
                    for a in 0..D {
                        pq[a] += pi[a] * acc[a];
                    }
                }
            }
            (ordered_sum(vq), ordered_sum(pq))
        });
        (
            ordered_sum(parts.iter().map(|p| p.0)),
            ordered_sum(parts.iter().map(|p| p.1)),
        )
    }

    /// With `step` = Some(α): y += αp, r −= αq. Then u = M_J r (point-wise part) gives
    /// (rᵀu, rᵀr), and Zᵀr is restricted into the coarse buffers. The multilevel
    /// preconditioner is not point-wise: its u = M⁻¹r is applied to the whole updated r
    /// and kept for [`Fused::direction`]. Returns (rᵀu, rᵀr).
    pub fn update(&mut self, step: Option<Step<'_>>, r: &mut [f64]) -> (f64, f64) {
        let d = self.d;
        let point = Point::of(self.pre, None);
        let (ys, alpha, p, q) = match step {
            Some((a, y, p, q)) => (Some(split(y, &self.bounds, d)), a, p, q),
            None => (None, 0.0, &[][..], &[][..]),
        };
        let mut ys = ys.map(|v| v.into_iter());
        // Per-chunk coarse buffers, with the first coarse index each holds.
        let (cc, mut bufs): (Option<&Coarse>, Vec<(&mut [f64], usize)>) = match self.coarse.as_mut()
        {
            Some(c) => {
                let mut out = Vec::with_capacity(c.range.len());
                let mut rest: &mut [f64] = &mut c.buf;
                for rg in &c.range {
                    let (a, b) = std::mem::take(&mut rest).split_at_mut(rg.len());
                    out.push((a, rg.start));
                    rest = b;
                }
                (Some(c.coarse), out)
            }
            None => (None, Vec::new()),
        };
        let mut bufs_it = bufs.drain(..);
        let items: Vec<_> = split(r, &self.bounds, d)
            .into_iter()
            .zip(self.bounds.windows(2))
            .map(|(rc, b)| (rc, b, ys.as_mut().and_then(|it| it.next()), bufs_it.next()))
            .collect();
        let parts = map_chunks(self.parallel, items, |(rc, b, yc, buf)| {
            let lo = b[0];
            let off = lo * d;
            let m = rc.len();
            if let Some(yc) = yc {
                let (pc, qc) = (&p[off..off + m], &q[off..off + m]);
                for k in 0..m {
                    yc[k] += alpha * pc[k];
                    rc[k] -= alpha * qc[k];
                }
            }
            let rc: &[f64] = rc;
            let rr = sum_lanes(m, |k| rc[k] * rc[k]);
            let ru = match point {
                Point::Identity => rr,
                // Summed below, once z = M⁻¹r is known.
                Point::Full(_) => 0.0,
                Point::Diagonal(dg) => {
                    let dg = &dg[off..off + m];
                    sum_lanes(m, |k| rc[k] * (rc[k] * dg[k]))
                }
                Point::Blocks(mb) => match d {
                    2 => block_dot::<2>(&mb[lo * 4..], rc),
                    _ => block_dot::<3>(&mb[lo * 9..], rc),
                },
            };
            if let (Some(c), Some((buf, base))) = (cc, buf) {
                buf.iter_mut().for_each(|v| *v = 0.0);
                c.restrict_nodes(rc, lo, base, buf);
            }
            (ru, rr)
        });
        let rr = ordered_sum(parts.iter().map(|p| p.1));
        if let (Some((z, work)), Some(m)) = (self.full.as_mut(), self.pre.multilevel_factors()) {
            let r: &[f64] = r;
            m.apply_with(r, z, work);
            let z: &[f64] = z;
            let items: Vec<_> = self.bounds.windows(2).collect();
            let dots = map_chunks(self.parallel, items, |b| {
                let (lo, hi) = (b[0] * d, b[1] * d);
                sum_lanes(hi - lo, |k| r[lo + k] * z[lo + k])
            });
            return (ordered_sum(dots), rr);
        }
        (ordered_sum(parts.iter().map(|p| p.0)), rr)
    }
}

impl Fused<'_> {
    /// c = E⁺Zᵀr from the chunks' restrictions of the last [`Fused::update`] (summed in
    /// chunk order); returns (Zᵀr)ᵀc = rᵀZE⁺Zᵀr, the coarse part of rᵀM⁻¹r (0 without a
    /// coarse space).
    pub fn coarse_solve(&mut self) -> f64 {
        let parallel = self.parallel;
        let Some(cc) = self.coarse.as_mut() else {
            return 0.0;
        };
        let CoarseChunks {
            coarse,
            range,
            start,
            buf,
            zr,
            c,
        } = cc;
        zr.iter_mut().for_each(|v| *v = 0.0);
        for (rg, &st) in range.iter().zip(start.iter()) {
            for (z, b) in zr[rg.clone()].iter_mut().zip(&buf[st..st + rg.len()]) {
                *z += b;
            }
        }
        let k = zr.len();
        let zr: &[f64] = zr;
        // Each entry of c is one row's dot product: the same bits on any thread.
        if parallel && k >= 96 {
            c.par_iter_mut()
                .zip(coarse.einv.par_chunks_exact(k))
                .for_each(|(ca, row)| *ca = crate::core::linalg::dot(row, zr));
        } else {
            for (ca, row) in c.iter_mut().zip(coarse.einv.chunks_exact(k)) {
                *ca = crate::core::linalg::dot(row, zr);
            }
        }
        crate::core::linalg::dot(zr, c)
    }

    /// p_new = M_J r + Z c + β p_old (with `beta` None: p_new = M⁻¹r), c from
    /// [`Fused::coarse_solve`], and its world copy `w` = V P p_new when given.
    pub fn direction(
        &self,
        beta: Option<f64>,
        r: &[f64],
        p_old: &[f64],
        p_new: &mut [f64],
        w: Option<&mut [f64]>,
    ) {
        let d = self.d;
        let point = Point::of(self.pre, self.full.as_ref().map(|(z, _)| &z[..]));
        let f = self.e.frames;
        let coarse = self.coarse.as_ref().map(|c| (c.coarse, &c.c[..]));
        let mut ws = w.map(|w| split(w, &self.bounds, d).into_iter());
        let items: Vec<_> = split(p_new, &self.bounds, d)
            .into_iter()
            .zip(self.bounds.windows(2))
            .map(|(pc, b)| (pc, b, ws.as_mut().and_then(|it| it.next())))
            .collect();
        map_chunks(self.parallel, items, |(pc, b, wc)| {
            let lo = b[0];
            let off = lo * d;
            let m = pc.len();
            let rc = &r[off..off + m];
            match (point, coarse, beta) {
                // The common case in one loop: (r·d) + βp rounds as the steps below do.
                (Point::Diagonal(dg), None, Some(beta)) => {
                    let (dg, po) = (&dg[off..off + m], &p_old[off..off + m]);
                    for k in 0..m {
                        pc[k] = rc[k] * dg[k] + beta * po[k];
                    }
                }
                _ => {
                    match point {
                        Point::Identity => pc.copy_from_slice(rc),
                        Point::Full(z) => pc.copy_from_slice(&z[off..off + m]),
                        Point::Diagonal(dg) => {
                            for (v, (x, g)) in pc.iter_mut().zip(rc.iter().zip(&dg[off..off + m])) {
                                *v = x * g;
                            }
                        }
                        Point::Blocks(mb) => match d {
                            2 => block_apply::<2>(&mb[lo * 4..], rc, pc),
                            _ => block_apply::<3>(&mb[lo * 9..], rc, pc),
                        },
                    }
                    if let Some((cs, c)) = coarse {
                        cs.prolong_nodes(c, lo, pc);
                    }
                    if let Some(beta) = beta {
                        for (v, po) in pc.iter_mut().zip(&p_old[off..off + m]) {
                            *v += beta * po;
                        }
                    }
                }
            }
            if let Some(wc) = wc {
                match d {
                    2 => world_chunk::<2>(f, lo, pc, wc),
                    _ => world_chunk::<3>(f, lo, pc, wc),
                }
            }
        });
    }
}

/// w = V P v over a chunk's nodes lo.. (`v`, `w` hold their components): a copy at
/// free unrotated nodes, masked and rotated where the node is constrained.
#[inline]
fn world_chunk<const D: usize>(f: &Frames, lo: usize, v: &[f64], w: &mut [f64]) {
    let hi = lo + v.len() / D;
    let (mask, rot) = (&f.mask[lo..hi], &f.rot_index[lo..hi]);
    for (((vi, wi), &m), &ri) in v
        .chunks_exact(D)
        .zip(w.chunks_exact_mut(D))
        .zip(mask)
        .zip(rot)
    {
        if m == 0 && ri == NO_ROTATION {
            wi.copy_from_slice(vi);
            continue;
        }
        let mut t = [0.0f64; D];
        for a in 0..D {
            t[a] = if m & (1 << a) != 0 { 0.0 } else { vi[a] };
        }
        if ri == NO_ROTATION {
            wi.copy_from_slice(&t);
        } else {
            let v = &f.rotations[ri as usize * D * D..(ri as usize + 1) * D * D];
            for k in 0..D {
                wi[k] = (0..D).map(|c| v[k * D + c] * t[c]).sum();
            }
        }
    }
}

/// The point-wise part of the preconditioner, matched once per pass.
#[derive(Clone, Copy)]
enum Point<'p> {
    Identity,
    /// 1/diag, per component.
    Diagonal(&'p [f64]),
    /// D×D inverse blocks, per node.
    Blocks(&'p [f64]),
    /// Not point-wise: z = M⁻¹r computed over the whole vector (`full`, when known).
    Full(&'p [f64]),
}

impl<'p> Point<'p> {
    fn of(pre: &'p BuiltPreconditioner, full: Option<&'p [f64]>) -> Self {
        match pre.kind() {
            Preconditioner::None => Point::Identity,
            Preconditioner::Multilevel => Point::Full(full.unwrap_or(&[])),
            Preconditioner::Jacobi => Point::Diagonal(pre.data()),
            Preconditioner::BlockJacobi => Point::Blocks(pre.data()),
        }
    }
}

/// u = M r node by node, M the D×D blocks from the chunk's first node on.
#[inline]
fn block_apply<const D: usize>(m: &[f64], r: &[f64], u: &mut [f64]) {
    for ((mi, ri), ui) in m
        .chunks_exact(D * D)
        .zip(r.chunks_exact(D))
        .zip(u.chunks_exact_mut(D))
    {
        for a in 0..D {
            let mut s = 0.0;
            for b in 0..D {
                s += mi[a * D + b] * ri[b];
            }
            ui[a] = s;
        }
    }
}

/// rᵀM r over a chunk, M the D×D blocks from the chunk's first node on.
#[inline]
fn block_dot<const D: usize>(m: &[f64], r: &[f64]) -> f64 {
    let mut t = 0.0;
    let mut u = [0.0f64; D];
    for (mi, ri) in m.chunks_exact(D * D).zip(r.chunks_exact(D)) {
        block_apply::<D>(mi, ri, &mut u);
        for a in 0..D {
            t += ri[a] * u[a];
        }
    }
    t
}

/// Σ f(k) for k < n in four interleaved partial sums (a fixed order, so the same bits
/// every time; the four chains hide the latency of the additions).
#[inline(always)]
fn sum_lanes(n: usize, f: impl Fn(usize) -> f64) -> f64 {
    let mut l = [0.0f64; 4];
    let m = n / 4 * 4;
    let mut k = 0;
    while k < m {
        l[0] += f(k);
        l[1] += f(k + 1);
        l[2] += f(k + 2);
        l[3] += f(k + 3);
        k += 4;
    }
    let mut t = (l[0] + l[1]) + (l[2] + l[3]);
    for k in m..n {
        t += f(k);
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cases::generate::{random_system, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn partition_covers_the_rows_and_balances_blocks() {
        let s = random_system(&SystemSpec::with_nodes(3, 4096, 3));
        let b = partition(&s.h.row_ptr);
        assert_eq!((b[0], *b.last().unwrap()), (0, s.h.n));
        assert!(b.len() > 3, "several chunks: {}", b.len() - 1);
        let rp = &s.h.row_ptr;
        let most_per_row = (0..s.h.n).map(|i| rp[i + 1] - rp[i]).max().unwrap();
        for w in b.windows(2) {
            assert!(w[1] > w[0]);
            let blocks = rp[w[1]] - rp[w[0]];
            // Every chunk but the last closes on the first row reaching CHUNK_BLOCKS.
            assert!(blocks < CHUNK_BLOCKS + most_per_row);
            if w[1] != s.h.n {
                assert!(blocks >= CHUNK_BLOCKS);
            }
        }
        assert_eq!(partition(&[0]), vec![0, 0]);
    }

    #[test]
    fn fused_product_equals_the_matrix_free_apply_to_the_bit() {
        for (dim, nodes, seed) in [(3, 3000, 5u64), (2, 6000, 6)] {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            assert!(s.frames.has_rotation());
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
            let pre = BuiltPreconditioner::new(&e, Preconditioner::Jacobi);
            let f = Fused::new(&e, &pre);
            let n = e.ndof();
            let v: Vec<f64> = (0..n).map(|k| ((k * 7919) % 23) as f64 - 11.0).collect();
            let mut w = vec![0.0; n];
            let mut q = vec![0.0; n];
            f.world(&v, &mut w);
            f.product(&v, &w, None, &mut q);
            let mut reference = vec![0.0; n];
            let mut work = vec![0.0; 2 * n];
            e.apply(&v, &mut reference, &mut work);
            assert_eq!(bits(&q), bits(&reference));
        }
    }
}
