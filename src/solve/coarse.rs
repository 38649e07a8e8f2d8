//! A coarse correction on the rigid translations, added to Jacobi or block-Jacobi:
//! M⁻¹r = M_J⁻¹r + Z E⁺ Zᵀr, with Z the d rigid translations in frame coordinates
//! (Z_i = P_i V_iᵀ, one column per axis) and E = ZᵀĤZ (d×d, pseudo-inverted).
//!
//! Why: when a body is free to translate (no sticky node, or only slip planes), the
//! smallest eigenvalues of Ĥ = M/h² + K belong to its translations (K annihilates them),
//! and a point-wise preconditioner cannot see them: κ(M_J⁻¹Ĥ) ≈ λ_max(K)/m grows as the
//! time step grows or the stiffness rises. The correction solves those d modes exactly,
//! so CG pays for κ of the rest of the spectrum only (kappa-1e6 at 81k DOFs: 663 → 450
//! iterations in f64, STABILITY.md). It needs no geometry (rotations would need node
//! positions, which an `.mtx` system does not carry), costs d extra dot products and d
//! multiply-adds per component and iteration, and keeps M⁻¹ symmetric positive definite
//! (E⁺ is positive semidefinite), so CG's theory is untouched.

mod einv;
pub use einv::{
    aggregates_einv_from_galerkin, aggregates_einv_with_basis, pseudo_inverse, AggregateBasis,
    NotPositive,
};
use einv::{symmetrize, PINV_RTOL};

/// A built coarse correction: Z node by node and E⁺. Z_i = s_i⁻¹ P_i V_iᵀ (s_i the node
/// scale of an equilibrated system, else 1). Applying it is one dense pass over r and one
/// over z as if every Z_i were s_i⁻¹·I, then a fix-up at the masked or rotated nodes only:
/// no basis vectors, no per-node branch in the dense passes.
#[derive(Debug, Clone)]
pub struct Coarse {
    dim: usize,
    n_nodes: usize,
    /// (node, P_i V_iᵀ) of the masked or rotated nodes, d×d row-major (row = frame
    /// component, column = axis), by node.
    special: Vec<(usize, [f64; 9])>,
    /// 1/s_i per node for an equilibrated system SĤS.
    inv_scale: Option<Vec<f64>>,
    /// The aggregates; `None`: one aggregate of every node (the rigid translations).
    agg: Option<Aggregation>,
    /// E⁺, k×k row-major (k = d × the number of aggregates).
    pub einv: Vec<f64>,
}

/// Nodes per aggregate that [`Aggregation::build`] aims at.
pub const AGGREGATE_NODES: usize = 64;
/// The most aggregates [`Aggregation::build`] makes (E⁺ is dense, (d·count)² values, and
/// applied once per CG iteration; larger systems get larger aggregates).
pub const MAX_AGGREGATES: usize = 128;
/// The aggregate of a node whose every component is constrained (its Z_i is zero).
pub const NO_AGGREGATE: u32 = u32::MAX;

/// A partition of the nodes into connected aggregates, from the graph of Ĥ's blocks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Aggregation {
    /// The aggregate of each node ([`NO_AGGREGATE`]: none, as [`Aggregation::single`]
    /// leaves a fully constrained node).
    pub of_node: Vec<u32>,
    /// The number of aggregates.
    pub count: usize,
}

impl Aggregation {
    /// Greedy breadth-first aggregation: each aggregate grows from a seed over unassigned
    /// neighbours until it holds `target` = max([`AGGREGATE_NODES`], nodes /
    /// [`MAX_AGGREGATES`]) nodes; the next seed is taken from the last aggregates' unassigned
    /// neighbours, so aggregates tile the mesh in a wave (compact, like cubes of 4³ nodes on
    /// a hexahedral grid), and an aggregate left below target/4 is merged into the neighbour
    /// it shares the most edges with. Deterministic (node order only).
    ///
    /// Every node joins an aggregate, constrained or not: a fully constrained node's Z_i is
    /// zero, so it adds nothing to Zᵀr or E, and an aggregate of such nodes only has an
    /// empty range of its translations' Gram matrix (no column of W). So the aggregates
    /// depend on H's pattern alone: one aggregation serves every constraint set of a mesh
    /// (a Newton loop's moving nodes snap without re-aggregating, and the device uploads
    /// the aggregates' index arrays once).
    pub fn build(h: &crate::core::sparse::BlockCsr) -> Self {
        Self::from_pattern(&h.row_ptr, &h.col_idx)
    }

