//! Mass-spring elasticity: E = k/(2 l₀) (l − l₀)² per spring (k in newtons: the energy of
//! a strain ε is ½ k l₀ ε²).

/// The springs of one body.
#[derive(Debug, Clone)]
pub struct Springs {
    pub dim: usize,
    pub edges: Vec<[usize; 2]>,
    pub rest: Vec<f64>,
    pub stiffness: f64,
}

impl Springs {
    /// Springs on `edges` with rest lengths from the positions `x`.
    pub fn new(
        dim: usize,
        x: &[f64],
        edges: Vec<[usize; 2]>,
        stiffness: f64,
    ) -> Result<Self, String> {
        let mut rest = Vec::with_capacity(edges.len());
        for (s, e) in edges.iter().enumerate() {
            let l = (0..dim)
                .map(|a| (x[e[1] * dim + a] - x[e[0] * dim + a]).powi(2))
                .sum::<f64>()
                .sqrt();
            // NaN (a non-finite node position) is rejected explicitly, like l ≤ 0.
            if l.is_nan() || l <= 0.0 {
                return Err(format!("spring {s} has zero rest length"));
            }
            rest.push(l);
        }
        Ok(Springs {
            dim,
            edges,
            rest,
            stiffness,
        })
    }

    fn diff(&self, x: &[f64], s: usize) -> ([f64; 3], f64) {
        let d = self.dim;
        let [i, j] = self.edges[s];
        let mut v = [0.0; 3];
        for a in 0..d {
            v[a] = x[j * d + a] - x[i * d + a];
        }
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        (v, l)
    }

    pub fn element_energy(&self, x: &[f64], s: usize) -> f64 {
        let (_, l) = self.diff(x, s);
        let l0 = self.rest[s];
        0.5 * self.stiffness / l0 * (l - l0).powi(2)
    }

    /// Gradient w.r.t. (x_i, x_j), length 2d.
    pub fn element_gradient(&self, x: &[f64], s: usize, out: &mut [f64]) {
        let d = self.dim;
        let (v, l) = self.diff(x, s);
        let l0 = self.rest[s];
        let c = if l > 0.0 {
            self.stiffness / l0 * (l - l0) / l
        } else {
            0.0
        };
        for a in 0..d {
            out[a] = -c * v[a];
            out[d + a] = c * v[a];
        }
    }

    /// Hessian w.r.t. (x_i, x_j), (2d)² row-major. The element matrix is [[K, −K], [−K, K]]
    /// whose eigenvalues are 2·eig(K) and 0, so projecting K to PSD (dropping the negative
    /// transverse term of a compressed spring) is the exact eigen-clamp of the element.
    pub fn element_hessian(&self, x: &[f64], s: usize, project: bool, out: &mut [f64]) {
        let d = self.dim;
        let (v, l) = self.diff(x, s);
        let l0 = self.rest[s];
        let k = self.stiffness / l0;
        let mut transverse = if l > 0.0 { (l - l0) / l } else { 0.0 };
        if project && transverse < 0.0 {
            transverse = 0.0;
        }
        let n = 2 * d;
        for a in 0..d {
            for b in 0..d {
                let uu = if l > 0.0 { v[a] * v[b] / (l * l) } else { 0.0 };
                let id = if a == b { 1.0 } else { 0.0 };
                let kab = k * (uu + transverse * (id - uu));
                out[a * n + b] = kab;
                out[(d + a) * n + d + b] = kab;
                out[a * n + d + b] = -kab;
                out[(d + a) * n + b] = -kab;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The closed-form projection (transverse stiffness clamped at zero) is the eigen-clamp
    /// of the element Hessian: it equals `project_psd` (nalgebra SymmetricEigen, negative
    /// eigenvalues set to zero) of the unprojected matrix to 1e-12 of its scale (both are
    /// sums of a few products of O(k/l₀) terms; rounding is ~1e-16), and it is PSD.
    #[test]
    fn projection_is_the_numerical_eigen_clamp() {
        for dim in [2usize, 3] {
            let x: Vec<f64> = (0..2 * dim)
                .map(|k| [0.1, -0.2, 0.05, 0.9, 0.3, -0.4][k])
                .collect();
            let s = Springs::new(dim, &x, vec![[0, 1]], 50.0).expect("valid spring");
            let n = 2 * dim;
            for stretch in [0.3, 0.8, 1.0, 1.4] {
                let mut y = x.clone();
                for a in 0..dim {
                    y[dim + a] = x[a] + stretch * (x[dim + a] - x[a]);
                }
                let mut exact = vec![0.0; n * n];
                s.element_hessian(&y, 0, false, &mut exact);
                let mut numeric = exact.clone();
                crate::sim::energy::project_psd(n, &mut numeric);
                let mut closed = vec![0.0; n * n];
                s.element_hessian(&y, 0, true, &mut closed);
                let scale = exact.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let err = numeric
                    .iter()
                    .zip(&closed)
                    .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                assert!(err <= 1e-12 * scale, "{dim}D stretch {stretch}: {err:e}");
                let m = nalgebra::DMatrix::from_row_slice(n, n, &closed);
                let min = nalgebra::SymmetricEigen::new(m).eigenvalues.min();
                assert!(min >= -1e-12 * scale, "{dim}D stretch {stretch}: {min:e}");
                // Compressed springs have a negative transverse eigenvalue to clamp.
                let changed = numeric
                    .iter()
                    .zip(&exact)
                    .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                assert_eq!(changed > 1e-3 * scale, stretch < 1.0, "{dim}D {stretch}");
            }
        }
    }
}
