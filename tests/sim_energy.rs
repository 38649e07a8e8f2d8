//! Finite-difference checks of the energies' gradients and Hessians, and PSD projection.

use stickslip::sim::energy::{ElementSet, Law, Model, NeoHookean, Springs};
use stickslip::sim::mesh;

/// Deterministic pseudo-random perturbation in [-amp, amp].
fn perturb(x: &mut [f64], amp: f64, seed: u64) {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    for v in x.iter_mut() {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let u = ((s >> 11) as f64) / ((1u64 << 53) as f64);
        *v += amp * (2.0 * u - 1.0);
    }
}

fn models() -> Vec<(&'static str, Model, Vec<f64>)> {
    let mut out = Vec::new();
    let r = mesh::rectangle(2, [1.0, 0.5], [3, 2]);
    let nh2 = NeoHookean::new(&r, 1e4, 0.4, Law::StableNeoHookean).expect("valid mesh");
    let sp2 = Springs::new(2, &r.x, r.edges(), 50.0).expect("valid mesh");
    let m2 = r.lumped_masses(100.0);
    let mut x2 = r.x.clone();
    perturb(&mut x2, 0.08, 1);
    out.push((
        "2D neo-Hookean + springs + gravity",
        Model::new(
            2,
            m2,
            Some(vec![0.0, -9.81]),
            vec![ElementSet::NeoHookean(nh2), ElementSet::Springs(sp2)],
        ),
        x2,
    ));
    let b = mesh::cuboid([1.0, 0.6, 0.4], [2, 2, 1]);
    let nh3 = NeoHookean::new(&b, 1e4, 0.3, Law::StableNeoHookean).expect("valid mesh");
    let sp3 = Springs::new(3, &b.x, b.edges(), 30.0).expect("valid mesh");
    let m3 = b.lumped_masses(100.0);
    let mut x3 = b.x.clone();
    perturb(&mut x3, 0.06, 2);
    out.push((
        "3D neo-Hookean + springs + gravity",
        Model::new(
            3,
            m3,
            Some(vec![0.0, -9.81, 1.0]),
            vec![ElementSet::NeoHookean(nh3), ElementSet::Springs(sp3)],
        ),
        x3,
    ));
    // The classical law (defined for J > 0): the same meshes, perturbed less, and a
    // strongly compressed (not inverted) box.
    for (d, law_mesh, amp, squeeze) in [
        (2, mesh::rectangle(2, [1.0, 0.5], [3, 2]), 0.03, 1.0),
        (3, mesh::cuboid([1.0, 0.6, 0.4], [2, 2, 1]), 0.03, 1.0),
        (3, mesh::cuboid([1.0, 1.0, 1.0], [1, 1, 1]), 0.02, 0.3),
    ] {
        let nh = NeoHookean::new(&law_mesh, 1e4, 0.4, Law::NeoHookean).expect("valid mesh");
        let m = law_mesh.lumped_masses(100.0);
        let mut x: Vec<f64> = law_mesh.x.iter().map(|v| squeeze * v).collect();
        perturb(&mut x, amp, 10 + d as u64);
        let model = Model::new(d, m, None, vec![ElementSet::NeoHookean(nh)]);
        let j = model.min_volume_ratio(&x)[0].j;
        assert!(
            j > 0.0,
            "the classical law's test state is not inverted: {j}"
        );
        out.push((
            if squeeze < 1.0 {
                "3D classical neo-Hookean, compressed"
            } else if d == 2 {
                "2D classical neo-Hookean"
            } else {
                "3D classical neo-Hookean"
            },
            model,
            x,
        ));
    }
    // A compressed, partly inverted state exercises the indefinite branch.
    let t = mesh::cuboid([1.0, 1.0, 1.0], [1, 1, 1]);
    let nh = NeoHookean::new(&t, 1e3, 0.45, Law::StableNeoHookean).expect("valid mesh");
    let m = t.lumped_masses(1.0);
    let mut xt: Vec<f64> = t.x.iter().map(|v| 0.4 * v).collect();
    perturb(&mut xt, 0.3, 3);
    out.push((
        "3D neo-Hookean, compressed/inverted",
        Model::new(3, m, None, vec![ElementSet::NeoHookean(nh)]),
        xt,
    ));
    out
}

#[test]
fn gradients_match_finite_differences() {
    for (name, model, x) in models() {
        let n = x.len();
        let mut g = vec![0.0; n];
        model.add_potential_gradient(&x, 1.0, &mut g);
        let eps = 1e-6;
        let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for k in 0..n {
            let mut xp = x.clone();
            let mut xm = x.clone();
            xp[k] += eps;
            xm[k] -= eps;
            let fd = (model.potential(&xp) - model.potential(&xm)) / (2.0 * eps);
            assert!(
                (fd - g[k]).abs() <= 1e-6 * scale.max(1.0),
                "{name}: dof {k}: analytic {} vs fd {fd}",
                g[k]
            );
        }
    }
}

