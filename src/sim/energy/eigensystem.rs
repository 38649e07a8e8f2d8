//! The analytic eigensystem of ∂²Ψ/∂F² for an isotropic energy Ψ(F) = ψ(σ(F)) (Smith,
//! de Goes and Kim 2019, "Analytic Eigensystems for Isotropic Distortion Energies"), and
//! the PSD projection built from it.
//!
//! With the rotation-variant SVD F = U diag(σ) Vᵀ (U, V rotations; the smallest σ carries
//! the sign of det F), the d² eigenmatrices of ∂²Ψ/∂F² are U M Vᵀ with
//! - for each pair i < j, the twist M = (e_i e_jᵀ − e_j e_iᵀ)/√2 with eigenvalue
//!   (ψ_i + ψ_j)/(σ_i + σ_j), and the flip M = (e_i e_jᵀ + e_j e_iᵀ)/√2 with eigenvalue
//!   (ψ_i − ψ_j)/(σ_i − σ_j) (ψ_i = ∂ψ/∂σ_i); an energy supplies both in closed form;
//! - d scaling modes M = diag(w) with (λ, w) the eigenpairs of the d×d block
//!   A_ij = ∂²ψ/∂σ_i∂σ_j.
//!
//! The projection keeps the positive eigenvalues: Σ max(λ, 0) vec(Q) vec(Q)ᵀ. It projects
//! ∂²Ψ/∂F², so an element Hessian built from it, (∂F/∂x)ᵀ proj(∂²Ψ/∂F²) (∂F/∂x), is PSD
//! but is not the projection of the element Hessian itself (that would need the
//! eigendecomposition of the 12×12 matrix; this needs an SVD of F and a d×d eigenproblem).

use nalgebra::{Matrix2, SymmetricEigen};

/// ∂²ψ/∂σ² and the pair eigenvalues of an isotropic energy at σ. Pairs are ordered
/// (0, 1), (0, 2), (1, 2); 2D uses the first only.
#[derive(Debug, Clone, Copy, Default)]
pub struct SingularValueHessian {
    /// A_ij = ∂²ψ/∂σ_i∂σ_j (the leading d×d block is used).
    pub a: [[f64; 3]; 3],
    /// (ψ_i + ψ_j)/(σ_i + σ_j) per pair.
    pub twist: [f64; 3],
    /// (ψ_i − ψ_j)/(σ_i − σ_j) per pair.
    pub flip: [f64; 3],
}

/// The pair (i, j) of each slot of [`SingularValueHessian::twist`] / `flip`.
pub const PAIRS: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];

/// F = U diag(σ) Vᵀ with U and V rotations (row-major d×d in the leading entries) and σ
/// signed: when det F < 0 the smallest singular value is negative.
pub fn signed_svd(d: usize, f: &[f64]) -> ([f64; 9], [f64; 3], [f64; 9]) {
    if d == 3 {
        return signed_svd3(&f[..9]);
    }
    let mut u = [0.0; 9];
    let mut v = [0.0; 9];
    let mut s = [0.0; 3];
    let m = Matrix2::new(f[0], f[1], f[2], f[3]);
    let svd = m.svd(true, true);
    let (mut uu, vt) = (svd.u.unwrap_or_default(), svd.v_t.unwrap_or_default());
    let mut vv = vt.transpose();
    let mut sv = [svd.singular_values[0], svd.singular_values[1]];
    let last = if sv[0].abs() < sv[1].abs() { 0 } else { 1 };
    let (du, dv) = (uu.determinant(), vv.determinant());
    fix_sign(&mut uu, &mut vv, &mut sv, last, du, dv);
    for r in 0..2 {
        for c in 0..2 {
            u[r * 2 + c] = uu[(r, c)];
            v[r * 2 + c] = vv[(r, c)];
        }
    }
    s[..2].copy_from_slice(&sv);
    (u, s, v)
}

