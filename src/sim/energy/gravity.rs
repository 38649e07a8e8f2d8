//! Gravity Ψ_g = −Σ m_i g·x_i (linear: constant gradient, no Hessian).

pub fn energy(mass: &[f64], dim: usize, g: &[f64], x: &[f64]) -> f64 {
    -x.iter()
        .enumerate()
        .map(|(k, xk)| mass[k / dim] * g[k % dim] * xk)
        .sum::<f64>()
}

pub fn add_gradient(mass: &[f64], dim: usize, g: &[f64], scale: f64, out: &mut [f64]) {
    for (k, o) in out.iter_mut().enumerate() {
        *o -= scale * mass[k / dim] * g[k % dim];
    }
}
