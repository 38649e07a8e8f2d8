//! Energies of the incremental potential and their assembly.
//!
//! E(x) = ½ (x − x̃)ᵀ M (x − x̃) + h² Ψ(x), Ψ = elastic + gravity. Only the terms a scene
//! uses exist in a [`Model`]: no gravity term when g = 0, one element set per body.
//! Element gradients and (PSD-projected) Hessians are computed in parallel with rayon into
//! flat per-element buffers that persist between calls ([`AssemblyWork`]); each block of
//! the Hessian (each node of the gradient) then gathers its elements' entries through a map
//! built once with the model, in parallel over blocks and in element order within one. No
//! locking, no sorting, and a sum order that does not depend on the thread count.

pub mod barrier;
pub mod digest;
pub mod eigensystem;
pub mod element_set;
mod gather;
pub mod gravity;
pub mod inertia;
pub mod kernels;
pub mod lanes;
pub mod neohookean;
pub mod spring;

use crate::core::sparse::BlockCsr;
use crate::gpu::Phase;
use crate::sim::memory::{try_vec, AllocError};
use crate::sim::phases::{self, HostPhases};
use gather::{
    block_pattern, grad_pass, hess_pass, BlockStart, Gather, GatherPass, CHUNK, GATHER_CHUNK,
};
use rayon::prelude::*;

pub use digest::{digest_f64s, digest_usizes};
pub use eigensystem::project_psd;
pub use element_set::ElementSet;
pub use neohookean::{Law, NeoHookean};
pub use spring::Springs;

/// The smallest element volume ratio of one law ([`Model::min_volume_ratio`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MinVolumeRatio {
    pub law: Law,
    pub j: f64,
    /// The element set (one per body) and the element within it.
    pub set: usize,
    pub element: usize,
}

/// Where a step along Δx first inverts an element ([`Model::inversion_bound`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InversionLimit {
    /// The exact root α of det F(x + αΔx) = 0.
    pub alpha: f64,
    pub set: usize,
    pub element: usize,
}

/// An element with J ≤ 0 where the classical law needs J > 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inverted {
    /// The element set (one per body) and the element within it.
    pub set: usize,
    pub element: usize,
    pub j: f64,
}

/// Element buffers of [`Model`]'s assembly, kept between calls so that a Newton loop
/// neither allocates nor touches fresh pages per iteration. Every entry is overwritten
/// before it is read.
#[derive(Debug, Clone, Default)]
pub struct AssemblyWork {
    hess: Vec<f64>,
    grad: Vec<f64>,
    /// Per block of the Hessian: its next gather entry in the current assembly (u32:
    /// the gather tables' entries fit, [`Gather::new`]).
    cursor: Vec<u32>,
    /// Per node: its next gradient gather entry in the current pass.
    grad_cursor: Vec<usize>,
    /// Per node: the force scale's running sums.
    sums: Vec<f64>,
    /// The run's profile: the element passes are timed as `element_terms`, the gathers
    /// as `assembly` (None: nothing is timed).
    pub phases: Option<HostPhases>,
}

impl AssemblyWork {
    /// Empty buffers whose passes are timed on `phases`.
    pub fn timed(phases: HostPhases) -> Self {
        AssemblyWork {
            phases: Some(phases),
            ..AssemblyWork::default()
        }
    }
}

/// Mass, gravity and elastic elements of a whole scene, with the Hessian's block pattern.
#[derive(Debug, Clone)]
pub struct Model {
    pub dim: usize,
    pub n_nodes: usize,
    /// Lumped mass per node.
    pub mass: Vec<f64>,
    /// Gravity, present only when nonzero.
    pub gravity: Option<Vec<f64>>,
    pub sets: Vec<ElementSet>,
    /// Element-to-block and element-to-node maps of the assembly.
    gather: Gather,
    /// The Hessian's block pattern (diagonal of every node plus element couplings):
    /// `row_ptr` and `col_idx` only, `values` empty ([`Model::zero_matrix`] has them).
    pub pattern: BlockCsr,
}

impl Model {
    /// [`Model::try_new`] for a model known to fit: a refused allocation aborts, as any
    /// infallible allocation does.
    pub fn new(
        dim: usize,
        mass: Vec<f64>,
        gravity: Option<Vec<f64>>,
        sets: Vec<ElementSet>,
    ) -> Self {
        Self::try_new(dim, mass, gravity, sets).unwrap_or_else(|e| crate::sim::memory::abort_on(&e))
    }