    /// [`Aggregation::build`] on a block pattern given by its row pointers and column
    /// indices (the device assembly's, which has no host values).
    pub fn from_pattern(row_ptr: &[usize], col_idx: &[usize]) -> Self {
        use std::collections::VecDeque;
        let n = row_ptr.len().saturating_sub(1);
        let free = vec![true; n];
        let target = AGGREGATE_NODES.max(n.div_ceil(MAX_AGGREGATES));
        let neighbours = |i: usize| col_idx[row_ptr[i]..row_ptr[i + 1]].iter().copied();
        let mut of = vec![NO_AGGREGATE; n];
        let mut sizes: Vec<usize> = Vec::new();
        let mut seeds = VecDeque::new();
        let mut bfs = VecDeque::new();
        let mut members = Vec::new();
        let mut next = 0usize;
        loop {
            let seed = loop {
                match seeds.pop_front() {
                    Some(s) if of[s] == NO_AGGREGATE => break Some(s),
                    Some(_) => continue,
                    None => {
                        while next < n && (of[next] != NO_AGGREGATE || !free[next]) {
                            next += 1;
                        }
                        break (next < n).then_some(next);
                    }
                }
            };
            let Some(seed) = seed else { break };
            let id = sizes.len() as u32;
            of[seed] = id;
            members.clear();
            members.push(seed);
            bfs.clear();
            bfs.push_back(seed);
            'grow: while let Some(i) = bfs.pop_front() {
                for j in neighbours(i) {
                    if members.len() >= target {
                        break 'grow;
                    }
                    if of[j] == NO_AGGREGATE && free[j] {
                        of[j] = id;
                        members.push(j);
                        bfs.push_back(j);
                    }
                }
            }
            sizes.push(members.len());
            for &i in &members {
                seeds.extend(neighbours(i).filter(|&j| of[j] == NO_AGGREGATE && free[j]));
            }
        }
        // Merge the small leftovers into their best-connected neighbour.
        let mut nodes_of: Vec<Vec<usize>> = vec![Vec::new(); sizes.len()];
        for (i, &a) in of.iter().enumerate() {
            if a != NO_AGGREGATE {
                nodes_of[a as usize].push(i);
            }
        }
        for a in 0..nodes_of.len() {
            if nodes_of[a].is_empty() || 4 * nodes_of[a].len() >= target {
                continue;
            }
            let mut links: Vec<(u32, usize)> = Vec::new();
            for &i in &nodes_of[a] {
                for j in neighbours(i) {
                    let b = of[j];
                    if b == NO_AGGREGATE || b == a as u32 {
                        continue;
                    }
                    match links.iter_mut().find(|(c, _)| *c == b) {
                        Some(l) => l.1 += 1,
                        None => links.push((b, 1)),
                    }
                }
            }
            // Most links, then the lowest id: deterministic.
            let Some(&(b, _)) = links
                .iter()
                .max_by(|x, y| x.1.cmp(&y.1).then(y.0.cmp(&x.0)))
            else {
                continue;
            };
            let moved = std::mem::take(&mut nodes_of[a]);
            for &i in &moved {
                of[i] = b;
            }
            nodes_of[b as usize].extend(moved);
        }
        // Compact ids in order of first node.
        let mut new_id = vec![NO_AGGREGATE; nodes_of.len()];
        let mut count = 0u32;
        for a in of.iter_mut().filter(|a| **a != NO_AGGREGATE) {
            let slot = &mut new_id[*a as usize];
            if *slot == NO_AGGREGATE {
                *slot = count;
                count += 1;
            }
            *a = *slot;
        }
        // Free nodes scattered among constrained ones leave isolated aggregates that no
        // edge can merge: group consecutive ids (Z's columns need no connectivity) so E
        // stays within MAX_AGGREGATES² blocks.
        let mut count = count as usize;
        if count > MAX_AGGREGATES {
            for a in of.iter_mut().filter(|a| **a != NO_AGGREGATE) {
                *a = (*a as usize * MAX_AGGREGATES / count) as u32;
            }
            count = MAX_AGGREGATES;
        }
        Aggregation { of_node: of, count }
    }

    /// One aggregate of every node that is not fully constrained (the rigid translations).
    pub fn single(frames: &crate::core::constraints::Frames) -> Self {
        let full = (1u32 << frames.dim) - 1;
        let of_node = (0..frames.n_nodes)
            .map(|i| {
                if u32::from(frames.mask[i]) & full == full {
                    NO_AGGREGATE
                } else {
                    0
                }
            })
            .collect();
        Aggregation { of_node, count: 1 }
    }

    /// The nodes of each aggregate as (offsets, nodes): aggregate a holds
    /// `nodes[offsets[a]..offsets[a + 1]]`, in increasing order.
    pub fn lists(&self) -> (Vec<u32>, Vec<u32>) {
        let mut offsets = vec![0u32; self.count + 1];
        for &a in self.of_node.iter().filter(|a| **a != NO_AGGREGATE) {
            offsets[a as usize + 1] += 1;
        }
        for a in 0..self.count {
            offsets[a + 1] += offsets[a];
        }
        let mut fill = offsets.clone();
        let mut nodes = vec![0u32; offsets[self.count] as usize];
        for (i, &a) in self.of_node.iter().enumerate() {
            if a != NO_AGGREGATE {
                let f = &mut fill[a as usize];
                nodes[*f as usize] = i as u32;
                *f += 1;
            }
        }
        (offsets, nodes)
    }
}

/// Z_i = P_i V_iᵀ of node i (d×d row-major: row = frame component, column = axis), or
/// `None` where it is the identity (a free node without rotation).
fn node_basis(frames: &crate::core::constraints::Frames, i: usize) -> Option<[f64; 9]> {
    let d = frames.dim;
    let mask = frames.mask[i];
    let v = frames.rotation(i);
    if mask == 0 && v.is_none() {
        return None;
    }
    let mut m = [0.0; 9];
    for c in (0..d).filter(|&c| mask & (1 << c) == 0) {
        for a in 0..d {
            m[c * d + a] = match v {
                Some(v) => v[a * d + c],
                None => f64::from(a == c),
            };
        }
    }
    Some(m)
}

/// The nodes whose Z_i is not the identity (constrained or rotated), with Z_i.
fn special_nodes(frames: &crate::core::constraints::Frames) -> Vec<(usize, [f64; 9])> {
    (0..frames.n_nodes)
        .filter_map(|i| node_basis(frames, i).map(|m| (i, m)))
        .collect()
}

/// 1/s_i per node of an equilibrated system.
fn inverse_scale(node_scale: Option<&[f64]>) -> Option<Vec<f64>> {
    node_scale.map(|s| s.iter().map(|v| 1.0 / v).collect())
}

impl Coarse {
    /// The translations of `frames` (scaled by 1/s_i per node when `node_scale` is given,
    /// for an equilibrated system SĤS), E = ZᵀĤZ with `apply` computing Ĥv. `None` when
    /// every translation is fully constrained, or E has no positive eigenvalue.
    pub fn translations(
        frames: &crate::core::constraints::Frames,
        node_scale: Option<&[f64]>,
        mut apply: impl FnMut(&[f64], &mut [f64]),
    ) -> Option<Self> {
        let d = frames.dim;
        let special = special_nodes(frames);
        let mut c = Coarse {
            dim: d,
            n_nodes: frames.n_nodes,
            special,
            inv_scale: inverse_scale(node_scale),
            agg: None,
            einv: Vec::new(),
        };
        let basis: Vec<Vec<f64>> = (0..d).map(|a| c.column(a)).collect();
        let e = galerkin(&basis, &mut apply);
        c.einv = pseudo_inverse(d, &e)?;
        Some(c)
    }

