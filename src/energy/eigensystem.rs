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

use nalgebra::{Matrix2, Matrix3, SymmetricEigen};

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
    let mut u = [0.0; 9];
    let mut v = [0.0; 9];
    let mut s = [0.0; 3];
    if d == 2 {
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
    } else {
        let m = Matrix3::from_row_slice(&f[..9]);
        let svd = m.svd(true, true);
        let (mut uu, vt) = (svd.u.unwrap_or_default(), svd.v_t.unwrap_or_default());
        let mut vv = vt.transpose();
        let mut sv = [
            svd.singular_values[0],
            svd.singular_values[1],
            svd.singular_values[2],
        ];
        let mut last = 0;
        for k in 1..3 {
            if sv[k].abs() < sv[last].abs() {
                last = k;
            }
        }
        let (du, dv) = (uu.determinant(), vv.determinant());
        fix_sign(&mut uu, &mut vv, &mut sv, last, du, dv);
        for r in 0..3 {
            for c in 0..3 {
                u[r * 3 + c] = uu[(r, c)];
                v[r * 3 + c] = vv[(r, c)];
            }
        }
        s = sv;
    }
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

/// Eigenvalues and eigenvectors (columns: vecs[a][k] is component a of vector k) of the
/// symmetric d×d block.
fn scaling_eigen(d: usize, a: &[[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut vals = [0.0; 3];
    let mut vecs = [[0.0; 3]; 3];
    if d == 2 {
        let e = SymmetricEigen::new(Matrix2::new(a[0][0], a[0][1], a[1][0], a[1][1]));
        for k in 0..2 {
            vals[k] = e.eigenvalues[k];
            for (r, row) in vecs.iter_mut().enumerate().take(2) {
                row[k] = e.eigenvectors[(r, k)];
            }
        }
    } else {
        let m = Matrix3::from_fn(|r, c| a[r][c]);
        let e = SymmetricEigen::new(m);
        for k in 0..3 {
            vals[k] = e.eigenvalues[k];
            for (r, row) in vecs.iter_mut().enumerate() {
                row[k] = e.eigenvectors[(r, k)];
            }
        }
    }
    (vals, vecs)
}