    /// The model of `sets` on `mass.len()` nodes: the Hessian's block pattern (every
    /// node's diagonal block and every element's node pairs) and the assembly's gather
    /// tables, each allocated fallibly: Err names the one the system refused and its bytes.
    pub fn try_new(
        dim: usize,
        mass: Vec<f64>,
        gravity: Option<Vec<f64>>,
        sets: Vec<ElementSet>,
    ) -> Result<Self, AllocError> {
        let n = mass.len();
        let pattern = block_pattern(dim, n, &sets)?;
        let gather = Gather::new(n, &sets, &pattern)?;
        let gravity = gravity.filter(|g| g.iter().any(|&v| v != 0.0));
        Ok(Model {
            dim,
            n_nodes: n,
            mass,
            gravity,
            sets,
            gather,
            pattern,
        })
    }

    pub fn ndof(&self) -> usize {
        self.dim * self.n_nodes
    }

    /// Feeds every value the model's terms depend on to `out` (numbers by their bits):
    /// the sizes, masses, gravity and each element set. The block pattern and the gather
    /// tables follow from the sets' elements.
    pub fn digest(&self, out: &mut dyn FnMut(&[u8])) {
        digest_usizes(out, &[self.dim, self.n_nodes, self.sets.len()]);
        digest_f64s(out, &self.mass);
        match &self.gravity {
            Some(g) => {
                out(b"gravity");
                digest_f64s(out, g);
            }
            None => out(b"no gravity"),
        }
        for s in &self.sets {
            match s {
                ElementSet::Springs(sp) => {
                    out(b"springs");
                    digest_usizes(out, &[sp.dim, sp.edges.len()]);
                    for e in &sp.edges {
                        digest_usizes(out, e);
                    }
                    digest_f64s(out, &sp.rest);
                    digest_f64s(out, &[sp.stiffness]);
                }
                ElementSet::NeoHookean(nh) => {
                    out(nh.law.name().as_bytes());
                    nh.digest(out);
                }
            }
        }
    }

    pub fn total_mass(&self) -> f64 {
        self.mass.iter().sum()
    }

    /// Elastic energy Σ_sets Σ_e Ψ_e(x), summed in fixed chunks of elements (the same
    /// bits on any number of threads).
    pub fn elastic_energy(&self, x: &[f64]) -> f64 {
        let mut total = 0.0;
        for s in &self.sets {
            let chunks: Vec<f64> = (0..s.len().div_ceil(CHUNK))
                .into_par_iter()
                .map(|c| {
                    let range = c * CHUNK..((c + 1) * CHUNK).min(s.len());
                    match s {
                        ElementSet::NeoHookean(nh) => {
                            nh.element_energy_sum(x, range.start, range.len())
                        }
                        ElementSet::Springs(_) => range.map(|e| s.energy(x, e)).sum::<f64>(),
                    }
                })
                .collect();
            total += chunks.iter().sum::<f64>();
        }
        total
    }

    /// Ψ(x): elastic plus gravitational potential.
    pub fn potential(&self, x: &[f64]) -> f64 {
        let mut e = self.elastic_energy(x);
        if let Some(g) = &self.gravity {
            e += gravity::energy(&self.mass, self.dim, g, x);
        }
        e
    }

    /// out += scale·∇Ψ(x).
    pub fn add_potential_gradient(&self, x: &[f64], scale: f64, out: &mut [f64]) {
        self.add_potential_gradient_with(x, scale, out, &mut AssemblyWork::default());
    }

    /// [`Model::add_potential_gradient`] with the element buffer kept in `work`: element
    /// gradients in parallel, then each node gathers its elements' entries in element
    /// order, in bounded passes (`Model::gradient_passes`).
    pub fn add_potential_gradient_with(
        &self,
        x: &[f64],
        scale: f64,
        out: &mut [f64],
        work: &mut AssemblyWork,
    ) {
        let d = self.dim;
        self.gradient_passes(x, work, &mut out[..self.n_nodes * d], d, |o, g| {
            for c in 0..d {
                o[c] += scale * g[c];
            }
        });
        if let Some(g) = &self.gravity {
            gravity::add_gradient(&self.mass, d, g, scale, out);
        }
    }

