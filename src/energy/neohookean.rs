//! Stable neo-Hookean elasticity (Smith, de Goes, Kim 2018) on linear triangles (2D) and
//! tetrahedra (3D):
//!
//! ```text
//! Ψ(F) = μ/2 (I_C − d) + λ/2 (J − α)² − μ/2 ln(I_C + 1) − Ψ(I),   α = 1 + μ d / (λ (d+1))
//! ```
//!
//! It is defined for inverted elements (J ≤ 0), so the line search needs no inversion
//! filter. μ, λ are remapped from the Lamé parameters of (E, ν) so that the small-strain
//! response is linear elasticity with those E and ν: μ = μ_L (d+1)/d,
//! λ = λ_L + μ_L − 2μ/(d+1)² (Smith et al. §3.4 for d = 3; the same algebra for d = 2).

use crate::mesh::Mesh;

/// Neo-Hookean elements of one body: rest shape data per element.
#[derive(Debug, Clone)]
pub struct NeoHookean {
    pub dim: usize,
    pub elements: Vec<Vec<usize>>,
    /// Per element: the gradients of the d+1 barycentric shape functions in the rest
    /// shape, G[a][j] (node a, axis j), flattened (d+1)·d.
    shape_grads: Vec<f64>,
    /// Rest measure per element.
    pub volume: Vec<f64>,
    pub mu: f64,
    pub lambda: f64,
    alpha: f64,
    rest_density: f64,
}

/// Lamé parameters (μ_L, λ_L) of Young's modulus and Poisson ratio.
pub fn lame(young: f64, poisson: f64) -> (f64, f64) {
    let mu = young / (2.0 * (1.0 + poisson));
    let lambda = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson));
    (mu, lambda)
}

/// An element whose rest volume is at most this fraction of (longest edge from its first
/// node)^d is degenerate: 64ε, rounding of the edge vectors' products.
pub const DEGENERATE_RELATIVE_VOLUME: f64 = 64.0 * f64::EPSILON;

impl NeoHookean {
    /// Builds the elements of `mesh` (its positions are the rest shape). Fails when an
    /// element is degenerate or inverted at rest.
    pub fn new(mesh: &Mesh, young: f64, poisson: f64) -> Result<Self, String> {
        let d = mesh.dim;
        let nn = d + 1;
        if mesh.elements.first().is_some_and(|e| e.len() != nn) {
            return Err(format!(
                "neo-Hookean needs {} elements in {d}D",
                if d == 2 { "triangle" } else { "tetrahedron" }
            ));
        }
        let (mu_l, lambda_l) = lame(young, poisson);
        let df = d as f64;
        let mu = mu_l * (df + 1.0) / df;
        let lambda = lambda_l + mu_l - 2.0 * mu / ((df + 1.0) * (df + 1.0));
        let alpha = 1.0 + mu * df / (lambda * (df + 1.0));
        let mut shape_grads = Vec::with_capacity(mesh.elements.len() * nn * d);
        let mut volume = Vec::with_capacity(mesh.elements.len());
        for (e, el) in mesh.elements.iter().enumerate() {
            let mut dm = nalgebra::DMatrix::<f64>::zeros(d, d);
            for a in 1..nn {
                for i in 0..d {
                    dm[(i, a - 1)] = mesh.x[el[a] * d + i] - mesh.x[el[0] * d + i];
                }
            }
            let det = dm.determinant();
            // NaN (a non-finite rest position) is rejected explicitly, like det ≤ 0.
            if det.is_nan() || det <= 0.0 {
                return Err(format!("element {e} is degenerate or inverted at rest"));
            }
            // Flat beyond f64's resolution (a box 1e-300 thick): its volume relative to its
            // longest edge^d is rounding, and its shape gradients would overflow.
            let longest = (0..d).map(|c| dm.column(c).norm()).fold(0.0f64, f64::max);
            let relative = (&dm / longest).determinant();
            if relative.is_nan() || relative <= DEGENERATE_RELATIVE_VOLUME {
                return Err(format!(
                    "element {e} is degenerate at rest: its volume is {relative:.1e} of its \
                     longest edge to the power {d}, below f64's resolution (a mesh flatter \
                     than its coordinates can resolve)"
                ));
            }
            volume.push(det / if d == 2 { 2.0 } else { 6.0 });
            let inv = dm
                .try_inverse()
                .ok_or_else(|| format!("element {e} is degenerate at rest"))?;
            // F = Ds Dm⁻¹ ⇒ ∂F_ij/∂x_{a,i} = (Dm⁻¹)_{a−1, j} for a ≥ 1; node 0 takes minus the sum.
            let mut g0 = vec![0.0; d];
            let start = shape_grads.len();
            shape_grads.extend(std::iter::repeat_n(0.0, nn * d));
            for a in 1..nn {
                for j in 0..d {
                    let v = inv[(a - 1, j)];
                    shape_grads[start + a * d + j] = v;
                    g0[j] -= v;
                }
            }
            shape_grads[start..start + d].copy_from_slice(&g0);
        }
        let mut s = NeoHookean {
            dim: d,
            elements: mesh.elements.clone(),
            shape_grads,
            volume,
            mu,
            lambda,
            alpha,
            rest_density: 0.0,
        };
        let mut id = [0.0; 9];
        for a in 0..d {
            id[a * d + a] = 1.0;
        }
        s.rest_density = s.density_raw(&id[..d * d]);
        Ok(s)
    }

