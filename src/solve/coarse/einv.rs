//! E⁺ of the aggregates' translations: one specification, run by the CPU CG here and by
//! the device PCG in shaders/coarse_factor.wgsl (src/gpu/pcg/coarse_factor.rs) with the
//! same operations in the same order for every entry, so both precondition with the same
//! bits wherever the device performs IEEE f64 operations as written.
//!
//! E = ZᵀĤZ (k×k, k = d·aggregates) is singular where an aggregate's constraints remove a
//! translation: its null space is that of each aggregate's Gram matrix G_a = Σ_{i∈a} Q_i.
//! W (k×m) holds, per aggregate, the eigenvectors of G_a whose eigenvalues exceed
//! [`PINV_RTOL`]·λ_max(G_a); W depends only on the constraint frames. Then
//!
//! ```text
//! Er = Wᵀ sym(E) W,   Er = L Lᵀ (Cholesky),   X = L⁻¹,   C = XᵀX = Er⁻¹,   E⁺ = W C Wᵀ
//! ```
//!
//! with sym(E) = (E + Eᵀ)/2. Er is SPD when Ĥ is SPD on the coarse space; a pivot that is
//! not positive and finite means it is not, and the caller falls back to the eigen
//! pseudo-inverse of the whole of sym(E) ([`pseudo_inverse`]).
//!
//! The order of every sum is fixed (ascending indices, starting from 0), products are
//! evaluated left to right, and only the lower triangles of Er, L, X and C are formed; E⁺
//! is formed for r ≥ c and mirrored, so it is symmetric bit for bit (the device reads its
//! rows as columns).

/// W of [`aggregates_einv_from_galerkin`]: per aggregate the eigenvectors of G_a kept
/// (unit length, d values each), its columns consecutive and in aggregate order.
#[derive(Debug, Clone, PartialEq)]
pub struct AggregateBasis {
    pub dim: usize,
    /// Columns of aggregate a: `ptr[a]..ptr[a + 1]`.
    pub ptr: Vec<usize>,
    /// The aggregate of each column.
    pub of: Vec<usize>,
    /// Column p's d values (its aggregate's translations), p-major.
    pub values: Vec<f64>,
}

impl AggregateBasis {
    /// W from the G_a of every aggregate (`count` blocks of d×d, row-major, symmetric:
    /// [`super::aggregate_projections`]); `None` when `g` has the wrong length or a value
    /// that is not finite.
    pub fn new(d: usize, count: usize, g: &[f64]) -> Option<Self> {
        if g.len() != count * d * d || g.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let mut basis = AggregateBasis {
            dim: d,
            ptr: vec![0],
            of: Vec::new(),
            values: Vec::new(),
        };
        for (a, ga) in g.chunks_exact(d * d).enumerate() {
            let eig = nalgebra::SymmetricEigen::new(nalgebra::DMatrix::from_row_slice(d, d, ga));
            let lmax = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
            for (j, &l) in eig.eigenvalues.iter().enumerate() {
                if l > PINV_RTOL * lmax {
                    basis.of.push(a);
                    basis
                        .values
                        .extend((0..d).map(|x| eig.eigenvectors[(x, j)]));
                }
            }
            basis.ptr.push(basis.of.len());
        }
        Some(basis)
    }

    /// Columns of W (m).
    pub fn columns(&self) -> usize {
        self.of.len()
    }

    /// Entry x of column p.
    fn w(&self, p: usize, x: usize) -> f64 {
        self.values[p * self.dim + x]
    }
}

/// A pivot of Er's Cholesky factorization that is not positive and finite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NotPositive {
    /// Its column.
    pub column: usize,
    pub pivot: f64,
}

/// Whether `v` is a usable pivot: positive and finite (1/∞ = 0). The device's test too.
fn positive_finite(v: f64) -> bool {
    v > 0.0 && 1.0 / v > 0.0
}

/// Entry (r, c) of sym(E) (k×k row-major): E's own on the diagonal, else the mean of
/// E_rc and E_cr (the same bits for (c, r)).
fn sym(e: &[f64], k: usize, r: usize, c: usize) -> f64 {
    if r == c {
        e[r * k + r]
    } else {
        0.5 * (e[r * k + c] + e[c * k + r])
    }
}