    /// Per node i, out\[i\] += scale · (Σ_e ‖∇_i Ψ_e(x)‖ + m_i‖g‖): the sizes of the forces
    /// that ∇Ψ sums at the node before they cancel (the force scale of a step's
    /// stationarity test).
    pub fn add_potential_force_scale(
        &self,
        x: &[f64],
        scale: f64,
        out: &mut [f64],
        work: &mut AssemblyWork,
    ) {
        let gnorm = self
            .gravity
            .as_ref()
            .map_or(0.0, |g| g.iter().map(|v| v * v).sum::<f64>().sqrt());
        // Each node's sum starts at its weight and adds its elements' norms in order.
        let mut sums = std::mem::take(&mut work.sums);
        sums.clear();
        sums.extend(self.mass.iter().map(|m| m * gnorm));
        self.gradient_passes(x, work, &mut sums, 1, |o, g| {
            o[0] += g.iter().map(|v| v * v).sum::<f64>().sqrt();
        });
        for (o, s) in out[..self.n_nodes].iter_mut().zip(&sums) {
            *o += scale * s;
        }
        work.sums = sums;
    }

    /// The element gradients at x, in passes over at most [`gather::GRAD_BUFFER_NODES`] element
    /// node vectors: each pass computes its elements' gradients in parallel, then each
    /// node touched by them (its `per_node` entries of `out`) takes `add` of each of its
    /// element vectors (d entries), in (set, element) order across the passes. The
    /// element buffer is bounded whatever the mesh, and every node sees the same
    /// sequence of `add`s whatever the passes and threads.
    fn gradient_passes(
        &self,
        x: &[f64],
        work: &mut AssemblyWork,
        out: &mut [f64],
        per_node: usize,
        add: impl Fn(&mut [f64], &[f64]) + Sync,
    ) {
        let d = self.dim;
        let gt = &self.gather;
        let buffer = self
            .sets
            .iter()
            .map(|s| grad_pass(s).min(s.len()) * s.arity())
            .max()
            .unwrap_or(0);
        work.grad.resize(buffer * d, 0.0);
        work.grad_cursor.clear();
        work.grad_cursor
            .extend_from_slice(&gt.grad_ptr[..self.n_nodes]);
        for ((s, &base), rows) in self.sets.iter().zip(&gt.grad_base).zip(&gt.grad_rows) {
            let ar = s.arity();
            let nl = ar * d;
            let per_pass = grad_pass(s);
            for (e0, &(rlo, rhi)) in (0..s.len()).step_by(per_pass).zip(rows) {
                let e1 = (e0 + per_pass).min(s.len());
                let (lo, hi) = (base + e0 * ar, base + e1 * ar);
                let elements = phases::open(work.phases.as_ref(), Phase::ElementTerms);
                work.grad[..(hi - lo) * d]
                    .par_chunks_mut(CHUNK * nl)
                    .enumerate()
                    .for_each(|(c, buf)| match s {
                        ElementSet::NeoHookean(nh) => {
                            nh.element_gradients_run(x, e0 + c * CHUNK, buf)
                        }
                        ElementSet::Springs(_) => {
                            for (k, b) in buf.chunks_exact_mut(nl).enumerate() {
                                s.gradient(x, e0 + c * CHUNK + k, b);
                            }
                        }
                    });
                drop(elements);
                let _gather = phases::open(work.phases.as_ref(), Phase::Assembly);
                if rlo > rhi {
                    continue;
                }
                let buf = &work.grad[..(hi - lo) * d];
                out[rlo * per_node..(rhi + 1) * per_node]
                    .par_chunks_mut(per_node)
                    .zip(work.grad_cursor[rlo..=rhi].par_iter_mut())
                    .enumerate()
                    .with_min_len(GATHER_CHUNK)
                    .for_each(|(i, (o, cur))| {
                        let end = gt.grad_ptr[rlo + i + 1];
                        while *cur < end {
                            let slot = gt.grad_src[*cur] as usize;
                            if slot >= hi {
                                break;
                            }
                            add(o, &buf[(slot - lo) * d..(slot - lo + 1) * d]);
                            *cur += 1;
                        }
                    });
            }
        }
    }

