//! The neo-Hookean element kernels of the assembly with the dimension a compile-time
//! constant: fixed-size stack arrays, unrolled loops, no per-element dispatch on d, and
//! each element Hessian written straight into its upper node blocks (the slots the
//! assembly gathers from); projected 3D Hessians run [`LANES`] elements side by side
//! ([`super::lanes`]). Every value is the same expression, evaluated in the same
//! order, as the per-element reference ([`NeoHookean::element_hessian`],
//! [`NeoHookean::element_gradient`], [`NeoHookean::element_energy`]), so the results are
//! equal to it bit for bit (the tests check it), and a scene's trajectory does not depend
//! on which one ran.

use super::eigensystem::{self, SingularValueHessian, LANES, PAIRS};
use super::lanes::{self, Lanes, SingularValueHessianLanes, BLOCK_VALUES};
use super::neohookean::{Coefficients, NeoHookean};

/// Lanes as plain arrays (the eigensolver's layout).
#[inline(always)]
fn to_arrays(m: &lanes::Mat3) -> [[[f64; LANES]; 3]; 3] {
    m.map(|row| row.map(|x| x.0))
}

#[inline(always)]
fn from_arrays(m: &[[[f64; LANES]; 3]; 3]) -> lanes::Mat3 {
    m.map(|row| row.map(Lanes))
}

impl NeoHookean {
    /// F of element e (row-major D×D in the leading entries), summed over the nodes in
    /// order from zero, as [`NeoHookean::deformation_gradient`].
    #[inline(always)]
    fn deformation_gradient_fixed<const D: usize>(&self, x: &[f64], e: usize) -> [f64; 9] {
        let g = self.grads(e);
        let nodes = self.nodes(e);
        let mut f = [0.0f64; 9];
        for a in 0..=D {
            let node = nodes[a];
            let xs = &x[node * D..node * D + D];
            for i in 0..D {
                let xi = xs[i];
                for j in 0..D {
                    f[i * D + j] += xi * g[a * D + j];
                }
            }
        }
        f
    }

    /// [`NeoHookean::singular_value_hessian`] with D fixed: the products of "the other"
    /// singular values written out (a product over no factor is 1, over one is that
    /// factor, exactly as the reference's running products from 1).
    #[inline(always)]
    fn singular_value_hessian_fixed<const D: usize>(
        &self,
        sigma: &[f64; 3],
    ) -> SingularValueHessian {
        let s3 = if D == 2 {
            [sigma[0], sigma[1], 1.0]
        } else {
            *sigma
        };
        let ic: f64 = s3[..D].iter().map(|v| v * v).sum();
        let j: f64 = s3[..D].iter().product();
        let Coefficients { s, q, w, t } = self.coefficients(ic, j);
        // others1[a]: the product of the singular values other than a, in index order.
        let others1 = if D == 2 {
            [s3[1], s3[0], 1.0]
        } else {
            [s3[1] * s3[2], s3[0] * s3[2], s3[0] * s3[1]]
        };
        // others2(a, b): the remaining one (3D) or none (2D).
        let others2 = |a: usize, b: usize| if D == 2 { 1.0 } else { s3[3 - a - b] };
        let mut h = SingularValueHessian::default();
        for a in 0..D {
            for b in 0..D {
                let mut v = q * s3[a] * s3[b] + w * others1[a] * others1[b];
                if a == b {
                    v += s;
                } else {
                    v += t * others2(a, b);
                }
                h.a[a][b] = v;
            }
        }
        let pairs = if D == 2 { 1 } else { 3 };
        for (p, &(a, b)) in PAIRS.iter().enumerate().take(pairs) {
            let k = others2(a, b);
            h.twist[p] = s + t * k;
            h.flip[p] = s - t * k;
        }
        h
    }

    /// The projected Hessian of element e as its upper node blocks (a ≤ b, each D×D
    /// row-major), `(D+1)(D+2)/2 · D²` values: [`NeoHookean::element_hessian`] with
    /// `project`, bit for bit.
    fn projected_blocks_fixed<const D: usize, const NL: usize, const NM: usize>(
        &self,
        x: &[f64],
        e: usize,
        out: &mut [f64],
    ) {
        let f = self.deformation_gradient_fixed::<D>(x, e);
        let (u, sigma, v) = eigensystem::signed_svd(D, &f[..D * D]);
        let h = self.singular_value_hessian_fixed::<D>(&sigma);
        let (vals, vecs) = eigensystem::scaling_eigen(D, &h.a);
        eigensystem::projected_element_blocks::<D, NL, NM>(
            &u,
            &v,
            &h,
            (&vals, &vecs),
            self.grads(e),
            self.volume[e],
            out,
        );
    }

