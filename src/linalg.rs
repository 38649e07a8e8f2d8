//! Small dense vector helpers shared by the modules (one home, one behaviour).

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
    use super::norm2;

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