    /// h += scale·∇²Ψ(x) on the model's pattern (`h` must have it); element matrices are
    /// projected to PSD when `project`.
    pub fn add_potential_hessian(&self, x: &[f64], scale: f64, project: bool, h: &mut BlockCsr) {
        self.add_potential_hessian_with(x, scale, project, h, &mut AssemblyWork::default());
    }

    /// [`Model::add_potential_hessian`] with the element buffer kept in `work`, in passes
    /// over at most `HESS_BUFFER_BLOCKS` element blocks: each pass computes its
    /// elements' matrices in parallel (their upper node blocks), then every block of `h`
    /// in the rows those elements touch adds the pass's contributions in element order
    /// (through the map built with the model, from where the last pass left it). Each
    /// block thus sums its elements one by one in (set, element) order whatever the
    /// passes and threads, and the element buffer is bounded whatever the mesh. No
    /// sorting, searching or allocation once `work` has its size.
    pub fn add_potential_hessian_with(
        &self,
        x: &[f64],
        scale: f64,
        project: bool,
        h: &mut BlockCsr,
        work: &mut AssemblyWork,
    ) {
        self.hessian_passes(x, scale, project, h, work, BlockStart::Values);
    }

    /// h = M + scale·∇²Ψ(x) on the model's pattern: the bits of zeroing h, then
    /// [`Model::add_mass`], then [`Model::add_potential_hessian_with`], in one pass over h
    /// (each block starts from zero and its mass where the assembly first reaches it).
    pub fn mass_and_potential_hessian_with(
        &self,
        x: &[f64],
        scale: f64,
        project: bool,
        h: &mut BlockCsr,
        work: &mut AssemblyWork,
    ) {
        self.hessian_passes(x, scale, project, h, work, BlockStart::Mass);
        // Blocks no element reaches (nodes of no element) hold their mass alone.
        let (d, gt) = (self.dim, &self.gather);
        for (i, &k) in gt.diag.iter().enumerate() {
            if gt.hess_ptr[k] == gt.hess_ptr[k + 1] {
                let blk = &mut h.values[k * d * d..(k + 1) * d * d];
                blk.iter_mut().for_each(|v| *v = 0.0);
                for a in 0..d {
                    blk[a * d + a] = 0.0 + self.mass[i];
                }
            }
        }
    }

    fn hessian_passes(
        &self,
        x: &[f64],
        scale: f64,
        project: bool,
        h: &mut BlockCsr,
        work: &mut AssemblyWork,
        start: BlockStart,
    ) {
        let d = self.dim;
        let dd = d * d;
        let gt = &self.gather;
        let nb = self.pattern.nnz_blocks();
        assert_eq!(h.nnz_blocks(), nb, "h must have the model's pattern");
        let buffer = self
            .sets
            .iter()
            .map(|s| hess_pass(s).min(s.len()) * s.arity() * (s.arity() + 1) / 2)
            .max()
            .unwrap_or(0);
        work.hess.resize(buffer * dd, 0.0);
        work.cursor.clear();
        work.cursor
            .extend(gt.hess_ptr[..nb].iter().map(|&p| p as u32));
        for ((s, &base), rows) in self.sets.iter().zip(&gt.hess_base).zip(&gt.hess_rows) {
            let np = s.arity() * (s.arity() + 1) / 2;
            let per_pass = hess_pass(s);
            for (e0, &(rlo, rhi)) in (0..s.len()).step_by(per_pass).zip(rows) {
                let e1 = (e0 + per_pass).min(s.len());
                let (lo, hi) = (base + e0 * np, base + e1 * np);
                let elements = phases::open(work.phases.as_ref(), Phase::ElementTerms);
                let buf = &mut work.hess[..(hi - lo) * dd];
                buf.par_chunks_mut(CHUNK * np * dd)
                    .enumerate()
                    .for_each(|(c, b)| s.hessian_blocks_run(x, e0 + c * CHUNK, project, b));
                drop(elements);
                let _gather = phases::open(work.phases.as_ref(), Phase::Assembly);
                // The rows the pass's elements touch (a block's slots belong to elements
                // holding its row's node), found with the model.
                if rlo > rhi {
                    continue;
                }
                let (k0, k1) = (self.pattern.row_ptr[rlo], self.pattern.row_ptr[rhi + 1]);
                let g = GatherPass {
                    gather: gt,
                    col_idx: &self.pattern.col_idx,
                    mass: &self.mass,
                    k0,
                    buf: &work.hess[..(hi - lo) * dd],
                    lo,
                    hi,
                    scale,
                    start,
                };
                let (values, cursor) = (&mut h.values[k0 * dd..k1 * dd], &mut work.cursor[k0..k1]);
                match d {
                    2 => g.run::<2>(values, cursor),
                    3 => g.run::<3>(values, cursor),
                    _ => unreachable!("a model is 2D or 3D"),
                }
            }
        }
    }