    /// The translations of each aggregate of [`Aggregation::build`] on Ĥ's graph, with
    /// E = ZᵀĤZ from H's blocks (the same for an equilibrated SĤS, whose Z_i carry
    /// 1/s_i). `None` when no translation is free or E is not finite.
    pub fn aggregates(
        h: &crate::core::sparse::BlockCsr,
        frames: &crate::core::constraints::Frames,
        node_scale: Option<&[f64]>,
    ) -> Option<Self> {
        let agg = Aggregation::build(h);
        let inv_scale = inverse_scale(node_scale);
        let einv = aggregates_einv(h, frames, &agg, inv_scale.as_deref())?;
        Some(Coarse {
            dim: h.dim,
            n_nodes: h.n,
            special: special_nodes(frames),
            inv_scale,
            agg: Some(agg),
            einv,
        })
    }

    /// The number of coarse modes (d per aggregate).
    pub fn k(&self) -> usize {
        self.dim * self.agg.as_ref().map_or(1, |a| a.count)
    }

    /// The aggregates (`None` for the rigid translations: one aggregate).
    pub fn aggregation(&self) -> Option<&Aggregation> {
        self.agg.as_ref()
    }

    /// The first coarse index of node i's aggregate, or `None` (fully constrained).
    fn offset(&self, i: usize) -> Option<usize> {
        match &self.agg {
            None => Some(0),
            Some(a) => {
                let g = a.of_node[i];
                (g != NO_AGGREGATE).then(|| g as usize * self.dim)
            }
        }
    }

    fn scale(&self, i: usize) -> f64 {
        self.inv_scale.as_ref().map_or(1.0, |v| v[i])
    }

    /// Column j of Z (the translation along axis j % d of aggregate j / d, in frame
    /// coordinates), length d·n.
    pub fn column(&self, j: usize) -> Vec<f64> {
        let d = self.dim;
        let (g, a) = (j / d, j % d);
        let mut out = vec![0.0; d * self.n_nodes];
        let ours = |i: usize| self.offset(i) == Some(g * d);
        for i in (0..self.n_nodes).filter(|&i| ours(i)) {
            out[i * d + a] = self.scale(i);
        }
        for (i, m) in self.special.iter().filter(|(i, _)| ours(*i)) {
            for c in 0..d {
                out[i * d + c] = self.scale(*i) * m[c * d + a];
            }
        }
        out
    }

    /// The coarse indices that nodes `lo..hi` touch (empty when all are fully
    /// constrained): the span a chunk of CG's row partition restricts into.
    pub(crate) fn index_range(&self, lo: usize, hi: usize) -> std::ops::Range<usize> {
        let mut first = usize::MAX;
        let mut last = 0;
        for o in (lo..hi).filter_map(|i| self.offset(i)) {
            first = first.min(o);
            last = last.max(o + self.dim);
        }
        if first == usize::MAX {
            0..0
        } else {
            first..last
        }
    }

    /// Zᵀr over the nodes lo..lo + r.len()/d (`r` holds their components), added into
    /// `out`, which holds coarse indices `base..base + out.len()` (from [`Self::index_range`]).
    pub(crate) fn restrict_nodes(&self, r: &[f64], lo: usize, base: usize, out: &mut [f64]) {
        let d = self.dim;
        let hi = lo + r.len() / d;
        let mut sp = self.special.partition_point(|(i, _)| *i < lo);
        for (i, ri) in (lo..hi).zip(r.chunks_exact(d)) {
            let special = match self.special.get(sp) {
                Some((j, m)) if *j == i => {
                    sp += 1;
                    Some(m)
                }
                _ => None,
            };
            let Some(o) = self.offset(i) else { continue };
            let s = self.scale(i);
            let acc = &mut out[o - base..o - base + d];
            match special {
                None => {
                    for (a, v) in acc.iter_mut().zip(ri) {
                        *a += s * v;
                    }
                }
                Some(m) => {
                    for (a, v) in acc.iter_mut().enumerate() {
                        *v += s * (0..d).map(|c| m[c * d + a] * ri[c]).sum::<f64>();
                    }
                }
            }
        }
    }

    /// z += Z c over the nodes lo..lo + z.len()/d (`z` holds their components).
    pub(crate) fn prolong_nodes(&self, c: &[f64], lo: usize, z: &mut [f64]) {
        let d = self.dim;
        let hi = lo + z.len() / d;
        let mut sp = self.special.partition_point(|(i, _)| *i < lo);
        for (i, zi) in (lo..hi).zip(z.chunks_exact_mut(d)) {
            let special = match self.special.get(sp) {
                Some((j, m)) if *j == i => {
                    sp += 1;
                    Some(m)
                }
                _ => None,
            };
            let Some(o) = self.offset(i) else { continue };
            let s = self.scale(i);
            let ca = &c[o..o + d];
            match special {
                None => {
                    for (v, x) in zi.iter_mut().zip(ca) {
                        *v += s * x;
                    }
                }
                Some(m) => {
                    for (ci, v) in zi.iter_mut().enumerate() {
                        *v += s * (0..d).map(|a| m[ci * d + a] * ca[a]).sum::<f64>();
                    }
                }
            }
        }
    }

    /// z += Z E⁺ Zᵀ r.
    pub fn add_correction(&self, r: &[f64], z: &mut [f64]) {
        let d = self.dim;
        let k = self.k();
        // Zᵀr: the dense pass as if Z_i = s_i⁻¹I, then the special nodes' difference.
        // Zᵀr and c: on the stack for the translations (k ≤ 3), where this runs once per
        // CG iteration on small systems too; on the heap for aggregates (k ≤ 3·128).
        let mut small = [0.0f64; 6];
        let mut big = Vec::new();
        let buf: &mut [f64] = if 2 * k <= small.len() {
            &mut small[..2 * k]
        } else {
            big.resize(2 * k, 0.0);
            &mut big
        };
        let (zr, cc) = buf.split_at_mut(k);
        for (i, ri) in r.chunks_exact(d).enumerate() {
            let Some(o) = self.offset(i) else { continue };
            let s = self.scale(i);
            for (acc, v) in zr[o..o + d].iter_mut().zip(ri) {
                *acc += s * v;
            }
        }
        for (i, m) in &self.special {
            let Some(o) = self.offset(*i) else { continue };
            let s = self.scale(*i);
            let ri = &r[i * d..(i + 1) * d];
            for (a, acc) in zr[o..o + d].iter_mut().enumerate() {
                *acc += s * ((0..d).map(|c| m[c * d + a] * ri[c]).sum::<f64>() - ri[a]);
            }
        }
        for (ca, row) in cc.iter_mut().zip(self.einv.chunks_exact(k)) {
            *ca = crate::core::linalg::dot(row, zr);
        }
        // z += Z c, the same way round.
        for (i, zi) in z.chunks_exact_mut(d).enumerate() {
            let Some(o) = self.offset(i) else { continue };
            let s = self.scale(i);
            for (v, ca) in zi.iter_mut().zip(&cc[o..o + d]) {
                *v += s * ca;
            }
        }
        for (i, m) in &self.special {
            let Some(o) = self.offset(*i) else { continue };
            let s = self.scale(*i);
            let c = &cc[o..o + d];
            let zi = &mut z[i * d..(i + 1) * d];
            for (ci, v) in zi.iter_mut().enumerate() {
                *v += s * ((0..d).map(|a| m[ci * d + a] * c[a]).sum::<f64>() - c[ci]);
            }
        }
    }
}

