//! The assembly's tables, built once per model, and its gathers: the Hessian's block
//! pattern, per block (and per node) the element slots that add into it in (set, element)
//! order, the node rows each bounded pass of elements touches, and one pass's gather into
//! h. Each block sums its elements one by one in that order whatever the passes and
//! threads: the same bits on any number of threads.

use super::element_set::ElementSet;
use crate::core::sparse::BlockCsr;
use crate::sim::memory::{try_vec, AllocError};
use rayon::prelude::*;

/// Elements per task of the parallel element loops. The chunks are fixed (they do not
/// depend on the thread count) and each one is reduced in element order, so energies,
/// gradients and Hessians come out bitwise the same on any number of threads.
pub(super) const CHUNK: usize = 1024;

/// Element blocks (d×d) of the Hessian assembly's element buffer: one pass of the
/// assembly computes at most this many (4.7 MB in 3D) before they are gathered.
pub(super) const HESS_BUFFER_BLOCKS: usize = 1 << 16;

/// Element node vectors (d entries) of the gradient's element buffer: one pass computes
/// at most this many before they are gathered.
pub(super) const GRAD_BUFFER_NODES: usize = 1 << 16;

/// Blocks (of the Hessian) or nodes (of the gradient) per task of the parallel gathers.
pub(super) const GATHER_CHUNK: usize = 4096;

/// What a block of the Hessian starts from when the assembly first reaches it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum BlockStart {
    /// Its values (the assembly adds to h).
    Values,
    /// Zero, plus the node's lumped mass on a diagonal block (h = M + the elements).
    Mass,
}

/// One pass's gather into the blocks `k0..` of h: the pass's element blocks `buf` are
/// the slots `lo..hi`.
pub(super) struct GatherPass<'a> {
    pub(super) gather: &'a Gather,
    /// The pattern's block columns and the nodes' lumped masses.
    pub(super) col_idx: &'a [usize],
    pub(super) mass: &'a [f64],
    pub(super) k0: usize,
    pub(super) buf: &'a [f64],
    pub(super) lo: usize,
    pub(super) hi: usize,
    pub(super) scale: f64,
    pub(super) start: BlockStart,
}

impl GatherPass<'_> {
    /// Every block of `values` (its cursor in `cursor`) adds the pass's slots in its
    /// gather list, in order, in registers: the block is read and written once per pass
    /// (and not read on its first pass with [`BlockStart::Mass`]). The same sums in the
    /// same order as adding each slot into h, hence the same bits.
    pub(super) fn run<const D: usize>(&self, values: &mut [f64], cursor: &mut [u32]) {
        let (gt, col_idx) = (self.gather, self.col_idx);
        let (lo, hi, scale, buf) = (self.lo, self.hi, self.scale, self.buf);
        values
            .par_chunks_mut(D * D)
            .zip(cursor.par_iter_mut())
            .enumerate()
            .with_min_len(GATHER_CHUNK)
            .for_each(|(i, (blk, cur))| {
                let k = self.k0 + i;
                let end = gt.hess_ptr[k + 1];
                let mut c = *cur as usize;
                if c >= end || (gt.hess_src[c] as usize >> 1) >= hi {
                    return;
                }
                let mut acc = [[0.0f64; D]; D];
                if self.start == BlockStart::Mass && c == gt.hess_ptr[k] {
                    let j = col_idx[k];
                    if gt.diag[j] == k {
                        for (a, row) in acc.iter_mut().enumerate() {
                            row[a] = 0.0 + self.mass[j];
                        }
                    }
                } else {
                    for (r, row) in acc.iter_mut().enumerate() {
                        row.copy_from_slice(&blk[r * D..(r + 1) * D]);
                    }
                }
                while c < end {
                    let src = gt.hess_src[c] as usize;
                    let slot = src >> 1;
                    if slot >= hi {
                        break;
                    }
                    let m = &buf[(slot - lo) * D * D..(slot - lo + 1) * D * D];
                    if src & 1 == 0 {
                        for (r, row) in acc.iter_mut().enumerate() {
                            for (cc, v) in row.iter_mut().enumerate() {
                                *v += scale * m[r * D + cc];
                            }
                        }
                    } else {
                        for (r, row) in acc.iter_mut().enumerate() {
                            for (cc, v) in row.iter_mut().enumerate() {
                                *v += scale * m[cc * D + r];
                            }
                        }
                    }
                    c += 1;
                }
                for (r, row) in acc.iter().enumerate() {
                    blk[r * D..(r + 1) * D].copy_from_slice(row);
                }
                *cur = c as u32;
            });
    }
}