#[test]
fn hessians_match_finite_differences_and_projection_is_psd() {
    for (name, model, x) in models() {
        let n = x.len();
        let mut h = model.zero_matrix();
        model.add_potential_hessian(&x, 1.0, false, &mut h);
        let hd = h.to_dense();
        let eps = 1e-6;
        let scale = hd.amax();
        for k in 0..n {
            let mut xp = x.clone();
            let mut xm = x.clone();
            xp[k] += eps;
            xm[k] -= eps;
            let mut gp = vec![0.0; n];
            let mut gm = vec![0.0; n];
            model.add_potential_gradient(&xp, 1.0, &mut gp);
            model.add_potential_gradient(&xm, 1.0, &mut gm);
            for r in 0..n {
                let fd = (gp[r] - gm[r]) / (2.0 * eps);
                assert!(
                    (fd - hd[(r, k)]).abs() <= 1e-6 * scale,
                    "{name}: H({r},{k}) analytic {} vs fd {fd}",
                    hd[(r, k)]
                );
            }
        }
        assert!(h.check_symmetric().is_ok(), "{name}: not symmetric");
        // Projected: PSD, and symmetric.
        let mut hp = model.zero_matrix();
        model.add_potential_hessian(&x, 1.0, true, &mut hp);
        let eig = nalgebra::SymmetricEigen::new(hp.to_dense());
        let min = eig.eigenvalues.min();
        assert!(
            min >= -1e-10 * scale,
            "{name}: projected Hessian has eigenvalue {min}"
        );
    }
}

#[test]
fn rest_state_is_stress_free_and_rigid_motions_cost_nothing() {
    for law in [Law::NeoHookean, Law::StableNeoHookean] {
        rest_state_is_stress_free_for(law);
    }
}

fn rest_state_is_stress_free_for(law: Law) {
    let b = mesh::cuboid([1.0, 0.5, 0.5], [2, 1, 1]);
    let nh = NeoHookean::new(&b, 1e5, 0.3, law).expect("valid mesh");
    let model = Model::new(
        3,
        b.lumped_masses(1.0),
        None,
        vec![ElementSet::NeoHookean(nh)],
    );
    let mut g = vec![0.0; b.x.len()];
    model.add_potential_gradient(&b.x, 1.0, &mut g);
    assert!(g.iter().all(|v| v.abs() < 1e-9), "rest gradient {g:?}");
    assert!(model.elastic_energy(&b.x).abs() < 1e-9);
    // Rotate by 40° about z and translate: energy stays zero.
    let (s, c) = (40f64.to_radians().sin(), 40f64.to_radians().cos());
    let xr: Vec<f64> =
        b.x.chunks(3)
            .flat_map(|p| {
                [
                    c * p[0] - s * p[1] + 1.0,
                    s * p[0] + c * p[1] - 2.0,
                    p[2] + 0.5,
                ]
            })
            .collect();
    assert!(model.elastic_energy(&xr).abs() < 1e-8);
}

#[test]
fn small_strain_matches_linear_elasticity() {
    // Uniaxial stretch ε with lateral faces free is not a homogeneous state we can impose
    // on the energy directly; instead check the Lamé remap: Ψ(I + εS) ≈ μ_L ε²|S|² + λ_L/2 ε² tr(S)².
    let (e, nu) = (2e5, 0.3);
    let (mu_l, la_l) = stickslip::sim::energy::neohookean::lame(e, nu);
    let t = mesh::cuboid([1.0, 1.0, 1.0], [1, 1, 1]);
    for law in [Law::NeoHookean, Law::StableNeoHookean] {
        let nh = NeoHookean::new(&t, e, nu, law).expect("valid mesh");
        small_strain_for(&nh, mu_l, la_l);
    }
}

/// Ψ(I + εS) against linear elasticity with the Lamé parameters (μ_L, λ_L).
fn small_strain_for(nh: &NeoHookean, mu_l: f64, la_l: f64) {
    let eps = 1e-5;
    let s = [1.0, 0.3, 0.0, 0.3, -0.5, 0.2, 0.0, 0.2, 0.7];
    let f: Vec<f64> = (0..9)
        .map(|k| if k % 4 == 0 { 1.0 } else { 0.0 } + eps * s[k])
        .collect();
    let tr: f64 = s[0] + s[4] + s[8];
    let ss: f64 = s.iter().map(|v| v * v).sum();
    let lin = mu_l * eps * eps * ss + 0.5 * la_l * eps * eps * tr * tr;
    let psi = nh.density(&f);
    assert!(
        (psi - lin).abs() <= 1e-3 * lin,
        "{}: Ψ = {psi}, linear {lin}",
        nh.law.name()
    );
}
