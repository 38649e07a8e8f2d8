//! Inertia ½ (x − x̃)ᵀ M (x − x̃) with a lumped (diagonal, per-node) mass.

pub fn energy(mass: &[f64], dim: usize, x: &[f64], x_tilde: &[f64]) -> f64 {
    let mut e = 0.0;
    for (k, (a, b)) in x.iter().zip(x_tilde).enumerate() {
        e += 0.5 * mass[k / dim] * (a - b) * (a - b);
    }
    e
}

pub fn add_gradient(mass: &[f64], dim: usize, x: &[f64], x_tilde: &[f64], g: &mut [f64]) {
    for k in 0..x.len() {
        g[k] += mass[k / dim] * (x[k] - x_tilde[k]);
    }
}
