//! Neo-Hookean elasticity on linear triangles (2D) and tetrahedra (3D), in two laws
//! ([`Law`]):
//!
//! - the classical compressible neo-Hookean law (as in IPC, PolyFEM and libuipc),
//!
//!   ```text
//!   Ψ(F) = μ/2 (I_C − d) − μ ln J + λ/2 (ln J)²
//!   ```
//!
//!   with the Lamé parameters μ, λ of (E, ν). It is +∞ for an inverted element (J ≤ 0), so
//!   the line search keeps every element's J positive ([`NeoHookean::inversion_bound`]).
//! - the stable neo-Hookean law of Smith, de Goes and Kim (2018),
//!
//!   ```text
//!   Ψ(F) = μ/2 (I_C − d) + λ/2 (J − α)² − μ/2 ln(I_C + 1) − Ψ(I),   α = 1 + μ d / (λ (d+1))
//!   ```
//!
//!   defined for inverted elements too. Its μ, λ are remapped from the Lamé parameters of
//!   (E, ν) so that the small-strain response is linear elasticity with those E and ν:
//!   μ = μ_L (d+1)/d, λ = λ_L + μ_L − 2μ/(d+1)² (Smith et al. §3.4 for d = 3; the same
//!   algebra for d = 2).
//!
//! Both are isotropic, and both write their first Piola–Kirchhoff stress as
//! P = s F + t cof(F) and their ∂²Ψ/∂F² as q F⊗F + w cof(F)⊗cof(F) + s I + t ∂²J/∂F² with
//! scalar coefficients of I_C and J ([`NeoHookean::coefficients`]); the PSD projection runs
//! through the same analytic eigensystem for both.

use super::digest::{digest_f64s, digest_usizes};
use super::eigensystem::{self, SingularValueHessian, PAIRS};
use crate::sim::mesh::Mesh;
use rayon::prelude::*;

/// Which neo-Hookean law a body follows (the scene's `material.model`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Law {
    /// μ/2 (I_C − d) − μ ln J + λ/2 (ln J)², the plain Lamé parameters of (E, ν).
    NeoHookean,
    /// Smith, de Goes and Kim (2018), remapped parameters; defined for J ≤ 0.
    StableNeoHookean,
}

impl Law {
    /// The scene file's name of the law.
    pub fn name(self) -> &'static str {
        match self {
            Law::NeoHookean => "neo-hookean",
            Law::StableNeoHookean => "stable-neo-hookean",
        }
    }
}

/// The scalar coefficients of P and ∂²Ψ/∂F² at (I_C, J): P = s F + t cof(F),
/// ∂²Ψ/∂F² = q F⊗F + w cof(F)⊗cof(F) + s I + t ∂²J/∂F².
#[derive(Debug, Clone, Copy)]
pub struct Coefficients {
    pub s: f64,
    pub q: f64,
    pub w: f64,
    pub t: f64,
}

/// Neo-Hookean elements of one body: rest shape data per element.
#[derive(Debug, Clone)]
pub struct NeoHookean {
    pub dim: usize,
    pub law: Law,
    /// Per element its d+1 nodes, element after element (one flat array: no heap block
    /// per element).
    nodes: Vec<usize>,
    /// Per element: the gradients of the d+1 barycentric shape functions in the rest
    /// shape, G[a][j] (node a, axis j), flattened (d+1)·d.
    shape_grads: Vec<f64>,
    /// Rest measure per element.
    pub volume: Vec<f64>,
    pub mu: f64,
    pub lambda: f64,
    /// The stable law's rest J of the volume term (1 for the classical law).
    pub(super) alpha: f64,
    /// Ψ(I) before the shift that makes the density zero at rest.
    pub(super) rest_density: f64,
}

/// Lamé parameters (μ_L, λ_L) of Young's modulus and Poisson ratio.
pub fn lame(young: f64, poisson: f64) -> (f64, f64) {
    let mu = young / (2.0 * (1.0 + poisson));
    let lambda = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson));
    (mu, lambda)
}

/// Elements per task of the parallel scans (J, the inversion bound): fixed, so the
/// element they find does not depend on the thread count.
pub(super) const SCAN_CHUNK: usize = 1024;

/// An element whose rest volume is at most this fraction of (longest edge from its first
/// node)^d is degenerate: 64ε, rounding of the edge vectors' products.
pub const DEGENERATE_RELATIVE_VOLUME: f64 = 64.0 * f64::EPSILON;