    /// h += M (the lumped mass on the diagonal blocks).
    pub fn add_mass(&self, h: &mut BlockCsr) {
        let d = self.dim;
        for i in 0..self.n_nodes {
            let k = h.diag_index(i).expect("every node has a diagonal block");
            for a in 0..d {
                h.values[k * d * d + a * d + a] += self.mass[i];
            }
        }
    }

    /// A zero matrix on the Hessian's pattern.
    /// Whether some element set follows `law`.
    pub fn has_law(&self, law: Law) -> bool {
        self.sets
            .iter()
            .any(|s| matches!(s, ElementSet::NeoHookean(nh) if nh.law == law))
    }

    /// The neo-Hookean laws that some element follows, in [`Law`] order: the laws
    /// [`Model::min_volume_ratio`] reports, without evaluating an element.
    pub fn solid_laws(&self) -> Vec<Law> {
        let mut laws: Vec<Law> = self
            .sets
            .iter()
            .filter_map(|s| match s {
                ElementSet::NeoHookean(nh) if !nh.is_empty() => Some(nh.law),
                _ => None,
            })
            .collect();
        laws.sort();
        laws.dedup();
        laws
    }

    /// Per neo-Hookean law of the model (in [`Law`] order): the smallest element volume
    /// ratio J at x with its set and element (within the set). Empty without neo-Hookean
    /// elements.
    pub fn min_volume_ratio(&self, x: &[f64]) -> Vec<MinVolumeRatio> {
        let mut out: Vec<MinVolumeRatio> = Vec::new();
        for (k, s) in self.sets.iter().enumerate() {
            let ElementSet::NeoHookean(nh) = s else {
                continue;
            };
            let Some((j, e)) = nh.min_volume_ratio(x) else {
                continue;
            };
            let m = MinVolumeRatio {
                law: nh.law,
                j,
                set: k,
                element: e,
            };
            match out.iter_mut().find(|o| o.law == nh.law) {
                Some(o) if j < o.j || j.is_nan() => *o = m,
                Some(_) => {}
                None => out.push(m),
            }
        }
        out.sort_by_key(|m| m.law);
        out
    }

    /// The first element (in set and element order) of a neo-Hookean set, either law,
    /// that has J > 0 at `before` and J ≤ 0 (or NaN) at `after`: an element that moving
    /// the nodes from `before` to `after` inverts. Elements already inverted at `before`
    /// are not counted.
    pub fn first_inverted_by(&self, before: &[f64], after: &[f64]) -> Option<MinVolumeRatio> {
        for (k, s) in self.sets.iter().enumerate() {
            let ElementSet::NeoHookean(nh) = s else {
                continue;
            };
            // In parallel, the first such element in order (whatever the threads).
            let inverted = |e: &usize| {
                let j = nh.volume_ratio(after, *e);
                (j.is_nan() || j <= 0.0) && nh.volume_ratio(before, *e) > 0.0
            };
            let first = (0..nh.len())
                .into_par_iter()
                .with_min_len(neohookean::SCAN_CHUNK)
                .find_first(inverted);
            if let Some(e) = first {
                return Some(MinVolumeRatio {
                    law: nh.law,
                    j: nh.volume_ratio(after, e),
                    set: k,
                    element: e,
                });
            }
        }
        None
    }