    fn grads(&self, e: usize) -> &[f64] {
        let k = (self.dim + 1) * self.dim;
        &self.shape_grads[e * k..(e + 1) * k]
    }

    /// Deformation gradient of element e, row-major d×d.
    pub fn deformation_gradient(&self, x: &[f64], e: usize, f: &mut [f64]) {
        let d = self.dim;
        let g = self.grads(e);
        f[..d * d].iter_mut().for_each(|v| *v = 0.0);
        for (a, &node) in self.elements[e].iter().enumerate() {
            for i in 0..d {
                let xi = x[node * d + i];
                for j in 0..d {
                    f[i * d + j] += xi * g[a * d + j];
                }
            }
        }
    }

    fn density_raw(&self, f: &[f64]) -> f64 {
        let d = self.dim;
        let ic: f64 = f[..d * d].iter().map(|v| v * v).sum();
        let j = det(d, f);
        0.5 * self.mu * (ic - d as f64) + 0.5 * self.lambda * (j - self.alpha).powi(2)
            - 0.5 * self.mu * (ic + 1.0).ln()
    }

    /// Ψ(F) per unit rest volume, zero at F = I.
    pub fn density(&self, f: &[f64]) -> f64 {
        self.density_raw(f) - self.rest_density
    }

    /// First Piola–Kirchhoff stress ∂Ψ/∂F, row-major.
    pub fn stress(&self, f: &[f64], p: &mut [f64]) {
        let d = self.dim;
        let ic: f64 = f[..d * d].iter().map(|v| v * v).sum();
        let j = det(d, f);
        let mut c = [0.0; 9];
        cofactor(d, f, &mut c);
        let s = self.mu - self.mu / (ic + 1.0);
        let t = self.lambda * (j - self.alpha);
        for k in 0..d * d {
            p[k] = s * f[k] + t * c[k];
        }
    }

    /// ∂²Ψ/∂F², d²×d² row-major over row-major vec(F).
    pub fn stress_derivative(&self, f: &[f64], out: &mut [f64]) {
        let d = self.dim;
        let dd = d * d;
        let ic: f64 = f[..dd].iter().map(|v| v * v).sum();
        let j = det(d, f);
        let mut c = [0.0; 9];
        cofactor(d, f, &mut c);
        let s = self.mu - self.mu / (ic + 1.0);
        let q = 2.0 * self.mu / ((ic + 1.0) * (ic + 1.0));
        let t = self.lambda * (j - self.alpha);
        for r in 0..dd {
            for k in 0..dd {
                let mut v = q * f[r] * f[k] + self.lambda * c[r] * c[k];
                if r == k {
                    v += s;
                }
                out[r * dd + k] = v;
            }
        }
        // + t ∂²J/∂F².
        if d == 2 {
            // J = F00 F11 − F01 F10.
            out[3] += t;
            out[3 * 4] += t;
            out[4 + 2] -= t;
            out[2 * 4 + 1] -= t;
        } else {
            // ∂²J/∂F_ij ∂F_kl = Σ_mn ε_ikm ε_jln F_mn.
            for i in 0..3 {
                for jj in 0..3 {
                    for k in 0..3 {
                        if k == i {
                            continue;
                        }
                        let m = 3 - i - k;
                        let eik = levi(i, k, m);
                        for l in 0..3 {
                            if l == jj {
                                continue;
                            }
                            let n = 3 - jj - l;
                            let v = eik * levi(jj, l, n) * f[m * 3 + n];
                            out[(i * 3 + jj) * 9 + k * 3 + l] += t * v;
                        }
                    }
                }
            }
        }
    }

