//! Distance barrier against analytic half-spaces (docs/method.md, "Contact with
//! half-spaces"):
//!
//! ```text
//! P_b(x) = Σ_i Σ_j w_i d̂_j b_j(d_ij(x)),
//! b_j(d) = κ_j/2 (d/d̂_j − 1) ln(d/d̂_j)   for d < d̂_j,   0 for d ≥ d̂_j,
//! ```
//!
//! with d_ij = n_jᵀ x_i − c_j the signed distance of node i to half-space j (unit outward
//! normal n_j, plane offset c_j = n_jᵀ p_j) and w_i the node's contact measure (area in
//! 3D, length in 2D; [`crate::sim::mesh::Mesh::boundary_measure`]). The integrator adds h² P_b to
//! the incremental potential. (This is the form d̂·b(d) with b linear times log, not the
//! (d − d̂)² ln variant of other IPC texts.) With s = d/d̂:
//!
//! ```text
//! ∂P/∂d  = w κ/2 (ln s + 1 − 1/s)       (≤ 0: the barrier pushes away from the plane)
//! ∂²P/∂d² = w κ/2 (1/d + d̂/d²)           (> 0)
//! ```
//!
//! so the gradient is ∂P/∂d · n and the Hessian ∂²P/∂d² · n nᵀ, PSD by construction (no
//! projection needed). b is C¹ at d = d̂ (b' → 0) while b'' jumps from κ/d̂ to 0 there.
//! κ is a pressure (Pa) in 2D and 3D alike (2D energies are per unit thickness).
//! Only pairs with d < d̂ contribute; d ≤ 0 gives +∞ energy (the CCD filter keeps every
//! iterate away from it).
//!
//! Interior nodes of a solid have w_i = 0: the barrier never acts on them. The CCD bound
//! and [`Barrier::min_distance`] still cover every node, so no node of any kind crosses a
//! plane; [`Ccd::limit`] says which node set the bound, so the integrator can tell when
//! only the bound (no barrier) holds a node off an obstacle.

use crate::core::sparse::BlockCsr;

/// One half-space n·x ≥ c at its current position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfSpace {
    /// Unit outward normal (pointing into the allowed side).
    pub normal: [f64; 3],
    /// Plane offset c = n·p.
    pub offset: f64,
    /// Activation distance d̂ (m).
    pub dhat: f64,
    /// Stiffness κ (Pa).
    pub kappa: f64,
}

impl HalfSpace {
    /// Signed distance of point p (first `dim` entries used).
    pub fn distance(&self, p: &[f64]) -> f64 {
        p.iter().zip(&self.normal).map(|(a, b)| a * b).sum::<f64>() - self.offset
    }
}

/// d̂ b(d) and its first two derivatives in d, unweighted; zero for d ≥ d̂.
pub fn scalar(d: f64, dhat: f64, kappa: f64) -> (f64, f64, f64) {
    if d >= dhat {
        return (0.0, 0.0, 0.0);
    }
    if d <= 0.0 {
        return (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY);
    }
    let s = d / dhat;
    let ls = s.ln();
    let e = dhat * 0.5 * kappa * (s - 1.0) * ls;
    let g = 0.5 * kappa * (ls + 1.0 - 1.0 / s);
    let h = 0.5 * kappa * (1.0 / d + dhat / (d * d));
    (e, g, h)
}

/// The barrier over a set of nodes: contact weights w_i (zero for interior nodes).
#[derive(Debug, Clone)]
pub struct Barrier {
    pub dim: usize,
    pub weight: Vec<f64>,
    /// Nodes with w_i > 0: the only ones the barrier energy acts on.
    pub surface: Vec<usize>,
}

/// The CCD bound of one Newton step, with the node and plane that set it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ccd {
    /// The largest admissible step α_C ∈ [0, 1].
    pub alpha: f64,
    /// (node, plane) whose distance sets α_C when α_C < 1; None when α_C = 1.
    pub limit: Option<(usize, usize)>,
}

impl Barrier {
    pub fn new(dim: usize, weight: Vec<f64>) -> Self {
        let surface = (0..weight.len()).filter(|&i| weight[i] > 0.0).collect();
        Barrier {
            dim,
            weight,
            surface,
        }
    }

    /// Calls `f(node, obstacle, d)` for every pair within d̂ (the active set).
    fn active(&self, x: &[f64], planes: &[HalfSpace], mut f: impl FnMut(usize, usize, f64)) {
        let d = self.dim;
        for &i in &self.surface {
            let p = &x[i * d..(i + 1) * d];
            for (j, o) in planes.iter().enumerate() {
                let dist = o.distance(p);
                if dist < o.dhat {
                    f(i, j, dist);
                }
            }
        }
    }

    /// P_b(x); +∞ when a node with w_i > 0 touches or crosses a plane (a node with w_i = 0
    /// adds nothing wherever it is).
    pub fn energy(&self, x: &[f64], planes: &[HalfSpace]) -> f64 {
        let mut e = 0.0;
        self.active(x, planes, |i, j, dist| {
            let o = &planes[j];
            e += self.weight[i] * scalar(dist, o.dhat, o.kappa).0;
        });
        e
    }