/// Where every element's contributions go, built once per model: per block of the
/// Hessian's pattern (and per node of the gradient) the element slots that add into it,
/// in the order a sequential loop over sets and elements would add them.
#[derive(Debug, Clone)]
pub(super) struct Gather {
    /// Per set: its first slot in the element Hessian buffer (upper node pairs a ≤ b,
    /// one d×d block each) and in the element gradient buffer (one d-vector per node).
    pub(super) hess_base: Vec<usize>,
    pub(super) grad_base: Vec<usize>,
    /// Hessian: block k of the pattern sums the slots `hess_src[hess_ptr[k]..hess_ptr[k+1]]`;
    /// a slot is stored as 2·slot + t, t = 1 when it is read transposed (a > b).
    pub(super) hess_ptr: Vec<usize>,
    pub(super) hess_src: Vec<u32>,
    /// Gradient: node i sums the slots `grad_src[grad_ptr[i]..grad_ptr[i+1]]`.
    pub(super) grad_ptr: Vec<usize>,
    pub(super) grad_src: Vec<u32>,
    /// Per node: its diagonal block in the pattern.
    pub(super) diag: Vec<usize>,
    /// Per set, per pass of the Hessian's ([`hess_pass`] elements) and of the gradient's
    /// ([`grad_pass`]) assembly: the node rows its elements touch, `lo..=hi` (the
    /// gathers visit those rows only).
    pub(super) hess_rows: Vec<Vec<(usize, usize)>>,
    pub(super) grad_rows: Vec<Vec<(usize, usize)>>,
}

/// Elements per pass of the Hessian's assembly of `s`: whole chunks, at most
/// [`HESS_BUFFER_BLOCKS`] element blocks.
pub(super) fn hess_pass(s: &ElementSet) -> usize {
    let np = s.arity() * (s.arity() + 1) / 2;
    (HESS_BUFFER_BLOCKS / np / CHUNK).max(1) * CHUNK
}

/// Elements per pass of the gradient's assembly of `s`: whole chunks, at most
/// [`GRAD_BUFFER_NODES`] element node vectors.
pub(super) fn grad_pass(s: &ElementSet) -> usize {
    (GRAD_BUFFER_NODES / s.arity() / CHUNK).max(1) * CHUNK
}

/// Per pass of `per_pass` elements of `s`, the smallest and largest node its elements
/// hold ((1, 0) for a pass without nodes).
fn pass_rows(s: &ElementSet, per_pass: usize) -> Vec<(usize, usize)> {
    (0..s.len())
        .step_by(per_pass)
        .map(|e0| {
            let (mut lo, mut hi) = (usize::MAX, 0);
            for e in e0..(e0 + per_pass).min(s.len()) {
                for &a in s.nodes(e) {
                    lo = lo.min(a);
                    hi = hi.max(a);
                }
            }
            if lo > hi {
                (1, 0)
            } else {
                (lo, hi)
            }
        })
        .collect()
}

/// The Hessian's block pattern: every node's diagonal block and the blocks of every
/// element's node pairs, columns sorted, no values; built in flat arrays allocated
/// fallibly.
pub(super) fn block_pattern(
    dim: usize,
    n: usize,
    sets: &[ElementSet],
) -> Result<BlockCsr, AllocError> {
    const WHAT: &str = "the Hessian's block pattern";
    // Room per row for its diagonal and every element pair, before duplicates go.
    let mut ptr = try_vec(n + 1, 0usize, WHAT)?;
    for s in sets {
        for e in 0..s.len() {
            for &a in s.nodes(e) {
                ptr[a + 1] += s.arity();
            }
        }
    }
    for i in 0..n {
        ptr[i + 1] += ptr[i] + 1;
    }
    let mut cols = try_vec(ptr[n], 0usize, WHAT)?;
    let mut next = try_vec(n, 0usize, WHAT)?;
    for i in 0..n {
        cols[ptr[i]] = i;
        next[i] = ptr[i] + 1;
    }
    for s in sets {
        for e in 0..s.len() {
            let nodes = s.nodes(e);
            for &a in nodes {
                for &b in nodes {
                    cols[next[a]] = b;
                    next[a] += 1;
                }
            }
        }
    }
    drop(next);
    // Sort and deduplicate each row, packing the rows to the front.
    let mut row_ptr = try_vec(n + 1, 0usize, WHAT)?;
    let mut w = 0;
    for i in 0..n {
        let row = &mut cols[ptr[i]..ptr[i + 1]];
        row.sort_unstable();
        let mut last = usize::MAX;
        for k in ptr[i]..ptr[i + 1] {
            let c = cols[k];
            if c != last {
                cols[w] = c;
                w += 1;
                last = c;
            }
        }
        row_ptr[i + 1] = w;
    }
    drop(ptr);
    cols.truncate(w);
    cols.shrink_to_fit();
    Ok(BlockCsr {
        dim,
        n,
        row_ptr,
        col_idx: cols,
        values: Vec::new(),
    })
}

