//! The dense cluster blocks: a Cholesky factorisation that drops singular pivots, and
//! the explicit inverse it gives.

/// A pivot at or below this fraction of its block's largest diagonal entry is dropped.
pub const PIVOT_DROP: f64 = 1e-12;

/// In place: the lower Cholesky factor of the symmetric m×m `a` (row-major, upper part
/// zeroed), a pivot ≤ [`PIVOT_DROP`] × max diag (or not finite) dropped with its column.
/// Returns the pivots dropped.
pub fn cholesky_dropping(m: usize, a: &mut [f64]) -> usize {
    let scale = (0..m).map(|k| a[k * m + k].abs()).fold(0.0f64, f64::max);
    let floor = PIVOT_DROP * scale;
    let mut dropped = 0;
    for k in 0..m {
        let mut p = a[k * m + k];
        for s in 0..k {
            p -= a[k * m + s] * a[k * m + s];
        }
        // Not above the floor, or NaN: dropped.
        if p.partial_cmp(&floor) != Some(std::cmp::Ordering::Greater) {
            dropped += 1;
            for r in k..m {
                a[r * m + k] = 0.0;
            }
            continue;
        }
        let l = p.sqrt();
        a[k * m + k] = l;
        // Four rows' sums side by side (each in its own order, s ascending): four
        // independent chains of subtractions instead of one waiting on the last.
        let mut r = k + 1;
        while r + 4 <= m {
            let mut v = [0.0f64; 4];
            for (q, vq) in v.iter_mut().enumerate() {
                *vq = a[(r + q) * m + k];
            }
            for s in 0..k {
                let ks = a[k * m + s];
                for (q, vq) in v.iter_mut().enumerate() {
                    *vq -= a[(r + q) * m + s] * ks;
                }
            }
            for (q, vq) in v.iter().enumerate() {
                a[(r + q) * m + k] = vq / l;
            }
            r += 4;
        }
        for r in r..m {
            let mut v = a[r * m + k];
            for s in 0..k {
                v -= a[r * m + s] * a[k * m + s];
            }
            a[r * m + k] = v / l;
        }
    }
    for r in 0..m {
        for c in r + 1..m {
            a[r * m + c] = 0.0;
        }
    }
    dropped
}

/// X = L⁺ for a factor from [`cholesky_dropping`]: lower triangular, m×m row-major, a
/// dropped pivot's row zero. (L Lᵀ)⁺ = XᵀX.
pub fn factor_inverse(m: usize, l: &[f64]) -> Vec<f64> {
    let mut x = vec![0.0; m * m];
    for k in 0..m {
        let piv = l[k * m + k];
        if piv == 0.0 {
            continue;
        }
        // Four columns' sums side by side, each over s = j.. in ascending order: the
        // first ones' leading terms alone, then all four together.
        let mut j = 0;
        while j + 4 <= k {
            let mut v = [0.0f64; 4];
            for q in 0..3 {
                for s in j + q..j + 3 {
                    v[q] -= l[k * m + s] * x[s * m + j + q];
                }
            }
            for s in j + 3..k {
                let ks = l[k * m + s];
                for (q, vq) in v.iter_mut().enumerate() {
                    *vq -= ks * x[s * m + j + q];
                }
            }
            for (q, vq) in v.iter().enumerate() {
                x[k * m + j + q] = vq / piv;
            }
            j += 4;
        }
        for j in j..=k {
            let mut v = if j == k { 1.0 } else { 0.0 };
            for s in j..k {
                v -= l[k * m + s] * x[s * m + j];
            }
            x[k * m + j] = v / piv;
        }
    }
    x
}

/// (L Lᵀ)⁺ for a factor from [`cholesky_dropping`]: X = L⁺ ([`factor_inverse`]), then
/// XᵀX, m×m symmetric row-major.
pub fn inverse_from_factor(m: usize, l: &[f64]) -> Vec<f64> {
    explicit_inverse(m, &factor_inverse(m, l))
}

/// XᵀX for a lower-triangular m×m `x`, symmetric row-major.
pub(super) fn explicit_inverse(m: usize, x: &[f64]) -> Vec<f64> {
    let mut inv = vec![0.0; m * m];
    for i in 0..m {
        for j in 0..=i {
            let mut v = 0.0;
            for k in i..m {
                v += x[k * m + i] * x[k * m + j];
            }
            inv[i * m + j] = v;
            inv[j * m + i] = v;
        }
    }
    inv
}