    /// out += scale·∇P_b(x). Returns the number of active pairs.
    pub fn add_gradient(
        &self,
        x: &[f64],
        planes: &[HalfSpace],
        scale: f64,
        out: &mut [f64],
    ) -> usize {
        let d = self.dim;
        let mut n = 0;
        self.active(x, planes, |i, j, dist| {
            let o = &planes[j];
            let g = self.weight[i] * scalar(dist, o.dhat, o.kappa).1;
            for a in 0..d {
                out[i * d + a] += scale * g * o.normal[a];
            }
            n += 1;
        });
        n
    }

    /// Per node i, out\[i\] += scale · Σ_planes ‖∇_i P_b‖: the sizes of the barrier forces
    /// before they add up (a node between two planes meets two).
    pub fn add_force_scale(&self, x: &[f64], planes: &[HalfSpace], scale: f64, out: &mut [f64]) {
        self.active(x, planes, |i, j, dist| {
            let o = &planes[j];
            out[i] += scale * (self.weight[i] * scalar(dist, o.dhat, o.kappa).1).abs();
        });
    }

    /// h += scale·∇²P_b(x) (node-diagonal blocks w b'' n nᵀ; every pattern has them).
    pub fn add_hessian(&self, x: &[f64], planes: &[HalfSpace], scale: f64, h: &mut BlockCsr) {
        let d = self.dim;
        self.active(x, planes, |i, j, dist| {
            let o = &planes[j];
            let k = self.weight[i] * scalar(dist, o.dhat, o.kappa).2;
            let kb = h.diag_index(i).expect("every node has a diagonal block");
            for a in 0..d {
                for c in 0..d {
                    h.values[kb * d * d + a * d + c] += scale * k * o.normal[a] * o.normal[c];
                }
            }
        });
    }

    /// Smallest signed distance of any node (interior nodes included) to any plane, with
    /// (node, plane). A NaN distance is returned as soon as it is met.
    pub fn min_distance(&self, x: &[f64], planes: &[HalfSpace]) -> (f64, usize, usize) {
        let d = self.dim;
        let mut best = (f64::INFINITY, 0, 0);
        for (i, p) in x.chunks_exact(d).enumerate() {
            for (j, o) in planes.iter().enumerate() {
                let dist = o.distance(p);
                if dist.is_nan() {
                    return (dist, i, j);
                }
                if dist < best.0 {
                    best = (dist, i, j);
                }
            }
        }
        best
    }