/// Upper node pairs (a, b), a ≤ b, of an element with `ar` nodes, in slot order.
fn upper_pairs(ar: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..ar).flat_map(move |a| (a..ar).map(move |b| (a, b)))
}

impl Gather {
    pub(super) fn new(
        n: usize,
        sets: &[ElementSet],
        pattern: &BlockCsr,
    ) -> Result<Self, AllocError> {
        const WHAT: &str = "the assembly's gather tables";
        let nb = pattern.nnz_blocks();
        let (mut hess_base, mut grad_base) = (Vec::new(), Vec::new());
        let (mut hs, mut gs) = (0usize, 0usize);
        let mut hess_count = try_vec(nb + 1, 0usize, WHAT)?;
        let mut grad_count = try_vec(n + 1, 0usize, WHAT)?;
        // Every element's ordered node pairs' blocks (a·arity + b), searched once: the
        // count below and the fill after it read them.
        let pairs: usize = sets.iter().map(|s| s.len() * s.arity() * s.arity()).sum();
        let mut block_of = try_vec(pairs, 0u32, WHAT)?;
        if nb > u32::MAX as usize {
            return Err(AllocError {
                what: WHAT.to_string(),
                bytes: (nb as u64).saturating_mul(8),
                nodes: None,
            });
        }
        let mut at = 0;
        for s in sets {
            let ar = s.arity();
            hess_base.push(hs);
            grad_base.push(gs);
            hs += s.len() * ar * (ar + 1) / 2;
            gs += s.len() * ar;
            for e in 0..s.len() {
                let nodes = s.nodes(e);
                for &a in nodes {
                    grad_count[a + 1] += 1;
                    for &b in nodes {
                        let k = pattern
                            .find(a, b)
                            .expect("pattern holds every element pair");
                        hess_count[k + 1] += 1;
                        block_of[at] = k as u32;
                        at += 1;
                    }
                }
            }
        }
        for k in 0..nb {
            hess_count[k + 1] += hess_count[k];
        }
        for i in 0..n {
            grad_count[i + 1] += grad_count[i];
        }
        let mut hess_ptr = try_vec(nb + 1, 0usize, WHAT)?;
        hess_ptr.copy_from_slice(&hess_count);
        let mut grad_ptr = try_vec(n + 1, 0usize, WHAT)?;
        grad_ptr.copy_from_slice(&grad_count);
        // Slots are stored as u32 (half the table): 2·slot + 1 must fit, and so must the
        // table's length (at most 2·slots), which holds below 2³¹ element blocks, far
        // beyond any mesh whose blocks fit in memory.
        if 2 * hs + 1 > u32::MAX as usize {
            return Err(AllocError {
                what: WHAT.to_string(),
                bytes: (hs as u64).saturating_mul(8),
                nodes: None,
            });
        }
        let mut hess_src = try_vec(hess_ptr[nb], 0u32, WHAT)?;
        let mut grad_src = try_vec(grad_ptr[n], 0u32, WHAT)?;
        // Filled in set and element order: each block's (node's) list is in the order of
        // the sequential loop.
        let (mut hnext, mut gnext) = (hess_count, grad_count);
        let mut at = 0;
        for (si, s) in sets.iter().enumerate() {
            let ar = s.arity();
            let np = ar * (ar + 1) / 2;
            for e in 0..s.len() {
                let nodes = s.nodes(e);
                let blocks = &block_of[at..at + ar * ar];
                at += ar * ar;
                for (p, (a, b)) in upper_pairs(ar).enumerate() {
                    let slot = hess_base[si] + e * np + p;
                    let k = blocks[a * ar + b] as usize;
                    hess_src[hnext[k]] = (2 * slot) as u32;
                    hnext[k] += 1;
                    if a != b {
                        let k = blocks[b * ar + a] as usize;
                        hess_src[hnext[k]] = (2 * slot + 1) as u32;
                        hnext[k] += 1;
                    }
                }
                for (a, &node) in nodes.iter().enumerate() {
                    grad_src[gnext[node]] = (grad_base[si] + e * ar + a) as u32;
                    gnext[node] += 1;
                }
            }
        }
        let mut diag = try_vec(n, 0usize, WHAT)?;
        for (i, k) in diag.iter_mut().enumerate() {
            *k = pattern
                .diag_index(i)
                .expect("every node has a diagonal block");
        }
        drop(block_of);
        Ok(Gather {
            hess_base,
            grad_base,
            hess_ptr,
            hess_src,
            grad_ptr,
            grad_src,
            diag,
            hess_rows: sets.iter().map(|s| pass_rows(s, hess_pass(s))).collect(),
            grad_rows: sets.iter().map(|s| pass_rows(s, grad_pass(s))).collect(),
        })
    }
}