impl NeoHookean {
    /// Builds the elements of `mesh` (its positions are the rest shape) for `law`. Fails
    /// when an element is degenerate or inverted at rest.
    pub fn new(mesh: &Mesh, young: f64, poisson: f64, law: Law) -> Result<Self, String> {
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
        let (mu, lambda, alpha) = match law {
            Law::NeoHookean => (mu_l, lambda_l, 1.0),
            Law::StableNeoHookean => {
                let mu = mu_l * (df + 1.0) / df;
                let lambda = lambda_l + mu_l - 2.0 * mu / ((df + 1.0) * (df + 1.0));
                (mu, lambda, 1.0 + mu * df / (lambda * (df + 1.0)))
            }
        };
        let mut shape_grads = Vec::with_capacity(mesh.elements.len() * nn * d);
        let mut volume = Vec::with_capacity(mesh.elements.len());
        // Dm, Dm / its longest edge and Dm⁻¹, allocated once and overwritten per element.
        let mut dm = nalgebra::DMatrix::<f64>::zeros(d, d);
        let mut scaled = nalgebra::DMatrix::<f64>::zeros(d, d);
        let mut inv = nalgebra::DMatrix::<f64>::zeros(d, d);
        for (e, el) in mesh.elements.iter().enumerate() {
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
            scaled.copy_from(&dm);
            scaled /= longest;
            let relative = scaled.determinant();
            if relative.is_nan() || relative <= DEGENERATE_RELATIVE_VOLUME {
                return Err(format!(
                    "element {e} is degenerate at rest: its volume is {relative:.1e} of its \
                     longest edge to the power {d}, below f64's resolution (a mesh flatter \
                     than its coordinates can resolve)"
                ));
            }
            volume.push(det / if d == 2 { 2.0 } else { 6.0 });
            inv.copy_from(&dm);
            if !inv.try_inverse_mut() {
                return Err(format!("element {e} is degenerate at rest"));
            }
            // F = Ds Dm⁻¹ ⇒ ∂F_ij/∂x_{a,i} = (Dm⁻¹)_{a−1, j} for a ≥ 1; node 0 takes minus the sum.
            let mut g0 = [0.0; 3];
            let start = shape_grads.len();
            shape_grads.extend(std::iter::repeat_n(0.0, nn * d));
            for a in 1..nn {
                for j in 0..d {
                    let v = inv[(a - 1, j)];
                    shape_grads[start + a * d + j] = v;
                    g0[j] -= v;
                }
            }
            shape_grads[start..start + d].copy_from_slice(&g0[..d]);
        }
        let mut s = NeoHookean {
            dim: d,
            law,
            nodes: mesh.elements.iter().flatten().copied().collect(),
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

    /// Elements in the set.
    pub fn len(&self) -> usize {
        self.volume.len()
    }

    pub fn is_empty(&self) -> bool {
        self.volume.is_empty()
    }

    /// The d+1 nodes of element e.
    pub fn nodes(&self, e: usize) -> &[usize] {
        let k = self.dim + 1;
        &self.nodes[e * k..(e + 1) * k]
    }

    /// Every element's nodes, element after element.
    pub fn all_nodes(&self) -> impl Iterator<Item = &[usize]> {
        self.nodes.chunks_exact(self.dim + 1)
    }

    /// Feeds the set's values to `out` ([`super::Model::digest`]).
    pub fn digest(&self, out: &mut dyn FnMut(&[u8])) {
        digest_usizes(out, &[self.dim]);
        digest_usizes(out, &self.nodes);
        digest_f64s(out, &self.shape_grads);
        digest_f64s(out, &self.volume);
        let scalars = [self.mu, self.lambda, self.alpha, self.rest_density];
        digest_f64s(out, &scalars);
    }

    /// Adds `offset` to every node index (the body's first node in the scene).
    pub fn shift_nodes(&mut self, offset: usize) {
        self.nodes.iter_mut().for_each(|v| *v += offset);
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
        for (a, &node) in self.nodes(e).iter().enumerate() {
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
        match self.law {
            Law::NeoHookean => {
                // J ≤ 0 (and NaN): +∞, which no line search accepts.
                if j.is_nan() || j <= 0.0 {
                    return f64::INFINITY;
                }
                let l = j.ln();
                0.5 * self.mu * (ic - d as f64) - self.mu * l + 0.5 * self.lambda * l * l
            }
            Law::StableNeoHookean => {
                0.5 * self.mu * (ic - d as f64) + 0.5 * self.lambda * (j - self.alpha).powi(2)
                    - 0.5 * self.mu * (ic + 1.0).ln()
            }
        }
    }

    /// The coefficients of P and ∂²Ψ/∂F² at I_C = ‖F‖² and J = det F. Classical law:
    /// s = μ, q = 0, t = (λ ln J − μ)/J, w = dt/dJ = (λ (1 − ln J) + μ)/J² (NaN for J ≤ 0,
    /// where the energy is +∞). Stable law: s = μ − μ/(I_C + 1), q = 2μ/(I_C + 1)², w = λ,
    /// t = λ (J − α).
    pub fn coefficients(&self, ic: f64, j: f64) -> Coefficients {
        let (mu, lambda) = (self.mu, self.lambda);
        match self.law {
            Law::NeoHookean => {
                let l = if j > 0.0 { j.ln() } else { f64::NAN };
                Coefficients {
                    s: mu,
                    q: 0.0,
                    w: (lambda * (1.0 - l) + mu) / (j * j),
                    t: (lambda * l - mu) / j,
                }
            }
            Law::StableNeoHookean => Coefficients {
                s: mu - mu / (ic + 1.0),
                q: 2.0 * mu / ((ic + 1.0) * (ic + 1.0)),
                w: lambda,
                t: lambda * (j - self.alpha),
            },
        }
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
        let Coefficients { s, t, .. } = self.coefficients(ic, j);
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
        let Coefficients { s, q, w, t } = self.coefficients(ic, j);
        for r in 0..dd {
            for k in 0..dd {
                let mut v = q * f[r] * f[k] + w * c[r] * c[k];
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
    /// form. With the [`Coefficients`] s, q, w, t at (I_C, J) and c_i = J/σ_i (the product
    /// of the other singular values): ψ_i = sσ_i + t c_i, so A = q σσᵀ + w c cᵀ + s I + t E
    /// with E_ij = J/(σ_iσ_j) off the diagonal, and for the pair (i, j) with third index k the
    /// twist eigenvalue is (ψ_i + ψ_j)/(σ_i + σ_j) = s + tσ_k and the flip eigenvalue
    /// (ψ_i − ψ_j)/(σ_i − σ_j) = s − tσ_k (2D: s ± t): no division, so repeated singular
    /// values need no care. For the classical law this is A_ij = λ/(σ_iσ_j) off the diagonal,
    /// A_ii = μ + (μ + λ − λ ln J)/σ_i², twist and flip μ ± (λ ln J − μ)/(σ_iσ_j).
    pub fn singular_value_hessian(&self, sigma: &[f64; 3]) -> SingularValueHessian {
        let d = self.dim;
        let s3 = if d == 2 {
            [sigma[0], sigma[1], 1.0]
        } else {
            *sigma
        };
        let ic: f64 = s3[..d].iter().map(|v| v * v).sum();
        let j: f64 = s3[..d].iter().product();
        let Coefficients { s, q, w, t } = self.coefficients(ic, j);
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
                let mut v = q * s3[a] * s3[b] + w * others(&[a]) * others(&[b]);
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

impl NeoHookean {
    /// J = det F of element e at x.
    pub fn volume_ratio(&self, x: &[f64], e: usize) -> f64 {
        let mut f = [0.0; 9];
        self.deformation_gradient(x, e, &mut f);
        det(self.dim, &f[..self.dim * self.dim])
    }

    /// The smallest J over the elements at x, with its element (the first one on ties);
    /// None without elements.
    /// A NaN J wins over every number, and the last NaN over earlier ones. Fixed chunks
    /// of elements in parallel, merged in order by the same rule: the element a
    /// sequential scan finds, on any number of threads.
    pub fn min_volume_ratio(&self, x: &[f64]) -> Option<(f64, usize)> {
        let keep = |best: Option<(f64, usize)>, (j, e): (f64, usize)| {
            if best.is_none_or(|(b, _)| j < b || j.is_nan()) {
                Some((j, e))
            } else {
                best
            }
        };
        let chunks: Vec<Option<(f64, usize)>> = (0..self.len().div_ceil(SCAN_CHUNK))
            .into_par_iter()
            .map(|c| {
                (c * SCAN_CHUNK..((c + 1) * SCAN_CHUNK).min(self.len()))
                    .fold(None, |best, e| keep(best, (self.volume_ratio(x, e), e)))
            })
            .collect();
        chunks.into_iter().flatten().fold(None, keep)
    }

    /// The step-size bound that keeps every element's J positive along x + αΔx: the
    /// smallest root α ∈ (0, `max`] over the elements of det F(x + αΔx) = 0, with its
    /// element; None when every element keeps J > 0 on (0, `max`]. F(α) = (Ds + αΔDs) Dm⁻¹
    /// with det Dm > 0, so the root is that of det(Ds + αΔDs), a polynomial of degree d in
    /// α ([`first_root`]). Err((element, J)) when an element is already inverted at x
    /// (J ≤ 0), the first one in element order.
    ///
    /// Every element's root is [`first_root`] on the whole (0, `max`], and the bound is the
    /// first strict minimum in element order: what each element contributes does not
    /// depend on the others, so a parallel reduction (the device loop's,
    /// `sim::device::checks`) finds the same element and the same bits.
    pub fn inversion_bound(
        &self,
        x: &[f64],
        dx: &[f64],
        max: f64,
    ) -> Result<Option<(f64, usize)>, (usize, f64)> {
        self.inversion_bound_below(x, dx, max, None)
    }

    /// [`NeoHookean::inversion_bound`] counting only a root below `below` (the bound of the
    /// element sets before this one): an element whose root is known to lie at or above
    /// the bound so far is not bisected further ([`root_below`]).
    pub(super) fn inversion_bound_below(
        &self,
        x: &[f64],
        dx: &[f64],
        max: f64,
        below: Option<f64>,
    ) -> Result<Option<(f64, usize)>, (usize, f64)> {
        let d = self.dim;
        let rest_factor = if d == 2 { 2.0 } else { 6.0 };
        // Fixed chunks in parallel, each from `below`; merged in order, a chunk's root
        // counts only below the bound so far: the first strict minimum (and the first
        // inverted element) in element order, whatever the threads.
        type Chunk = Result<Option<(f64, usize)>, (usize, f64)>;
        let chunks: Vec<Chunk> = (0..self.len().div_ceil(SCAN_CHUNK))
            .into_par_iter()
            .map(|k| {
                let range = k * SCAN_CHUNK..((k + 1) * SCAN_CHUNK).min(self.len());
                if d == 3 {
                    return self.inversion_scan3(x, dx, max, below, range.start, range.len());
                }
                let mut best: Option<(f64, usize)> = None;
                for e in range {
                    let c = step_det_polynomial(d, self.nodes(e), x, dx);
                    if c[0].is_nan() || c[0] <= 0.0 {
                        return Err((e, c[0] / (rest_factor * self.volume[e])));
                    }
                    if let Some(r) = root_below(&c, max, best.map(|(r, _)| r).or(below)) {
                        best = Some((r, e));
                    }
                }
                Ok(best)
            })
            .collect();
        let mut best: Option<(f64, usize)> = None;
        for chunk in chunks {
            if let Some((r, e)) = chunk? {
                if best.is_none_or(|(b, _)| r < b) {
                    best = Some((r, e));
                }
            }
        }
        Ok(best)
    }
}

/// det(Ds + α ΔDs) of element `el` (node indices) at positions `x` along the step `dx`
/// ([`det_polynomial`]); Ds and ΔDs row-major, column a − 1 node a minus node 0.
pub(super) fn step_det_polynomial(d: usize, el: &[usize], x: &[f64], dx: &[f64]) -> [f64; 4] {
    let mut a = [0.0; 9];
    let mut b = [0.0; 9];
    for k in 1..=d {
        for i in 0..d {
            a[i * d + k - 1] = x[el[k] * d + i] - x[el[0] * d + i];
            b[i * d + k - 1] = dx[el[k] * d + i] - dx[el[0] * d + i];
        }
    }
    det_polynomial(d, &a[..d * d], &b[..d * d])
}

/// det(A + αB) = c_0 + c_1 α + c_2 α² + c_3 α³ for d×d row-major A, B (d = 2: c_3 = 0):
/// c_0 = det A, c_1 = Σ cof(A)∘B, c_2 = Σ cof(B)∘A (2D: det B), c_3 = det B (3D).
pub fn det_polynomial(d: usize, a: &[f64], b: &[f64]) -> [f64; 4] {
    let dd = d * d;
    let mut ca = [0.0; 9];
    cofactor(d, a, &mut ca);
    let c1: f64 = (0..dd).map(|k| ca[k] * b[k]).sum();
    if d == 2 {
        return [det(2, a), c1, det(2, b), 0.0];
    }
    let mut cb = [0.0; 9];
    cofactor(d, b, &mut cb);
    let c2: f64 = (0..dd).map(|k| cb[k] * a[k]).sum();
    [det(3, a), c1, c2, det(3, b)]
}

/// The smallest root in (0, `max`] of p(α) = c_0 + c_1 α + c_2 α² + c_3 α³ with
/// p(0) = c_0 > 0, to rounding: the critical points of p (the real roots of p′ in
/// (0, `max`)) cut (0, `max`] into pieces on which p is monotone; the first piece whose
/// right end has p ≤ 0 holds the root, which bisection pins down until its bracket is two
/// adjacent floats (the right one is returned, so p(root) ≤ 0 as evaluated). Any leading
/// coefficients may vanish (a quadratic, linear or constant p). None when p > 0 at every
/// cut and at `max`.
pub fn first_root(c: &[f64; 4], max: f64) -> Option<f64> {
    root_below(c, max, None)
}

/// [`first_root`] of `c` on (0, `max`] when it is below `stop`, else None. The search is
/// [`first_root`]'s, ended early once the root is known to lie above `stop` (the bracket's
/// left end reached it: the root returned is always right of that end), so whatever it
/// returns is [`first_root`]'s value, bit for bit.
pub(super) fn root_below(c: &[f64; 4], max: f64, stop: Option<f64>) -> Option<f64> {
    let beyond = |v: f64| stop.is_some_and(|s| v >= s);
    let p = |a: f64| ((c[3] * a + c[2]) * a + c[1]) * a + c[0];
    let mut cuts = [max; 3];
    let mut n = 0;
    for r in quadratic_roots(3.0 * c[3], 2.0 * c[2], c[1])
        .into_iter()
        .flatten()
    {
        if r > 0.0 && r < max {
            cuts[n] = r;
            n += 1;
        }
    }
    cuts[..n].sort_by(f64::total_cmp);
    cuts[n] = max;
    let mut lo = 0.0f64;
    for &hi in &cuts[..=n] {
        if beyond(lo) {
            return None;
        }
        if p(hi) <= 0.0 {
            let mut hi = hi;
            loop {
                if beyond(lo) {
                    return None;
                }
                let mid = 0.5 * (lo + hi);
                if mid <= lo || mid >= hi {
                    return (!beyond(hi)).then_some(hi);
                }
                if p(mid) > 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
        }
        lo = hi;
    }
    None
}

/// The real roots of a α² + b α + c (None for each missing one), by the cancellation-free
/// formula; a = 0 gives the linear root, a = b = 0 none.
fn quadratic_roots(a: f64, b: f64, c: f64) -> [Option<f64>; 2] {
    if a == 0.0 {
        return [(b != 0.0).then(|| -c / b), None];
    }
    let disc = b * b - 4.0 * a * c;
    if disc.is_nan() || disc < 0.0 {
        return [None, None];
    }
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    if q == 0.0 {
        return [Some(0.0), None];
    }
    [Some(q / a), Some(c / q)]
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
    fn material(d: usize, law: Law) -> NeoHookean {
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
        NeoHookean::new(&mesh, 1e5, 0.45, law).expect("unit simplex")
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
        let nearly_inverted = [1.5, 0.6, 2e-3];
        out.push((
            "nearly inverted".into(),
            compose(&u, &nearly_inverted[3 - d..], &v),
        ));
        let inverted = [1.2, 0.8, -0.3];
        out.push(("inverted".into(), compose(&u, &inverted[3 - d..], &v)));
        let repeated = [1.3, 1.3, 0.7];
        out.push(("repeated σ".into(), compose(&u, &repeated[..d], &v)));
        out.push(("rotation".into(), compose(&u, &[1.0; 3][..d], &v)));
        let squashed = [0.2, 0.2, 0.2];
        out.push(("squashed".into(), compose(&u, &squashed[..d], &v)));
        out
    }

    /// [`gradients`] for `law`: the classical law is not defined for J ≤ 0.
    fn cases(d: usize, law: Law, rng: &mut StdRng) -> Vec<(String, Vec<f64>)> {
        gradients(d, rng)
            .into_iter()
            .filter(|(_, f)| law == Law::StableNeoHookean || det(d, f) > 0.0)
            .collect()
    }

    const LAWS: [Law; 2] = [Law::NeoHookean, Law::StableNeoHookean];

    fn max_abs(m: &[f64]) -> f64 {
        m.iter().fold(0.0f64, |a, v| a.max(v.abs()))
    }

    #[test]
    fn the_eigensystem_reassembles_the_stress_derivative() {
        let mut rng = StdRng::seed_from_u64(17);
        for (d, law) in [2, 3].into_iter().flat_map(|d| LAWS.map(|l| (d, l))) {
            let nh = material(d, law);
            let dd = d * d;
            for (name, f) in cases(d, law, &mut rng) {
                let name = format!("{} {name}", law.name());
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
        for (d, law) in [2, 3].into_iter().flat_map(|d| LAWS.map(|l| (d, l))) {
            let nh = material(d, law);
            let dd = d * d;
            let nl = (d + 1) * d;
            for (name, f) in cases(d, law, &mut rng) {
                let name = format!("{} {name}", law.name());
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
        let mut projected_some = [false; 2];
        for (d, law) in [2, 3].into_iter().flat_map(|d| LAWS.map(|l| (d, l))) {
            let nh = material(d, law);
            let dd = d * d;
            for (name, f) in cases(d, law, &mut rng) {
                let name = format!("{} {name}", law.name());
                let mut numeric = vec![0.0; dd * dd];
                nh.stress_derivative(&f, &mut numeric);
                let scale = max_abs(&numeric);
                let eig = nalgebra::SymmetricEigen::new(nalgebra::DMatrix::from_row_slice(
                    dd, dd, &numeric,
                ));
                projected_some[law as usize] |= eig.eigenvalues.min() < -1e-8 * scale;
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
        // The cases include indefinite ∂²Ψ/∂F² (inverted, squashed, nearly inverted): the
        // clamp is exercised for both laws.
        assert_eq!(projected_some, [true; 2]);
    }

    /// ∂φ/∂F_k by the seven-point stencil: error O(h⁶), rounding O(ε φ/h).
    fn seven_point(f: &[f64], k: usize, h: f64, mut phi: impl FnMut(&[f64]) -> f64) -> f64 {
        let mut g = f.to_vec();
        let mut at = |t: f64| {
            g[k] = f[k] + t;
            phi(&g)
        };
        (-at(-3.0 * h) + 9.0 * at(-2.0 * h) - 45.0 * at(-h) + 45.0 * at(h) - 9.0 * at(2.0 * h)
            + at(3.0 * h))
            / (60.0 * h)
    }

    /// The classical law's stress is the derivative of its energy and its ∂²Ψ/∂F² the
    /// derivative of its stress, by finite differences (a seven-point stencil; per case the
    /// best of the steps h = 3e-2, 1e-2 and 3e-3 of the smallest singular value), on
    /// well-shaped, flat and nearly inverted F. Bound: 1e-10 relative to the array's
    /// largest entry (for P, or μ if larger), except for the flat F (σ = 1e-6): there det F (≈ 1e-6, formed from
    /// O(1) entries) carries an absolute rounding of ~ε, ε/J relative, which the stencil
    /// divides by h/J, so the differences themselves are only good to ε/h ≈ 1e-8 and the
    /// bound is 1e-7 (the analytic values are checked to 1e-10 against the numerical
    /// eigendecomposition above).
    #[test]
    fn classical_stress_and_stress_derivative_match_finite_differences() {
        let mut rng = StdRng::seed_from_u64(53);
        for d in [2, 3] {
            let nh = material(d, Law::NeoHookean);
            let dd = d * d;
            for (name, f) in cases(d, Law::NeoHookean, &mut rng) {
                let (_, sigma, _) = eigensystem::signed_svd(d, &f);
                let smin = sigma[..d].iter().fold(f64::INFINITY, |a, v| a.min(v.abs()));
                let tol = if smin < 1e-4 { 1e-7 } else { 1e-10 };
                let mut p = [0.0; 9];
                nh.stress(&f, &mut p);
                let mut a = vec![0.0; dd * dd];
                nh.stress_derivative(&f, &mut a);
                // P vanishes at a rotation: its scale is at least μ.
                let (p_scale, a_scale) = (max_abs(&p[..dd]).max(nh.mu), max_abs(&a));
                let mut best = [f64::INFINITY; 2];
                for step in [3e-2, 1e-2, 3e-3] {
                    let h = step * smin.min(1.0);
                    let mut errs = [0.0f64; 2];
                    for k in 0..dd {
                        let fd = seven_point(&f, k, h, |g| nh.density(g));
                        errs[0] = errs[0].max((fd - p[k]).abs() / p_scale);
                        for r in 0..dd {
                            let fd = seven_point(&f, k, h, |g| {
                                let mut q = [0.0; 9];
                                nh.stress(g, &mut q);
                                q[r]
                            });
                            errs[1] = errs[1].max((fd - a[r * dd + k]).abs() / a_scale);
                        }
                    }
                    best[0] = best[0].min(errs[0]);
                    best[1] = best[1].min(errs[1]);
                }
                println!(
                    "{d}D {name}: finite differences, P {:.1e}, ∂²Ψ/∂F² {:.1e}",
                    best[0], best[1]
                );
                assert!(best[0] <= tol, "{d}D {name}: P {:e}", best[0]);
                assert!(best[1] <= tol, "{d}D {name}: ∂²Ψ/∂F² {:e}", best[1]);
            }
        }
    }

    /// The classical law with the plain Lamé parameters: Ψ(I) = 0, P(I) = 0, and
    /// ∂²Ψ/∂F² at I is linear elasticity's μ (δδ + transpose) + λ I⊗I.
    #[test]
    fn classical_law_is_linear_elasticity_at_rest() {
        for d in [2, 3] {
            let nh = material(d, Law::NeoHookean);
            let (mu, lambda) = lame(1e5, 0.45);
            assert_eq!((nh.mu, nh.lambda), (mu, lambda));
            let dd = d * d;
            let mut id = vec![0.0; dd];
            for a in 0..d {
                id[a * d + a] = 1.0;
            }
            assert_eq!(nh.density(&id), 0.0);
            let mut p = [0.0; 9];
            nh.stress(&id, &mut p);
            assert!(max_abs(&p[..dd]) <= 1e-9 * mu, "{d}D: P(I) = {p:?}");
            let mut a = vec![0.0; dd * dd];
            nh.stress_derivative(&id, &mut a);
            for (i, j, k, l) in (0..d).flat_map(|i| {
                (0..d)
                    .flat_map(move |j| (0..d).flat_map(move |k| (0..d).map(move |l| (i, j, k, l))))
            }) {
                let delta = |a: usize, b: usize| if a == b { 1.0 } else { 0.0 };
                let want = mu * (delta(i, k) * delta(j, l) + delta(i, l) * delta(j, k))
                    + lambda * delta(i, j) * delta(k, l);
                let got = a[(i * d + j) * dd + k * d + l];
                assert!(
                    (got - want).abs() <= 1e-9 * lambda,
                    "{d}D ({i}{j}{k}{l}): {got} vs {want}"
                );
            }
            // Inverted: +∞.
            let mut flipped = id.clone();
            flipped[0] = -1.0;
            assert_eq!(nh.density(&flipped), f64::INFINITY);
        }
    }

    /// Over a mesh the bound is the first strict minimum, in element order, of every
    /// element's own [`first_root`] on (0, max]: the search cut short by the bound so far
    /// ([`root_below`]) never changes a root nor the element, ties included (a uniform
    /// deformation gives every element the same root up to rounding).
    #[test]
    fn inversion_bound_is_the_first_minimum_of_the_elements_roots() {
        let mut rng = StdRng::seed_from_u64(17);
        let max = 1.0 / 0.9;
        for d in [2, 3] {
            let mesh = if d == 2 {
                crate::sim::mesh::rectangle(2, [1.0, 0.5], [6, 3])
            } else {
                crate::sim::mesh::cuboid([1.0, 0.4, 0.4], [4, 2, 2])
            };
            let nh = NeoHookean::new(&mesh, 1e5, 0.3, Law::NeoHookean).expect("valid mesh");
            let n = mesh.x.len() / d;
            let mut rooted = 0;
            for t in 0..60 {
                let (x, dx): (Vec<f64>, Vec<f64>) = if t % 3 == 0 {
                    // Uniform: x = X, Δx = G X.
                    let g: Vec<f64> = (0..d * d).map(|_| rng.random_range(-2.0..1.0)).collect();
                    let dx = (0..n * d)
                        .map(|k| {
                            let (i, a) = (k / d, k % d);
                            (0..d).map(|b| g[a * d + b] * mesh.x[i * d + b]).sum()
                        })
                        .collect();
                    (mesh.x.clone(), dx)
                } else {
                    let size = 10f64.powf(rng.random_range(-3.0..0.0));
                    let x = mesh
                        .x
                        .iter()
                        .map(|v| v + rng.random_range(-0.02..0.02))
                        .collect();
                    let dx = (0..n * d)
                        .map(|_| size * rng.random_range(-1.0..1.0))
                        .collect();
                    (x, dx)
                };
                let got = nh.inversion_bound(&x, &dx, max).expect("not inverted");
                let mut want: Option<(f64, usize)> = None;
                for (e, el) in nh.all_nodes().enumerate() {
                    let c = step_det_polynomial(d, el, &x, &dx);
                    if let Some(r) = first_root(&c, max) {
                        if want.is_none_or(|(w, _)| r < w) {
                            want = Some((r, e));
                        }
                        let stop = rng.random_range(0.0..max);
                        assert_eq!(root_below(&c, max, Some(stop)), (r < stop).then_some(r));
                    }
                }
                assert_eq!(got, want, "{d}D case {t}");
                rooted += got.is_some() as usize;
            }
            assert!(rooted > 20, "{d}D: only {rooted} cases with a root");
        }
    }

    /// det(Ds + αΔDs) = 0 by its polynomial: the bound is the exact root to rounding,
    /// against bisection on the determinant itself (formed from the positions at α), for
    /// known roots, degenerate leading coefficients and random elements and directions.
    #[test]
    fn inversion_bound_is_the_smallest_positive_root() {
        // Known roots: det(I + α diag(−2, 0, 0)) = 1 − 2α; det(I + α(−I)) = (1 − α)^d;
        // det(I + α diag(−4, −1)) = (1 − 4α)(1 − α): the smaller root; ΔDs = 0: none.
        assert_eq!(first_root(&[1.0, -2.0, 0.0, 0.0], 10.0), Some(0.5));
        // (1 − α)(1 − 2α)(1 + α) = 1 − 2α − α² + 2α³: 0.5 exactly.
        assert_eq!(first_root(&[1.0, -2.0, -1.0, 2.0], 10.0), Some(0.5));
        // A triple root (1 − α)³ is found to its conditioning, ε^(1/3).
        let triple = first_root(&[1.0, -3.0, 3.0, -1.0], 10.0).expect("root");
        assert!((triple - 1.0).abs() <= 1e-5, "{triple}");
        assert_eq!(first_root(&[1.0, -5.0, 4.0, 0.0], 10.0), Some(0.25));
        assert_eq!(first_root(&[1.0, 0.0, 0.0, 0.0], 10.0), None);
        // A root beyond `max`, and a double root (a touch at α = 1: (1 − α)², found to its
        // conditioning √ε).
        assert_eq!(first_root(&[1.0, -0.5, 0.0, 0.0], 1.0), None);
        let double = first_root(&[1.0, -2.0, 1.0, 0.0], 10.0).expect("root");
        assert!((double - 1.0).abs() <= 1e-7, "{double}");
        // Positive cubic with a local minimum above zero: no root.
        assert_eq!(first_root(&[1.0, -3.0, 3.0, 0.0], 10.0), None);
        let mut rng = StdRng::seed_from_u64(7);
        let mut found = 0;
        for d in [2, 3] {
            let nh = material(d, Law::NeoHookean);
            let nl = (d + 1) * d;
            for _ in 0..200 {
                let mut x = vec![0.0; nl];
                for a in 1..=d {
                    x[a * d + a - 1] = 1.0;
                }
                for v in x.iter_mut() {
                    *v += rng.random_range(-0.2..0.2);
                }
                let dx: Vec<f64> = (0..nl).map(|_| rng.random_range(-1.0..1.0)).collect();
                let det_at = |alpha: f64| {
                    let m = nalgebra::DMatrix::from_fn(d, d, |i, k| {
                        let p = |n: usize| x[n * d + i] + alpha * dx[n * d + i];
                        p(k + 1) - p(0)
                    });
                    m.determinant()
                };
                let got = nh.inversion_bound(&x, &dx, 4.0).expect("not inverted");
                // Reference: scan for the first sign change, then bisect det itself.
                let steps = 2_000;
                let mut reference = None;
                for k in 1..=steps {
                    let b = 4.0 * k as f64 / steps as f64;
                    if det_at(b) <= 0.0 {
                        let (mut lo, mut hi) = (4.0 * (k - 1) as f64 / steps as f64, b);
                        for _ in 0..200 {
                            let mid = 0.5 * (lo + hi);
                            if det_at(mid) > 0.0 {
                                lo = mid;
                            } else {
                                hi = mid;
                            }
                        }
                        reference = Some(hi);
                        break;
                    }
                }
                match (got, reference) {
                    (Some((r, 0)), Some(want)) => {
                        found += 1;
                        assert!((r - want).abs() <= 1e-12 * want, "{d}D: {r} vs {want}");
                        assert!(det_at(0.9 * r) > 0.0);
                    }
                    (None, None) => {}
                    other => panic!("{d}D: bound {other:?}"),
                }
            }
        }
        assert!(found > 100, "only {found} of the random directions invert");
        // An element already inverted at x is named with its J.
        let nh = material(2, Law::NeoHookean);
        let x = [0.0, 0.0, 0.0, 1.0, 1.0, 0.0];
        assert_eq!(nh.inversion_bound(&x, &[0.0; 6], 1.0), Err((0, -1.0)));
    }
}