/// Turns reflections in U or V (determinants `det_u`, `det_v`) into a negative singular
/// value at `last`.
fn fix_sign<const D: usize>(
    u: &mut nalgebra::SMatrix<f64, D, D>,
    v: &mut nalgebra::SMatrix<f64, D, D>,
    s: &mut [f64; D],
    last: usize,
    det_u: f64,
    det_v: f64,
) {
    if det_u < 0.0 {
        u.column_mut(last).neg_mut();
        s[last] = -s[last];
    }
    if det_v < 0.0 {
        v.column_mut(last).neg_mut();
        s[last] = -s[last];
    }
}

/// out (d²×d², row-major over row-major vec(F)) = Σ_k clamp(λ_k) vec(U M_k Vᵀ) vec(U M_k Vᵀ)ᵀ
/// over the eigensystem of `h`, with clamp = max(·, 0) when `project`, the identity
/// otherwise (which reassembles ∂²Ψ/∂F² itself: the tests check the eigensystem so).
pub fn assemble(
    d: usize,
    u: &[f64; 9],
    v: &[f64; 9],
    h: &SingularValueHessian,
    project: bool,
    out: &mut [f64],
) {
    let dd = d * d;
    out[..dd * dd].iter_mut().for_each(|x| *x = 0.0);
    let clamp = |l: f64| if project { l.max(0.0) } else { l };
    // vec(U M Vᵀ)_{(r,c)} = Σ_ab U_ra M_ab V_cb.
    let mut add = |l: f64, m: &[[f64; 3]; 3]| {
        if l == 0.0 {
            return;
        }
        let mut q = [0.0; 9];
        for r in 0..d {
            for c in 0..d {
                let mut s = 0.0;
                for a in 0..d {
                    for b in 0..d {
                        s += u[r * d + a] * m[a][b] * v[c * d + b];
                    }
                }
                q[r * d + c] = s;
            }
        }
        for i in 0..dd {
            for j in 0..dd {
                out[i * dd + j] += l * q[i] * q[j];
            }
        }
    };
    // Scaling modes.
    let (vals, vecs) = scaling_eigen(d, &h.a);
    for k in 0..d {
        let mut m = [[0.0; 3]; 3];
        for a in 0..d {
            m[a][a] = vecs[a][k];
        }
        add(clamp(vals[k]), &m);
    }
    // Twist and flip modes.
    let r = std::f64::consts::FRAC_1_SQRT_2;
    let pairs = if d == 2 { 1 } else { 3 };
    for (p, &(i, j)) in PAIRS.iter().enumerate().take(pairs) {
        let mut twist = [[0.0; 3]; 3];
        twist[i][j] = r;
        twist[j][i] = -r;
        add(clamp(h.twist[p]), &twist);
        let mut flip = [[0.0; 3]; 3];
        flip[i][j] = r;
        flip[j][i] = r;
        add(clamp(h.flip[p]), &flip);
    }
}

