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

/// (L Lᵀ)⁺ for a factor from [`cholesky_dropping`]: X = L⁺ (`factor_inverse`), then
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

/// The lower triangle of the m×m row-major `x` packed row by row into `out`
/// ([`packed_len`] values).
pub fn pack_lower(m: usize, x: &[f64], out: &mut [f64]) {
    let mut at = 0;
    for k in 0..m {
        out[at..at + k + 1].copy_from_slice(&x[k * m..k * m + k + 1]);
        at += k + 1;
    }
}

/// The side of a [`pack_tiled_f32`] tile: four rows by four columns.
pub const TILE: usize = 4;

/// m rounded up to whole tiles: the length of the vectors [`apply_tiled`] reads and
/// writes (the components past m are zero).
pub fn tiled_side(m: usize) -> usize {
    m.div_ceil(TILE) * TILE
}

/// Values of an m×m lower-triangular matrix in 4×4 tiles ([`pack_tiled_f32`]): tile row b
/// holds b + 1 tiles of 16, so (b + 1)(b + 2)/2 · 16 for b = ⌈m/4⌉ − 1.
pub fn tiled_len(m: usize) -> usize {
    let nb = m.div_ceil(TILE);
    TILE * TILE * nb * (nb + 1) / 2
}

/// Where entry (k, j), j ≤ k, of a tiled lower triangle sits ([`pack_tiled_f32`]).
pub fn tiled_index(k: usize, j: usize) -> usize {
    let (b, q) = (k / TILE, k % TILE);
    let (t, c) = (j / TILE, j % TILE);
    TILE * TILE * (b * (b + 1) / 2 + t) + TILE * q + c
}

/// The lower triangle of the m×m row-major `x`, rounded to f32, in 4×4 tiles: tile row b
/// (rows 4b..4b + 4) holds its tiles t = 0..=b (columns 4t..4t + 4) one after the
/// other, each row-major; entries above the diagonal or past m are zero. Every row of
/// tiles is whole, so [`apply_tiled`] runs four lanes wide with no remainder, at about
/// 6 % more values than the triangle packed by rows (m ≈ 48).
pub fn pack_tiled_f32(m: usize, x: &[f64], out: &mut [f32]) {
    out.iter_mut().for_each(|v| *v = 0.0);
    for k in 0..m {
        for j in 0..=k {
            out[tiled_index(k, j)] = x[k * m + j] as f32;
        }
    }
}

/// z = Gᵀ(G r) for G lower-triangular in f32 tiles ([`pack_tiled_f32`]), every product
/// and sum in f64; `r` and `z` have [`tiled_side`] components (r's past m zero). Tile row
/// b gives y = G[4b..4b + 4]·r (four rows side by side, each in four lanes over the
/// columns, the lanes added as (l0 + l1) + (l2 + l3)) and, while in cache, its share of
/// Gᵀy (z[..4b + 4] += Σ_q y_q G[4b + q], q in order), so G is read once. zᵀr = ‖y‖² up
/// to the f64 roundings of the sums, so the block is semidefinite whatever G's entries
/// are: rounding the factor to f32 cannot make it indefinite, as rounding an explicit
/// inverse can on a stiff block.
pub fn apply_tiled(g: &[f32], r: &[f64], z: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        unsafe { apply_tiled_avx2(g, r, z) };
        return;
    }
    apply_tiled_scalar(g, r, z);
}

/// [`apply_tiled`] without vector instructions: the same products and sums in the same
/// order as [`apply_tiled_avx2`] (a multiply, then an add: never fused), so the same bits.
fn apply_tiled_scalar(g: &[f32], r: &[f64], z: &mut [f64]) {
    const T: usize = TILE;
    let nb = r.len() / T;
    z.iter_mut().for_each(|v| *v = 0.0);
    let mut at = 0;
    for b in 0..nb {
        let tiles = &g[at..at + T * T * (b + 1)];
        let mut acc = [[0.0f64; T]; T];
        for (tile, rj) in tiles.chunks_exact(T * T).zip(r.chunks_exact(T)) {
            for (q, aq) in acc.iter_mut().enumerate() {
                for l in 0..T {
                    aq[l] += f64::from(tile[q * T + l]) * rj[l];
                }
            }
        }
        let y = acc.map(|a| (a[0] + a[1]) + (a[2] + a[3]));
        for (tile, zj) in tiles.chunks_exact(T * T).zip(z.chunks_exact_mut(T)) {
            for (q, yq) in y.iter().enumerate() {
                for l in 0..T {
                    zj[l] += f64::from(tile[q * T + l]) * yq;
                }
            }
        }
        at += T * T * (b + 1);
    }
}