/// E⁺ = W (Wᵀ sym(E) W)⁻¹ Wᵀ (k×k row-major) from E = ZᵀĤZ as reduced (not symmetrized)
/// and W; the error names the first pivot of Er that is not positive and finite. Every
/// step below is what shaders/coarse_factor.wgsl does, entry by entry:
///
/// 1. Er_pq (p ≥ q; columns p of aggregate a, q of b): s = 0, then for x, y in 0..d:
///    s = s + (W_{a·d+x,p} · sym(E)_{a·d+x, b·d+y}) · W_{b·d+y,q}   (`agg_er`)
/// 2. L_ij (j ≤ i), column by column: t = Er_ij, then for k < j: t = t − L_ik·L_jk;
///    L_jj = √t (t must pass the pivot test), L_ij = t / L_jj   (`agg_chol`)
/// 3. X = L⁻¹ (i ≥ c): X_cc = 1 / L_cc; for i > c: t = 0, then for j in c..i:
///    t = t − L_ij·X_jc; X_ic = t / L_ii   (`agg_linv`)
/// 4. C_pq = (XᵀX)_pq (p ≥ q): s = 0, then for i in p..m: s = s + X_ip·X_iq   (`agg_cinv`)
/// 5. E⁺_rc (r ≥ c; aggregates a ∋ r, b ∋ c): s = 0, then for p in a's columns, q in b's:
///    s = s + (W_rp · C_pq) · W_cq with C_pq = C_qp above the diagonal; E⁺_cr = E⁺_rc
///    (`agg_expand`)
pub fn aggregates_einv_with_basis(
    k: usize,
    e: &[f64],
    w: &AggregateBasis,
) -> Result<Vec<f64>, NotPositive> {
    let d = w.dim;
    let m = w.columns();
    let mut l = vec![0.0; m * m];
    for p in 0..m {
        let a = w.of[p];
        for q in 0..=p {
            let b = w.of[q];
            let mut s = 0.0;
            for x in 0..d {
                for y in 0..d {
                    s += w.w(p, x) * sym(e, k, a * d + x, b * d + y) * w.w(q, y);
                }
            }
            l[p * m + q] = s;
        }
    }
    for j in 0..m {
        for i in j..m {
            let mut t = l[i * m + j];
            for kk in 0..j {
                t -= l[i * m + kk] * l[j * m + kk];
            }
            if i == j {
                if !positive_finite(t) {
                    return Err(NotPositive {
                        column: j,
                        pivot: t,
                    });
                }
                l[j * m + j] = t.sqrt();
            } else {
                l[i * m + j] = t / l[j * m + j];
            }
        }
    }
    let mut x = vec![0.0; m * m];
    for c in 0..m {
        x[c * m + c] = 1.0 / l[c * m + c];
        for i in c + 1..m {
            let mut t = 0.0;
            for j in c..i {
                t -= l[i * m + j] * x[j * m + c];
            }
            x[i * m + c] = t / l[i * m + i];
        }
    }
    let mut cinv = vec![0.0; m * m];
    for p in 0..m {
        for q in 0..=p {
            let mut s = 0.0;
            for i in p..m {
                s += x[i * m + p] * x[i * m + q];
            }
            cinv[p * m + q] = s;
        }
    }
    let mut out = vec![0.0; k * k];
    for r in 0..k {
        for c in 0..=r {
            let (a, b) = (r / d, c / d);
            let mut s = 0.0;
            for p in w.ptr[a]..w.ptr[a + 1] {
                for q in w.ptr[b]..w.ptr[b + 1] {
                    let cpq = if p >= q {
                        cinv[p * m + q]
                    } else {
                        cinv[q * m + p]
                    };
                    s += w.w(p, r % d) * cpq * w.w(q, c % d);
                }
            }
            out[r * k + c] = s;
            out[c * k + r] = s;
        }
    }
    Ok(out)
}