/// E⁺ of the translations straight from H's blocks, in one pass and without the basis
/// (what the GPU solver needs after each update): E = Σ_ij Q_i H_ij Q_j with
/// Q_i = V_i P_i V_iᵀ, the identity at free unrotated nodes. Equal to ZᵀĤZ of
/// [`Coarse::translations`] (Ĥ's D on constrained components never meets Z). `None` as
/// there.
pub fn translations_einv_from_blocks(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
) -> Option<Vec<f64>> {
    let (e, _) = translations_galerkin_from_blocks(h, frames);
    pseudo_inverse(h.dim, &e)
}

/// The smallest Rayleigh quotient tᵀĤt/tᵀt over the translations t = Zc (the stiffness
/// of the softest rigid translation per unit displacement²; for a free body its mass
/// term), from E and G = ZᵀZ. `None` when every translation is constrained.
pub fn softest_translation(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
) -> Option<f64> {
    let d = h.dim;
    let (e, g) = translations_galerkin_from_blocks(h, frames);
    if e.iter().chain(&g).any(|v| !v.is_finite()) {
        return None;
    }
    // G^{-1/2} on G's range, then λ_min of G^{-1/2} E G^{-1/2}.
    let ge = nalgebra::SymmetricEigen::new(nalgebra::DMatrix::from_row_slice(d, d, &g));
    let gmax = ge.eigenvalues.iter().copied().fold(0.0, f64::max);
    if gmax <= 0.0 {
        return None;
    }
    let mut w = nalgebra::DMatrix::<f64>::zeros(d, d);
    let mut rank = 0;
    for (j, &l) in ge.eigenvalues.iter().enumerate() {
        if l > PINV_RTOL * gmax {
            let v = ge.eigenvectors.column(j);
            w += v * v.transpose() / l.sqrt();
            rank += 1;
        }
    }
    let m = &w * nalgebra::DMatrix::from_row_slice(d, d, &e) * &w;
    let ev = nalgebra::SymmetricEigen::new(m).eigenvalues;
    // The d − rank null directions of G show up as zeros: skip them.
    let mut vals: Vec<f64> = ev.iter().copied().collect();
    vals.sort_by(f64::total_cmp);
    vals.get(d - rank).copied().filter(|v| *v > 0.0)
}

/// (E, G) = (Σ_ij Q_i H_ij Q_j, Σ_i Q_i), d×d each, symmetrized.
/// E = ZᵀĤZ of the whole body's translations (d×d, symmetrized) and G = Σ_i Q_i.
pub fn translations_galerkin_from_blocks(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
) -> (Vec<f64>, Vec<f64>) {
    galerkin_from_blocks(h, frames, &Aggregation::single(frames), None)
}

/// g += Q_i (d×d, row-major; None is the identity).
fn add_projection(d: usize, q: &Option<[f64; 9]>, g: &mut [f64]) {
    match q {
        None => (0..d).for_each(|a| g[a * d + a] += 1.0),
        Some(qi) => g.iter_mut().zip(&qi[..d * d]).for_each(|(x, y)| *x += y),
    }
}

/// Q_i = Z_iᵀZ_i = V_i P_i V_iᵀ where Z_i is not the identity.
fn node_projections(frames: &crate::core::constraints::Frames) -> Vec<Option<[f64; 9]>> {
    let d = frames.dim;
    (0..frames.n_nodes)
        .map(|i| {
            node_basis(frames, i).map(|m| {
                let mut out = [0.0; 9];
                for a in 0..d {
                    for b in 0..d {
                        out[a * d + b] = (0..d).map(|c| m[c * d + a] * m[c * d + b]).sum();
                    }
                }
                out
            })
        })
        .collect()
}