    /// The projected Hessians of the 3D elements `e` ([`LANES`] of them, repeats allowed)
    /// as their upper node blocks, element after element into `out`, for the first
    /// `out.len() / 90` lanes: every stage runs lane-innermost ([`lanes`],
    /// [`eigensystem::symmetric_eigen3_lanes`]). Bit for bit
    /// [`NeoHookean::element_hessian`] with `project` of each element.
    #[inline(always)]
    fn projected_blocks3_lanes(
        &self,
        x: &[f64],
        e: [usize; LANES],
        modes: &mut lanes::Modes,
        out: &mut [f64],
    ) {
        let (f, g, scale) = self.gather3(x, &e);
        let (lam, ev) = eigensystem::symmetric_eigen3_lanes(&to_arrays(&lanes::gram3(&f)));
        let (u, sigma, v) = lanes::signed_svd3(&f, &lam.map(Lanes), &from_arrays(&ev));
        let h = self.singular_value_hessian_lanes(&sigma);
        let (vals, vecs) = eigensystem::symmetric_eigen3_lanes(&to_arrays(&h.a));
        modes.fill(
            (&u, &v),
            &h,
            (&vals.map(Lanes), &from_arrays(&vecs)),
            &g,
            scale,
        );
        modes.store_upper_blocks(out);
    }

    /// Per lane, F, the shape gradients `G[a][j]` and the rest volume of element `e[l]`.
    #[inline(always)]
    fn gather3(&self, x: &[f64], e: &[usize; LANES]) -> (lanes::Mat3, [lanes::Vec3; 4], Lanes) {
        let zero = Lanes::splat(0.0);
        let mut f = [[zero; 3]; 3];
        let mut g = [[zero; 3]; 4];
        let mut scale = zero;
        for (l, &el) in e.iter().enumerate() {
            let fl = self.deformation_gradient_fixed::<3>(x, el);
            let gl = self.grads(el);
            for r in 0..3 {
                for c in 0..3 {
                    f[r][c].0[l] = fl[r * 3 + c];
                }
            }
            for a in 0..4 {
                for j in 0..3 {
                    g[a][j].0[l] = gl[a * 3 + j];
                }
            }
            scale.0[l] = self.volume[el];
        }
        (f, g, scale)
    }

    /// [`NeoHookean::singular_value_hessian_fixed`] (3D) of each lane.
    #[inline(always)]
    fn singular_value_hessian_lanes(&self, s3: &lanes::Vec3) -> SingularValueHessianLanes {
        let ic = s3[0] * s3[0] + s3[1] * s3[1] + s3[2] * s3[2];
        let j = s3[0] * s3[1] * s3[2];
        let zero = Lanes::splat(0.0);
        let (mut s, mut q, mut w, mut t) = (zero, zero, zero, zero);
        for l in 0..LANES {
            let c = self.coefficients(ic.0[l], j.0[l]);
            (s.0[l], q.0[l], w.0[l], t.0[l]) = (c.s, c.q, c.w, c.t);
        }
        let others1 = [s3[1] * s3[2], s3[0] * s3[2], s3[0] * s3[1]];
        let mut h = SingularValueHessianLanes {
            a: [[zero; 3]; 3],
            twist: [zero; 3],
            flip: [zero; 3],
        };
        for a in 0..3 {
            for b in 0..3 {
                let v = q * s3[a] * s3[b] + w * others1[a] * others1[b];
                h.a[a][b] = if a == b { v + s } else { v + t * s3[3 - a - b] };
            }
        }
        for (p, &(a, b)) in PAIRS.iter().enumerate() {
            let k = s3[3 - a - b];
            h.twist[p] = s + t * k;
            h.flip[p] = s - t * k;
        }
        h
    }

    /// The Hessians of the elements `first..first + n` (n = `out.len()` / the block
    /// values of one element) as their upper node blocks, element after element:
    /// [`NeoHookean::element_hessian_blocks`] of each, 3D projected ones [`LANES`] at a
    /// time.
    pub fn element_hessian_blocks_run(
        &self,
        x: &[f64],
        first: usize,
        project: bool,
        out: &mut [f64],
    ) {
        let d = self.dim;
        let size = (d + 1) * (d + 2) / 2 * d * d;
        if !(project && d == 3) {
            for (k, o) in out.chunks_exact_mut(size).enumerate() {
                self.element_hessian_blocks(x, first + k, project, o);
            }
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2, checked just above.
            unsafe { self.projected_run3_avx2(x, first, out) };
            return;
        }
        self.projected_run3(x, first, out);
    }

