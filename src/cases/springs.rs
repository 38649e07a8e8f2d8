//! Mass-spring incremental potential: the CPU reference for the GPU's matrix-free,
//! element-by-element Hessian product (shaders/springs.wgsl).
//!
//! E(x) = ½ Σ_i m_i ‖x_i − x̃_i‖² + h² Σ_e ½ k_e (‖x_i − x_j‖ − L_e)²
//!
//! Each spring's Hessian block K_e = k_e [u uᵀ + (1 − L/l)(I − u uᵀ)] has the eigenvalue
//! k_e along u and k_e(1 − L/l) across it; the latter is negative for a compressed spring,
//! so it is clamped at zero (projected Newton): K_e = k_e [(1 − t) u uᵀ + t I] with
//! t = max(0, 1 − L/l). H = M + h² Σ_e [K_e −K_e; −K_e K_e] is then SPD.

// Index loops mirror the math (node i, component a) like the rest of the crate.
#![allow(clippy::needless_range_loop)]

use crate::core::sparse::BlockCsr;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

#[derive(Debug, Clone, PartialEq)]
pub struct MassSpring {
    pub dim: usize,
    /// Current positions x, d per node.
    pub positions: Vec<f64>,
    /// Springs as node pairs.
    pub edges: Vec<[usize; 2]>,
    pub rest_lengths: Vec<f64>,
    pub stiffness: Vec<f64>,
    /// Lumped mass per node.
    pub masses: Vec<f64>,
    /// Time step.
    pub h: f64,
}

impl MassSpring {
    pub fn n_nodes(&self) -> usize {
        self.masses.len()
    }

    pub fn ndof(&self) -> usize {
        self.dim * self.n_nodes()
    }

    /// The clamped (PSD) Hessian block K_e of spring e, row-major, without the h² factor.
    /// A spring of zero length has no direction and contributes nothing.
    pub fn spring_hessian(&self, e: usize) -> [f64; 9] {
        let d = self.dim;
        let [i, j] = self.edges[e];
        let mut dx = [0.0f64; 3];
        for a in 0..d {
            dx[a] = self.positions[i * d + a] - self.positions[j * d + a];
        }
        let l = dx[..d].iter().map(|v| v * v).sum::<f64>().sqrt();
        let mut k = [0.0f64; 9];
        if l > 0.0 {
            let t = (1.0 - self.rest_lengths[e] / l).max(0.0);
            let s = self.stiffness[e];
            for r in 0..d {
                for c in 0..d {
                    let uu = (dx[r] / l) * (dx[c] / l);
                    k[r * d + c] = s * ((1.0 - t) * uu + if r == c { t } else { 0.0 });
                }
            }
        }
        k
    }

    /// H = M + h² Σ_e K_e, assembled (both triangles).
    pub fn assemble(&self) -> BlockCsr {
        let n = self.n_nodes();
        let d = self.dim;
        let mut rows: Vec<Vec<usize>> = (0..n).map(|i| vec![i]).collect();
        for &[i, j] in &self.edges {
            rows[i].push(j);
            rows[j].push(i);
        }
        for r in rows.iter_mut() {
            r.sort_unstable();
            r.dedup();
        }
        let mut h = BlockCsr::from_pattern(d, &rows);
        let h2 = self.h * self.h;
        for (e, &[i, j]) in self.edges.iter().enumerate() {
            let k = self.spring_hessian(e);
            for (p, q, sign) in [(i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)] {
                let kb = h.find(p, q).expect("pattern holds every spring");
                for c in 0..d * d {
                    h.values[kb * d * d + c] += sign * h2 * k[c];
                }
            }
        }
        for i in 0..n {
            let kb = h.diag_index(i).expect("diagonal present");
            for a in 0..d {
                h.values[kb * d * d + a * d + a] += self.masses[i];
            }
        }
        h
    }

    /// out = H w without assembling H (the CPU twin of the GPU kernel).
    pub fn apply(&self, w: &[f64], out: &mut [f64]) {
        let d = self.dim;
        for i in 0..self.n_nodes() {
            for a in 0..d {
                out[i * d + a] = self.masses[i] * w[i * d + a];
            }
        }
        let h2 = self.h * self.h;
        for (e, &[i, j]) in self.edges.iter().enumerate() {
            let k = self.spring_hessian(e);
            for r in 0..d {
                let mut s = 0.0;
                for c in 0..d {
                    s += k[r * d + c] * (w[i * d + c] - w[j * d + c]);
                }
                out[i * d + r] += h2 * s;
                out[j * d + r] -= h2 * s;
            }
        }
    }

