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
        for r in k + 1..m {
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

/// (L Lᵀ)⁺ for a factor from [`cholesky_dropping`]: X = L⁺ (a dropped pivot's row zero),
/// then XᵀX, m×m symmetric row-major.
pub fn inverse_from_factor(m: usize, l: &[f64]) -> Vec<f64> {
    let mut x = vec![0.0; m * m];
    for k in 0..m {
        let piv = l[k * m + k];
        if piv == 0.0 {
            continue;
        }
        for j in 0..=k {
            let mut v = if j == k { 1.0 } else { 0.0 };
            for s in j..k {
                v -= l[k * m + s] * x[s * m + j];
            }
            x[k * m + j] = v / piv;
        }
    }
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

/// The first d² values of a block, in a 9-array.
pub(super) fn block9(d: usize, b: &[f64]) -> [f64; 9] {
    let mut o = [0.0; 9];
    o[..d * d].copy_from_slice(&b[..d * d]);
    o
}