/// E = ZᵀĤZ over the aggregates' translations, (E_ab)_{xy} = Σ_{i∈a, j∈b} (Q_i H_ij Q_j)_{xy}
/// (k×k, k = d·count, symmetrized), and G_a = Σ_{i∈a} Q_i (count blocks of d×d). With
/// `inv_scale` (1/s_i), `h` is an equilibrated SHS and Z_i carries 1/s_i: the same E.
fn galerkin_from_blocks(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
    agg: &Aggregation,
    inv_scale: Option<&[f64]>,
) -> (Vec<f64>, Vec<f64>) {
    let w = |i: usize| inv_scale.map_or(1.0, |v| v[i]);
    let d = h.dim;
    let dd = d * d;
    let k = d * agg.count;
    let q = node_projections(frames);
    let mut e = vec![0.0; k * k];
    let mut t = [0.0; 9];
    let mut u = [0.0; 9];
    // Row i's blocks summed per column aggregate first: for a nearly free body they (size
    // ‖K‖) cancel to the mass term, and summing every block straight into E would carry
    // rounding of ‖K‖ into an E of size n·m (kappa-1e8-balanced at 81k DOFs: 505 mixed
    // iterations against 456 with the row sums first, as with matrix-free products).
    let mut row: Vec<(u32, [f64; 9])> = Vec::new();
    for i in 0..h.n {
        let ai = agg.of_node[i];
        if ai == NO_AGGREGATE {
            continue;
        }
        row.clear();
        for kb in h.row_ptr[i]..h.row_ptr[i + 1] {
            let j = h.col_idx[kb];
            let aj = agg.of_node[j];
            if aj == NO_AGGREGATE {
                continue;
            }
            let b = h.block(kb);
            // t = B Q_j.
            match &q[j] {
                None => t[..dd].copy_from_slice(b),
                Some(qj) => mat_mul(d, b, &qj[..dd], &mut t[..dd]),
            }
            let wj = w(j);
            let slot = match row.iter().position(|(a, _)| *a == aj) {
                Some(p) => p,
                None => {
                    row.push((aj, [0.0; 9]));
                    row.len() - 1
                }
            };
            for (re, te) in row[slot].1[..dd].iter_mut().zip(&t[..dd]) {
                *re += wj * te;
            }
        }
        for (aj, part) in &row {
            // u = Q_i part.
            match &q[i] {
                None => u[..dd].copy_from_slice(&part[..dd]),
                Some(qi) => mat_mul(d, &qi[..dd], &part[..dd], &mut u[..dd]),
            }
            let (r0, c0) = (ai as usize * d, *aj as usize * d);
            let wi = w(i);
            for x in 0..d {
                for y in 0..d {
                    e[(r0 + x) * k + c0 + y] += wi * u[x * d + y];
                }
            }
        }
    }
    symmetrize(k, &mut e);
    (e, aggregate_projections(frames, agg))
}

/// E⁺ of the aggregates' translations from H's blocks (what the GPU solver needs after
/// each update), k×k. E's null space is that of Z, aggregate by aggregate (the
/// translations an aggregate's constraints remove: the null space of G_a), so
/// E⁺ = W (WᵀEW)⁻¹ Wᵀ with W the range of each G_a; WᵀEW is SPD for an SPD Ĥ and is
/// inverted by Cholesky ([`aggregates_einv_from_galerkin`], the device PCG's
/// specification too; the eigen-decomposition of the whole of E is the fallback). `None`
/// when no translation is free or E is not finite.
pub fn aggregates_einv_from_blocks(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
    agg: &Aggregation,
) -> Option<Vec<f64>> {
    aggregates_einv(h, frames, agg, None)
}

fn aggregates_einv(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
    agg: &Aggregation,
    inv_scale: Option<&[f64]>,
) -> Option<Vec<f64>> {
    let (e, g) = galerkin_from_blocks(h, frames, agg, inv_scale);
    aggregates_einv_from_galerkin(h.dim, agg.count, e, &g)
}

/// G_a = Σ_{i∈a} Q_i of every aggregate (count blocks of d×d, symmetrized): the Gram
/// matrix of aggregate a's translations, whose null space is what its constraints remove.
pub fn aggregate_projections(
    frames: &crate::core::constraints::Frames,
    agg: &Aggregation,
) -> Vec<f64> {
    let d = frames.dim;
    let dd = d * d;
    let q = node_projections(frames);
    let mut g = vec![0.0; agg.count * dd];
    for (i, &a) in agg.of_node.iter().enumerate() {
        if a != NO_AGGREGATE {
            add_projection(d, &q[i], &mut g[a as usize * dd..(a as usize + 1) * dd]);
        }
    }
    for ga in g.chunks_exact_mut(dd) {
        symmetrize(d, ga);
    }
    g
}

fn mat_mul(d: usize, a: &[f64], b: &[f64], out: &mut [f64]) {
    for r in 0..d {
        for c in 0..d {
            out[r * d + c] = (0..d).map(|m| a[r * d + m] * b[m * d + c]).sum();
        }
    }
}

/// E = ZᵀĤZ, symmetrized.
fn galerkin(basis: &[Vec<f64>], apply: &mut impl FnMut(&[f64], &mut [f64])) -> Vec<f64> {
    let k = basis.len();
    let nd = basis.first().map_or(0, Vec::len);
    let mut e = vec![0.0; k * k];
    let mut hz = vec![0.0; nd];
    for b in 0..k {
        apply(&basis[b], &mut hz);
        for a in 0..k {
            e[a * k + b] = crate::core::linalg::dot(&basis[a], &hz);
        }
    }
    symmetrize(k, &mut e);
    e
}

/// How far below the rows of Ĥ a rigid translation's stiffness may fall before it counts
/// as pinned by nothing, in units of f64's ε: a translation t of a connected group of free
/// nodes is unpinned when tᵀĤt/tᵀt ≤ `UNPINNED_EPS` · ε · (mean absolute row sum of Ĥ
/// over the group's free components). A floating body's translation energy is the
/// rounding of its row sums: below 1 ε of the rows for a free neo-Hookean box and a free
/// spring grid. The softest legitimate case of the hard suite (a free grid with
/// κ(H) = 1e12, its mass term 1e-12 of its rows) sits at 4.5·10³ ε, so 64 leaves a
/// factor of about 70 on that side and 300 on the other (see the tests).
pub const UNPINNED_EPS: f64 = 64.0;

pub use crate::error::Unpinned;
pub use crate::solve::options::CoarseSpace;

/// The first rigid translation that nothing pins, if any: for each connected group of
/// free nodes of Ĥ's graph (nodes joined by a nonzero block P_iV_iᵀH_ijV_jP_j), the d
/// translations restricted to the free components (Z_i = P_iV_iᵀ, as the coarse space
/// uses), E = ZᵀĤZ and G = ZᵀZ, and the smallest Rayleigh quotient over range(G). One
/// pass over H's blocks. A group whose softest translation is below [`UNPINNED_EPS`]·ε of
/// its rows makes Ĥ singular: every solver must refuse it (Cholesky meets a zero pivot;
/// CG would converge to one solution of a family that differ by the translation).
///
/// Rotations are not checked (they need node positions, which a Matrix Market system
/// does not carry): a body pinned at one node and without a mass term passes here.
pub fn unpinned_translation(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
) -> Option<Unpinned> {
    softest_translations(h, frames)
        .into_iter()
        .find(is_unpinned)
}

/// 2^-64: the scale of the running sums of |Ĥ| in [`softest_translations`] (and the
/// device device PCG's).
pub const ABS_SUM_SCALE: f64 = 1.0 / 18_446_744_073_709_551_616.0;