/// Values of an m×m lower-triangular matrix packed row by row (row k: its k + 1 entries
/// from column 0), m(m + 1)/2 in all.
pub fn packed_len(m: usize) -> usize {
    m * (m + 1) / 2
}

/// The lower triangle of the m×m row-major `x`, rounded to f32, packed row by row into
/// `out` ([`packed_len`] values).
pub fn pack_lower_f32(m: usize, x: &[f64], out: &mut [f32]) {
    let mut at = 0;
    for k in 0..m {
        for (o, v) in out[at..at + k + 1].iter_mut().zip(&x[k * m..k * m + k + 1]) {
            *o = *v as f32;
        }
        at += k + 1;
    }
}

/// The lower triangle of the m×m row-major `x` packed row by row into `out`
/// ([`packed_len`] values).
pub fn pack_lower(m: usize, x: &[f64], out: &mut [f64]) {
    let mut at = 0;
    for k in 0..m {
        out[at..at + k + 1].copy_from_slice(&x[k * m..k * m + k + 1]);
        at += k + 1;
    }
}

/// z = Gᵀ(G r) for G lower-triangular m×m packed row by row in f32
/// ([`pack_lower_f32`]), every sum in f64: row k gives y_k = G[k]·r and, while in cache,
/// its share of Gᵀy (z[..=k] += y_k G[k]), so G is read once. zᵀr = ‖y‖² up to the f64
/// roundings of the sums, so the block is semidefinite whatever G's entries are: rounding
/// the factor to f32 cannot make it indefinite, as rounding an explicit inverse can on a
/// stiff block. `y` is scratch of m values.
pub fn apply_packed(g: &[f32], r: &[f64], z: &mut [f64], y: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        unsafe { apply_packed_avx2(g, r, z, y) };
        return;
    }
    apply_packed_body(g, r, z, y);
}

/// [`apply_packed`] compiled for AVX2: four f32 → f64 conversions and products per
/// instruction instead of two. The same operations in the same order, so the same bits
/// (Rust never fuses a multiply and an add).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn apply_packed_avx2(g: &[f32], r: &[f64], z: &mut [f64], y: &mut [f64]) {
    apply_packed_body(g, r, z, y);
}

/// [`apply_packed`]'s loops, inlined into each of its compilations.
#[inline(always)]
fn apply_packed_body(g: &[f32], r: &[f64], z: &mut [f64], y: &mut [f64]) {
    let m = r.len();
    z.iter_mut().for_each(|v| *v = 0.0);
    // Row k of G gives y_k and, while in cache, its part of Gᵀy: z[..=k] += G[k] y_k.
    let mut at = 0;
    for k in 0..m {
        let row = &g[at..at + k + 1];
        let yk = dot_f32_f64(row, &r[..k + 1]);
        y[k] = yk;
        for (zv, gv) in z[..k + 1].iter_mut().zip(row) {
            *zv += f64::from(*gv) * yk;
        }
        at += k + 1;
    }
}