    /// CCD for x + αΔx: the largest α ≤ 1 that lets every approaching node (interior nodes
    /// included) cover at most `fraction` of its distance to every plane,
    /// α_C = min(1, fraction·d_i/(−n·Δx_i)) (IPC's 1 − s with s = 1 − fraction), so every
    /// iterate keeps d > 0. Nodes move linearly in α and the planes hold still within a
    /// step (a moving plane sits at its end-of-step position), so this is exact: no
    /// conservative root finding is needed.
    pub fn ccd(&self, x: &[f64], dx: &[f64], planes: &[HalfSpace], fraction: f64) -> Ccd {
        let d = self.dim;
        let mut out = Ccd {
            alpha: 1.0,
            limit: None,
        };
        for (i, (p, v)) in x.chunks_exact(d).zip(dx.chunks_exact(d)).enumerate() {
            for (j, o) in planes.iter().enumerate() {
                let rate: f64 = v.iter().zip(&o.normal).map(|(a, b)| a * b).sum();
                if rate < 0.0 {
                    let a = fraction * o.distance(p) / -rate;
                    if a < out.alpha {
                        out = Ccd {
                            alpha: a,
                            limit: Some((i, j)),
                        };
                    }
                }
            }
        }
        out.alpha = out.alpha.max(0.0);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scalar_derivatives_match_finite_differences() {
        let (dhat, kappa) = (0.01, 3e4);
        for &d in &[1e-4, 1e-3, 5e-3, 9.9e-3] {
            let (_, g, h) = scalar(d, dhat, kappa);
            let eps = 1e-7 * d;
            let fd_g =
                (scalar(d + eps, dhat, kappa).0 - scalar(d - eps, dhat, kappa).0) / (2.0 * eps);
            let fd_h =
                (scalar(d + eps, dhat, kappa).1 - scalar(d - eps, dhat, kappa).1) / (2.0 * eps);
            assert!((g - fd_g).abs() <= 1e-6 * g.abs(), "d {d}: {g} vs {fd_g}");
            assert!((h - fd_h).abs() <= 1e-6 * h.abs(), "d {d}: {h} vs {fd_h}");
            assert!(g < 0.0 && h > 0.0);
        }
        assert_eq!(scalar(dhat, dhat, kappa), (0.0, 0.0, 0.0));
    }

    /// The assembled gradient and Hessian (w b'(d) n and w b''(d) n nᵀ per active pair,
    /// summed over planes) are the derivatives of P_b(x): central differences of the
    /// energy and of the gradient, with a step of 1e-7 of d̂ (truncation ~1e-14 of the
    /// curvature scale, rounding ~1e-9), agree to 1e-6 relative.
    #[test]
    fn node_gradient_and_hessian_match_finite_differences() {
        for dim in [2usize, 3] {
            let len = (0.3f64 * 0.3 + 0.9 * 0.9 + if dim == 3 { 0.2 * 0.2 } else { 0.0 }).sqrt();
            let tilted = [
                0.3 / len,
                0.9 / len,
                if dim == 3 { -0.2 / len } else { 0.0 },
            ];
            let planes = [
                HalfSpace {
                    normal: [0.0, 1.0, 0.0],
                    offset: 0.0,
                    dhat: 0.05,
                    kappa: 1e4,
                },
                HalfSpace {
                    normal: tilted,
                    offset: -0.01,
                    dhat: 0.08,
                    kappa: 3e3,
                },
            ];
            // Node 0 near both planes, node 1 near the ground only, node 2 weightless.
            let mut x = vec![0.0; 3 * dim];
            x[1] = 0.02;
            x[dim] = 0.5;
            x[dim + 1] = 0.03;
            x[2 * dim + 1] = 0.01;
            let bar = Barrier::new(dim, vec![0.7, 0.4, 0.0]);
            let n = x.len();
            let mut g = vec![0.0; n];
            bar.add_gradient(&x, &planes, 1.0, &mut g);
            let rows: Vec<Vec<usize>> = (0..3).map(|i| vec![i]).collect();
            let mut h = BlockCsr::from_pattern(dim, &rows);
            bar.add_hessian(&x, &planes, 1.0, &mut h);
            let hd = h.to_dense();
            let gs = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let hs = hd.amax();
            assert!(gs > 0.0 && hs > 0.0);
            let eps = 1e-7 * 0.05;
            for k in 0..n {
                let (mut xp, mut xm) = (x.clone(), x.clone());
                xp[k] += eps;
                xm[k] -= eps;
                let fd = (bar.energy(&xp, &planes) - bar.energy(&xm, &planes)) / (2.0 * eps);
                assert!(
                    (fd - g[k]).abs() <= 1e-6 * gs,
                    "{dim}D dof {k}: {} vs {fd}",
                    g[k]
                );
                let (mut gp, mut gm) = (vec![0.0; n], vec![0.0; n]);
                bar.add_gradient(&xp, &planes, 1.0, &mut gp);
                bar.add_gradient(&xm, &planes, 1.0, &mut gm);
                for r in 0..n {
                    let fd = (gp[r] - gm[r]) / (2.0 * eps);
                    assert!(
                        (fd - hd[(r, k)]).abs() <= 1e-6 * hs,
                        "{dim}D H({r},{k}): {} vs {fd}",
                        hd[(r, k)]
                    );
                }
            }
            // The weightless node contributes nothing.
            assert!(g[2 * dim..].iter().all(|&v| v == 0.0));
        }
    }

    /// A node without barrier weight is still covered by the CCD bound and by
    /// `min_distance`, and the bound says which node and plane set it.
    #[test]
    fn ccd_and_min_distance_cover_weightless_nodes() {
        let ground = HalfSpace {
            normal: [0.0, 1.0, 0.0],
            offset: 0.0,
            dhat: 0.01,
            kappa: 1e5,
        };
        let ceiling = HalfSpace {
            normal: [0.0, -1.0, 0.0],
            offset: -1.0,
            dhat: 0.01,
            kappa: 1e5,
        };
        let planes = [ground, ceiling];
        // Node 1 (weight 0) is nearest the ground and moves towards it fastest.
        let bar = Barrier::new(2, vec![0.5, 0.0, 0.5]);
        let x = [0.0, 0.3, 0.5, 0.2, 1.0, 0.6];
        assert_eq!(bar.min_distance(&x, &planes), (0.2, 1, 0));
        let dx = [0.0, -0.1, 0.0, -0.4, 0.0, 0.1];
        let c = bar.ccd(&x, &dx, &planes, 0.9);
        // Node 1 sets it: 0.9·0.2/0.4 = 0.45 (node 0: 0.9·0.3/0.1, node 2: 0.9·0.4/0.1).
        assert_eq!(c.limit, Some((1, 0)));
        assert!((c.alpha - 0.45).abs() <= 1e-15, "{}", c.alpha);
        for (i, p) in x.chunks_exact(2).enumerate() {
            let q = [p[0] + c.alpha * dx[2 * i], p[1] + c.alpha * dx[2 * i + 1]];
            for o in &planes {
                assert!(o.distance(&q) > 0.0, "node {i}");
            }
        }
        // Moving away from both planes: no bound.
        let away = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let c = bar.ccd(&x, &away, &planes, 0.9);
        assert_eq!((c.alpha, c.limit), (1.0, None));
        // A weightless node adds no energy, even past a plane; a weighted one gives +∞.
        assert_eq!(bar.energy(&[0.0, 0.3, 0.5, -0.1, 1.0, 0.6], &planes), 0.0);
        assert_eq!(
            bar.energy(&[0.0, -0.1, 0.5, 0.2, 1.0, 0.6], &planes),
            f64::INFINITY
        );
    }
}
