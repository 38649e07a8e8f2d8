//! Small dense vector helpers shared by the modules (one home, one behaviour).

/// Euclidean norm, scaled so that entries near 1e±200 neither overflow nor underflow.
///
/// Returns 0 for an all-zero (or empty) vector, and the largest |entry| itself when it is
/// not finite (∞, or NaN only if every entry is NaN: `f64::max` skips NaN).
pub fn norm2(v: &[f64]) -> f64 {
    // Scaled to survive entries near 1e±200.
    let s = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
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
pub fn norm3(a: &[f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

/// a / ‖a‖ with the scaled [`norm2`] (no guard: a zero vector gives NaN entries).
pub fn unit(a: &[f64]) -> Vec<f64> {
    let n = norm2(a);
    a.iter().map(|v| v / n).collect()
}