    /// [`NeoHookean::projected_run3`] compiled for AVX2 (the lanes in three registers).
    /// Same operations, so the same bits: Rust never fuses a multiply and an add.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn projected_run3_avx2(&self, x: &[f64], first: usize, out: &mut [f64]) {
        self.projected_run3(x, first, out);
    }

    /// The projected 3D element Hessians of [`NeoHookean::element_hessian_blocks_run`],
    /// [`LANES`] elements at a time.
    #[inline(always)]
    fn projected_run3(&self, x: &[f64], first: usize, out: &mut [f64]) {
        let mut modes = lanes::Modes::default();
        for (b, group) in out.chunks_mut(LANES * BLOCK_VALUES).enumerate() {
            let count = group.len() / BLOCK_VALUES;
            let e0 = first + b * LANES;
            // A short last group repeats its last element in the spare lanes.
            let e = std::array::from_fn(|l| e0 + l.min(count - 1));
            self.projected_blocks3_lanes(x, e, &mut modes, group);
        }
    }

    /// The Hessian of element e as its upper node blocks (a ≤ b in node order, each d×d
    /// row-major): the slots of the assembly's element buffer. Projected, it runs the
    /// fixed-size kernel; unprojected, the reference, copied out.
    pub fn element_hessian_blocks(&self, x: &[f64], e: usize, project: bool, out: &mut [f64]) {
        match (project, self.dim) {
            (true, 3) => self.projected_blocks_fixed::<3, 12, 9>(x, e, out),
            (true, 2) => self.projected_blocks_fixed::<2, 6, 4>(x, e, out),
            _ => {
                let d = self.dim;
                let nl = (d + 1) * d;
                let mut m = [0.0f64; 144];
                self.element_hessian(x, e, project, &mut m[..nl * nl]);
                upper_blocks_of(d, d + 1, &m[..nl * nl], out);
            }
        }
    }

    /// [`NeoHookean::element_gradient`] with the dimension fixed, bit for bit.
    pub fn element_gradient_fast(&self, x: &[f64], e: usize, out: &mut [f64]) {
        match self.dim {
            3 => self.gradient_fixed::<3>(x, e, out),
            2 => self.gradient_fixed::<2>(x, e, out),
            _ => self.element_gradient(x, e, out),
        }
    }

    #[inline(always)]
    fn gradient_fixed<const D: usize>(&self, x: &[f64], e: usize, out: &mut [f64]) {
        let f = self.deformation_gradient_fixed::<D>(x, e);
        let mut p = [0.0; 9];
        self.stress(&f, &mut p);
        let g = self.grads(e);
        let v = self.volume[e];
        for a in 0..=D {
            for c in 0..D {
                out[a * D + c] = v * (0..D).map(|j| p[c * D + j] * g[a * D + j]).sum::<f64>();
            }
        }
    }

    /// [`NeoHookean::element_energy`] with the dimension fixed, bit for bit.
    pub fn element_energy_fast(&self, x: &[f64], e: usize) -> f64 {
        let f = match self.dim {
            3 => self.deformation_gradient_fixed::<3>(x, e),
            2 => self.deformation_gradient_fixed::<2>(x, e),
            _ => return self.element_energy(x, e),
        };
        self.volume[e] * self.density(&f[..self.dim * self.dim])
    }
}