    /// The largest step along Δx from x before an element of the classical law inverts:
    /// the smallest root α ∈ (0, `max`] of det F(x + αΔx) = 0 over those elements
    /// ([`NeoHookean::inversion_bound`]), with its (set, element), the first in (set,
    /// element) order on ties; None when none inverts on (0, `max`]. Err names an element
    /// already inverted at x, the first in that order.
    pub fn inversion_bound(
        &self,
        x: &[f64],
        dx: &[f64],
        max: f64,
    ) -> Result<Option<InversionLimit>, Inverted> {
        let mut best: Option<InversionLimit> = None;
        for (k, s) in self.sets.iter().enumerate() {
            let ElementSet::NeoHookean(nh) = s else {
                continue;
            };
            if nh.law != Law::NeoHookean {
                continue;
            }
            // Only a root below the earlier sets' bound counts (and is the new bound).
            if let Some((alpha, e)) = nh
                .inversion_bound_below(x, dx, max, best.map(|b| b.alpha))
                .map_err(|(element, j)| Inverted { set: k, element, j })?
            {
                best = Some(InversionLimit {
                    alpha,
                    set: k,
                    element: e,
                });
            }
        }
        Ok(best)
    }

    pub fn zero_matrix(&self) -> BlockCsr {
        self.try_zero_matrix()
            .unwrap_or_else(|e| crate::sim::memory::abort_on(&e))
    }

