//! The 3D projected element Hessian of [`LANES`] elements side by side: every quantity is
//! a [`Lanes`], one value per element, so that each step maps to SIMD registers. Each
//! lane runs the same operations, in the same order, as the per-element functions of
//! [`super::eigensystem`] (`signed_svd3_from_eigen` and
//! [`projected_element_blocks`](super::eigensystem::projected_element_blocks); the two
//! eigenproblems run in [`symmetric_eigen3_lanes`](super::eigensystem::symmetric_eigen3_lanes)); where
//! those branch, the lanes compute both sides and select (an exact choice), so each
//! lane's result equals the per-element one bit for bit. Rust never fuses a multiply and
//! an add, so this holds whatever vector width the code is compiled for. The 3D
//! gradients, energies and step polynomials of [`super::kernels`] use the same types
//! (with [`cofactor3`], [`det3`] and [`entry_dot`]).
//!
//! Arrays of lanes are built and converted with written-out loops or [`vec3`]/[`mat3`],
//! not `array::map`/`array::from_fn`: whether the optimiser inlines those depends on the
//! rest of the code generation unit, and out of line they keep a lane group in memory.

// Lane loops index several arrays by the same lane: the form that vectorises.
#![allow(clippy::needless_range_loop)]

use super::eigensystem::{LANES, PAIRS};
use std::ops::{Add, Div, Mul, Neg, Not, Sub};

/// One f64 per lane.
#[derive(Debug, Clone, Copy)]
#[repr(transparent)]
pub struct Lanes(pub [f64; LANES]);

/// One condition per lane.
#[derive(Debug, Clone, Copy)]
pub struct Mask([bool; LANES]);

/// A 3-vector of lanes.
pub type Vec3 = [Lanes; 3];

/// A 3×3 matrix of lanes, `m[row][column]`.
pub type Mat3 = [[Lanes; 3]; 3];