/// The upper node blocks (a ≤ b, each d×d row-major) of the matrix `m` of an element
/// with `ar` nodes ((ar·d) square, row-major).
pub fn upper_blocks_of(d: usize, ar: usize, m: &[f64], out: &mut [f64]) {
    let nl = ar * d;
    let dd = d * d;
    let mut p = 0;
    for a in 0..ar {
        for b in a..ar {
            let blk = &mut out[p * dd..(p + 1) * dd];
            for r in 0..d {
                for c in 0..d {
                    blk[r * d + c] = m[(a * d + r) * nl + b * d + c];
                }
            }
            p += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::energy::neohookean::Law;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// Meshes of both dimensions, deformed at random (stretched, sheared, some elements
    /// inverted or flattened).
    fn deformed(d: usize, law: Law, rng: &mut StdRng) -> (NeoHookean, Vec<f64>) {
        let mesh = if d == 2 {
            crate::sim::mesh::rectangle(2, [1.0, 0.5], [6, 3])
        } else {
            crate::sim::mesh::cuboid([1.0, 0.4, 0.4], [4, 2, 2])
        };
        let nh = NeoHookean::new(&mesh, 1e5, 0.45, law).expect("valid mesh");
        let amp = rng.random_range(0.01..0.3);
        let x = mesh
            .x
            .iter()
            .map(|v| 1.3 * v + rng.random_range(-amp..amp))
            .collect();
        (nh, x)
    }

    /// The fixed-size kernels against the per-element reference, for both laws and
    /// dimensions, projected and not: equal bit for bit (same expressions in the same
    /// order), including NaN where the classical law meets an inverted element.
    #[test]
    fn fixed_size_kernels_equal_the_reference_bit_for_bit() {
        let mut rng = StdRng::seed_from_u64(41);
        let mut inverted = 0;
        for (d, law) in [2, 3]
            .into_iter()
            .flat_map(|d| [Law::NeoHookean, Law::StableNeoHookean].map(|l| (d, l)))
        {
            for _ in 0..20 {
                let (nh, x) = deformed(d, law, &mut rng);
                let nl = (d + 1) * d;
                let np = (d + 1) * (d + 2) / 2;
                for e in 0..nh.len() {
                    inverted += (nh.volume_ratio(&x, e) <= 0.0) as usize;
                    for project in [true, false] {
                        let mut full = vec![0.0; nl * nl];
                        nh.element_hessian(&x, e, project, &mut full);
                        let mut want = vec![0.0; np * d * d];
                        upper_blocks_of(d, d + 1, &full, &mut want);
                        let mut got = vec![0.0; np * d * d];
                        nh.element_hessian_blocks(&x, e, project, &mut got);
                        let bits = |v: &[f64]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
                        assert_eq!(bits(&got), bits(&want), "{d}D {law:?} element {e}");
                    }
                    let mut want = vec![0.0; nl];
                    nh.element_gradient(&x, e, &mut want);
                    if e == 0 {
                        // Runs of every length up to two lane groups and a remainder,
                        // from every start: lanes, spare lanes and the tail.
                        let size = np * d * d;
                        for first in 0..3 {
                            for n in 0..=(2 * LANES + 1).min(nh.len() - first) {
                                let mut run = vec![0.0; n * size];
                                nh.element_hessian_blocks_run(&x, first, true, &mut run);
                                for (k, got) in run.chunks_exact(size).enumerate() {
                                    let mut one = vec![0.0; size];
                                    nh.element_hessian_blocks(&x, first + k, true, &mut one);
                                    let bits = |v: &[f64]| {
                                        v.iter().map(|f| f.to_bits()).collect::<Vec<_>>()
                                    };
                                    assert_eq!(bits(got), bits(&one), "{d}D run {first}+{k}");
                                }
                            }
                        }
                    }
                    let mut got = vec![0.0; nl];
                    nh.element_gradient_fast(&x, e, &mut got);
                    for (a, b) in got.iter().zip(&want) {
                        assert_eq!(a.to_bits(), b.to_bits(), "{d}D {law:?} gradient {e}");
                    }
                    let (a, b) = (nh.element_energy_fast(&x, e), nh.element_energy(&x, e));
                    assert_eq!(a.to_bits(), b.to_bits(), "{d}D {law:?} energy {e}");
                }
            }
        }
        // The deformations reach inverted elements too (the clamp and the classical
        // law's NaN are exercised).
        assert!(inverted > 0);
    }

    /// Half the nodes moved onto a line (elements there flat: F of rank one, U's second
    /// column from the fallback) or onto a point (collapsed: F = 0, U's first column from
    /// the fallback too), beside ordinary elements in the same lane groups: every lane
    /// takes the per-element reference's branch, bit for bit.
    #[test]
    fn lanes_equal_the_reference_on_flat_and_collapsed_elements() {
        let mut rng = StdRng::seed_from_u64(43);
        for law in [Law::NeoHookean, Law::StableNeoHookean] {
            let (nh, x) = deformed(3, law, &mut rng);
            let nodes = x.len() / 3;
            for first_kept_axis in [1, 0] {
                let mut y = x.clone();
                for p in &mut y[..nodes / 2 * 3] {
                    *p = 0.0;
                }
                for node in 0..nodes / 2 {
                    y[node * 3..node * 3 + first_kept_axis]
                        .copy_from_slice(&x[node * 3..node * 3 + first_kept_axis]);
                }
                // det F is exactly zero when two rows of F are.
                let degenerate = (0..nh.len())
                    .filter(|&e| nh.volume_ratio(&y, e) == 0.0)
                    .count();
                assert!(degenerate > 0 && degenerate < nh.len(), "{degenerate}");
                let size = BLOCK_VALUES;
                let mut run = vec![0.0; nh.len() * size];
                nh.element_hessian_blocks_run(&y, 0, true, &mut run);
                for (e, got) in run.chunks_exact(size).enumerate() {
                    let mut full = vec![0.0; 144];
                    nh.element_hessian(&y, e, true, &mut full);
                    let mut want = vec![0.0; size];
                    upper_blocks_of(3, 4, &full, &mut want);
                    let bits = |v: &[f64]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(got), bits(&want), "{law:?} element {e}");
                }
            }
        }
    }
}