/// [`apply_tiled`] in AVX2: a tile row's four rows in four f64 lanes each (f32 → f64
/// four at a time), the lanes reduced by pairwise adds in [`apply_tiled_scalar`]'s order.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn apply_tiled_avx2(g: &[f32], r: &[f64], z: &mut [f64]) {
    use std::arch::x86_64::*;
    const T: usize = TILE;
    let nb = r.len() / T;
    z.iter_mut().for_each(|v| *v = 0.0);
    assert!(g.len() >= tiled_len(nb * T) && z.len() == nb * T);
    let (gp, rp, zp) = (g.as_ptr(), r.as_ptr(), z.as_mut_ptr());
    let mut at = 0;
    for b in 0..nb {
        // SAFETY (every access below): tile row b's tiles lie in g[at..at + 16(b + 1)]
        // and its columns in r and z [0..4(b + 1)], within the lengths asserted above.
        let mut acc = [_mm256_setzero_pd(); T];
        for t in 0..=b {
            let rj = _mm256_loadu_pd(rp.add(T * t));
            let tile = gp.add(at + T * T * t);
            for (q, aq) in acc.iter_mut().enumerate() {
                let gq = _mm256_cvtps_pd(_mm_loadu_ps(tile.add(T * q)));
                *aq = _mm256_add_pd(*aq, _mm256_mul_pd(gq, rj));
            }
        }
        // [a0 + a1, b0 + b1, a2 + a3, b2 + b3] and the same for rows 2 and 3, then the
        // low halves plus the high ones: y_q = (l0 + l1) + (l2 + l3).
        let h01 = _mm256_hadd_pd(acc[0], acc[1]);
        let h23 = _mm256_hadd_pd(acc[2], acc[3]);
        let y = _mm256_add_pd(
            _mm256_permute2f128_pd(h01, h23, 0x20),
            _mm256_permute2f128_pd(h01, h23, 0x31),
        );
        let mut ys = [0.0f64; T];
        _mm256_storeu_pd(ys.as_mut_ptr(), y);
        let yq = ys.map(|v| _mm256_set1_pd(v));
        for t in 0..=b {
            let zt = zp.add(T * t);
            let tile = gp.add(at + T * T * t);
            let mut zj = _mm256_loadu_pd(zt);
            for (q, yv) in yq.iter().enumerate() {
                let gq = _mm256_cvtps_pd(_mm_loadu_ps(tile.add(T * q)));
                zj = _mm256_add_pd(zj, _mm256_mul_pd(gq, *yv));
            }
            _mm256_storeu_pd(zt, zj);
        }
        at += T * T * (b + 1);
    }
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
        let mut g = vec![0.0f32; tiled_len(m)];
        pack_tiled_f32(m, &factor_inverse(m, &l), &mut g);
        let mut z = vec![0.0; tiled_side(m)];
        apply_tiled(&g, &r, &mut z);
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
            apply_tiled(&g, &v, &mut z);
            let zv: f64 = z.iter().zip(&v).map(|(a, b)| a * b).sum();
            assert!(zv > 0.0, "seed {seed}, vector {k}: zᵀv = {zv:e}");
        }
    }

    /// GᵀG from the tiled f32 factor is the explicit inverse XᵀX of the f32-rounded X, on
    /// a block whose side is not a whole number of tiles: the tiles hold the lower
    /// triangle and zeros past it.
    #[test]
    fn the_tiled_factor_applies_its_explicit_inverse() {
        let m = 7;
        let (a, _) = stiff_block(m, 3);
        let mut l = a;
        cholesky_dropping(m, &mut l);
        let x = factor_inverse(m, &l);
        let x32: Vec<f64> = x.iter().map(|&v| f64::from(v as f32)).collect();
        let inv = explicit_inverse(m, &x32);
        let mut g = vec![0.0f32; tiled_len(m)];
        pack_tiled_f32(m, &x, &mut g);
        let mut z = vec![0.0; tiled_side(m)];
        for k in 0..m {
            let mut e = vec![0.0; tiled_side(m)];
            e[k] = 1.0;
            apply_tiled(&g, &e, &mut z);
            assert!(z[m..].iter().all(|&v| v == 0.0), "past m: {:?}", &z[m..]);
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

    /// The vector build of the tiled product (where the CPU has AVX2) gives the bits of
    /// the scalar one: the same products and sums in the same order.
    #[test]
    fn the_tiled_product_has_the_same_bits_in_every_build() {
        for mm in [2, 6, 13, 48] {
            let (a, _) = stiff_block(mm, 5);
            let mut l = a;
            cholesky_dropping(mm, &mut l);
            let mut g = vec![0.0f32; tiled_len(mm)];
            pack_tiled_f32(mm, &factor_inverse(mm, &l), &mut g);
            let mut r = vec![0.0; tiled_side(mm)];
            for (k, v) in r[..mm].iter_mut().enumerate() {
                *v = ((k * 7919) % 23) as f64 - 11.3;
            }
            let (mut fast, mut slow) = (vec![0.0; r.len()], vec![0.0; r.len()]);
            apply_tiled(&g, &r, &mut fast);
            apply_tiled_scalar(&g, &r, &mut slow);
            let same = fast
                .iter()
                .zip(&slow)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "m = {mm}: {fast:?} vs {slow:?}");
        }
    }
}