/// E⁺ of the aggregates' translations from E = ZᵀĤZ (k×k row-major, k = d·count) and G of
/// [`super::aggregate_projections`]: [`aggregates_einv_with_basis`] with W from G, or, when
/// a pivot fails (Ĥ indefinite on the coarse space), the eigen pseudo-inverse of sym(E).
/// `None` when no translation is free or E is not finite.
pub fn aggregates_einv_from_galerkin(
    d: usize,
    count: usize,
    e: Vec<f64>,
    g: &[f64],
) -> Option<Vec<f64>> {
    let k = d * count;
    if e.len() != k * k || e.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let w = AggregateBasis::new(d, count, g)?;
    if w.columns() == 0 {
        return None;
    }
    aggregates_einv_with_basis(k, &e, &w).ok().or_else(|| {
        let mut es = e;
        symmetrize(k, &mut es);
        pseudo_inverse(k, &es)
    })
}

/// Relative size below which an eigenvalue of E counts as zero (a translation whose
/// every component is constrained: its column of Z vanishes).
pub(super) const PINV_RTOL: f64 = 1e-12;

pub(super) fn symmetrize(k: usize, e: &mut [f64]) {
    for a in 0..k {
        for b in 0..a {
            let m = 0.5 * (e[a * k + b] + e[b * k + a]);
            e[a * k + b] = m;
            e[b * k + a] = m;
        }
    }
}