    /// [`Model::zero_matrix`], allocated fallibly (Err: the bytes of the Hessian).
    pub fn try_zero_matrix(&self) -> Result<BlockCsr, AllocError> {
        let p = &self.pattern;
        let mut row_ptr = try_vec(p.row_ptr.len(), 0usize, "the Hessian")?;
        row_ptr.copy_from_slice(&p.row_ptr);
        let mut col_idx = try_vec(p.col_idx.len(), 0usize, "the Hessian")?;
        col_idx.copy_from_slice(&p.col_idx);
        let values = try_vec(p.nnz_blocks() * p.dim * p.dim, 0.0, "the Hessian")?;
        Ok(BlockCsr {
            dim: p.dim,
            n: p.n,
            row_ptr,
            col_idx,
            values,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// On a mesh of many chunks of elements (10,368 tetrahedra, the scans run in
    /// parallel chunks): the inversion bound is the first strict minimum of the elements'
    /// roots in element order, an inverted element is the first one in that order, and the
    /// smallest J is the first minimum (the last NaN when there is one), as sequential
    /// scans find them.
    #[test]
    fn chunked_scans_find_what_a_sequential_scan_finds() {
        let mut rng = StdRng::seed_from_u64(29);
        let mesh = crate::sim::mesh::cuboid([1.0, 1.0, 1.0], [12, 12, 12]);
        let nh = NeoHookean::new(&mesh, 1e5, 0.3, Law::NeoHookean).expect("valid mesh");
        assert!(nh.len() > 8 * neohookean::SCAN_CHUNK, "several chunks");
        let max = 1.0 / 0.9;
        let sequential_bound = |x: &[f64], dx: &[f64]| {
            let mut want: Option<(f64, usize)> = None;
            for (e, el) in nh.all_nodes().enumerate() {
                let c = neohookean::step_det_polynomial(3, el, x, dx);
                if c[0].is_nan() || c[0] <= 0.0 {
                    return Err(e);
                }
                if let Some(r) = neohookean::first_root(&c, max) {
                    if want.is_none_or(|(w, _)| r < w) {
                        want = Some((r, e));
                    }
                }
            }
            Ok(want)
        };
        let sequential_min = |x: &[f64]| {
            let mut best: Option<(f64, usize)> = None;
            for e in 0..nh.len() {
                let j = nh.volume_ratio(x, e);
                if best.is_none_or(|(b, _)| j < b || j.is_nan()) {
                    best = Some((j, e));
                }
            }
            best
        };
        let bits = |v: Option<(f64, usize)>| v.map(|(r, e)| (r.to_bits(), e));
        let mut rooted = 0;
        for t in 0..8 {
            let size = 10f64.powf(rng.random_range(-2.0..-0.5));
            let x: Vec<f64> = mesh
                .x
                .iter()
                .map(|v| v + rng.random_range(-0.01..0.01))
                .collect();
            let dx: Vec<f64> = (0..x.len())
                .map(|_| size * rng.random_range(-1.0..1.0))
                .collect();
            let got = nh.inversion_bound(&x, &dx, max).map_err(|(e, _)| e);
            let want = sequential_bound(&x, &dx);
            assert_eq!(got.map(bits), want.map(bits), "case {t}");
            rooted += matches!(got, Ok(Some(_))) as usize;
            assert_eq!(
                bits(nh.min_volume_ratio(&x)),
                bits(sequential_min(&x)),
                "case {t}"
            );
        }
        assert!(rooted >= 2, "only {rooted} cases with a root");
        // Two inverted elements in different chunks: the first one is named. Two NaN
        // volume ratios: the last one is the smallest.
        let mut x = mesh.x.clone();
        let late = nh.nodes(7 * neohookean::SCAN_CHUNK + 5)[0];
        let early = nh.nodes(3 * neohookean::SCAN_CHUNK + 2)[0];
        for node in [late, early] {
            x[node * 3 + 2] += 5.0;
        }
        let dx = vec![0.0; x.len()];
        assert_eq!(
            nh.inversion_bound(&x, &dx, max).map_err(|(e, _)| e),
            sequential_bound(&x, &dx)
        );
        assert!(nh.inversion_bound(&x, &dx, max).is_err());
        let mut y = mesh.x.clone();
        y[early * 3] = f64::NAN;
        y[late * 3] = f64::NAN;
        let got = nh.min_volume_ratio(&y).expect("elements");
        assert!(got.0.is_nan());
        assert_eq!(bits(Some(got)), bits(sequential_min(&y)));
        // The first element that moving the nodes inverts, in element order.
        let sequential_first = |before: &[f64], after: &[f64]| {
            (0..nh.len()).find(|&e| {
                let j = nh.volume_ratio(after, e);
                (j.is_nan() || j <= 0.0) && nh.volume_ratio(before, e) > 0.0
            })
        };
        let want = sequential_first(&mesh.x, &x).expect("an inverted element");
        assert!(
            want > neohookean::SCAN_CHUNK,
            "the first inverted element is past a chunk"
        );
        let model = Model::new(
            3,
            vec![1.0; mesh.x.len() / 3],
            None,
            vec![ElementSet::NeoHookean(nh.clone())],
        );
        let got = model
            .first_inverted_by(&mesh.x, &x)
            .expect("an inverted element");
        assert_eq!((got.set, got.element), (0, want));
        assert_eq!(got.j.to_bits(), nh.volume_ratio(&x, want).to_bits());
        assert!(model.first_inverted_by(&mesh.x, &mesh.x).is_none());
    }

    /// The laws a model reports without evaluating an element are those whose volume
    /// ratios it reports: a set of springs and a stable set before a classical one, each
    /// law once.
    #[test]
    fn solid_laws_are_the_laws_of_the_volume_ratios() {
        let mesh = crate::sim::mesh::cuboid([1.0, 1.0, 1.0], [2, 2, 2]);
        let n = mesh.x.len() / 3;
        let springs = Springs::new(3, &mesh.x, vec![[0, 1]], 50.0).expect("valid spring");
        let set =
            |law| ElementSet::NeoHookean(NeoHookean::new(&mesh, 1e5, 0.4, law).expect("mesh"));
        let model = Model::new(
            3,
            vec![1.0; n],
            None,
            vec![
                ElementSet::Springs(springs),
                set(Law::StableNeoHookean),
                set(Law::NeoHookean),
                set(Law::StableNeoHookean),
            ],
        );
        let reported: Vec<Law> = model
            .min_volume_ratio(&mesh.x)
            .iter()
            .map(|m| m.law)
            .collect();
        assert_eq!(model.solid_laws(), reported);
        assert_eq!(reported, vec![Law::NeoHookean, Law::StableNeoHookean]);
        let plain = Model::new(3, vec![1.0; n], None, Vec::new());
        assert!(plain.solid_laws().is_empty() && plain.min_volume_ratio(&mesh.x).is_empty());
    }

    /// h = M + scale·∇²Ψ in one pass over h gives the bits of zeroing h, adding the mass,
    /// then adding the elements, on meshes of several passes in 2D and 3D with a node of
    /// no element (its block holds its mass alone) and masses that differ per node; and
    /// it overwrites whatever h held.
    #[test]
    fn mass_and_hessian_in_one_pass_equal_the_three_passes_bit_for_bit() {
        let mut rng = StdRng::seed_from_u64(5);
        for d in [2, 3] {
            let mesh = if d == 2 {
                crate::sim::mesh::rectangle(2, [1.0, 1.0], [90, 90])
            } else {
                crate::sim::mesh::cuboid([1.0, 1.0, 1.0], [12, 12, 12])
            };
            let nh = NeoHookean::new(&mesh, 1e5, 0.4, Law::NeoHookean).expect("valid mesh");
            // One node beyond the mesh, in no element.
            let n = mesh.x.len() / d + 1;
            let mass: Vec<f64> = (0..n).map(|_| rng.random_range(0.5..2.0)).collect();
            let model = Model::new(d, mass, None, vec![ElementSet::NeoHookean(nh)]);
            let mut x: Vec<f64> = mesh
                .x
                .iter()
                .map(|v| 1.1 * v + rng.random_range(-0.004..0.004))
                .collect();
            x.extend(std::iter::repeat_n(2.0, d));
            let scale = 0.37;
            let mut want = model.zero_matrix();
            model.add_mass(&mut want);
            let mut work = AssemblyWork::default();
            model.add_potential_hessian_with(&x, scale, true, &mut want, &mut work);
            let mut got = model.zero_matrix();
            got.values
                .iter_mut()
                .for_each(|v| *v = rng.random_range(-1.0..1.0));
            model.mass_and_potential_hessian_with(&x, scale, true, &mut got, &mut work);
            let bits = |v: &[f64]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert!(bits(&got.values) == bits(&want.values), "{d}D");
            let k = got.diag_index(n - 1).expect("diagonal block");
            assert_eq!(
                got.values[k * d * d],
                model.mass[n - 1],
                "{d}D: the lone node"
            );
        }
    }

    /// The assembly in passes (a mesh of several passes, both laws, 2D and 3D) against
    /// the plainest one: every element's full reference matrix (and gradient) added into
    /// its blocks (nodes) one element after another. Equal bit for bit: each block sums
    /// the same terms in the same order.
    #[test]
    fn assembly_in_passes_equals_the_sequential_sum_bit_for_bit() {
        let mut rng = StdRng::seed_from_u64(3);
        for d in [2, 3] {
            let mesh = if d == 2 {
                crate::sim::mesh::rectangle(2, [1.0, 1.0], [120, 120])
            } else {
                crate::sim::mesh::cuboid([1.0, 1.0, 1.0], [14, 14, 14])
            };
            for law in [Law::NeoHookean, Law::StableNeoHookean] {
                let nh = NeoHookean::new(&mesh, 1e5, 0.4, law).expect("valid mesh");
                let np = (d + 1) * (d + 2) / 2;
                assert!(
                    nh.len() * np > 2 * gather::HESS_BUFFER_BLOCKS,
                    "several passes"
                );
                let n = mesh.x.len() / d;
                let model = Model::new(d, vec![1.0; n], None, vec![ElementSet::NeoHookean(nh)]);
                let x: Vec<f64> = mesh
                    .x
                    .iter()
                    .map(|v| 1.1 * v + rng.random_range(-0.004..0.004))
                    .collect();
                let scale = 0.37;
                let mut h = model.zero_matrix();
                let mut work = AssemblyWork::default();
                model.add_potential_hessian_with(&x, scale, true, &mut h, &mut work);
                let mut g = vec![0.0; n * d];
                model.add_potential_gradient_with(&x, scale, &mut g, &mut work);
                let mut want_h = model.zero_matrix();
                let mut want_g = vec![0.0; n * d];
                let s = &model.sets[0];
                let nl = (d + 1) * d;
                let (mut m, mut ge) = (vec![0.0; nl * nl], vec![0.0; nl]);
                for e in 0..s.len() {
                    let ElementSet::NeoHookean(nh) = s else {
                        unreachable!("one neo-Hookean set")
                    };
                    nh.element_hessian(&x, e, true, &mut m);
                    nh.element_gradient(&x, e, &mut ge);
                    let nodes = s.nodes(e);
                    for (a, &na) in nodes.iter().enumerate() {
                        for c in 0..d {
                            want_g[na * d + c] += scale * ge[a * d + c];
                        }
                        for (b, &nb) in nodes.iter().enumerate() {
                            let k = want_h.find(na, nb).expect("pattern pair");
                            for r in 0..d {
                                for c in 0..d {
                                    want_h.values[k * d * d + r * d + c] +=
                                        scale * m[(a * d + r) * nl + b * d + c];
                                }
                            }
                        }
                    }
                }
                let bits = |v: &[f64]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
                assert!(bits(&h.values) == bits(&want_h.values), "{d}D {law:?}: H");
                assert!(bits(&g) == bits(&want_g), "{d}D {law:?}: gradient");
            }
        }
    }
}