    /// Energy of element e.
    pub fn element_energy(&self, x: &[f64], e: usize) -> f64 {
        let mut f = [0.0; 9];
        self.deformation_gradient(x, e, &mut f);
        self.volume[e] * self.density(&f[..self.dim * self.dim])
    }

    /// Gradient of element e w.r.t. its (d+1)·d node coordinates.
    pub fn element_gradient(&self, x: &[f64], e: usize, out: &mut [f64]) {
        let d = self.dim;
        let mut f = [0.0; 9];
        let mut p = [0.0; 9];
        self.deformation_gradient(x, e, &mut f);
        self.stress(&f, &mut p);
        let g = self.grads(e);
        let v = self.volume[e];
        for a in 0..=d {
            for c in 0..d {
                out[a * d + c] = v * (0..d).map(|j| p[c * d + j] * g[a * d + j]).sum::<f64>();
            }
        }
    }

    /// Hessian of element e, ((d+1)d)² row-major; projected to PSD when `project`.
    pub fn element_hessian(&self, x: &[f64], e: usize, project: bool, out: &mut [f64]) {
        let d = self.dim;
        let dd = d * d;
        let nl = (d + 1) * d;
        let mut f = [0.0; 9];
        let mut h = [0.0; 81];
        self.deformation_gradient(x, e, &mut f);
        self.stress_derivative(&f, &mut h);
        let g = self.grads(e);
        let v = self.volume[e];
        for a in 0..=d {
            for c in 0..d {
                for b in 0..=d {
                    for ee in 0..d {
                        let mut s = 0.0;
                        for j in 0..d {
                            for l in 0..d {
                                s += h[(c * d + j) * dd + ee * d + l] * g[a * d + j] * g[b * d + l];
                            }
                        }
                        out[(a * d + c) * nl + b * d + ee] = v * s;
                    }
                }
            }
        }
        if project {
            super::project_psd(nl, out);
        }
    }
}

fn levi(i: usize, j: usize, k: usize) -> f64 {
    match (i, j, k) {
        (0, 1, 2) | (1, 2, 0) | (2, 0, 1) => 1.0,
        (0, 2, 1) | (2, 1, 0) | (1, 0, 2) => -1.0,
        _ => 0.0,
    }
}

fn det(d: usize, f: &[f64]) -> f64 {
    if d == 2 {
        f[0] * f[3] - f[1] * f[2]
    } else {
        f[0] * (f[4] * f[8] - f[5] * f[7]) - f[1] * (f[3] * f[8] - f[5] * f[6])
            + f[2] * (f[3] * f[7] - f[4] * f[6])
    }
}

/// ∂J/∂F (the cofactor matrix), row-major.
fn cofactor(d: usize, f: &[f64], c: &mut [f64]) {
    if d == 2 {
        c[0] = f[3];
        c[1] = -f[2];
        c[2] = -f[1];
        c[3] = f[0];
    } else {
        for i in 0..3 {
            for j in 0..3 {
                let (i1, i2) = ((i + 1) % 3, (i + 2) % 3);
                let (j1, j2) = ((j + 1) % 3, (j + 2) % 3);
                c[i * 3 + j] = f[i1 * 3 + j1] * f[i2 * 3 + j2] - f[i1 * 3 + j2] * f[i2 * 3 + j1];
            }
        }
    }
}