/// The pseudo-inverse of the symmetric k×k `e` over its eigenvalues above
/// PINV_RTOL·λ_max (negative ones, which an SPD Ĥ cannot give, are dropped too, so the
/// result is positive semidefinite). `None` when nothing is left or `e` is not finite.
pub fn pseudo_inverse(k: usize, e: &[f64]) -> Option<Vec<f64>> {
    if e.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let m = nalgebra::DMatrix::from_row_slice(k, k, e);
    let eig = nalgebra::SymmetricEigen::new(m);
    let lmax = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    if lmax <= 0.0 || !lmax.is_finite() {
        return None;
    }
    let mut out = vec![0.0; k * k];
    for (j, &l) in eig.eigenvalues.iter().enumerate() {
        if l <= PINV_RTOL * lmax {
            continue;
        }
        let v = eig.eigenvectors.column(j);
        for a in 0..k {
            for b in 0..k {
                out[a * k + b] += v[a] * v[b] / l;
            }
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random stream in [-1, 1).
    fn stream(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    /// G of `count` aggregates in 3D: full rank, rank 2 (a slip plane with normal n: I − nnᵀ
    /// times a node count), rank 1 and rank 2 again, repeated.
    fn grams(count: usize) -> Vec<f64> {
        let n = [0.3f64, 1.0, -0.25];
        let nn = n.iter().map(|v| v * v).sum::<f64>();
        let mut g = Vec::new();
        for a in 0..count {
            let mut ga = [0.0; 9];
            match a % 3 {
                0 => (0..3).for_each(|x| ga[x * 4] = 5.0),
                1 => {
                    for x in 0..3 {
                        for y in 0..3 {
                            ga[x * 3 + y] = 4.0 * (f64::from(u8::from(x == y)) - n[x] * n[y] / nn);
                        }
                    }
                }
                _ => ga[0] = 2.0,
            }
            g.extend(ga);
        }
        g
    }

    /// W as a dense k×m matrix.
    fn basis_matrix(w: &AggregateBasis, k: usize) -> nalgebra::DMatrix<f64> {
        nalgebra::DMatrix::from_fn(k, w.columns(), |r, p| {
            if w.of[p] == r / w.dim {
                w.w(p, r % w.dim)
            } else {
                0.0
            }
        })
    }

    /// E = Z_fᵀ A Z_f for a random SPD A on the free translations (Z_f = W's columns), plus
    /// garbage of order one in the directions W drops (which E⁺ must ignore), not symmetric.
    fn galerkin(w: &AggregateBasis, k: usize, seed: u64) -> Vec<f64> {
        let m = w.columns();
        let mut rnd = stream(seed);
        let b: Vec<f64> = (0..m * m).map(|_| rnd()).collect();
        // Er = BBᵀ + m·I: SPD, κ of a few.
        let mut er = vec![0.0; m * m];
        for p in 0..m {
            for q in 0..m {
                er[p * m + q] = (0..m).map(|t| b[p * m + t] * b[q * m + t]).sum::<f64>()
                    + if p == q { m as f64 } else { 0.0 };
            }
        }
        // E = W Er Wᵀ + (I − WWᵀ) N (I − WWᵀ) with N random, asymmetric by rounding.
        let wm = basis_matrix(w, k);
        let erm = nalgebra::DMatrix::from_row_slice(m, m, &er);
        let proj = nalgebra::DMatrix::identity(k, k) - &wm * wm.transpose();
        let noise = nalgebra::DMatrix::from_fn(k, k, |_, _| rnd());
        let e = &wm * erm * wm.transpose() + &proj * noise * &proj;
        (0..k * k).map(|t| e[(t / k, t % k)]).collect()
    }

    /// E⁺ is the pseudo-inverse of sym(E) restricted to range(W), computed independently by
    /// nalgebra's eigen-decomposition of P sym(E) P (P = WWᵀ): within 1e-12 of the largest
    /// entry (both backward stable; κ(Er) ≤ 10 here, so a few hundred ulps at most). It is
    /// symmetric bit for bit and ignores E outside range(W).
    #[test]
    fn einv_is_the_pseudo_inverse_on_the_range_of_w() {
        let (d, count) = (3, 7);
        let k = d * count;
        let g = grams(count);
        let w = AggregateBasis::new(d, count, &g).expect("finite G");
        assert_eq!(w.columns(), 3 * 3 + 2 * 2 + 2);
        let e = galerkin(&w, k, 4);
        let got = aggregates_einv_with_basis(k, &e, &w).expect("SPD on range(W)");
        for r in 0..k {
            for c in 0..r {
                assert_eq!(got[r * k + c].to_bits(), got[c * k + r].to_bits());
            }
        }
        let wm = basis_matrix(&w, k);
        let p = &wm * wm.transpose();
        let mut es = e.clone();
        super::symmetrize(k, &mut es);
        let pep = &p * nalgebra::DMatrix::from_row_slice(k, k, &es) * &p;
        let pep: Vec<f64> = (0..k * k).map(|t| pep[(t / k, t % k)]).collect();
        let want = super::pseudo_inverse(k, &pep).expect("modes");
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (x, y) in got.iter().zip(&want) {
            assert!((x - y).abs() <= 1e-12 * scale, "{x:e} vs {y:e}");
        }
        // The wrapper takes the same path.
        let wrapped = aggregates_einv_from_galerkin(d, count, e, &g).expect("E⁺");
        assert_eq!(wrapped, got);
    }

    /// An E whose restriction to range(W) is indefinite: the Cholesky path reports the
    /// pivot, and the wrapper falls back to the eigen pseudo-inverse of sym(E) (its
    /// negative eigenvalues dropped); a non-finite E gives nothing.
    #[test]
    fn indefinite_e_falls_back_to_the_eigen_pseudo_inverse() {
        let (d, count) = (3, 4);
        let k = d * count;
        let g = grams(count);
        let w = AggregateBasis::new(d, count, &g).expect("finite G");
        let mut e = galerkin(&w, k, 9);
        // Er − s·I: E − s·WWᵀ with s midway between Er's extreme eigenvalues.
        let wm = basis_matrix(&w, k);
        let mut es = e.clone();
        super::symmetrize(k, &mut es);
        let er = wm.transpose() * nalgebra::DMatrix::from_row_slice(k, k, &es) * &wm;
        let ev = nalgebra::SymmetricEigen::new(er).eigenvalues;
        let s = 0.5 * (ev.min() + ev.max());
        for r in 0..k {
            for c in 0..k {
                let mut wwt = 0.0;
                for p in 0..w.columns() {
                    if w.of[p] == r / d && w.of[p] == c / d {
                        wwt += w.w(p, r % d) * w.w(p, c % d);
                    }
                }
                e[r * k + c] -= s * wwt;
            }
        }
        let err = aggregates_einv_with_basis(k, &e, &w).expect_err("indefinite");
        assert!(err.pivot <= 0.0, "{err:?}");
        let mut es = e.clone();
        super::symmetrize(k, &mut es);
        let want = super::pseudo_inverse(k, &es).expect("positive part");
        let got = aggregates_einv_from_galerkin(d, count, e.clone(), &g).expect("fallback");
        assert_eq!(got, want);
        e[5] = f64::NAN;
        assert!(aggregates_einv_from_galerkin(d, count, e, &g).is_none());
        assert!(!positive_finite(f64::INFINITY) && !positive_finite(f64::NAN));
        assert!(!positive_finite(0.0) && positive_finite(f64::MIN_POSITIVE));
    }
}
