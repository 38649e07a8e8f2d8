//! One body's elastic elements: springs or a neo-Hookean law, behind one interface for
//! the model's loops.

use super::kernels;
use super::neohookean::NeoHookean;
use super::spring::Springs;

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
            ElementSet::NeoHookean(s) => s.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn nodes(&self, e: usize) -> &[usize] {
        match self {
            ElementSet::Springs(s) => &s.edges[e],
            ElementSet::NeoHookean(s) => s.nodes(e),
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
            ElementSet::NeoHookean(s) => s.element_energy_fast(x, e),
        }
    }

    pub fn gradient(&self, x: &[f64], e: usize, out: &mut [f64]) {
        match self {
            ElementSet::Springs(s) => s.element_gradient(x, e, out),
            ElementSet::NeoHookean(s) => s.element_gradient_fast(x, e, out),
        }
    }

    /// The Hessians of the elements `first..` as their upper node blocks, one element
    /// after another filling `out` ([`ElementSet::hessian_blocks`] of each).
    pub fn hessian_blocks_run(&self, x: &[f64], first: usize, project: bool, out: &mut [f64]) {
        match self {
            ElementSet::NeoHookean(s) => s.element_hessian_blocks_run(x, first, project, out),
            ElementSet::Springs(_) => {
                let size = self.arity() * (self.arity() + 1) / 2 * self.dim_of() * self.dim_of();
                for (k, o) in out.chunks_exact_mut(size).enumerate() {
                    self.hessian_blocks(x, first + k, project, o);
                }
            }
        }
    }

    fn dim_of(&self) -> usize {
        match self {
            ElementSet::Springs(s) => s.dim,
            ElementSet::NeoHookean(s) => s.dim,
        }
    }

    /// The Hessian of element e as its upper node blocks (a ≤ b, each d×d row-major), the
    /// slots of the assembly's element buffer.
    pub fn hessian_blocks(&self, x: &[f64], e: usize, project: bool, out: &mut [f64]) {
        match self {
            ElementSet::Springs(s) => {
                let mut m = [0.0f64; 36];
                let nl = 2 * s.dim;
                s.element_hessian(x, e, project, &mut m[..nl * nl]);
                kernels::upper_blocks_of(s.dim, 2, &m[..nl * nl], out);
            }
            ElementSet::NeoHookean(s) => s.element_hessian_blocks(x, e, project, out),
        }
    }

    pub fn hessian(&self, x: &[f64], e: usize, project: bool, out: &mut [f64]) {
        match self {
            ElementSet::Springs(s) => s.element_hessian(x, e, project, out),
            ElementSet::NeoHookean(s) => s.element_hessian(x, e, project, out),
        }
    }
}