/// Q_i B Q_j of H's block `kb` (row i), with the projections `q` of
/// [`node_projections`]: the stored block itself where neither node is projected (most
/// nodes of a mesh), else formed in `buf`. Reading the block in place keeps
/// [`softest_translations`], which every CG solve runs, a small part of the solve.
fn projected_block<'a>(
    h: &'a crate::core::sparse::BlockCsr,
    q: &[Option<[f64; 9]>],
    i: usize,
    kb: usize,
    buf: &'a mut [f64; 9],
) -> &'a [f64] {
    let d = h.dim;
    let dd = d * d;
    let j = h.col_idx[kb];
    if q[i].is_none() && q[j].is_none() {
        return h.block(kb);
    }
    let b = h.block(kb);
    let mut t = [0.0; 9];
    match &q[j] {
        None => t[..dd].copy_from_slice(b),
        Some(qj) => mat_mul(d, b, &qj[..dd], &mut t[..dd]),
    }
    match &q[i] {
        None => buf[..dd].copy_from_slice(&t[..dd]),
        Some(qi) => mat_mul(d, &qi[..dd], &t[..dd], &mut buf[..dd]),
    }
    &buf[..dd]
}

/// The softest translation of every connected group of free nodes (see
/// [`unpinned_translation`]), in the order of the groups' first nodes.
pub fn softest_translations(
    h: &crate::core::sparse::BlockCsr,
    frames: &crate::core::constraints::Frames,
) -> Vec<Unpinned> {
    let d = h.dim;
    let dd = d * d;
    let n = h.n;
    let full = (1u8 << d) - 1;
    let q = node_projections(frames);
    let free = |i: usize| frames.mask[i] & full != full;
    let mut group = vec![u32::MAX; n];
    let mut stack = Vec::new();
    let mut buf = [0.0; 9];
    let mut count = 0u32;
    for seed in 0..n {
        if group[seed] != u32::MAX || !free(seed) {
            continue;
        }
        group[seed] = count;
        stack.push(seed);
        while let Some(i) = stack.pop() {
            for kb in h.row_ptr[i]..h.row_ptr[i + 1] {
                let j = h.col_idx[kb];
                if group[j] != u32::MAX || !free(j) {
                    continue;
                }
                let pb = projected_block(h, &q, i, kb, &mut buf);
                if pb.iter().any(|v| *v != 0.0) {
                    group[j] = count;
                    stack.push(j);
                }
            }
        }
        count += 1;
    }
    let groups = count as usize;
    let mut e = vec![0.0; groups * dd];
    let mut g = vec![0.0; groups * dd];
    // Per group and world axis a: Σ |entries| of the rows of component a (scaled).
    let mut abs = vec![0.0; groups * d];
    let mut first = vec![usize::MAX; groups];
    let mut size = vec![0usize; groups];
    let mut row = [0.0; 9];
    for i in 0..n {
        let c = group[i];
        if c == u32::MAX {
            continue;
        }
        let c = c as usize;
        first[c] = first[c].min(i);
        size[c] += 1;
        add_projection(d, &q[i], &mut g[c * dd..(c + 1) * dd]);
        // Row i's projected blocks summed first (for a floating body they cancel), then
        // added to the group's E: rounding stays at the size of a row.
        row[..dd].iter_mut().for_each(|v| *v = 0.0);
        for kb in h.row_ptr[i]..h.row_ptr[i + 1] {
            let j = h.col_idx[kb];
            if group[j] != c as u32 {
                continue;
            }
            let pb = projected_block(h, &q, i, kb, &mut buf);
            for (r, v) in row[..dd].iter_mut().zip(pb) {
                *r += v;
            }
            // Scaled by 2^-64 while summed: rows near the top of the f64 range would
            // overflow the group's total (and every translation would look unpinned).
            for a in 0..d {
                abs[c * d + a] += pb[a * d..(a + 1) * d]
                    .iter()
                    .map(|v| v.abs() * ABS_SUM_SCALE)
                    .sum::<f64>();
            }
        }
        for (x, v) in e[c * dd..(c + 1) * dd].iter_mut().zip(&row[..dd]) {
            *x += v;
        }
    }
    (0..groups)
        .filter_map(|c| {
            group_translation(
                d,
                &e[c * dd..(c + 1) * dd],
                &g[c * dd..(c + 1) * dd],
                &abs[c * d..(c + 1) * d],
                first[c],
                size[c],
            )
        })
        .collect()
}

/// The softest translation of one group of free nodes from its E = ZᵀĤZ, G = ZᵀZ (d×d)
/// and, per world axis a, 2^-64 · Σ |entries| of its rows of component a (`abs`); `node`
/// and `nodes` name the group. None when E or G is not finite or G is zero. The device
/// Newton CG reduces the same three sums over all its free nodes and asks this too.
pub fn group_translation(
    d: usize,
    e: &[f64],
    g: &[f64],
    abs: &[f64],
    node: usize,
    nodes: usize,
) -> Option<Unpinned> {
    // A non-finite E (overflowed data) is left to the solvers' own checks.
    let (stiffness, direction) = softest(d, e, g)?;
    // The rows the translation moves: Σ_a t_a² |rows of a| over tᵀGt (Gt's free
    // components, as many as the translation moves). For a body whose stiffness is alike
    // along every axis this is the mean absolute row sum; a component far softer than the
    // node's others is measured against its own rows, not theirs.
    let moved: f64 = (0..d)
        .map(|a| direction[a] * (0..d).map(|b| g[a * d + b] * direction[b]).sum::<f64>())
        .sum();
    let rows: f64 = (0..d).map(|a| direction[a] * direction[a] * abs[a]).sum();
    let row_scale = rows / moved.max(1.0) / ABS_SUM_SCALE;
    Some(Unpinned {
        node,
        nodes,
        direction,
        stiffness,
        row_scale,
    })
}

/// Whether a group's softest translation ([`group_translation`]) is pinned by nothing:
/// below [`UNPINNED_EPS`]·ε of its rows. Clearly negative is indefinite, not floating:
/// the solvers report that.
pub fn is_unpinned(t: &Unpinned) -> bool {
    t.stiffness.abs() <= UNPINNED_EPS * f64::EPSILON * t.row_scale
}

