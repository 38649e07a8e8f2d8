//! The neo-Hookean element kernels of the assembly with the dimension a compile-time
//! constant: fixed-size stack arrays, unrolled loops, no per-element dispatch on d, and
//! each element Hessian written straight into its upper node blocks (the slots the
//! assembly gathers from). In 3D the projected Hessians, the gradients, the energies
//! and the inversion bound's step polynomials run [`LANES`] elements side by side
//! ([`super::lanes`]), AVX2 where the CPU has it (`lane_pass!`); sums over elements (the
//! energy's, the inversion bound's minimum) still take the elements one after another in
//! order. Every value is the same expression, evaluated in the same order, as the
//! per-element reference ([`NeoHookean::element_hessian`],
//! [`NeoHookean::element_gradient`], [`NeoHookean::element_energy`],
//! `neohookean::step_det_polynomial`), so the results are equal to it bit for bit (the
//! tests check it), and a scene's trajectory does not depend on which one ran.

use super::eigensystem::{self, SingularValueHessian, LANES, PAIRS};
use super::lanes::{self, Lanes, SingularValueHessianLanes, BLOCK_VALUES};
use super::neohookean::{root_below, Coefficients, Law, NeoHookean};

/// Defines the method `$name`, which calls `self.$body(args)` (an `#[inline(always)]`
/// lane pass) compiled for AVX2 where the CPU has it (a [`Lanes`] in three registers),
/// else for the baseline target. The same operations either way, so the same bits: Rust
/// never fuses a multiply and an add, and the lane passes' `ln` stays one libm call per
/// lane.
macro_rules! lane_pass {
    ($(#[$doc:meta])* $vis:vis fn $name:ident(&self $(, $a:ident: $t:ty)*) $(-> $r:ty)?
        => $body:ident) => {
        $(#[$doc])*
        $vis fn $name(&self $(, $a: $t)*) $(-> $r)? {
            /// # Safety
            /// The CPU must have AVX2.
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            unsafe fn avx2(nh: &NeoHookean $(, $a: $t)*) $(-> $r)? {
                nh.$body($($a),*)
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2, checked just above.
                return unsafe { avx2(self $(, $a)*) };
            }
            self.$body($($a),*)
        }
    };
}

// The conversions below are written as loops, not `array::map`: an out-of-line `map`
// would keep a lane group's values in memory, whatever the optimiser's budget.

/// Lanes as plain arrays (the eigensolver's layout).
#[inline(always)]
fn to_arrays(m: &lanes::Mat3) -> [[[f64; LANES]; 3]; 3] {
    let mut a = [[[0.0; LANES]; 3]; 3];
    for (ar, mr) in a.iter_mut().zip(m) {
        for (e, x) in ar.iter_mut().zip(mr) {
            *e = x.0;
        }
    }
    a
}

#[inline(always)]
fn from_arrays(m: &[[[f64; LANES]; 3]; 3]) -> lanes::Mat3 {
    lanes::mat3(|r, c| Lanes(m[r][c]))
}

#[inline(always)]
fn from_array3(v: &[[f64; LANES]; 3]) -> lanes::Vec3 {
    lanes::vec3(|r| Lanes(v[r]))
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
        let (u, sigma, v) = lanes::signed_svd3(&f, &from_array3(&lam), &from_arrays(&ev));
        let h = self.singular_value_hessian_lanes(&sigma);
        let (vals, vecs) = eigensystem::symmetric_eigen3_lanes(&to_arrays(&h.a));
        modes.fill(
            (&u, &v),
            &h,
            (&from_array3(&vals), &from_arrays(&vecs)),
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
        self.projected_run3(x, first, out);
    }

    lane_pass! {
        /// The projected 3D element Hessians of [`NeoHookean::element_hessian_blocks_run`].
        fn projected_run3(&self, x: &[f64], first: usize, out: &mut [f64]) => projected_lanes3
    }

    /// [`NeoHookean::projected_run3`], [`LANES`] elements at a time.
    #[inline(always)]
    fn projected_lanes3(&self, x: &[f64], first: usize, out: &mut [f64]) {
        let mut modes = lanes::Modes::default();
        for (b, group) in out.chunks_mut(LANES * BLOCK_VALUES).enumerate() {
            let count = group.len() / BLOCK_VALUES;
            let e = lane_elements(first + b * LANES, count);
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

    /// The gradients of the elements `first..first + n` (n = `out.len()` / its (d+1)·d
    /// entries), element after element: [`NeoHookean::element_gradient_fast`] of each,
    /// bit for bit; 3D ones [`LANES`] at a time.
    pub fn element_gradients_run(&self, x: &[f64], first: usize, out: &mut [f64]) {
        if self.dim != 3 {
            let nl = (self.dim + 1) * self.dim;
            for (k, o) in out.chunks_exact_mut(nl).enumerate() {
                self.element_gradient_fast(x, first + k, o);
            }
            return;
        }
        self.gradients_run3(x, first, out);
    }

    lane_pass! {
        /// The 3D element gradients of [`NeoHookean::element_gradients_run`].
        fn gradients_run3(&self, x: &[f64], first: usize, out: &mut [f64]) => gradients_lanes3
    }

    /// [`NeoHookean::gradients_run3`], [`LANES`] elements at a time: per lane
    /// [`NeoHookean::gradient_fixed`]'s operations in its order.
    #[inline(always)]
    fn gradients_lanes3(&self, x: &[f64], first: usize, out: &mut [f64]) {
        const NL: usize = 12;
        for (b, group) in out.chunks_mut(LANES * NL).enumerate() {
            let count = group.len() / NL;
            let e = lane_elements(first + b * LANES, count);
            let (f, g, volume) = self.gather3(x, &e);
            let p = self.stress_lanes3(&f);
            let mut o = [Lanes::splat(0.0); NL];
            for a in 0..4 {
                for c in 0..3 {
                    let s = lanes::sum_start()
                        + p[c][0] * g[a][0]
                        + p[c][1] * g[a][1]
                        + p[c][2] * g[a][2];
                    o[a * 3 + c] = volume * s;
                }
            }
            for (l, ol) in group.chunks_exact_mut(NL).enumerate() {
                for (v, ok) in ol.iter_mut().zip(&o) {
                    *v = ok.0[l];
                }
            }
        }
    }

    /// [`NeoHookean::stress`] (3D) of each lane's F: P = s F + t cof(F).
    #[inline(always)]
    fn stress_lanes3(&self, f: &lanes::Mat3) -> lanes::Mat3 {
        let ic = lanes::entry_dot(f, f);
        let j = lanes::det3(f);
        let c = lanes::cofactor3(f);
        let (s, _, _, t) = self.coefficients_lanes(ic, j);
        lanes::mat3(|r, k| s * f[r][k] + t * c[r][k])
    }

    /// [`NeoHookean::coefficients`] of each lane, (s, q, w, t): the same expressions in
    /// the same order, and each lane's logarithm the same `ln` call.
    #[inline(always)]
    fn coefficients_lanes(&self, ic: Lanes, j: Lanes) -> (Lanes, Lanes, Lanes, Lanes) {
        let (mu, lambda) = (Lanes::splat(self.mu), Lanes::splat(self.lambda));
        match self.law {
            Law::NeoHookean => {
                let l = j.map(|v| if v > 0.0 { v.ln() } else { f64::NAN });
                (
                    mu,
                    Lanes::splat(0.0),
                    (lambda * (Lanes::splat(1.0) - l) + mu) / (j * j),
                    (lambda * l - mu) / j,
                )
            }
            Law::StableNeoHookean => {
                let one = Lanes::splat(1.0);
                (
                    mu - mu / (ic + one),
                    Lanes::splat(2.0 * self.mu) / ((ic + one) * (ic + one)),
                    lambda,
                    lambda * (j - Lanes::splat(self.alpha)),
                )
            }
        }
    }

    /// [`NeoHookean::density`] (3D) of each lane's F: the same expressions in the same
    /// order (the classical law's +∞ where J ≤ 0 or NaN chosen per lane), and each lane's
    /// logarithm the same `ln` call.
    #[inline(always)]
    fn density_lanes(&self, f: &lanes::Mat3) -> Lanes {
        let ic = lanes::entry_dot(f, f);
        let j = lanes::det3(f);
        let half_mu = Lanes::splat(0.5 * self.mu);
        let stretch = half_mu * (ic - Lanes::splat(3.0));
        let raw = match self.law {
            Law::NeoHookean => {
                let l = j.map(f64::ln);
                let v =
                    stretch - Lanes::splat(self.mu) * l + Lanes::splat(0.5 * self.lambda) * l * l;
                // !(J > 0): J ≤ 0 or NaN.
                Lanes::select(!j.gt(Lanes::splat(0.0)), Lanes::splat(f64::INFINITY), v)
            }
            Law::StableNeoHookean => {
                let dj = (j - Lanes::splat(self.alpha)).map(|v| v.powi(2));
                stretch + Lanes::splat(0.5 * self.lambda) * dj
                    - half_mu * (ic + Lanes::splat(1.0)).map(f64::ln)
            }
        };
        raw - Lanes::splat(self.rest_density)
    }

    /// Σ of the energies of the elements `first..first + n` in element order:
    /// `.sum::<f64>()` of [`NeoHookean::element_energy_fast`] of each, bit for bit; 3D
    /// energies [`LANES`] at a time, then added one after another.
    pub fn element_energy_sum(&self, x: &[f64], first: usize, n: usize) -> f64 {
        if self.dim != 3 {
            return (first..first + n)
                .map(|e| self.element_energy_fast(x, e))
                .sum();
        }
        self.energy_sum3(x, first, n)
    }

    lane_pass! {
        /// The 3D energy sum of [`NeoHookean::element_energy_sum`].
        fn energy_sum3(&self, x: &[f64], first: usize, n: usize) -> f64 => energy_sum_lanes3
    }

    /// [`NeoHookean::energy_sum3`]: per lane [`NeoHookean::element_energy_fast`]'s
    /// operations, then the lanes' energies summed in element order.
    #[inline(always)]
    fn energy_sum_lanes3(&self, x: &[f64], first: usize, n: usize) -> f64 {
        // `Iterator::sum`'s fold, written out (so that it inlines here).
        let mut sum = lanes::sum_start_f64();
        for e0 in (first..first + n).step_by(LANES) {
            let count = LANES.min(first + n - e0);
            let (f, _, volume) = self.gather3(x, &lane_elements(e0, count));
            let energy = volume * self.density_lanes(&f);
            for e in &energy.0[..count] {
                sum += e;
            }
        }
        sum
    }

    lane_pass! {
        /// The inversion-bound scan of the 3D elements `first..first + n` (one chunk of
        /// [`NeoHookean::inversion_bound`]'s): per element in order, Err((e, J)) at the
        /// first one inverted at x, else its root below the bound so far (the chunk's,
        /// else `below`). The polynomials run [`LANES`] elements at a time, each lane
        /// [`step_det_polynomial`](super::neohookean::step_det_polynomial)'s operations in
        /// its order; the checks and the root
        /// searches ([`root_below`], cut short by the bound so far) one element after
        /// another, as per element.
        pub(super) fn inversion_scan3(
            &self,
            x: &[f64],
            dx: &[f64],
            max: f64,
            below: Option<f64>,
            first: usize,
            n: usize
        ) -> Result<Option<(f64, usize)>, (usize, f64)> => inversion_scan_lanes3
    }

    /// [`NeoHookean::inversion_scan3`], its polynomials [`LANES`] at a time.
    #[inline(always)]
    fn inversion_scan_lanes3(
        &self,
        x: &[f64],
        dx: &[f64],
        max: f64,
        below: Option<f64>,
        first: usize,
        n: usize,
    ) -> Result<Option<(f64, usize)>, (usize, f64)> {
        let mut best: Option<(f64, usize)> = None;
        for e0 in (first..first + n).step_by(LANES) {
            let count = LANES.min(first + n - e0);
            let c = self.step_det_polynomials3(x, dx, &lane_elements(e0, count));
            for l in 0..count {
                let e = e0 + l;
                let c = [c[0].0[l], c[1].0[l], c[2].0[l], c[3].0[l]];
                if c[0].is_nan() || c[0] <= 0.0 {
                    return Err((e, c[0] / (6.0 * self.volume[e])));
                }
                if let Some(r) = root_below(&c, max, best.map(|(r, _)| r).or(below)) {
                    best = Some((r, e));
                }
            }
        }
        Ok(best)
    }

    /// [`step_det_polynomial`](super::neohookean::step_det_polynomial) (3D) of the
    /// elements `e`, one per lane: Ds and ΔDs
    /// (column k − 1 node k minus node 0), then
    /// [`det_polynomial`](super::neohookean::det_polynomial)'s cofactors, sums and
    /// determinants.
    #[inline(always)]
    fn step_det_polynomials3(&self, x: &[f64], dx: &[f64], e: &[usize; LANES]) -> [Lanes; 4] {
        let zero = Lanes::splat(0.0);
        // Per node a and axis i, the position and the step, node a of each lane.
        let (mut p, mut q) = ([[zero; 3]; 4], [[zero; 3]; 4]);
        for (l, &el) in e.iter().enumerate() {
            for (a, &node) in self.nodes(el).iter().enumerate() {
                for i in 0..3 {
                    p[a][i].0[l] = x[node * 3 + i];
                    q[a][i].0[l] = dx[node * 3 + i];
                }
            }
        }
        let a = lanes::mat3(|i, k| p[k + 1][i] - p[0][i]);
        let b = lanes::mat3(|i, k| q[k + 1][i] - q[0][i]);
        let c1 = lanes::entry_dot(&lanes::cofactor3(&a), &b);
        let c2 = lanes::entry_dot(&lanes::cofactor3(&b), &a);
        [lanes::det3(&a), c1, c2, lanes::det3(&b)]
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

/// The elements of a lane group: `e0..e0 + count` (1 ≤ count ≤ [`LANES`]), a short group
/// repeating its last element in the spare lanes.
#[inline(always)]
pub(super) fn lane_elements(e0: usize, count: usize) -> [usize; LANES] {
    let mut e = [e0; LANES];
    for (l, el) in e.iter_mut().enumerate() {
        *el = e0 + l.min(count - 1);
    }
    e
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

    /// Per-element bits.
    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|f| f.to_bits()).collect()
    }

    /// A 3D mesh in positions of every kind a lane group meets: deformed at random
    /// (stretched, sheared, some elements inverted), and the same with half the nodes
    /// moved onto a line (flat elements, F of rank one) or onto a point (collapsed, F = 0)
    /// beside ordinary ones.
    fn lane_cases(law: Law, rng: &mut StdRng) -> Vec<(NeoHookean, Vec<f64>, &'static str)> {
        let mut cases = Vec::new();
        for _ in 0..6 {
            let (nh, x) = deformed(3, law, rng);
            cases.push((nh, x, "deformed"));
        }
        let (nh, x) = deformed(3, law, rng);
        let nodes = x.len() / 3;
        for (kept, name) in [(1, "flat"), (0, "collapsed")] {
            let mut y = x.clone();
            for node in 0..nodes / 2 {
                for i in kept..3 {
                    y[node * 3 + i] = 0.0;
                }
            }
            cases.push((nh.clone(), y, name));
        }
        cases
    }

    /// Runs of every length up to two lane groups and a remainder, from several starts,
    /// and the whole mesh: the lanes, the spare lanes of a short tail and the group
    /// boundaries.
    fn runs(len: usize) -> Vec<(usize, usize)> {
        let mut r: Vec<(usize, usize)> = (0..3)
            .flat_map(|first| (0..=(2 * LANES + 1).min(len - first)).map(move |n| (first, n)))
            .collect();
        r.push((0, len));
        r.push((5, len - 5));
        r
    }

    /// The lane-wise 3D gradients and energy sums against the per-element reference
    /// ([`NeoHookean::element_gradient`], and `.sum::<f64>()` of
    /// [`NeoHookean::element_energy`] in element order), both laws, on deformed, inverted,
    /// flat and collapsed elements: equal bit for bit (NaN gradients and +∞ energies of the
    /// classical law's inverted elements included).
    #[test]
    fn lane_gradients_and_energy_sums_equal_the_reference_bit_for_bit() {
        let mut rng = StdRng::seed_from_u64(47);
        let mut seen = [0usize; 3];
        for law in [Law::NeoHookean, Law::StableNeoHookean] {
            for (nh, x, name) in lane_cases(law, &mut rng) {
                for e in 0..nh.len() {
                    let j = nh.volume_ratio(&x, e);
                    seen[0] += (j < 0.0) as usize;
                    seen[1] += (j == 0.0) as usize;
                }
                let mut want = vec![0.0; nh.len() * 12];
                for (e, o) in want.chunks_exact_mut(12).enumerate() {
                    nh.element_gradient(&x, e, o);
                }
                seen[2] += want.iter().filter(|v| v.is_nan()).count();
                for (first, n) in runs(nh.len()) {
                    let at = &want[first * 12..(first + n) * 12];
                    let want: f64 = (first..first + n).map(|e| nh.element_energy(&x, e)).sum();
                    // The dispatched pass (AVX2 where the CPU has it) and the baseline one.
                    let mut got = vec![0.0; n * 12];
                    nh.element_gradients_run(&x, first, &mut got);
                    let mut baseline = vec![0.0; n * 12];
                    nh.gradients_lanes3(&x, first, &mut baseline);
                    for g in [&got, &baseline] {
                        assert_eq!(bits(g), bits(at), "{law:?} {name} gradients {first}+{n}");
                    }
                    let got = nh.element_energy_sum(&x, first, n);
                    let baseline = nh.energy_sum_lanes3(&x, first, n);
                    for g in [got, baseline] {
                        assert_eq!(
                            g.to_bits(),
                            want.to_bits(),
                            "{law:?} {name} energy {first}+{n}: {g} vs {want}"
                        );
                    }
                }
            }
        }
        // Inverted, degenerate (J = 0) and NaN-gradient elements were among them.
        assert!(seen.iter().all(|&k| k > 0), "{seen:?}");
    }

    /// One chunk of the inversion bound's scan per element, the reference: the step's
    /// determinant polynomial, the inverted-at-x check and the root search cut short by
    /// the bound so far, in element order.
    fn scan_reference(
        nh: &NeoHookean,
        (x, dx): (&[f64], &[f64]),
        max: f64,
        below: Option<f64>,
        (first, n): (usize, usize),
    ) -> Result<Option<(f64, usize)>, (usize, f64)> {
        let mut best: Option<(f64, usize)> = None;
        for e in first..first + n {
            let c = crate::sim::energy::neohookean::step_det_polynomial(3, nh.nodes(e), x, dx);
            if c[0].is_nan() || c[0] <= 0.0 {
                return Err((e, c[0] / (6.0 * nh.volume[e])));
            }
            if let Some(r) = root_below(&c, max, best.map(|(r, _)| r).or(below)) {
                best = Some((r, e));
            }
        }
        Ok(best)
    }

    /// The lane-wise inversion-bound scan against the per-element one: the same element
    /// and the same bits (root, or J of the first element inverted at x), with and
    /// without a bound from earlier sets, on unstrained meshes along random steps (roots
    /// of every size), and on deformed, flat and collapsed ones (inverted at x).
    #[test]
    fn lane_inversion_scan_equals_the_reference_bit_for_bit() {
        let mut rng = StdRng::seed_from_u64(59);
        let max = 1.0 / 0.9;
        let (mut roots, mut inverted, mut cut) = (0, 0, 0);
        for law in [Law::NeoHookean, Law::StableNeoHookean] {
            let mut cases = lane_cases(law, &mut rng);
            let mesh = crate::sim::mesh::cuboid([1.0, 0.4, 0.4], [4, 2, 2]);
            for _ in 0..6 {
                let nh = NeoHookean::new(&mesh, 1e5, 0.45, law).expect("valid mesh");
                let x = mesh.x.iter().map(|v| v + rng.random_range(-0.01..0.01));
                cases.push((nh, x.collect(), "unstrained"));
            }
            for (nh, x, name) in cases {
                let size = 10f64.powf(rng.random_range(-2.0..0.0));
                let dx: Vec<f64> = x
                    .iter()
                    .map(|_| size * rng.random_range(-1.0..1.0))
                    .collect();
                for (first, n) in runs(nh.len()) {
                    let key = |r: &Result<Option<(f64, usize)>, (usize, f64)>| match *r {
                        Ok(b) => Ok(b.map(|(r, e)| (r.to_bits(), e))),
                        Err((e, j)) => Err((e, j.to_bits())),
                    };
                    let unbounded = scan_reference(&nh, (&x, &dx), max, None, (first, n));
                    for below in [None, Some(rng.random_range(0.0..max))] {
                        let want = scan_reference(&nh, (&x, &dx), max, below, (first, n));
                        // The dispatched pass (AVX2 where the CPU has it) and the baseline.
                        let got = nh.inversion_scan3(&x, &dx, max, below, first, n);
                        let baseline = nh.inversion_scan_lanes3(&x, &dx, max, below, first, n);
                        for g in [&got, &baseline] {
                            assert_eq!(key(g), key(&want), "{law:?} {name} {first}+{n}");
                        }
                        roots += matches!(want, Ok(Some(_))) as usize;
                        inverted += want.is_err() as usize;
                        // A root the bound from earlier sets hides.
                        cut += (matches!(unbounded, Ok(Some(_))) && want == Ok(None)) as usize;
                    }
                }
            }
        }
        assert!(
            roots > 0 && inverted > 0 && cut > 0,
            "{roots} {inverted} {cut}"
        );
    }
}
