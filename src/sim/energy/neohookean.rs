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

use super::eigensystem::{self, SingularValueHessian, PAIRS};
use crate::sim::mesh::Mesh;

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

    /// Shape-function gradients of element e in the rest shape, `G[a][j]` flattened
    /// (d+1)·d: rows 1..=d are Dm⁻¹, row 0 minus their sum.
    pub fn grads(&self, e: usize) -> &[f64] {
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

    /// ∂²ψ/∂σ² and the twist and flip eigenvalues at signed singular values σ, in closed
    /// form. With s = μ − μ/(I_C + 1), q = 2μ/(I_C + 1)², t = λ(J − α), c_i = J/σ_i:
    /// ψ_i = sσ_i + t c_i, so A = q σσᵀ + λ c cᵀ + s I + t E with E_ij = J/(σ_iσ_j) off the
    /// diagonal, and for the pair (i, j) with third index k the twist eigenvalue is
    /// (ψ_i + ψ_j)/(σ_i + σ_j) = s + tσ_k and the flip eigenvalue (ψ_i − ψ_j)/(σ_i − σ_j) =
    /// s − tσ_k (2D: s ± t): no division, so repeated singular values need no care.
    pub fn singular_value_hessian(&self, sigma: &[f64; 3]) -> SingularValueHessian {
        let d = self.dim;
        let s3 = if d == 2 {
            [sigma[0], sigma[1], 1.0]
        } else {
            *sigma
        };
        let ic: f64 = s3[..d].iter().map(|v| v * v).sum();
        let j: f64 = s3[..d].iter().product();
        let s = self.mu - self.mu / (ic + 1.0);
        let q = 2.0 * self.mu / ((ic + 1.0) * (ic + 1.0));
        let t = self.lambda * (j - self.alpha);
        // Products of the other singular values (s3[2] = 1 in 2D keeps one formula).
        let others = |skip: &[usize]| -> f64 {
            (0..d)
                .filter(|k| !skip.contains(k))
                .map(|k| s3[k])
                .product()
        };
        let mut h = SingularValueHessian::default();
        for a in 0..d {
            for b in 0..d {
                let mut v = q * s3[a] * s3[b] + self.lambda * others(&[a]) * others(&[b]);
                if a == b {
                    v += s;
                } else {
                    v += t * others(&[a, b]);
                }
                h.a[a][b] = v;
            }
        }
        for (p, &(a, b)) in PAIRS.iter().enumerate() {
            let k = if d == 2 { 1.0 } else { others(&[a, b]) };
            h.twist[p] = s + t * k;
            h.flip[p] = s - t * k;
        }
        h
    }

    /// ∂²Ψ/∂F² projected to PSD through its analytic eigensystem
    /// ([`eigensystem`]), d²×d² row-major over row-major vec(F).
    pub fn projected_stress_derivative(&self, f: &[f64], out: &mut [f64]) {
        let (u, sigma, v) = eigensystem::signed_svd(self.dim, f);
        let h = self.singular_value_hessian(&sigma);
        eigensystem::assemble(self.dim, &u, &v, &h, true, out);
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

    /// Hessian of element e, ((d+1)d)² row-major. With `project` it is built from the
    /// PSD projection of ∂²Ψ/∂F² (analytic eigensystem), (∂F/∂x)ᵀ proj(∂²Ψ/∂F²) (∂F/∂x):
    /// PSD, though not the projection of the element Hessian itself.
    pub fn element_hessian(&self, x: &[f64], e: usize, project: bool, out: &mut [f64]) {
        let d = self.dim;
        let dd = d * d;
        let nl = (d + 1) * d;
        let mut f = [0.0; 9];
        self.deformation_gradient(x, e, &mut f);
        let g = self.grads(e);
        let v = self.volume[e];
        if project {
            // Straight from the eigensystem, without forming proj(∂²Ψ/∂F²).
            let (u, sigma, vv) = eigensystem::signed_svd(d, &f[..dd]);
            let h = self.singular_value_hessian(&sigma);
            eigensystem::projected_element_hessian(d, &u, &vv, &h, g, v, out);
            return;
        }
        let mut h = [0.0; 81];
        self.stress_derivative(&f, &mut h);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::mesh::ElementKind;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// One rest element (the unit simplex) of a soft-ish material.
    fn material(d: usize) -> NeoHookean {
        let mut x = vec![0.0; (d + 1) * d];
        for a in 0..d {
            x[(a + 1) * d + a] = 1.0;
        }
        let kind = if d == 2 {
            ElementKind::Triangle
        } else {
            ElementKind::Tetrahedron
        };
        let mesh = Mesh {
            dim: d,
            x,
            kind,
            elements: vec![(0..=d).collect()],
        };
        NeoHookean::new(&mesh, 1e5, 0.45).expect("unit simplex")
    }

    /// Deformation gradients of every kind the projection meets: well-shaped, nearly flat,
    /// inverted, with repeated singular values, and a pure rotation.
    fn gradients(d: usize, rng: &mut StdRng) -> Vec<(String, Vec<f64>)> {
        let mut out = Vec::new();
        let rot = |rng: &mut StdRng| -> Vec<f64> {
            let m = nalgebra::DMatrix::<f64>::from_fn(d, d, |_, _| rng.random_range(-1.0..1.0));
            let q = m.qr().q();
            let mut r: Vec<f64> = (0..d * d).map(|k| q[(k / d, k % d)]).collect();
            if nalgebra::DMatrix::from_row_slice(d, d, &r).determinant() < 0.0 {
                r.iter_mut().take(d).for_each(|v| *v = -*v);
            }
            r
        };
        let compose = |a: &[f64], s: &[f64], b: &[f64]| -> Vec<f64> {
            let mut f = vec![0.0; d * d];
            for r in 0..d {
                for c in 0..d {
                    f[r * d + c] = (0..d).map(|k| a[r * d + k] * s[k] * b[c * d + k]).sum();
                }
            }
            f
        };
        for k in 0..6 {
            let f: Vec<f64> = (0..d * d)
                .map(|i| if i % (d + 1) == 0 { 1.0 } else { 0.0 } + rng.random_range(-0.4..0.4))
                .collect();
            out.push((format!("random {k}"), f));
        }
        let (u, v) = (rot(rng), rot(rng));
        let flat = [1.1, 0.9, 1e-6];
        out.push(("nearly flat".into(), compose(&u, &flat[3 - d..], &v)));
        let inverted = [1.2, 0.8, -0.3];
        out.push(("inverted".into(), compose(&u, &inverted[3 - d..], &v)));
        let repeated = [1.3, 1.3, 0.7];
        out.push(("repeated σ".into(), compose(&u, &repeated[..d], &v)));
        out.push(("rotation".into(), compose(&u, &[1.0; 3][..d], &v)));
        let squashed = [0.2, 0.2, 0.2];
        out.push(("squashed".into(), compose(&u, &squashed[..d], &v)));
        out
    }

    fn max_abs(m: &[f64]) -> f64 {
        m.iter().fold(0.0f64, |a, v| a.max(v.abs()))
    }

    #[test]
    fn the_eigensystem_reassembles_the_stress_derivative() {
        let mut rng = StdRng::seed_from_u64(17);
        for d in [2, 3] {
            let nh = material(d);
            let dd = d * d;
            for (name, f) in gradients(d, &mut rng) {
                let mut exact = vec![0.0; dd * dd];
                nh.stress_derivative(&f, &mut exact);
                let (u, s, v) = eigensystem::signed_svd(d, &f);
                let mut back = vec![0.0; dd * dd];
                eigensystem::assemble(d, &u, &v, &nh.singular_value_hessian(&s), false, &mut back);
                let err = max_abs(
                    &exact
                        .iter()
                        .zip(&back)
                        .map(|(a, b)| a - b)
                        .collect::<Vec<_>>(),
                );
                // Both are sums of O(1) terms times μ, λ ≈ 1e5: 1e-10 relative is far above
                // rounding (~1e-15) and far below any formula error.
                assert!(err <= 1e-10 * max_abs(&exact), "{d}D {name}: {err:e}");
            }
        }
    }

    /// The projected element Hessian built from the eigenmodes equals the contraction
    /// (∂F/∂x)ᵀ proj(∂²Ψ/∂F²) (∂F/∂x) of the projected stress derivative, and is exactly
    /// symmetric.
    #[test]
    fn projected_element_hessian_equals_the_contracted_projection() {
        let mut rng = StdRng::seed_from_u64(41);
        for d in [2, 3] {
            let nh = material(d);
            let dd = d * d;
            let nl = (d + 1) * d;
            for (name, f) in gradients(d, &mut rng) {
                // Positions whose deformation gradient is F: x_a = F X_a on the unit simplex.
                let mut x = vec![0.0; nl];
                for a in 1..=d {
                    for i in 0..d {
                        x[a * d + i] = f[i * d + (a - 1)];
                    }
                }
                let mut p = vec![0.0; dd * dd];
                nh.projected_stress_derivative(&f, &mut p);
                let g = nh.grads(0);
                let vol = nh.volume[0];
                let mut reference = vec![0.0; nl * nl];
                for a in 0..=d {
                    for c in 0..d {
                        for b in 0..=d {
                            for e in 0..d {
                                let mut s = 0.0;
                                for j in 0..d {
                                    for l in 0..d {
                                        s += p[(c * d + j) * dd + e * d + l]
                                            * g[a * d + j]
                                            * g[b * d + l];
                                    }
                                }
                                reference[(a * d + c) * nl + b * d + e] = vol * s;
                            }
                        }
                    }
                }
                let mut fast = vec![0.0; nl * nl];
                nh.element_hessian(&x, 0, true, &mut fast);
                let scale = max_abs(&reference);
                let err = max_abs(
                    &reference
                        .iter()
                        .zip(&fast)
                        .map(|(a, b)| a - b)
                        .collect::<Vec<_>>(),
                );
                // Sums of a few dozen O(scale) products: 1e-12 relative is far above
                // rounding and far below any wrong mode or index.
                assert!(err <= 1e-12 * scale, "{d}D {name}: {err:e} of {scale:e}");
                for r in 0..nl {
                    for c in 0..nl {
                        assert_eq!(
                            fast[r * nl + c],
                            fast[c * nl + r],
                            "{d}D {name}: ({r}, {c})"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn analytic_projection_equals_the_numerical_one_and_is_psd() {
        let mut rng = StdRng::seed_from_u64(29);
        let mut projected_some = false;
        for d in [2, 3] {
            let nh = material(d);
            let dd = d * d;
            for (name, f) in gradients(d, &mut rng) {
                let mut numeric = vec![0.0; dd * dd];
                nh.stress_derivative(&f, &mut numeric);
                let scale = max_abs(&numeric);
                let eig = nalgebra::SymmetricEigen::new(nalgebra::DMatrix::from_row_slice(
                    dd, dd, &numeric,
                ));
                projected_some |= eig.eigenvalues.min() < -1e-8 * scale;
                crate::sim::energy::project_psd(dd, &mut numeric);
                let mut analytic = vec![0.0; dd * dd];
                nh.projected_stress_derivative(&f, &mut analytic);
                let err = max_abs(
                    &numeric
                        .iter()
                        .zip(&analytic)
                        .map(|(a, b)| a - b)
                        .collect::<Vec<_>>(),
                );
                assert!(err <= 1e-10 * scale, "{d}D {name}: {err:e} of {scale:e}");
                let m = nalgebra::DMatrix::from_row_slice(dd, dd, &analytic);
                let min = nalgebra::SymmetricEigen::new(m).eigenvalues.min();
                assert!(min >= -1e-12 * scale, "{d}D {name}: eigenvalue {min:e}");
            }
        }
        // The cases include indefinite ∂²Ψ/∂F² (inverted, squashed): the clamp is exercised.
        assert!(projected_some);
    }
}
