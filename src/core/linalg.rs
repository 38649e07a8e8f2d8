//! Small dense vector helpers shared by the modules (one home, one behaviour).

/// 2^round(e), e clamped to ±1000: a scale factor whose products are exact (short of
/// over- or underflow), for the power-of-two scalings of the solvers.
pub fn power_of_two(e: f64) -> f64 {
    e.round().clamp(-1000.0, 1000.0).exp2()
}

/// Euclidean norm, scaled so that entries near 1e±200 neither overflow nor underflow.
///
/// Returns 0 for an all-zero (or empty) vector, NaN when any entry is NaN (a residual
/// with a NaN in it must never look small), and ∞ when an entry is infinite.
pub fn norm2(v: &[f64]) -> f64 {
    let mut s = 0.0f64;
    for x in v {
        if x.is_nan() {
            return f64::NAN;
        }
        s = s.max(x.abs());
    }
    if s == 0.0 || !s.is_finite() {
        return s;
    }
    s * v.iter().map(|x| (x / s) * (x / s)).sum::<f64>().sqrt()
}

/// Plain dot product Σ aₖbₖ (over the shorter of the two).
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// ‖a − b‖/‖b‖ with the scaled [`norm2`]: 0 when both vanish, ∞ when only b does (no
/// relative size is small against a zero reference), NaN when either holds a NaN.
pub fn relative_error(a: &[f64], b: &[f64]) -> f64 {
    let diff: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    let dn = norm2(&diff);
    let bn = norm2(b);
    if bn == 0.0 {
        if dn == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    } else {
        dn / bn
    }
}

/// a × b.
pub fn cross3(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Unscaled Euclidean norm of a 3-vector, √(a₀² + a₁² + a₂²).
#[cfg(feature = "sim")]
pub fn norm3(a: &[f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

/// a / ‖a‖ with the scaled [`norm2`] (no guard: a zero vector gives NaN entries).
pub fn unit(a: &[f64]) -> Vec<f64> {
    let n = norm2(a);
    a.iter().map(|v| v / n).collect()
}

#[cfg(test)]
mod tests {
    use super::{norm2, relative_error};

    #[test]
    fn relative_error_against_zero_and_nan_references() {
        assert_eq!(relative_error(&[1.0, 2.0], &[1.0, 2.0]), 0.0);
        assert_eq!(relative_error(&[0.0; 3], &[0.0; 3]), 0.0);
        assert_eq!(relative_error(&[1e-300, 0.0], &[0.0, 0.0]), f64::INFINITY);
        assert!(relative_error(&[f64::NAN], &[1.0]).is_nan());
        // Entries near 1e200 square past f64's range; the scaled norms do not. The
        // difference is exact here, so only the two norms and the quotient round.
        let b = [3e200, 4e200];
        let a = [3e200 * 1.5, 4e200 * 1.5];
        assert!((relative_error(&a, &b) - 0.5).abs() <= 4.0 * f64::EPSILON);
    }

    #[test]
    fn norm2_propagates_nan_and_survives_extreme_scales() {
        assert!(norm2(&[1.0, f64::NAN, 2.0]).is_nan());
        assert!(norm2(&[f64::NAN; 4]).is_nan());
        assert_eq!(norm2(&[1.0, f64::INFINITY]), f64::INFINITY);
        assert_eq!(norm2(&[]), 0.0);
        // A handful of roundings (scale, square, sum, root, rescale): 8 ulps.
        for sc in [1e200, 1e-200] {
            let n = norm2(&[3.0 * sc, 4.0 * sc]);
            assert!((n / (5.0 * sc) - 1.0).abs() <= 8.0 * f64::EPSILON, "{n:e}");
        }
    }
}