/// Eigenvalues and eigenvectors (columns: `vecs[a][k]` is component a of vector k) of the
/// symmetric d×d block.
pub fn scaling_eigen(d: usize, a: &[[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    if d == 3 {
        return symmetric_eigen3(a);
    }
    let mut vals = [0.0; 3];
    let mut vecs = [[0.0; 3]; 3];
    let e = SymmetricEigen::new(Matrix2::new(a[0][0], a[0][1], a[1][0], a[1][1]));
    for k in 0..2 {
        vals[k] = e.eigenvalues[k];
        for (r, row) in vecs.iter_mut().enumerate().take(2) {
            row[k] = e.eigenvectors[(r, k)];
        }
    }
    (vals, vecs)
}

/// The element Hessian (∂F/∂x)ᵀ proj(∂²Ψ/∂F²) (∂F/∂x) · `scale`, ((d+1)d)² row-major,
/// straight from the eigensystem: proj(∂²Ψ/∂F²) = Σ_k max(λ_k, 0) q_k q_kᵀ with
/// q_k = vec(U M_k Vᵀ), so the element Hessian is Σ_k max(λ_k, 0) w_k w_kᵀ with
/// w_k = (∂F/∂x)ᵀ q_k, w_k[(a, c)] = Σ_pq U_cp (M_k)_pq (G V)_aq. `g` holds the shape
/// gradients `G[a][j]` ((d+1)·d, row-major). About a tenth of the arithmetic of forming the
/// d²×d² projection and contracting it with G twice; only the upper triangle is summed and
/// mirrored, so the result is exactly symmetric.
pub fn projected_element_hessian(
    d: usize,
    u: &[f64; 9],
    v: &[f64; 9],
    h: &SingularValueHessian,
    g: &[f64],
    scale: f64,
    out: &mut [f64],
) {
    if d == 3 {
        modes_into::<12, 9>(3, u, v, h, g, scale, out);
    } else {
        modes_into::<6, 4>(2, u, v, h, g, scale, out);
    }
}

/// [`projected_element_hessian`] with the element size NL = (d+1)d and the mode count
/// NM = d² fixed, so that the Σ_k over modes is an unrolled fixed-length dot product.
fn modes_into<const NL: usize, const NM: usize>(
    d: usize,
    u: &[f64; 9],
    v: &[f64; 9],
    h: &SingularValueHessian,
    g: &[f64],
    scale: f64,
    out: &mut [f64],
) {
    let (vals, vecs) = scaling_eigen(d, &h.a);
    let (lw, w) = modes::<NL, NM>(d, u, v, h, (&vals, &vecs), g, scale);
    let out = &mut out[..NL * NL];
    for i in 0..NL {
        for j in i..NL {
            let s = mode_dot(&lw[i], &w[j]);
            out[i * NL + j] = s;
            out[j * NL + i] = s;
        }
    }
}

/// Σ_k lw_k w_k in k order: one entry of the element Hessian.
#[inline(always)]
fn mode_dot<const NM: usize>(lw: &[f64; NM], w: &[f64; NM]) -> f64 {
    let mut s = 0.0;
    for k in 0..NM {
        s += lw[k] * w[k];
    }
    s
}

/// The element Hessian of [`projected_element_hessian`] written as its upper node blocks
/// (a ≤ b, in `upper_pairs` order, each D×D row-major; the element's slots of the
/// assembly's buffer), with D fixed. Each entry is the same sum, in the same order, as
/// the full matrix's (a diagonal block's lower entries are its upper ones mirrored), so
/// the blocks equal those of [`projected_element_hessian`] bit for bit.
/// `scaling` holds the eigenpairs of the d×d block `h.a` (as `scaling_eigen` returns them).
#[inline(always)]
pub fn projected_element_blocks<const D: usize, const NL: usize, const NM: usize>(
    u: &[f64; 9],
    v: &[f64; 9],
    h: &SingularValueHessian,
    scaling: (&[f64; 3], &[[f64; 3]; 3]),
    g: &[f64],
    scale: f64,
    out: &mut [f64],
) {
    let (lw, w) = modes::<NL, NM>(D, u, v, h, scaling, g, scale);
    // Every sum Σ_k lw[i][k] w[j][k] in k order, a whole row j = 0..NL at a time (the
    // row's sums side by side: SIMD across j, each one still added in k order).
    let mut wt = [[0.0f64; NL]; NM];
    for (j, row) in w.iter().enumerate() {
        for k in 0..NM {
            wt[k][j] = row[k];
        }
    }
    let mut full = [[0.0f64; NL]; NL];
    for (i, acc) in full.iter_mut().enumerate() {
        for k in 0..NM {
            let l = lw[i][k];
            for j in 0..NL {
                acc[j] += l * wt[k][j];
            }
        }
    }
    let mut slot = 0;
    for a in 0..=D {
        for b in a..=D {
            let blk = &mut out[slot * D * D..(slot + 1) * D * D];
            for r in 0..D {
                let i = a * D + r;
                for c in 0..D {
                    let j = b * D + c;
                    // The reference sums the upper triangle and mirrors it.
                    blk[r * D + c] = if i <= j { full[i][j] } else { full[j][i] };
                }
            }
            slot += 1;
        }
    }
}

/// The modes of the element Hessian Σ_k max(λ_k, 0)·scale·w_k w_kᵀ: w[i][k], entry i of
/// w_k, and lw[i][k] = max(λ_k, 0)·scale·w[i][k]. A clamped mode has zero weight (it adds
/// exact zeros).
#[inline(always)]
#[allow(clippy::type_complexity)]
fn modes<const NL: usize, const NM: usize>(
    d: usize,
    u: &[f64; 9],
    v: &[f64; 9],
    h: &SingularValueHessian,
    (vals, vecs): (&[f64; 3], &[[f64; 3]; 3]),
    g: &[f64],
    scale: f64,
) -> ([[f64; NM]; NL], [[f64; NM]; NL]) {
    let nn = d + 1;
    // gv[a][q] = Σ_j G[a][j] V[j][q].
    let mut gv = [[0.0f64; 3]; 4];
    for (a, row) in gv.iter_mut().enumerate().take(nn) {
        for (q, e) in row.iter_mut().enumerate().take(d) {
            *e = (0..d).map(|j| g[a * d + j] * v[j * d + q]).sum();
        }
    }
    let mut w = [[0.0f64; NM]; NL];
    let mut lw = [[0.0f64; NM]; NL];
    let mut lam = [0.0f64; NM];
    // Scaling modes: M = diag(e_k), w[(a, c)] = Σ_p U_cp e_k[p] gv[a][p].
    for k in 0..d {
        lam[k] = vals[k].max(0.0) * scale;
        for a in 0..nn {
            for c in 0..d {
                w[a * d + c][k] = (0..d).map(|p| u[c * d + p] * vecs[p][k] * gv[a][p]).sum();
            }
        }
    }
    // Twist and flip modes of the pair (i, j): M = (e_i e_jᵀ ∓ e_j e_iᵀ)/√2.
    let r = std::f64::consts::FRAC_1_SQRT_2;
    let pairs = if d == 2 { 1 } else { 3 };
    for (p, &(i, j)) in PAIRS.iter().enumerate().take(pairs) {
        let (kt, kf) = (d + 2 * p, d + 2 * p + 1);
        lam[kt] = h.twist[p].max(0.0) * scale;
        lam[kf] = h.flip[p].max(0.0) * scale;
        for a in 0..nn {
            for c in 0..d {
                let x = u[c * d + i] * gv[a][j];
                let y = u[c * d + j] * gv[a][i];
                w[a * d + c][kt] = r * (x - y);
                w[a * d + c][kf] = r * (x + y);
            }
        }
    }
    for (lrow, wrow) in lw.iter_mut().zip(&w) {
        for k in 0..NM {
            lrow[k] = lam[k] * wrow[k];
        }
    }
    (lw, w)
}

/// Eigenpairs of a symmetric 3×3 matrix by cyclic Jacobi rotations (Golub and Van Loan,
/// Algorithm 8.5.2): (λ, V) with A = V diag(λ) Vᵀ, `vecs[r][k]` component r of vector k.
/// Jacobi converges quadratically and is accurate to rounding; sweeps stop once the
/// off-diagonal part is below rounding of ‖A‖. An order of magnitude cheaper than the
/// general tridiagonal QR for this size, and it is called once or twice per element and
/// Newton iteration.
pub fn symmetric_eigen3(m: &[[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    // Exact symmetry: the upper triangle mirrored.
    let mut a: [[f64; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| if c >= r { m[r][c] } else { m[c][r] }));
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let norm2: f64 = a.iter().flatten().map(|x| x * x).sum();
    let tiny = 0.25 * f64::EPSILON * f64::EPSILON * norm2;
    for _sweep in 0..32 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        if off.is_nan() || off <= tiny {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            let apq = a[p][q];
            if apq == 0.0 {
                continue;
            }
            let tau = (a[q][q] - a[p][p]) / (2.0 * apq);
            // t = tan θ, the smaller root of t² + 2τt − 1 = 0 (|θ| ≤ π/4).
            let t = if tau.abs() > 1e150 {
                0.5 / tau
            } else if tau >= 0.0 {
                1.0 / (tau + (1.0 + tau * tau).sqrt())
            } else {
                -1.0 / (-tau + (1.0 + tau * tau).sqrt())
            };
            let c = 1.0 / (1.0 + t * t).sqrt();
            let s = t * c;
            let r = 3 - p - q;
            a[p][p] -= t * apq;
            a[q][q] += t * apq;
            a[p][q] = 0.0;
            a[q][p] = 0.0;
            let (arp, arq) = (a[r][p], a[r][q]);
            a[r][p] = c * arp - s * arq;
            a[r][q] = s * arp + c * arq;
            a[p][r] = a[r][p];
            a[q][r] = a[r][q];
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// Lanes of [`symmetric_eigen3_lanes`]: elements whose eigenproblems run side by side.
/// Twelve: three AVX2 registers of four, so that three independent chains of divisions
/// and square roots (the rotations are latency-bound) overlap; more lanes spill registers.
pub const LANES: usize = 12;

/// [`symmetric_eigen3`] of [`LANES`] matrices at once, laid out lane-innermost
/// (`m[r][c][lane]`), so that the rotations of independent matrices overlap (and map to
/// SIMD lanes). Every lane runs the same operations in the same order as
/// [`symmetric_eigen3`] on its own matrix; where that one skips a rotation or stops
/// sweeping, the lane keeps its values (an exact select), so each lane's result equals
/// [`symmetric_eigen3`]'s bit for bit.
#[inline(always)]
#[allow(clippy::type_complexity)]
pub fn symmetric_eigen3_lanes(
    m: &[[[f64; LANES]; 3]; 3],
) -> ([[f64; LANES]; 3], [[[f64; LANES]; 3]; 3]) {
    const L: usize = LANES;
    // The upper triangle, mirrored.
    let mut a = *m;
    for r in 1..3 {
        for c in 0..r {
            a[r][c] = m[c][r];
        }
    }
    let mut v = [[[0.0; L]; 3]; 3];
    for (k, row) in v.iter_mut().enumerate() {
        row[k] = [1.0; L];
    }
    let tiny: [f64; L] = lanewise(|l| {
        let norm2: f64 = a.iter().flatten().map(|x| x[l] * x[l]).sum();
        0.25 * f64::EPSILON * f64::EPSILON * norm2
    });
    let mut active = [true; L];
    for _sweep in 0..32 {
        for l in 0..L {
            let off = a[0][1][l] * a[0][1][l] + a[0][2][l] * a[0][2][l] + a[1][2][l] * a[1][2][l];
            if off.is_nan() || off <= tiny[l] {
                active[l] = false;
            }
        }
        if !active.iter().any(|&x| x) {
            break;
        }
        // The pivots unrolled (constant indices keep the lanes in registers).
        rotate_lanes::<0, 1>(&mut a, &mut v, &active);
        rotate_lanes::<0, 2>(&mut a, &mut v, &active);
        rotate_lanes::<1, 2>(&mut a, &mut v, &active);
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// `[f(0), …, f(LANES − 1)]`, as a loop the lane functions inline whatever the
/// optimiser's budget (an out-of-line `std::array::from_fn` would keep each lane group's
/// values in memory).
#[inline(always)]
fn lanewise<T: Copy + Default>(f: impl Fn(usize) -> T) -> [T; LANES] {
    let mut r = [T::default(); LANES];
    for (l, e) in r.iter_mut().enumerate() {
        *e = f(l);
    }
    r
}

/// One Jacobi rotation of [`symmetric_eigen3_lanes`] at the pivot (P, Q), in the lanes
/// still `active`: [`symmetric_eigen3`]'s rotation, lane by lane.
#[inline(always)]
fn rotate_lanes<const P: usize, const Q: usize>(
    a: &mut [[[f64; LANES]; 3]; 3],
    v: &mut [[[f64; LANES]; 3]; 3],
    active: &[bool; LANES],
) {
    const L: usize = LANES;
    let pick = |c: [bool; L], x: [f64; L], y: [f64; L]| -> [f64; L] {
        lanewise(|l| if c[l] { x[l] } else { y[l] })
    };
    let (p, q) = (P, Q);
    let apq = a[p][q];
    let go: [bool; L] = lanewise(|l| active[l] && apq[l] != 0.0);
    let tau: [f64; L] = lanewise(|l| (a[q][q][l] - a[p][p][l]) / (2.0 * apq[l]));
    // The reference's three quotients as one: its numerator and denominator
    // picked per lane (no branch), then divided.
    let root: [f64; L] = lanewise(|l| (1.0 + tau[l] * tau[l]).sqrt());
    let big: [bool; L] = lanewise(|l| tau[l].abs() > 1e150);
    let pos: [bool; L] = lanewise(|l| tau[l] >= 0.0);
    let den = pick(
        big,
        tau,
        pick(
            pos,
            lanewise(|l| tau[l] + root[l]),
            lanewise(|l| -tau[l] + root[l]),
        ),
    );
    let num = pick(big, [0.5; L], pick(pos, [1.0; L], [-1.0; L]));
    let t: [f64; L] = lanewise(|l| num[l] / den[l]);
    let c: [f64; L] = lanewise(|l| 1.0 / (1.0 + t[l] * t[l]).sqrt());
    let s: [f64; L] = lanewise(|l| t[l] * c[l]);
    let r = 3 - p - q;
    a[p][p] = pick(go, lanewise(|l| a[p][p][l] - t[l] * apq[l]), a[p][p]);
    a[q][q] = pick(go, lanewise(|l| a[q][q][l] + t[l] * apq[l]), a[q][q]);
    a[p][q] = pick(go, [0.0; L], a[p][q]);
    a[q][p] = pick(go, [0.0; L], a[q][p]);
    let (arp, arq) = (a[r][p], a[r][q]);
    a[r][p] = pick(go, lanewise(|l| c[l] * arp[l] - s[l] * arq[l]), arp);
    a[r][q] = pick(go, lanewise(|l| s[l] * arp[l] + c[l] * arq[l]), arq);
    a[p][r] = a[r][p];
    a[q][r] = a[r][q];
    for row in v.iter_mut() {
        let (vp, vq) = (row[p], row[q]);
        row[p] = pick(go, lanewise(|l| c[l] * vp[l] - s[l] * vq[l]), vp);
        row[q] = pick(go, lanewise(|l| s[l] * vp[l] + c[l] * vq[l]), vq);
    }
}

/// 3D [`signed_svd`]: V from the eigenvectors of FᵀF ([`symmetric_eigen3`]), sorted by
/// decreasing eigenvalue and made a rotation; B = F V; U by Gram–Schmidt on B's columns
/// (u₃ = u₁ × u₂, so U is a rotation) and σ_k = u_kᵀ b_k, the last one signed. A
/// vanishing column (a flat or collapsed element) takes any unit vector orthogonal to the
/// others: its singular value is zero, so F = U diag(σ) Vᵀ holds whatever it is.
fn signed_svd3(f: &[f64]) -> ([f64; 9], [f64; 3], [f64; 9]) {
    let (lam, ev) = symmetric_eigen3(&gram3(f));
    signed_svd3_from_eigen(f, &lam, &ev)
}

/// FᵀF of a row-major 3×3 F.
#[inline(always)]
fn gram3(f: &[f64]) -> [[f64; 3]; 3] {
    let mut ata = [[0.0f64; 3]; 3];
    for (r, row) in ata.iter_mut().enumerate() {
        for (c, e) in row.iter_mut().enumerate() {
            *e = (0..3).map(|k| f[k * 3 + r] * f[k * 3 + c]).sum();
        }
    }
    ata
}

/// [`signed_svd`] of a 3×3 F from the eigenpairs of FᵀF ([`gram3`],
/// [`symmetric_eigen3`]).
#[inline(always)]
fn signed_svd3_from_eigen(
    f: &[f64],
    lam: &[f64; 3],
    ev: &[[f64; 3]; 3],
) -> ([f64; 9], [f64; 3], [f64; 9]) {
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| lam[j].total_cmp(&lam[i]));
    let mut v = [0.0f64; 9];
    for r in 0..3 {
        for k in 0..3 {
            v[r * 3 + k] = ev[r][order[k]];
        }
    }
    if det3(&v) < 0.0 {
        for r in 0..3 {
            v[r * 3 + 2] = -v[r * 3 + 2];
        }
    }
    // Columns of B = F V.
    let mut b = [[0.0f64; 3]; 3];
    for (k, col) in b.iter_mut().enumerate() {
        for (r, e) in col.iter_mut().enumerate() {
            *e = (0..3).map(|j| f[r * 3 + j] * v[j * 3 + k]).sum();
        }
    }
    let dot = |x: &[f64; 3], y: &[f64; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
    let cross = |x: &[f64; 3], y: &[f64; 3]| {
        [
            x[1] * y[2] - x[2] * y[1],
            x[2] * y[0] - x[0] * y[2],
            x[0] * y[1] - x[1] * y[0],
        ]
    };
    let normalized = |x: [f64; 3]| -> Option<[f64; 3]> {
        let n = dot(&x, &x).sqrt();
        (n > f64::MIN_POSITIVE && n.is_finite()).then(|| [x[0] / n, x[1] / n, x[2] / n])
    };
    // Any unit vector orthogonal to the unit vector x: x × (the axis least along x).
    let orthogonal = |x: &[f64; 3]| -> [f64; 3] {
        let mut k = 0;
        for a in 1..3 {
            if x[a].abs() < x[k].abs() {
                k = a;
            }
        }
        let mut e = [0.0; 3];
        e[k] = 1.0;
        normalized(cross(x, &e)).unwrap_or([0.0, 0.0, 1.0])
    };
    let u1 = normalized(b[0]).unwrap_or([1.0, 0.0, 0.0]);
    let mut w = b[1];
    // Twice is enough: the second pass removes what rounding left of u₁.
    for _ in 0..2 {
        let p = dot(&u1, &w);
        for a in 0..3 {
            w[a] -= p * u1[a];
        }
    }
    let u2 = normalized(w).unwrap_or_else(|| orthogonal(&u1));
    let u3 = cross(&u1, &u2);
    let sigma = [dot(&u1, &b[0]), dot(&u2, &b[1]), dot(&u3, &b[2])];
    let mut u = [0.0f64; 9];
    for r in 0..3 {
        u[r * 3] = u1[r];
        u[r * 3 + 1] = u2[r];
        u[r * 3 + 2] = u3[r];
    }
    (u, sigma, v)
}

fn det3(m: &[f64; 9]) -> f64 {
    m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
        + m[2] * (m[3] * m[7] - m[4] * m[6])
}

/// Projects a symmetric n×n row-major matrix to the nearest PSD one (eigenvalues clamped
/// at zero). Exact symmetry is restored first, so round-off cannot leak in.
pub fn project_psd(n: usize, m: &mut [f64]) {
    let mut a = nalgebra::DMatrix::<f64>::zeros(n, n);
    for r in 0..n {
        for c in 0..n {
            a[(r, c)] = 0.5 * (m[r * n + c] + m[c * n + r]);
        }
    }
    let eig = nalgebra::SymmetricEigen::new(a);
    if eig.eigenvalues.iter().all(|&l| l >= 0.0) {
        return;
    }
    let mut out = nalgebra::DMatrix::<f64>::zeros(n, n);
    for (k, &l) in eig.eigenvalues.iter().enumerate() {
        if l > 0.0 {
            let v = eig.eigenvectors.column(k);
            out += l * v * v.transpose();
        }
    }
    for r in 0..n {
        for c in 0..n {
            m[r * n + c] = out[(r, c)];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn max_abs(m: &[f64]) -> f64 {
        m.iter().fold(0.0f64, |a, v| a.max(v.abs()))
    }

    /// Random, nearly repeated, rank-deficient, diagonal and zero matrices.
    fn matrices(rng: &mut StdRng) -> Vec<[f64; 9]> {
        let mut out = Vec::new();
        for _ in 0..200 {
            out.push(std::array::from_fn(|_| rng.random_range(-2.0..2.0)));
        }
        out.push([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        out.push([0.0; 9]);
        out.push([2.0, 0.0, 0.0, 0.0, -3.0, 0.0, 0.0, 0.0, 1e-9]);
        out.push([1.0, 1e-12, 0.0, 0.0, 1.0, 1e-12, 0.0, 0.0, 1.0]);
        // Rank 1 and rank 2.
        out.push([1.0, 2.0, 3.0, 2.0, 4.0, 6.0, -1.0, -2.0, -3.0]);
        out.push([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 5.0, 7.0, 9.0]);
        // Inverted (det < 0) and nearly flat.
        out.push([1.2, 0.1, 0.0, 0.0, 0.9, 0.2, 0.1, 0.0, -0.3]);
        out.push([1.1, 0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0, 1e-7]);
        out
    }

    #[test]
    fn jacobi_eigenpairs_reassemble_the_matrix_and_are_orthonormal() {
        let mut rng = StdRng::seed_from_u64(5);
        for m in matrices(&mut rng) {
            let a: [[f64; 3]; 3] = std::array::from_fn(|r| {
                std::array::from_fn(|c| 0.5 * (m[r * 3 + c] + m[c * 3 + r]))
            });
            let (l, v) = symmetric_eigen3(&a);
            let scale = max_abs(&m).max(f64::MIN_POSITIVE);
            for r in 0..3 {
                for c in 0..3 {
                    let back: f64 = (0..3).map(|k| v[r][k] * l[k] * v[c][k]).sum();
                    let vtv: f64 = (0..3).map(|k| v[k][r] * v[k][c]).sum();
                    // A few dozen rotations of O(‖A‖) entries: 1e-13 relative is far above
                    // rounding and far below a wrong rotation.
                    assert!((back - a[r][c]).abs() <= 1e-13 * scale, "{m:?}: ({r}, {c})");
                    let id = if r == c { 1.0 } else { 0.0 };
                    assert!((vtv - id).abs() <= 1e-14, "{m:?}: VᵀV ({r}, {c}) = {vtv}");
                }
            }
        }
    }

    #[test]
    fn signed_svd_reassembles_f_with_rotations_and_the_sign_of_det_f() {
        let mut rng = StdRng::seed_from_u64(11);
        for m in matrices(&mut rng) {
            let (u, s, v) = signed_svd(3, &m);
            let scale = max_abs(&m).max(f64::MIN_POSITIVE);
            for r in 0..3 {
                for c in 0..3 {
                    let back: f64 = (0..3).map(|k| u[r * 3 + k] * s[k] * v[c * 3 + k]).sum();
                    // Same reasoning as above; F's entries are O(1).
                    assert!(
                        (back - m[r * 3 + c]).abs() <= 1e-13 * scale,
                        "{m:?}: ({r}, {c})"
                    );
                }
            }
            assert!((det3(&u) - 1.0).abs() <= 1e-14 && (det3(&v) - 1.0).abs() <= 1e-14);
            assert!(s[0] >= s[1] && s[1] >= s[2].abs(), "{m:?}: σ = {s:?}");
            let det = det3(&m);
            // The sign of det F is carried by σ₃ (a zero determinant may go either way).
            assert!(
                det * s[2] >= 0.0 || det.abs() <= 1e-13 * scale.powi(3),
                "{m:?}: σ = {s:?}"
            );
        }
    }
}