/// Σ a_k b_k in f64, in eight interleaved partial sums added in a fixed order: the same
/// bits on every run, and lanes a vector unit fills (one running sum would wait on each
/// addition).
#[inline(always)]
fn dot_f32_f64(a: &[f32], b: &[f64]) -> f64 {
    const L: usize = 8;
    let mut acc = [0.0f64; L];
    let (ac, bc) = (a.chunks_exact(L), b.chunks_exact(L));
    let (ar, br) = (ac.remainder(), bc.remainder());
    for (x, y) in ac.zip(bc) {
        for l in 0..L {
            acc[l] += f64::from(x[l]) * y[l];
        }
    }
    for (l, (x, y)) in ar.iter().zip(br).enumerate() {
        acc[l] += f64::from(*x) * y;
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// The first d² values of a block, in a 9-array.
pub(super) fn block9(d: usize, b: &[f64]) -> [f64; 9] {
    let mut o = [0.0; 9];
    o[..d * d].copy_from_slice(&b[..d * d]);
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A symmetric m×m block with eigenvalues 1 down to 1e-10 (κ = 1e10) in a seeded random
    /// orthonormal basis, and the eigenvector of eigenvalue 1.
    fn stiff_block(m: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        // Gram–Schmidt on random columns: q[k] is the k-th basis vector.
        let mut q: Vec<Vec<f64>> = Vec::new();
        while q.len() < m {
            let mut v: Vec<f64> = (0..m).map(|_| next()).collect();
            for _ in 0..2 {
                for u in &q {
                    let p: f64 = u.iter().zip(&v).map(|(a, b)| a * b).sum();
                    v.iter_mut().zip(u).for_each(|(a, b)| *a -= p * b);
                }
            }
            let n = v.iter().map(|a| a * a).sum::<f64>().sqrt();
            v.iter_mut().for_each(|a| *a /= n);
            q.push(v);
        }
        let lam = |k: usize| 10f64.powf(-10.0 * k as f64 / (m - 1) as f64);
        let mut a = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..m {
                a[i * m + j] = (0..m).map(|k| lam(k) * q[k][i] * q[k][j]).sum();
            }
        }
        (a, q[0].clone())
    }

    /// On a block with κ = 1e10 its explicit inverse has entries near 1e9 and eigenvalues
    /// down to 1: rounding those entries to f32 (a relative 6e-8 each, tens of units) can
    /// leave a negative eigenvalue, seen as rᵀX̃r < 0 for the block's stiffest direction r
    /// (rᵀB⁻¹r = 1). The factor form of the same block, G rounded to f32 and
    /// applied as GᵀG, keeps zᵀr = ‖G r‖² > 0 there and on every other vector tried.
    #[test]
    fn the_f32_factor_form_stays_definite_where_a_rounded_inverse_does_not() {
        let m = 12;
        let found = (0..64u64).find_map(|seed| {
            let (a, r) = stiff_block(m, seed);
            let mut l = a.clone();
            assert_eq!(
                cholesky_dropping(m, &mut l),
                0,
                "seed {seed}: a pivot dropped"
            );
            let inv = inverse_from_factor(m, &l);
            // rᵀX̃r in f64 from the f32-rounded entries.
            let rounded: f64 = (0..m)
                .map(|i| {
                    (0..m)
                        .map(|j| f64::from(inv[i * m + j] as f32) * r[j])
                        .sum::<f64>()
                        * r[i]
                })
                .sum();
            (rounded < 0.0).then_some((seed, l, r, rounded))
        });
        let (seed, l, r, rounded) = found.expect("a seed whose rounded inverse is indefinite");
        let mut g = vec![0.0f32; packed_len(m)];
        pack_lower_f32(m, &factor_inverse(m, &l), &mut g);
        let (mut z, mut y) = (vec![0.0; m], vec![0.0; m]);
        apply_packed(&g, &r, &mut z, &mut y);
        let zr: f64 = z.iter().zip(&r).map(|(a, b)| a * b).sum();
        // rᵀB⁻¹r = ‖G r‖² = 1; G's rounding (entries up to √κ = 1e5, each a relative
        // 6e-8) moves G r by about 1e-2 at most, far from 0.
        assert!(
            zr > 0.5,
            "seed {seed}: factor form zᵀr = {zr:e} (rounded inverse: {rounded:e})"
        );
        for k in 0..m {
            let v: Vec<f64> = (0..m)
                .map(|i| ((i * 7 + k * 13) % 11) as f64 - 5.0)
                .collect();
            apply_packed(&g, &v, &mut z, &mut y);
            let zv: f64 = z.iter().zip(&v).map(|(a, b)| a * b).sum();
            assert!(zv > 0.0, "seed {seed}, vector {k}: zᵀv = {zv:e}");
        }
    }

    /// GᵀG from the packed f32 factor is the explicit inverse XᵀX of the f32-rounded X:
    /// the packing reads the lower triangle row by row.
    #[test]
    fn the_packed_factor_applies_its_explicit_inverse() {
        let m = 7;
        let (a, _) = stiff_block(m, 3);
        let mut l = a;
        cholesky_dropping(m, &mut l);
        let x = factor_inverse(m, &l);
        let x32: Vec<f64> = x.iter().map(|&v| f64::from(v as f32)).collect();
        let inv = explicit_inverse(m, &x32);
        let mut g = vec![0.0f32; packed_len(m)];
        pack_lower_f32(m, &x, &mut g);
        let (mut z, mut y) = (vec![0.0; m], vec![0.0; m]);
        for k in 0..m {
            let mut e = vec![0.0; m];
            e[k] = 1.0;
            apply_packed(&g, &e, &mut z, &mut y);
            for i in 0..m {
                let want = inv[i * m + k];
                // The same products summed in another order: a few ulps of the terms'
                // magnitudes summed.
                let scale = (0..m)
                    .map(|t| (x32[t * m + i] * x32[t * m + k]).abs())
                    .sum::<f64>();
                assert!(
                    (z[i] - want).abs() <= 1e-14 * scale,
                    "({i}, {k}): {} vs {want}",
                    z[i]
                );
            }
        }
    }
}