macro_rules! lanewise {
    ($trait:ident, $f:ident, $op:tt) => {
        impl $trait for Lanes {
            type Output = Lanes;
            #[inline(always)]
            fn $f(self, o: Lanes) -> Lanes {
                let mut r = [0.0; LANES];
                for l in 0..LANES {
                    r[l] = self.0[l] $op o.0[l];
                }
                Lanes(r)
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

impl Neg for Lanes {
    type Output = Lanes;
    #[inline(always)]
    fn neg(self) -> Lanes {
        self.map(|x| -x)
    }
}

impl Lanes {
    #[inline(always)]
    pub fn splat(x: f64) -> Lanes {
        Lanes([x; LANES])
    }

    #[inline(always)]
    pub fn map(self, f: impl Fn(f64) -> f64) -> Lanes {
        let mut r = [0.0; LANES];
        for l in 0..LANES {
            r[l] = f(self.0[l]);
        }
        Lanes(r)
    }

    #[inline(always)]
    fn test(self, o: Lanes, f: impl Fn(f64, f64) -> bool) -> Mask {
        let mut r = [false; LANES];
        for l in 0..LANES {
            r[l] = f(self.0[l], o.0[l]);
        }
        Mask(r)
    }

    #[inline(always)]
    pub fn lt(self, o: Lanes) -> Mask {
        self.test(o, |a, b| a < b)
    }

    #[inline(always)]
    pub fn gt(self, o: Lanes) -> Mask {
        self.test(o, |a, b| a > b)
    }

    #[inline(always)]
    pub fn sqrt(self) -> Lanes {
        self.map(f64::sqrt)
    }

    #[inline(always)]
    pub fn abs(self) -> Lanes {
        self.map(f64::abs)
    }

    /// `f64::max(x, 0.0)` per lane (NaN gives 0).
    #[inline(always)]
    pub fn max0(self) -> Lanes {
        self.map(|x| x.max(0.0))
    }

    /// `a` where `m`, else `b`.
    #[inline(always)]
    pub fn select(m: Mask, a: Lanes, b: Lanes) -> Lanes {
        let mut r = [0.0; LANES];
        for l in 0..LANES {
            r[l] = if m.0[l] { a.0[l] } else { b.0[l] };
        }
        Lanes(r)
    }
}

impl Not for Mask {
    type Output = Mask;
    #[inline(always)]
    fn not(self) -> Mask {
        self.zip(self, |a, _| !a)
    }
}

impl Mask {
    #[inline(always)]
    fn zip(self, o: Mask, f: impl Fn(bool, bool) -> bool) -> Mask {
        let mut r = [false; LANES];
        for l in 0..LANES {
            r[l] = f(self.0[l], o.0[l]);
        }
        Mask(r)
    }

    #[inline(always)]
    pub fn and(self, o: Mask) -> Mask {
        self.zip(o, |a, b| a && b)
    }

    #[inline(always)]
    pub fn and_not(self, o: Mask) -> Mask {
        self.zip(o, |a, b| a && !b)
    }

    #[inline(always)]
    pub fn all(self) -> bool {
        self.0.iter().all(|&x| x)
    }

    /// 1 where set, else 0.
    #[inline(always)]
    fn indicator(self) -> Lanes {
        Lanes::select(self, Lanes::splat(1.0), Lanes::splat(0.0))
    }
}

/// [f(0), f(1), f(2)], written out (no out-of-line array builder, no copies).
#[inline(always)]
pub fn vec3(f: impl Fn(usize) -> Lanes) -> Vec3 {
    [f(0), f(1), f(2)]
}

/// The matrix of entries f(row, column).
#[inline(always)]
pub fn mat3(f: impl Fn(usize, usize) -> Lanes) -> Mat3 {
    [vec3(|c| f(0, c)), vec3(|c| f(1, c)), vec3(|c| f(2, c))]
}

#[inline(always)]
fn select3(m: Mask, a: Vec3, b: Vec3) -> Vec3 {
    vec3(|r| Lanes::select(m, a[r], b[r]))
}

#[inline(always)]
fn splat3(x: [f64; 3]) -> Vec3 {
    vec3(|r| Lanes::splat(x[r]))
}

#[inline(always)]
fn dot(x: &Vec3, y: &Vec3) -> Lanes {
    x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
}

#[inline(always)]
fn cross(x: &Vec3, y: &Vec3) -> Vec3 {
    [
        x[1] * y[2] - x[2] * y[1],
        x[2] * y[0] - x[0] * y[2],
        x[0] * y[1] - x[1] * y[0],
    ]
}

/// x/‖x‖, and where that is a unit vector (‖x‖ normal and finite).
#[inline(always)]
fn normalized(x: Vec3) -> (Vec3, Mask) {
    let n = dot(&x, &x).sqrt();
    let ok = n
        .gt(Lanes::splat(f64::MIN_POSITIVE))
        .and(n.lt(Lanes::splat(f64::INFINITY)));
    ([x[0] / n, x[1] / n, x[2] / n], ok)
}

/// A unit vector orthogonal to the unit vector x: x × (the axis least along x, the first
/// of equals), or e₃ where that vanishes.
#[inline(always)]
fn orthogonal(x: &Vec3) -> Vec3 {
    let ax = vec3(|r| x[r].abs());
    let k1 = ax[1].lt(ax[0]);
    let k2 = ax[2].lt(Lanes::select(k1, ax[1], ax[0]));
    let e = [
        (!k2).and_not(k1).indicator(),
        k1.and_not(k2).indicator(),
        k2.indicator(),
    ];
    let (n, ok) = normalized(cross(x, &e));
    select3(ok, n, splat3([0.0, 0.0, 1.0]))
}

/// The cofactor matrix ∂(det m)/∂m, as `neohookean::cofactor` (3D): entry (i, j) is the
/// 2×2 minor of the rows and columns after i and j, cyclically.
#[inline(always)]
pub fn cofactor3(m: &Mat3) -> Mat3 {
    mat3(|i, j| {
        let (i1, i2) = ((i + 1) % 3, (i + 2) % 3);
        let (j1, j2) = ((j + 1) % 3, (j + 2) % 3);
        m[i1][j1] * m[i2][j2] - m[i1][j2] * m[i2][j1]
    })
}

/// Σ_k x_k y_k over the nine entries in row-major order, added one after another from the
/// start of `Iterator::sum`: a per-element `.map(|k| x[k] * y[k]).sum::<f64>()`, bit for bit.
#[inline(always)]
pub fn entry_dot(x: &Mat3, y: &Mat3) -> Lanes {
    let mut s = sum_start();
    for r in 0..3 {
        for c in 0..3 {
            s = s + x[r][c] * y[r][c];
        }
    }
    s
}

/// The value `Iterator::sum` of f64 starts from (its neutral element), in every lane:
/// starting a lane sum there keeps the bits of a per-element `.sum::<f64>()` also where
/// all its terms are zeros of one sign.
#[inline(always)]
pub fn sum_start() -> Lanes {
    Lanes::splat(sum_start_f64())
}

/// [`sum_start`] of one value.
#[inline(always)]
pub fn sum_start_f64() -> f64 {
    std::iter::empty::<f64>().sum()
}

/// FᵀF.
#[inline(always)]
pub fn gram3(f: &Mat3) -> Mat3 {
    mat3(|r, c| f[0][r] * f[0][c] + f[1][r] * f[1][c] + f[2][r] * f[2][c])
}

/// The keys of `f64::total_cmp`: integers in the same order.
#[inline(always)]
fn total_order_keys(x: Lanes) -> [i64; LANES] {
    let mut k = [0i64; LANES];
    for l in 0..LANES {
        let b = x.0[l].to_bits() as i64;
        k[l] = b ^ (((b >> 63) as u64) >> 1) as i64;
    }
    k
}

/// The eigenvectors (columns of `ev`) sorted by decreasing eigenvalue `lam`, equal ones
/// in their order (the stable sort by `total_cmp`): three adjacent exchanges, each only
/// where the later one is strictly greater.
#[inline(always)]
fn sorted_columns(lam: &Vec3, ev: &Mat3) -> Mat3 {
    let mut key = [
        total_order_keys(lam[0]),
        total_order_keys(lam[1]),
        total_order_keys(lam[2]),
    ];
    let mut col: [Vec3; 3] = mat3(|k, r| ev[r][k]);
    for (i, j) in [(0, 1), (1, 2), (0, 1)] {
        let mut swap = [false; LANES];
        for l in 0..LANES {
            swap[l] = key[j][l] > key[i][l];
            let (ki, kj) = (key[i][l], key[j][l]);
            key[i][l] = if swap[l] { kj } else { ki };
            key[j][l] = if swap[l] { ki } else { kj };
        }
        let (ci, cj) = (col[i], col[j]);
        col[i] = select3(Mask(swap), cj, ci);
        col[j] = select3(Mask(swap), ci, cj);
    }
    mat3(|r, k| col[k][r])
}

/// det m, as `neohookean::det` (3D).
#[inline(always)]
pub fn det3(m: &Mat3) -> Lanes {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// `eigensystem::signed_svd3_from_eigen` per lane: (U, σ, V) of F from the eigenpairs
/// (λ, E) of FᵀF.
#[inline(always)]
pub fn signed_svd3(f: &Mat3, lam: &Vec3, ev: &Mat3) -> (Mat3, Vec3, Mat3) {
    let mut v = sorted_columns(lam, ev);
    let reflect = det3(&v).lt(Lanes::splat(0.0));
    for row in v.iter_mut() {
        row[2] = Lanes::select(reflect, -row[2], row[2]);
    }
    // Columns of B = F V.
    let b: [Vec3; 3] = mat3(|k, r| f[r][0] * v[0][k] + f[r][1] * v[1][k] + f[r][2] * v[2][k]);
    let (n1, ok1) = normalized(b[0]);
    let u1 = select3(ok1, n1, splat3([1.0, 0.0, 0.0]));
    let mut w = b[1];
    for _ in 0..2 {
        let p = dot(&u1, &w);
        for a in 0..3 {
            w[a] = w[a] - p * u1[a];
        }
    }
    let (n2, ok2) = normalized(w);
    // The fallback only where some lane needs it (flat or collapsed elements).
    let u2 = if ok2.all() {
        n2
    } else {
        select3(ok2, n2, orthogonal(&u1))
    };
    let u3 = cross(&u1, &u2);
    let sigma = [dot(&u1, &b[0]), dot(&u2, &b[1]), dot(&u3, &b[2])];
    let u = mat3(|r, k| [u1, u2, u3][k][r]);
    (u, sigma, v)
}

/// [`SingularValueHessian`](super::eigensystem::SingularValueHessian) of each lane.
#[derive(Debug, Clone, Copy)]
pub struct SingularValueHessianLanes {
    pub a: Mat3,
    pub twist: Vec3,
    pub flip: Vec3,
}

/// The modes of the element Hessians, `w[i][k]` (entry i of mode k) and
/// `lw[i][k] = max(λ_k, 0)·scale·w[i][k]`, per lane, as the per-element `modes` of
/// [`super::eigensystem`], and the upper triangle of the element Hessians they sum to.
/// About 34 KiB: made once and refilled group after group (no copies of it move).
pub struct Modes {
    w: [[Lanes; 9]; 12],
    lw: [[Lanes; 9]; 12],
    upper: [[Lanes; 12]; 12],
}

impl Default for Modes {
    fn default() -> Modes {
        let zero = Lanes::splat(0.0);
        Modes {
            w: [[zero; 9]; 12],
            lw: [[zero; 9]; 12],
            upper: [[zero; 12]; 12],
        }
    }
}

impl Modes {
    /// The modes of the eigensystem (U, V, `h`, with the eigenpairs `vals`, `vecs` of
    /// `h.a`) of elements with shape gradients `g[a][j]` and rest volumes `scale`.
    #[inline(always)]
    pub fn fill(
        &mut self,
        (u, v): (&Mat3, &Mat3),
        h: &SingularValueHessianLanes,
        (vals, vecs): (&Vec3, &Mat3),
        g: &[Vec3; 4],
        scale: Lanes,
    ) {
        // gv[a][q] = Σ_j G[a][j] V[j][q].
        let mut gv = [[Lanes::splat(0.0); 3]; 4];
        for (a, row) in gv.iter_mut().enumerate() {
            for (q, e) in row.iter_mut().enumerate() {
                *e = g[a][0] * v[0][q] + g[a][1] * v[1][q] + g[a][2] * v[2][q];
            }
        }
        let w = &mut self.w;
        let mut lam = [Lanes::splat(0.0); 9];
        // Scaling modes: w[(a, c)] = Σ_p U_cp vecs[p][k] gv[a][p].
        for k in 0..3 {
            lam[k] = vals[k].max0() * scale;
            for a in 0..4 {
                for c in 0..3 {
                    w[a * 3 + c][k] = u[c][0] * vecs[0][k] * gv[a][0]
                        + u[c][1] * vecs[1][k] * gv[a][1]
                        + u[c][2] * vecs[2][k] * gv[a][2];
                }
            }
        }
        // Twist and flip modes of the pair (i, j).
        let r = Lanes::splat(std::f64::consts::FRAC_1_SQRT_2);
        for (p, &(i, j)) in PAIRS.iter().enumerate() {
            let (kt, kf) = (3 + 2 * p, 4 + 2 * p);
            lam[kt] = h.twist[p].max0() * scale;
            lam[kf] = h.flip[p].max0() * scale;
            for a in 0..4 {
                for c in 0..3 {
                    let x = u[c][i] * gv[a][j];
                    let y = u[c][j] * gv[a][i];
                    w[a * 3 + c][kt] = r * (x - y);
                    w[a * 3 + c][kf] = r * (x + y);
                }
            }
        }
        for (lrow, wrow) in self.lw.iter_mut().zip(w.iter()) {
            for k in 0..9 {
                lrow[k] = lam[k] * wrow[k];
            }
        }
    }

    /// The element Hessians' upper node blocks (a ≤ b, each 3×3 row-major, 90 values an
    /// element) into `out`, element after element, for the first `out.len() / 90` lanes.
    #[inline(always)]
    pub fn store_upper_blocks(&mut self, out: &mut [f64]) {
        for i in 0..12 {
            // The rest of the diagonal block's row, then the blocks right of it.
            match i % 3 {
                0 => self.row_sums::<3>(i, i),
                1 => self.row_sums::<2>(i, i),
                _ => self.row_sums::<1>(i, i),
            }
            for j0 in (3 * (i / 3 + 1)..12).step_by(3) {
                self.row_sums::<3>(i, j0);
            }
        }
        for (l, blocks) in out.chunks_exact_mut(BLOCK_VALUES).enumerate() {
            for (o, &(i, j)) in blocks.iter_mut().zip(BLOCK_SOURCES.iter()) {
                *o = self.upper[i as usize][j as usize].0[l];
            }
        }
    }

    /// Entries (i, j0..j0 + N), j0 ≥ i, of the upper triangle: Σ_k lw[i][k] w[j][k] in k
    /// order from zero, as per element; the N sums side by side, so that their additions
    /// overlap instead of waiting on each other.
    #[inline(always)]
    fn row_sums<const N: usize>(&mut self, i: usize, j0: usize) {
        let mut s = [Lanes::splat(0.0); N];
        for k in 0..9 {
            let l = self.lw[i][k];
            for (n, e) in s.iter_mut().enumerate() {
                *e = *e + l * self.w[j0 + n][k];
            }
        }
        self.upper[i][j0..j0 + N].copy_from_slice(&s);
    }
}

/// Values of one 3D element's upper node blocks.
pub const BLOCK_VALUES: usize = 90;

/// Per value of the upper node blocks (in `upper_pairs` order, each row-major), the entry
/// (i, j ≥ i) of the element Hessian's upper triangle it equals (a diagonal block's lower
/// entries mirror its upper ones).
const BLOCK_SOURCES: [(u8, u8); BLOCK_VALUES] = block_sources();

const fn block_sources() -> [(u8, u8); BLOCK_VALUES] {
    let mut t = [(0u8, 0u8); BLOCK_VALUES];
    let mut m = 0;
    let mut a = 0;
    while a < 4 {
        let mut b = a;
        while b < 4 {
            let mut r = 0;
            while r < 3 {
                let mut c = 0;
                while c < 3 {
                    let (i, j) = (a * 3 + r, b * 3 + c);
                    t[m] = if i <= j {
                        (i as u8, j as u8)
                    } else {
                        (j as u8, i as u8)
                    };
                    m += 1;
                    c += 1;
                }
                r += 1;
            }
            b += 1;
        }
        a += 1;
    }
    t
}
