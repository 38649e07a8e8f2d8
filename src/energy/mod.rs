//! Energies of the incremental potential and their assembly.
//!
//! E(x) = ½ (x − x̃)ᵀ M (x − x̃) + h² Ψ(x), Ψ = elastic + gravity. Only the terms a scene
//! uses exist in a [`Model`]: no gravity term when g = 0, one element set per body.
//! Element gradients and (PSD-projected) Hessians are computed in parallel with rayon into
//! flat per-element buffers, then scattered into a block-sparse matrix whose pattern is
//! built once (scatter indices precomputed), so no locking and a deterministic sum order.

pub mod barrier;
pub mod eigensystem;
pub mod gravity;
pub mod inertia;
pub mod neohookean;
pub mod spring;

use crate::sparse::BlockCsr;
use rayon::prelude::*;

pub use neohookean::NeoHookean;
pub use spring::Springs;

/// One body's elastic elements.
#[derive(Debug, Clone)]
pub enum ElementSet {
    Springs(Springs),
    NeoHookean(NeoHookean),
}

impl ElementSet {
    pub fn len(&self) -> usize {
        match self {
            ElementSet::Springs(s) => s.edges.len(),
            ElementSet::NeoHookean(s) => s.elements.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn nodes(&self, e: usize) -> &[usize] {
        match self {
            ElementSet::Springs(s) => &s.edges[e],
            ElementSet::NeoHookean(s) => &s.elements[e],
        }
    }

    /// Nodes per element.
    pub fn arity(&self) -> usize {
        match self {
            ElementSet::Springs(_) => 2,
            ElementSet::NeoHookean(s) => s.dim + 1,
        }
    }

    pub fn energy(&self, x: &[f64], e: usize) -> f64 {
        match self {
            ElementSet::Springs(s) => s.element_energy(x, e),
            ElementSet::NeoHookean(s) => s.element_energy(x, e),
        }
    }

    pub fn gradient(&self, x: &[f64], e: usize, out: &mut [f64]) {
        match self {
            ElementSet::Springs(s) => s.element_gradient(x, e, out),
            ElementSet::NeoHookean(s) => s.element_gradient(x, e, out),
        }
    }

    pub fn hessian(&self, x: &[f64], e: usize, project: bool, out: &mut [f64]) {
        match self {
            ElementSet::Springs(s) => s.element_hessian(x, e, project, out),
            ElementSet::NeoHookean(s) => s.element_hessian(x, e, project, out),
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
    /// Per set: per element, arity² block indices into `pattern` (row-major node pairs).
    scatter: Vec<Vec<usize>>,
    /// The Hessian's block pattern (diagonal of every node plus element couplings).
    pub pattern: BlockCsr,
}

impl Model {
    pub fn new(
        dim: usize,
        mass: Vec<f64>,
        gravity: Option<Vec<f64>>,
        sets: Vec<ElementSet>,
    ) -> Self {
        let n = mass.len();
        let mut rows: Vec<Vec<usize>> = (0..n).map(|i| vec![i]).collect();
        for s in &sets {
            for e in 0..s.len() {
                let nodes = s.nodes(e);
                for &a in nodes {
                    for &b in nodes {
                        rows[a].push(b);
                    }
                }
            }
        }
        for r in rows.iter_mut() {
            r.sort_unstable();
            r.dedup();
        }
        let pattern = BlockCsr::from_pattern(dim, &rows);
        let scatter = sets
            .iter()
            .map(|s| {
                let mut idx = Vec::with_capacity(s.len() * s.arity() * s.arity());
                for e in 0..s.len() {
                    let nodes = s.nodes(e);
                    for &a in nodes {
                        for &b in nodes {
                            idx.push(
                                pattern
                                    .find(a, b)
                                    .expect("pattern holds every element pair"),
                            );
                        }
                    }
                }
                idx
            })
            .collect();
        let gravity = gravity.filter(|g| g.iter().any(|&v| v != 0.0));
        Model {
            dim,
            n_nodes: n,
            mass,
            gravity,
            sets,
            scatter,
            pattern,
        }
    }

    pub fn ndof(&self) -> usize {
        self.dim * self.n_nodes
    }

    pub fn total_mass(&self) -> f64 {
        self.mass.iter().sum()
    }

    /// Elastic energy Σ_sets Σ_e Ψ_e(x).
    pub fn elastic_energy(&self, x: &[f64]) -> f64 {
        self.sets
            .iter()
            .map(|s| {
                (0..s.len())
                    .into_par_iter()
                    .map(|e| s.energy(x, e))
                    .sum::<f64>()
            })
            .sum()
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
        let d = self.dim;
        for s in &self.sets {
            let nl = s.arity() * d;
            let mut buf = vec![0.0; s.len() * nl];
            buf.par_chunks_mut(nl)
                .enumerate()
                .for_each(|(e, b)| s.gradient(x, e, b));
            for e in 0..s.len() {
                for (a, &node) in s.nodes(e).iter().enumerate() {
                    for c in 0..d {
                        out[node * d + c] += scale * buf[e * nl + a * d + c];
                    }
                }
            }
        }
        if let Some(g) = &self.gravity {
            gravity::add_gradient(&self.mass, d, g, scale, out);
        }
    }

    /// h += scale·∇²Ψ(x) on the model's pattern (`h` must have it); element matrices are
    /// projected to PSD when `project`.
    pub fn add_potential_hessian(&self, x: &[f64], scale: f64, project: bool, h: &mut BlockCsr) {
        let d = self.dim;
        let dd = d * d;
        for (s, idx) in self.sets.iter().zip(&self.scatter) {
            let ar = s.arity();
            let nl = ar * d;
            let mut buf = vec![0.0; s.len() * nl * nl];
            buf.par_chunks_mut(nl * nl)
                .enumerate()
                .for_each(|(e, b)| s.hessian(x, e, project, b));
            for e in 0..s.len() {
                let m = &buf[e * nl * nl..(e + 1) * nl * nl];
                for a in 0..ar {
                    for b in 0..ar {
                        let k = idx[e * ar * ar + a * ar + b];
                        let blk = &mut h.values[k * dd..(k + 1) * dd];
                        for r in 0..d {
                            for c in 0..d {
                                blk[r * d + c] += scale * m[(a * d + r) * nl + b * d + c];
                            }
                        }
                    }
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
    pub fn zero_matrix(&self) -> BlockCsr {
        self.pattern.clone()
    }
}

/// Projects a symmetric n×n row-major matrix to the nearest PSD one (eigenvalues clamped
/// at zero). Exact symmetry is restored first, so round-off cannot leak in.
pub fn project_psd(n: usize, m: &mut [f64]) {
    let mut a = nalgebra::DMatrix::<f64>::zeros(n, n);
    for r in 0..n {
        for c in 0..n {
            a[(r, c)] = 0.5 * (m[r * n + c] + m[c * n + r]);
        }
    }
    let eig = nalgebra::SymmetricEigen::new(a);
    if eig.eigenvalues.iter().all(|&l| l >= 0.0) {
        return;
    }
    let mut out = nalgebra::DMatrix::<f64>::zeros(n, n);
    for (k, &l) in eig.eigenvalues.iter().enumerate() {
        if l > 0.0 {
            let v = eig.eigenvectors.column(k);
            out += l * v * v.transpose();
        }
    }
    for r in 0..n {
        for c in 0..n {
            m[r * n + c] = out[(r, c)];
        }
    }
}