/// The translations of every free node as one group: G = ZᵀZ and the nodes it covers.
#[derive(Debug, Clone, PartialEq)]
pub struct TranslationGram {
    /// G = ZᵀZ = Σ_i Q_i over the nodes with a free component (d×d, row-major).
    pub g: Vec<f64>,
    /// The first node with a free component (`usize::MAX` when none has one).
    pub first: usize,
    /// The number of nodes with a free component.
    pub count: usize,
}

/// G = ZᵀZ of the translations of every node with a free component, as one group.
pub fn translation_gram(frames: &crate::core::constraints::Frames) -> TranslationGram {
    let d = frames.dim;
    let full = (1u8 << d) - 1;
    let mut g = vec![0.0; d * d];
    let (mut first, mut count) = (usize::MAX, 0);
    for (i, q) in node_projections(frames).iter().enumerate() {
        if frames.mask[i] & full == full {
            continue;
        }
        first = first.min(i);
        count += 1;
        add_projection(d, q, &mut g);
    }
    TranslationGram { g, first, count }
}

/// The smallest Rayleigh quotient vᵀEv/vᵀGv over range(G) (d×d symmetric E, G) and its
/// direction (unit, world axes). `None` when G is zero or anything is not finite.
fn softest(d: usize, e: &[f64], g: &[f64]) -> Option<(f64, Vec<f64>)> {
    if e.iter().chain(g).any(|v| !v.is_finite()) {
        return None;
    }
    let mut es = e.to_vec();
    symmetrize(d, &mut es);
    let ge = nalgebra::SymmetricEigen::new(nalgebra::DMatrix::from_row_slice(d, d, g));
    let gmax = ge.eigenvalues.iter().copied().fold(0.0, f64::max);
    if gmax <= 0.0 {
        return None;
    }
    // W = G^{-1/2} on G's range; λ_min of W E W over that range.
    let basis: Vec<usize> = (0..d)
        .filter(|&j| ge.eigenvalues[j] > PINV_RTOL * gmax)
        .collect();
    let r = basis.len();
    let mut u = nalgebra::DMatrix::<f64>::zeros(d, r);
    for (col, &j) in basis.iter().enumerate() {
        let s = ge.eigenvalues[j].sqrt();
        for x in 0..d {
            u[(x, col)] = ge.eigenvectors[(x, j)] / s;
        }
    }
    let m = u.transpose() * nalgebra::DMatrix::from_row_slice(d, d, &es) * &u;
    let ev = nalgebra::SymmetricEigen::new(m);
    let (k, &lmin) = ev
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let v = &u * ev.eigenvectors.column(k);
    let norm = v.norm();
    let dir = v.iter().map(|x| x / norm).collect();
    Some((lmin, dir))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::constraints::{Constraint, ConstraintKind, Frames};

    /// A chain of n nodes with unit springs in every axis: Laplacian ⊗ I_d.
    fn chain(d: usize, n: usize) -> crate::core::sparse::BlockCsr {
        let mut t = Vec::new();
        for i in 0..n - 1 {
            for a in 0..d {
                let (p, q) = (i * d + a, (i + 1) * d + a);
                t.extend([(p, p, 1.0), (q, q, 1.0), (p, q, -1.0), (q, p, -1.0)]);
            }
        }
        crate::core::sparse::BlockCsr::from_triplets(d, d * n, &t, false)
    }

    /// Floating bodies (no constraint, no mass term, or one far below rounding) are
    /// found, and the softest direction is the free one; pinned ones are not.
    #[test]
    fn unpinned_translations_are_found() {
        let h = chain(2, 12);
        let free = Frames::unconstrained(2, 12);
        let u = unpinned_translation(&h, &free).expect("a floating chain");
        assert_eq!((u.node, u.nodes), (0, 12));
        assert_eq!(u.stiffness, 0.0);
        // One sticky node pins it.
        let sticky = |node: usize| Constraint {
            node,
            kind: ConstraintKind::Sticky { displacement: None },
            label: format!("c{node}"),
        };
        let pinned = Frames::build(2, 12, &[sticky(2)]).unwrap();
        assert!(unpinned_translation(&h, &pinned).is_none());
        // Two chains, one pinned: the other one is reported, from its first node.
        let mut t = Vec::new();
        for (base, n) in [(0usize, 5usize), (5, 7)] {
            let c = chain(2, n);
            for i in 0..n {
                for k in c.row_ptr[i]..c.row_ptr[i + 1] {
                    let j = c.col_idx[k];
                    for r in 0..2 {
                        for q in 0..2 {
                            let v = c.block(k)[r * 2 + q];
                            if v != 0.0 {
                                t.push(((base + i) * 2 + r, (base + j) * 2 + q, v));
                            }
                        }
                    }
                }
            }
        }
        let two = crate::core::sparse::BlockCsr::from_triplets(2, 24, &t, false);
        let u = unpinned_translation(&two, &pinned).expect("the second chain floats");
        assert_eq!((u.node, u.nodes), (5, 7));
        // A 3D chain whose every node slides on the plane x + y + z = 0 (rotated frames):
        // the translations within the plane float, the normal one is constrained.
        let h3 = chain(3, 10);
        let n = [1.0, 1.0, 1.0];
        let cs: Vec<Constraint> = (0..10)
            .map(|node| Constraint {
                node,
                kind: ConstraintKind::Plane {
                    normal: n.to_vec(),
                    offset: 0.0,
                },
                label: format!("c{node}"),
            })
            .collect();
        let f3 = Frames::build(3, 10, &cs).unwrap();
        let u = unpinned_translation(&h3, &f3).expect("slides in its plane");
        let along: f64 = u.direction.iter().zip(n).map(|(a, b)| a * b).sum();
        assert!(along.abs() < 1e-12, "{:?}", u.direction);
    }

    /// E⁺ of an SPD matrix is its inverse; a zero row and column is dropped.
    #[test]
    fn pseudo_inverse_inverts_and_drops_null_modes() {
        let e = [4.0, 1.0, 1.0, 3.0];
        let p = pseudo_inverse(2, &e).expect("SPD");
        let det = 11.0;
        let want = [3.0 / det, -1.0 / det, -1.0 / det, 4.0 / det];
        for (a, b) in p.iter().zip(want) {
            // A 2×2 eigen-decomposition: a few ulps.
            assert!((a - b).abs() <= 1e-14, "{p:?} vs {want:?}");
        }
        let e = [2.0, 0.0, 0.0, 0.0];
        let p = pseudo_inverse(2, &e).expect("one mode");
        assert_eq!(p[1], 0.0);
        assert_eq!(p[3], 0.0);
        assert!((p[0] - 0.5).abs() <= 1e-15);
        assert!(pseudo_inverse(2, &[0.0; 4]).is_none());
        assert!(pseudo_inverse(1, &[f64::NAN]).is_none());
    }

    /// On Ĥ = m I + L (L a path-graph Laplacian per component, null on translations) the
    /// correction maps a translation exactly: Z E⁺ Zᵀ Ĥ t = t for t in range(Z).
    #[test]
    fn correction_is_exact_on_translations() {
        let (d, n, m) = (2usize, 5usize, 1e-3);
        let frames = Frames::build(d, n, &[]).expect("no constraints");
        let apply = |v: &[f64], out: &mut [f64]| {
            for i in 0..n {
                for a in 0..d {
                    let mut s = m * v[i * d + a];
                    if i > 0 {
                        s += v[i * d + a] - v[(i - 1) * d + a];
                    }
                    if i + 1 < n {
                        s += v[i * d + a] - v[(i + 1) * d + a];
                    }
                    out[i * d + a] = s;
                }
            }
        };
        let c = Coarse::translations(&frames, None, apply).expect("free body");
        assert_eq!(c.k(), 2);
        let t: Vec<f64> = (0..n * d)
            .map(|k| if k % d == 0 { 2.0 } else { -1.0 })
            .collect();
        let mut ht = vec![0.0; n * d];
        apply(&t, &mut ht);
        let mut z = vec![0.0; n * d];
        c.add_correction(&ht, &mut z);
        for (a, b) in z.iter().zip(&t) {
            // E = m·n·I exactly representable; a few roundings.
            assert!((a - b).abs() <= 1e-12, "{z:?}");
        }
        // Sticky nodes: the columns of Z vanish there (masked), E stays SPD.
        let cons = vec![Constraint {
            node: 0,
            kind: ConstraintKind::Sticky { displacement: None },
            label: "sticky".into(),
        }];
        let frames = Frames::build(d, n, &cons).expect("sticky");
        let c = Coarse::translations(&frames, None, apply).expect("still two modes");
        assert!((0..d).all(|a| {
            let v = c.column(a);
            v[0] == 0.0 && v[1] == 0.0 && v[2 + a] == 1.0
        }));
    }

    /// The one-pass E⁺ from H's blocks equals the one from ZᵀĤZ with matrix-free products,
    /// on generated systems with sticky, slip (rotated) and line nodes, 2D and 3D.
    #[test]
    fn blocks_path_matches_the_matrix_free_galerkin_product() {
        use crate::cases::generate::{random_system, SystemSpec};
        use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
        for (dim, seed) in [(2, 1u64), (3, 2), (3, 5)] {
            let s = random_system(&SystemSpec::small(dim, seed));
            assert!(s.frames.has_rotation());
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
            let mut work = vec![0.0; 2 * e.ndof()];
            let a = Coarse::translations(&s.frames, None, |v, o| e.apply(v, o, &mut work))
                .expect("modes")
                .einv;
            let b = translations_einv_from_blocks(&s.h, &s.frames).expect("modes");
            let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (x, y) in a.iter().zip(&b) {
                // Two summation orders of the same O(nnz) sum, inverted: 1e-12 relative.
                assert!((x - y).abs() <= 1e-12 * scale, "{a:?} vs {b:?}");
            }
        }
    }

    /// The aggregates' E⁺ from H's blocks (Cholesky on each aggregate's free translations)
    /// is the pseudo-inverse of ZᵀĤZ formed with matrix-free products of Z's columns, on
    /// generated systems with sticky, slip (rotated) and line nodes, 2D and 3D; and the
    /// correction is exact on the coarse space: Z E⁺ Zᵀ Ĥ v = v for v = Z c.
    #[test]
    fn aggregates_einv_is_the_pseudo_inverse_of_the_galerkin_product() {
        use crate::cases::generate::{random_system, SystemSpec};
        use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
        for (dim, seed, nodes) in [(2, 1u64, 900), (3, 2, 700), (3, 5, 1000)] {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            assert!(s.frames.has_rotation());
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
            let c = Coarse::aggregates(&s.h, &s.frames, None).expect("modes");
            let k = c.k();
            assert!(k >= 3 * dim, "{k} coarse modes");
            let mut work = vec![0.0; 2 * e.ndof()];
            let basis: Vec<Vec<f64>> = (0..k).map(|j| c.column(j)).collect();
            let eg = galerkin(&basis, &mut |v: &[f64], o: &mut [f64]| {
                e.apply(v, o, &mut work)
            });
            let want = pseudo_inverse(k, &eg).expect("modes");
            let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (x, y) in c.einv.iter().zip(&want) {
                // Two factorizations (Cholesky, eigen) of the same k×k matrix, whose
                // condition number is far below 1e4 here: 1e-9 relative to the largest entry.
                assert!((x - y).abs() <= 1e-9 * scale, "{x:e} vs {y:e}");
            }
            let coef: Vec<f64> = (0..k).map(|j| 1.0 + (j % 7) as f64).collect();
            let mut v = vec![0.0; e.ndof()];
            for (b, cj) in basis.iter().zip(&coef) {
                v.iter_mut().zip(b).for_each(|(vi, bi)| *vi += cj * bi);
            }
            let mut hv = vec![0.0; v.len()];
            e.apply(&v, &mut hv, &mut work);
            let mut z = vec![0.0; v.len()];
            c.add_correction(&hv, &mut z);
            let vn = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            for (a, b) in z.iter().zip(&v) {
                // E⁺ applied to ZᵀĤZc: c back to about κ(E)·ε.
                assert!((a - b).abs() <= 1e-8 * vn, "{a} vs {b}");
            }
        }
    }
}