    /// ∇E at the current positions for the inertial target x̃ (d per node).
    pub fn gradient(&self, x_tilde: &[f64]) -> Vec<f64> {
        let d = self.dim;
        let mut g: Vec<f64> = (0..self.ndof())
            .map(|k| self.masses[k / d] * (self.positions[k] - x_tilde[k]))
            .collect();
        let h2 = self.h * self.h;
        for (e, &[i, j]) in self.edges.iter().enumerate() {
            let mut dx = [0.0f64; 3];
            for a in 0..d {
                dx[a] = self.positions[i * d + a] - self.positions[j * d + a];
            }
            let l = dx[..d].iter().map(|v| v * v).sum::<f64>().sqrt();
            if l > 0.0 {
                let f = h2 * self.stiffness[e] * (l - self.rest_lengths[e]) / l;
                for a in 0..d {
                    g[i * d + a] += f * dx[a];
                    g[j * d + a] -= f * dx[a];
                }
            }
        }
        g
    }

    /// A jittered grid of `grid` nodes per axis with springs to the mesh neighbours
    /// (2D: 8-neighbourhood; 3D: 14), rest lengths perturbed by ±20 % so that some
    /// springs are compressed (and get clamped) and some stretched.
    pub fn random_grid(dim: usize, grid: [usize; 3], seed: u64) -> Self {
        assert!(dim == 2 || dim == 3, "dimension must be 2 or 3");
        let mut rng = StdRng::seed_from_u64(seed);
        let gz = if dim == 2 { 1 } else { grid[2] };
        let grid = [grid[0], grid[1], gz];
        let mut positions = Vec::new();
        for c in crate::cases::generate::grid_coords(grid) {
            for &v in &c[..dim] {
                positions.push(v as f64 + rng.random_range(-0.1..0.1));
            }
        }
        let offs =
            crate::cases::generate::stencil_offsets(dim, crate::cases::generate::Stencil::Mesh);
        let edges: Vec<[usize; 2]> = crate::cases::generate::grid_edges(grid, offs)
            .into_iter()
            .map(|(i, j, _)| [i, j])
            .collect();
        let n = positions.len() / dim;
        let mut rest_lengths = Vec::with_capacity(edges.len());
        for &[i, j] in &edges {
            let l = (0..dim)
                .map(|a| (positions[i * dim + a] - positions[j * dim + a]).powi(2))
                .sum::<f64>()
                .sqrt();
            rest_lengths.push(l * rng.random_range(0.8..1.2));
        }
        let stiffness = (0..edges.len())
            .map(|_| rng.random_range(50.0..150.0))
            .collect();
        let masses = (0..n).map(|_| rng.random_range(0.5..1.5)).collect();
        MassSpring {
            dim,
            positions,
            edges,
            rest_lengths,
            stiffness,
            masses,
            h: 0.01,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrix_free_equals_assembled_and_blocks_are_psd() {
        for dim in [2, 3] {
            let ms = MassSpring::random_grid(dim, [4, 3, 3], 7);
            let h = ms.assemble();
            assert!(h.check_symmetric().is_ok());
            let n = ms.ndof();
            let w: Vec<f64> = (0..n).map(|k| ((k * 31) % 17) as f64 - 8.0).collect();
            let mut a = vec![0.0; n];
            let mut b = vec![0.0; n];
            ms.apply(&w, &mut a);
            h.matvec(&w, &mut b);
            let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for k in 0..n {
                assert!((a[k] - b[k]).abs() <= 1e-13 * scale);
            }
            let mut clamped = 0;
            for e in 0..ms.edges.len() {
                let k = ms.spring_hessian(e);
                let m = nalgebra::DMatrix::from_row_slice(dim, dim, &k[..dim * dim]);
                let ev = m.symmetric_eigenvalues();
                assert!(ev.iter().all(|&v| v >= -1e-12 * ms.stiffness[e]));
                if ev.iter().any(|&v| v.abs() <= 1e-12 * ms.stiffness[e]) {
                    clamped += 1;
                }
            }
            assert!(clamped > 0, "some compressed spring must be clamped");
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let ms = MassSpring::random_grid(3, [3, 3, 2], 3);
        let xt: Vec<f64> = ms.positions.iter().map(|v| v + 0.01).collect();
        let g = ms.gradient(&xt);
        let energy = |m: &MassSpring| -> f64 {
            let d = m.dim;
            let mut e = 0.0;
            for k in 0..m.ndof() {
                e += 0.5 * m.masses[k / d] * (m.positions[k] - xt[k]).powi(2);
            }
            for (s, &[i, j]) in m.edges.iter().enumerate() {
                let l = (0..d)
                    .map(|a| (m.positions[i * d + a] - m.positions[j * d + a]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                e += m.h * m.h * 0.5 * m.stiffness[s] * (l - m.rest_lengths[s]).powi(2);
            }
            e
        };
        for k in [0, 5, 17] {
            let mut p = ms.clone();
            let mut q = ms.clone();
            p.positions[k] += 1e-6;
            q.positions[k] -= 1e-6;
            let fd = (energy(&p) - energy(&q)) / 2e-6;
            assert!(
                (fd - g[k]).abs() <= 1e-6 * (1.0 + g[k].abs()),
                "{k}: {fd} vs {}",
                g[k]
            );
        }
    }
}
