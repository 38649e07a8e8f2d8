//! Hard cases for the solvers (STABILITY.md): seeded, CI-sized by default and scalable.
//!
//! Every case is an eliminated Newton system (H, g, constraints) that stresses one thing:
//! stiffness contrast, near incompressibility (neo-Hookean Hessians of a tet box), sliver
//! and needle elements, extreme time steps, heavy or total constraint, slip normals within
//! 1e-12 of an axis, nearly redundant planes, entries near 1e±30, and a prescribed
//! condition number up to 1e12. [`reference()`] gives an extended-precision solution
//! (Cholesky plus iterative refinement with double-double residuals) to measure errors
//! against when the oracle's own error κ·ε is not negligible; [`condition_number`] the
//! exact κ(Ĥ) of small cases by a dense eigen solve.

use crate::core::constraints::{Constraint, ConstraintKind, Frames};
use crate::core::elimination::{norm2, ConstrainedDiagonal, Eliminated};
use crate::core::sparse::BlockCsr;
use crate::sim::energy::{ElementSet, Law, Model, NeoHookean};
use crate::sim::mesh;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// One hard system.
#[derive(Debug, Clone)]
pub struct HardCase {
    pub name: String,
    /// What makes it hard, in a few words.
    pub what: String,
    pub h: BlockCsr,
    pub g: Vec<f64>,
    pub constraints: Vec<Constraint>,
    pub frames: Frames,
}

impl HardCase {
    /// The eliminated system (D = I).
    pub fn eliminated(&self) -> Eliminated<'_> {
        Eliminated::new(
            &self.h,
            &self.g,
            &self.frames,
            ConstrainedDiagonal::Identity,
        )
    }

    pub fn ndof(&self) -> usize {
        self.h.ndof()
    }
}

/// Size of the suite: `Ci` keeps every case at hundreds to ~2,000 DOFs (dense κ and
/// references stay cheap); `Scale(k)` multiplies the grid edge by k.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Size {
    Ci,
    Scale(usize),
}

impl Size {
    /// The size of a command-line grid scale: 0 or 1 is the CI size.
    pub fn from_scale(scale: usize) -> Size {
        if scale <= 1 {
            Size::Ci
        } else {
            Size::Scale(scale)
        }
    }

    fn k(self) -> usize {
        match self {
            Size::Ci => 1,
            Size::Scale(k) => k.max(1),
        }
    }
}

fn label(node: usize) -> String {
    format!("node {node}")
}

fn sticky(node: usize) -> Constraint {
    Constraint {
        node,
        kind: ConstraintKind::Sticky { displacement: None },
        label: label(node),
    }
}

fn plane(node: usize, normal: Vec<f64>) -> Constraint {
    Constraint {
        node,
        kind: ConstraintKind::Plane {
            normal,
            offset: 0.0,
        },
        label: label(node),
    }
}

/// A 3D grid of springs (face and Kuhn-diagonal neighbours, like a tet mesh): block
/// K = k (a aᵀ + 0.1 I) per edge along the edge direction a, plus a lumped mass per node.
/// `stiffness(i, j)` and `mass(i)` take grid coordinates.
fn spring_grid(
    n: [usize; 3],
    stiffness: impl Fn([usize; 3], [usize; 3]) -> f64,
    mass: impl Fn([usize; 3]) -> f64,
) -> (BlockCsr, Vec<[usize; 3]>) {
    let coords = crate::cases::generate::grid_coords(n);
    let offs = crate::cases::generate::stencil_offsets(3, crate::cases::generate::Stencil::Mesh);
    let edges = crate::cases::generate::grid_edges(n, offs);
    let nn = coords.len();
    let mut rows: Vec<Vec<usize>> = (0..nn).map(|i| vec![i]).collect();
    for &(i, j, _) in &edges {
        rows[i].push(j);
        rows[j].push(i);
    }
    for r in rows.iter_mut() {
        r.sort_unstable();
    }
    let mut h = BlockCsr::from_pattern(3, &rows);
    for &(i, j, o) in &edges {
        let k = stiffness(coords[i], coords[j]);
        // The offsets are 0 or 1 per axis: |o|² = o₀ + o₁ + o₂.
        let len = ((o[0] + o[1] + o[2]) as f64).sqrt();
        let dir = [o[0] as f64 / len, o[1] as f64 / len, o[2] as f64 / len];
        let mut blk = [0.0; 9];
        for r in 0..3 {
            for c in 0..3 {
                blk[r * 3 + c] = k * (dir[r] * dir[c]) + if r == c { 0.1 * k } else { 0.0 };
            }
        }
        for (p, q, sign) in [(i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)] {
            let kb = h.find(p, q).expect("pattern holds every edge");
            for (e, v) in blk.iter().enumerate() {
                h.values[kb * 9 + e] += sign * v;
            }
        }
    }
    for (i, &c) in coords.iter().enumerate() {
        let kb = h.diag_index(i).expect("diagonal present");
        let m = mass(c);
        for a in 0..3 {
            h.values[kb * 9 + a * 3 + a] += m;
        }
    }
    (h, coords)
}

fn random_vec(rng: &mut StdRng, n: usize) -> Vec<f64> {
    (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
}

fn case(
    name: &str,
    what: &str,
    h: BlockCsr,
    g: Vec<f64>,
    constraints: Vec<Constraint>,
) -> HardCase {
    let frames = Frames::build(h.dim, h.n, &constraints)
        .unwrap_or_else(|e| panic!("hard case {name}: constraints rejected: {e}"));
    HardCase {
        name: name.into(),
        what: what.into(),
        h,
        g,
        constraints,
        frames,
    }
}

/// Springs 1 on one half of a grid and `contrast` on the other; x = 0 face sticky.
pub fn stiffness_contrast(size: Size, contrast: f64) -> HardCase {
    let s = 6 * size.k();
    let (h, coords) = spring_grid(
        [s, s, s],
        |a, b| {
            if a[0] < s / 2 && b[0] < s / 2 {
                contrast
            } else {
                1.0
            }
        },
        |_| 1e-2,
    );
    let mut rng = StdRng::seed_from_u64(11);
    let g = random_vec(&mut rng, h.ndof());
    let cons = coords
        .iter()
        .enumerate()
        .filter(|(_, c)| c[0] == 0)
        .map(|(i, _)| sticky(i))
        .collect();
    case(
        &format!("contrast-{contrast:.0e}"),
        &format!("spring stiffness 1 vs {contrast:.0e} between two halves"),
        h,
        g,
        cons,
    )
}

/// Options of a neo-Hookean box Newton system.
#[derive(Debug, Clone, Copy)]
pub struct BoxSpec {
    pub size: [f64; 3],
    pub cells: [usize; 3],
    pub young: f64,
    pub poisson: f64,
    pub density: f64,
    pub time_step: f64,
}

/// H = M + h²∇²Ψ (element Hessians projected to PSD) and g = M(x − x_rest) + h²∇Ψ of a
/// neo-Hookean tet box at a twisted, perturbed configuration; the x = 0 face sticky.
pub fn neo_hookean_box(name: &str, what: &str, spec: &BoxSpec, seed: u64) -> HardCase {
    let m = mesh::cuboid(spec.size, spec.cells);
    let nh = NeoHookean::new(&m, spec.young, spec.poisson, Law::StableNeoHookean)
        .unwrap_or_else(|e| panic!("hard case {name}: {e}"));
    let mass = m.lumped_masses(spec.density);
    let model = Model::new(3, mass.clone(), None, vec![ElementSet::NeoHookean(nh)]);
    let mut rng = StdRng::seed_from_u64(seed);
    let len = spec.size[0];
    let mut x = m.x.clone();
    // Twist about the x axis by up to 0.3 rad along the bar, plus noise of 1% of the
    // smallest cell edge, so the Hessian is far from the rest state (and some elements
    // need projection).
    let hmin = (0..3)
        .map(|a| spec.size[a] / spec.cells[a] as f64)
        .fold(f64::INFINITY, f64::min);
    let cy = 0.5 * spec.size[1];
    let cz = 0.5 * spec.size[2];
    for i in 0..m.n_nodes() {
        let th = 0.3 * m.x[3 * i] / len;
        let (y, z) = (m.x[3 * i + 1] - cy, m.x[3 * i + 2] - cz);
        x[3 * i + 1] = cy + th.cos() * y - th.sin() * z;
        x[3 * i + 2] = cz + th.sin() * y + th.cos() * z;
        for a in 0..3 {
            x[3 * i + a] += 0.01 * hmin * rng.random_range(-1.0..1.0);
        }
    }
    let dt2 = spec.time_step * spec.time_step;
    let mut h = model.zero_matrix();
    model.add_mass(&mut h);
    model.add_potential_hessian(&x, dt2, true, &mut h);
    let mut g = vec![0.0; 3 * m.n_nodes()];
    for k in 0..g.len() {
        g[k] = mass[k / 3] * (x[k] - m.x[k]);
    }
    model.add_potential_gradient(&x, dt2, &mut g);
    let cons = (0..m.n_nodes())
        .filter(|&i| m.x[3 * i] <= 1e-12 * len)
        .map(sticky)
        .collect();
    case(name, what, h, g, cons)
}

fn default_box(size: Size) -> BoxSpec {
    let k = size.k();
    BoxSpec {
        size: [1.0, 0.25, 0.25],
        cells: [8 * k, 2 * k, 2 * k],
        young: 1e5,
        poisson: 0.3,
        density: 1000.0,
        time_step: 1e-2,
    }
}

/// Near-incompressible neo-Hookean (Poisson ratio ν).
pub fn incompressible(size: Size, poisson: f64) -> HardCase {
    let spec = BoxSpec {
        poisson,
        young: 1e7,
        ..default_box(size)
    };
    neo_hookean_box(
        &format!("neohookean-nu{poisson}"),
        &format!("neo-Hookean tet box, ν = {poisson}, E = 1e7, h = 1e-2"),
        &spec,
        21,
    )
}

/// Sliver tets (a plate 1e-3 thick, one cell through the thickness).
pub fn slivers(size: Size) -> HardCase {
    let k = size.k();
    let spec = BoxSpec {
        size: [1.0, 1.0, 1e-3],
        cells: [6 * k, 6 * k, 1],
        ..default_box(size)
    };
    neo_hookean_box(
        "slivers",
        "plate 1e-3 thick: flat sliver tets (aspect 1e3)",
        &spec,
        22,
    )
}

/// Needle tets (a bar 1e-3 wide, one cell across).
pub fn needles(size: Size) -> HardCase {
    let k = size.k();
    let spec = BoxSpec {
        size: [1.0, 1e-3, 1e-3],
        cells: [40 * k, 1, 1],
        ..default_box(size)
    };
    neo_hookean_box(
        "needles",
        "bar 1e-3 wide: needle tets (aspect 1e3 after 40 cells along)",
        &spec,
        23,
    )
}

/// A neo-Hookean box with time step h (mass-dominated for small h, stiffness-dominated for
/// large h).
pub fn time_step(size: Size, dt: f64) -> HardCase {
    let spec = BoxSpec {
        time_step: dt,
        ..default_box(size)
    };
    neo_hookean_box(
        &format!("dt-{dt:.0e}"),
        &format!("neo-Hookean box, ν = 0.3, time step {dt:e}"),
        &spec,
        24,
    )
}

fn base_grid(size: Size, seed: u64) -> (BlockCsr, Vec<[usize; 3]>, Vec<f64>) {
    let s = 6 * size.k();
    let (h, coords) = spring_grid([s, s, s], |_, _| 1.0, |_| 1e-1);
    let mut rng = StdRng::seed_from_u64(seed);
    let g = random_vec(&mut rng, h.ndof());
    (h, coords, g)
}

/// 90% of the nodes sticky (chosen at random), the rest free.
pub fn mostly_constrained(size: Size) -> HardCase {
    let (h, _, g) = base_grid(size, 31);
    let mut rng = StdRng::seed_from_u64(32);
    let n = h.n;
    let mut order: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    let keep_free = n.div_ceil(10);
    let cons = order[keep_free..].iter().map(|&i| sticky(i)).collect();
    case(
        "constrained-90pct",
        "90% of the nodes sticky, the free ones scattered",
        h,
        g,
        cons,
    )
}

/// Every node sticky but one.
pub fn single_free_node(size: Size) -> HardCase {
    let (h, _, g) = base_grid(size, 33);
    let free = h.n / 2;
    let cons = (0..h.n).filter(|&i| i != free).map(sticky).collect();
    case(
        "single-free-node",
        "every node sticky except one (3 free DOFs)",
        h,
        g,
        cons,
    )
}

/// Plane and line slips whose normals (directions) are within 1e-12 of ±e_x, ±e_y, ±e_z.
pub fn near_axis_normals(size: Size) -> HardCase {
    let (h, coords, g) = base_grid(size, 34);
    let mut rng = StdRng::seed_from_u64(35);
    let s = coords.iter().map(|c| c[0]).max().unwrap_or(0);
    let mut cons = Vec::new();
    for (i, c) in coords.iter().enumerate() {
        if c[0] == 0 {
            cons.push(sticky(i));
            continue;
        }
        if c[1] != 0 && c[2] != 0 && c[0] != s {
            continue;
        }
        let axis = (i / 2) % 3;
        let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        let mut nrm = vec![0.0; 3];
        nrm[axis] = sign;
        for (a, v) in nrm.iter_mut().enumerate() {
            if a != axis {
                *v += 1e-12 * rng.random_range(-1.0..1.0);
            }
        }
        let kind = if i % 5 == 0 {
            ConstraintKind::Line {
                direction: nrm,
                offset: None,
            }
        } else {
            ConstraintKind::Plane {
                normal: nrm,
                offset: 0.0,
            }
        };
        cons.push(Constraint {
            node: i,
            kind,
            label: label(i),
        });
    }
    case(
        "near-axis-normals",
        "plane/line slips within 1e-12 of ±e_x, ±e_y, ±e_z",
        h,
        g,
        cons,
    )
}

/// Two planes 1e-10 rad apart on each boundary node (numerically one plane), and on some
/// a third orthogonal plane (numerically a line).
pub fn redundant_planes(size: Size) -> HardCase {
    let (h, coords, g) = base_grid(size, 36);
    let mut rng = StdRng::seed_from_u64(37);
    let mut cons = Vec::new();
    for (i, c) in coords.iter().enumerate() {
        if c[0] == 0 {
            cons.push(sticky(i));
            continue;
        }
        if c[1] != 0 {
            continue;
        }
        let n: Vec<f64> = random_vec(&mut rng, 3);
        let nn = norm2(&n);
        let n: Vec<f64> = n.iter().map(|v| v / nn).collect();
        // A unit vector orthogonal to n, and n rotated by 1e-10 rad towards it.
        let t = crate::core::constraints::tangents(&[n[0], n[1], n[2]]).0;
        let th = 1e-10f64;
        let n2: Vec<f64> = (0..3).map(|a| th.cos() * n[a] + th.sin() * t[a]).collect();
        cons.push(plane(i, n.clone()));
        cons.push(plane(i, n2));
        if i % 3 == 0 {
            cons.push(plane(i, t.to_vec()));
        }
    }
    case(
        "redundant-planes",
        "two planes 1e-10 rad apart per boundary node (rank 1), some plus a third (rank 2)",
        h,
        g,
        cons,
    )
}

/// The base grid with a realistic constraint mix, H scaled by `sh` and g by `sg`.
pub fn scaled(size: Size, sh: f64, sg: f64) -> HardCase {
    let (mut h, coords, mut g) = base_grid(size, 38);
    for v in h.values.iter_mut() {
        *v *= sh;
    }
    for v in g.iter_mut() {
        *v *= sg;
    }
    let mut cons = Vec::new();
    for (i, c) in coords.iter().enumerate() {
        if c[0] == 0 {
            cons.push(sticky(i));
        } else if c[1] == 0 {
            cons.push(plane(i, vec![0.3, 1.0, 0.1]));
        }
    }
    case(
        &format!("scale-H{sh:.0e}-g{sg:.0e}"),
        &format!("H × {sh:.0e}, g × {sg:.0e}"),
        h,
        g,
        cons,
    )
}

/// A free-floating spring grid (no constraints) with a uniform lumped mass chosen so that
/// κ(H) = (λ_max(K) + m)/m equals `kappa` (K has the 3 translations as its null space).
/// `balanced`: g has zero net force (like internal forces), so the solution has no
/// rigid-translation part to hide the ill-conditioning behind: errors of order κ·ε in
/// the translation directions show up in the relative error.
pub fn conditioned(size: Size, kappa: f64, balanced: bool) -> HardCase {
    let s = 6 * size.k();
    let (k, _) = spring_grid([s, s, s], |_, _| 1.0, |_| 0.0);
    let lmax = largest_eigenvalue(&k);
    let m = lmax / (kappa - 1.0);
    let mut h = k;
    for i in 0..h.n {
        let kb = h.diag_index(i).expect("diagonal present");
        for a in 0..3 {
            h.values[kb * 9 + a * 3 + a] += m;
        }
    }
    let mut rng = StdRng::seed_from_u64(if balanced { 41 } else { 40 });
    let mut g = random_vec(&mut rng, h.ndof());
    if balanced {
        for a in 0..3 {
            let mean = (0..h.n).map(|i| g[3 * i + a]).sum::<f64>() / h.n as f64;
            for i in 0..h.n {
                g[3 * i + a] -= mean;
            }
        }
    }
    case(
        &format!(
            "kappa-{kappa:.0e}{}",
            if balanced { "-balanced" } else { "" }
        ),
        &format!(
            "free spring grid, mass set for κ(H) = {kappa:.0e}{}",
            if balanced { ", zero net force" } else { "" }
        ),
        h,
        g,
        Vec::new(),
    )
}

/// λ_max of a symmetric PSD block matrix by power iteration (to ~1e-6 relative).
fn largest_eigenvalue(h: &BlockCsr) -> f64 {
    let n = h.ndof();
    let mut v: Vec<f64> = (0..n)
        .map(|k| 1.0 + ((k * 7919) % 17) as f64 * 0.01)
        .collect();
    let mut w = vec![0.0; n];
    let mut lam = 0.0;
    for _ in 0..2000 {
        let nv = norm2(&v);
        v.iter_mut().for_each(|x| *x /= nv);
        h.matvec(&v, &mut w);
        let l = v.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>();
        std::mem::swap(&mut v, &mut w);
        if (l - lam).abs() <= 1e-9 * l {
            return l;
        }
        lam = l;
    }
    lam
}

/// The whole suite.
pub fn suite(size: Size) -> Vec<HardCase> {
    vec![
        stiffness_contrast(size, 1e4),
        stiffness_contrast(size, 1e8),
        incompressible(size, 0.49),
        incompressible(size, 0.499),
        slivers(size),
        needles(size),
        time_step(size, 1e-6),
        time_step(size, 1e2),
        mostly_constrained(size),
        single_free_node(size),
        near_axis_normals(size),
        redundant_planes(size),
        scaled(size, 1e30, 1e30),
        scaled(size, 1e-30, 1e-30),
        scaled(size, 1e30, 1e-30),
        conditioned(size, 1e6, false),
        conditioned(size, 1e10, false),
        conditioned(size, 1e12, false),
        conditioned(size, 1e8, true),
        conditioned(size, 1e10, true),
        conditioned(size, 1e12, true),
    ]
}

/// The case of the suite named `name`, at `size`.
pub fn named(size: Size, name: &str) -> Option<HardCase> {
    suite(size).into_iter().find(|c| c.name == name)
}

/// Extreme eigenvalues (λ_min, λ_max) of Ĥ restricted to the free components, by a dense
/// symmetric eigen solve (small cases only: O(n³)). The constrained components decouple
/// exactly (their rows and columns hold only D) and every solver returns them exactly, so
/// they take no part in the conditioning; including D = 1 next to entries near 1e±30 would
/// only measure the arbitrary choice of D.
pub fn eigen_extremes(e: &Eliminated) -> (f64, f64) {
    let a = e.assemble().to_dense();
    let d = e.h.dim;
    let free: Vec<usize> = (0..e.ndof())
        .filter(|&k| e.frames.is_free(k / d, k % d))
        .collect();
    if free.is_empty() {
        return (1.0, 1.0);
    }
    let sub = nalgebra::DMatrix::from_fn(free.len(), free.len(), |r, c| a[(free[r], free[c])]);
    let eig = nalgebra::SymmetricEigen::new(sub);
    let lo = eig
        .eigenvalues
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min);
    let hi = eig
        .eigenvalues
        .iter()
        .copied()
        .fold(f64::NEG_INFINITY, f64::max);
    (lo, hi)
}

/// κ₂ of the free block of Ĥ = λ_max/λ_min (infinite when Ĥ is not positive definite).
pub fn condition_number(e: &Eliminated) -> f64 {
    let (lo, hi) = eigen_extremes(e);
    if lo > 0.0 {
        hi / lo
    } else {
        f64::INFINITY
    }
}

/// An extended-precision reference solution.
#[derive(Debug, Clone)]
pub struct Reference {
    pub y: Vec<f64>,
    /// Refinement steps taken after the first Cholesky solve.
    pub refinements: usize,
    /// ‖last correction‖/‖y‖: the reference's own accuracy (≈ ε when trusted).
    pub last_correction: f64,
    /// Whether refinement converged (correction below 1e-14 relative).
    pub trusted: bool,
}

/// Solves the assembled Ĥ y = b̂ by sparse Cholesky, then refines with residuals in
/// double-double until the correction is below 1e-16 relative (at most 30 steps). The
/// result is the solution of the assembled f64 matrix Ĥ to about ε when κ(Ĥ)·ε ≪ 1
/// (each step gains a factor ~κε). Fails when the Cholesky does.
pub fn reference(e: &Eliminated) -> Result<Reference, crate::error::SolveError> {
    let a = e.assemble();
    let mut oracle = crate::solve::oracle::CholeskyOracle::analyze(e)?;
    let (mut y, _) = oracle.solve(e)?;
    let mut sub = e.clone();
    let mut last = f64::INFINITY;
    let mut steps = 0;
    while steps < 30 {
        let r = a.residual_dd(&e.rhs, &y);
        if norm2(&r) == 0.0 {
            last = 0.0;
            break;
        }
        sub.rhs = r;
        let (c, _) = oracle.solve(&sub)?;
        for (v, dv) in y.iter_mut().zip(&c) {
            *v += dv;
        }
        steps += 1;
        let yn = norm2(&y);
        last = if yn > 0.0 { norm2(&c) / yn } else { 0.0 };
        if last <= 1e-16 {
            break;
        }
    }
    Ok(Reference {
        y,
        refinements: steps,
        last_correction: last,
        trusted: last <= 1e-14,
    })
}

pub use crate::core::linalg::relative_error;

/// One row of the `stickslip bench --hard` table.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TableRow {
    pub case: String,
    pub dofs: usize,
    /// κ of the free block of Ĥ (dense eigen solve; None when too large for it).
    pub kappa: Option<f64>,
    pub solver: String,
    pub tol: f64,
    /// Whether the solver reported success.
    pub claimed: bool,
    /// Relative error against the reference (of the iterate reached, also on failure
    /// where the solver returns one; None otherwise).
    pub error: Option<f64>,
    pub iterations: Option<usize>,
    pub seconds: f64,
    pub note: String,
}

/// Runs every solver on every case of `suite(size)` and returns the rows. GPU rows need
/// `gpu` (a context); κ is computed for cases with at most `dense_max` free DOFs.
pub fn table(
    size: Size,
    gpu: Option<&crate::gpu::GpuContext>,
    dense_max: usize,
) -> Result<Vec<TableRow>, String> {
    use crate::gpu::{GpuParams, Precision};
    use crate::solve::cg::{CgParams, Preconditioner, Scaling};
    use crate::solve::coarse::CoarseSpace;
    use crate::{SolveDetails, SolverConfig, Step};
    use std::time::Instant;
    let mut rows = Vec::new();
    for case in suite(size) {
        let e = case.eliminated();
        let kappa = (case.frames.free_dofs() <= dense_max).then(|| condition_number(&e));
        let r = reference(&e).map_err(|err| format!("{}: reference: {err}", case.name))?;
        let row = |solver: &str,
                   tol: f64,
                   claimed: bool,
                   y: Option<&[f64]>,
                   it: Option<usize>,
                   s: f64,
                   note: String| TableRow {
            case: case.name.clone(),
            dofs: case.ndof(),
            kappa,
            solver: solver.into(),
            tol,
            claimed,
            error: y.map(|y| relative_error(y, &r.y)),
            iterations: it,
            seconds: s,
            note,
        };
        let t = Instant::now();
        match solve_once(SolverConfig::cholesky(), &e) {
            Ok(Step { y, .. }) => rows.push(row(
                "cholesky",
                0.0,
                true,
                Some(&y),
                None,
                t.elapsed().as_secs_f64(),
                String::new(),
            )),
            Err(err) => rows.push(row(
                "cholesky",
                0.0,
                false,
                None,
                None,
                t.elapsed().as_secs_f64(),
                err.to_string(),
            )),
        }
        // Default coarse correction (aggregates) unless the name says otherwise.
        for (name, pc, scaling, coarse) in [
            (
                "cg jacobi",
                Preconditioner::Jacobi,
                Scaling::None,
                CoarseSpace::Aggregates,
            ),
            (
                "cg jacobi translations",
                Preconditioner::Jacobi,
                Scaling::None,
                CoarseSpace::Translations,
            ),
            (
                "cg jacobi no coarse",
                Preconditioner::Jacobi,
                Scaling::None,
                CoarseSpace::None,
            ),
            (
                "cg block-jacobi",
                Preconditioner::BlockJacobi,
                Scaling::None,
                CoarseSpace::Aggregates,
            ),
            (
                "cg none",
                Preconditioner::None,
                Scaling::None,
                CoarseSpace::Aggregates,
            ),
            (
                "cg none+scaling",
                Preconditioner::None,
                Scaling::NodeDiagonal,
                CoarseSpace::Aggregates,
            ),
        ] {
            let tol = 1e-10;
            let params = CgParams {
                tol,
                max_iters: 20_000,
                preconditioner: pc,
                scaling,
                coarse,
                ..Default::default()
            };
            let t = Instant::now();
            match solve_once(SolverConfig::cg().cg_params(params), &e) {
                Ok(Step { y, stats, .. }) => rows.push(row(
                    name,
                    tol,
                    true,
                    Some(&y),
                    stats.iterations,
                    t.elapsed().as_secs_f64(),
                    match stats.details {
                        SolveDetails::Cg(info) => info
                            .condition_estimate
                            .map_or(String::new(), |k| format!("κ̃(M⁻¹Ĥ) {k:.1e}")),
                        _ => String::new(),
                    },
                )),
                Err(err) => rows.push(row(
                    name,
                    tol,
                    false,
                    None,
                    None,
                    t.elapsed().as_secs_f64(),
                    err.to_string(),
                )),
            }
        }
        let Some(ctx) = gpu else { continue };
        for (precision, tol, error_tol, coarse) in [
            (Precision::F32, 1e-5, None, CoarseSpace::Aggregates),
            (Precision::F64, 1e-10, None, CoarseSpace::Aggregates),
            (Precision::Mixed, 1e-10, None, CoarseSpace::Aggregates),
            (Precision::Mixed, 1e-10, None, CoarseSpace::Translations),
            (Precision::Mixed, 1e-10, None, CoarseSpace::None),
            (
                Precision::Mixed,
                1e-10,
                Some(1e-10),
                CoarseSpace::Aggregates,
            ),
        ] {
            let params = GpuParams {
                precision,
                tol,
                max_iters: 20_000,
                error_tol,
                coarse,
                ..Default::default()
            };
            let suffix = match coarse {
                CoarseSpace::None => " no coarse",
                CoarseSpace::Translations => " translations",
                CoarseSpace::Aggregates => "",
            };
            let name = match error_tol {
                Some(et) => format!("gpu {precision} error_tol {et:.0e}{suffix}"),
                None => format!("gpu {precision}{suffix}"),
            };
            let t = Instant::now();
            let config = SolverConfig::gpu(precision)
                .gpu_params(params)
                .gpu_context(ctx.clone());
            let res = solve_once(config, &e).and_then(|step| match step.stats.details {
                SolveDetails::Gpu(info) => Ok((step.y, *info)),
                _ => Err(crate::Error::Gpu(crate::gpu::GpuError::Internal(
                    "not a GPU solve".into(),
                ))),
            });
            match res {
                Ok((y, info)) => rows.push(row(
                    &name,
                    tol,
                    true,
                    Some(&y),
                    Some(info.iterations),
                    info.seconds.solve,
                    info.error_estimate
                        .map(|est| format!("error estimate {est:.1e}"))
                        .into_iter()
                        .chain(info.fallback.map(|f| format!("fell back to f64: {f}")))
                        .chain(info.notes.into_iter().filter(|n| n.starts_with("mixed: Ĥ")))
                        .collect::<Vec<_>>()
                        .join("; "),
                )),
                Err(err) => rows.push(row(
                    &name,
                    tol,
                    false,
                    None,
                    None,
                    t.elapsed().as_secs_f64(),
                    err.to_string(),
                )),
            }
        }
    }
    Ok(rows)
}

/// One solve of `e` with a fresh solver of `config`.
fn solve_once(config: crate::SolverConfig, e: &Eliminated) -> Result<crate::Step, crate::Error> {
    crate::Solver::new(config)?.solve_eliminated(crate::LayoutKey::fresh(), e)
}

/// The rows as a Markdown table.
pub fn table_markdown(rows: &[TableRow]) -> String {
    let mut s = String::from(
        "| case | DOFs | κ(Ĥ_free) | solver | tol | claimed | rel. error | iterations | seconds | note |\n|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let note: String = r.note.replace('|', "/").chars().take(90).collect();
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {:.4} | {} |\n",
            r.case,
            r.dofs,
            r.kappa.map_or("—".into(), |k| format!("{k:.1e}")),
            r.solver,
            if r.tol == 0.0 {
                "—".into()
            } else {
                format!("{:.0e}", r.tol)
            },
            if r.claimed { "yes" } else { "**no**" },
            r.error.map_or("—".into(), |e| format!("{e:.1e}")),
            r.iterations.map_or("—".into(), |i| i.to_string()),
            r.seconds,
            note
        ));
    }
    s
}

/// Timed solves per solver in [`mixed_speed`] (after one warm-up solve).
pub const SPEED_REPS: usize = 5;

/// One case of [`mixed_speed`]: best solve seconds, iterations and relative error of GPU
/// f64 CG and of mixed precision (None for a failed solve).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SpeedRow {
    pub case: String,
    pub dofs: usize,
    /// The coarse correction both solvers used.
    pub coarse: String,
    pub f64_seconds: Option<f64>,
    pub mixed_seconds: Option<f64>,
    pub f64_iterations: Option<usize>,
    pub mixed_iterations: Option<usize>,
    pub f64_error: Option<f64>,
    pub mixed_error: Option<f64>,
    /// Why mixed left f32, when it did.
    pub mixed_fallback: Option<String>,
}

/// GPU f64 CG against mixed precision on larger cases, both Jacobi with the coarse
/// correction `coarse`, at tolerance `tol`, best of [`SPEED_REPS`] after a warm-up. The
/// cantilever cases (`neohookean-nu0.49`, `dt-1e2`) run at `size`, and with
/// `cantilevers_twice` at twice its scale too. `progress` sees each row when it is done.
pub fn mixed_speed(
    size: Size,
    ctx: &crate::gpu::GpuContext,
    tol: f64,
    coarse: crate::solve::coarse::CoarseSpace,
    cantilevers_twice: bool,
    progress: &mut dyn FnMut(&SpeedRow),
) -> Result<Vec<SpeedRow>, String> {
    use crate::gpu::{GpuParams, Precision};
    use crate::{LayoutKey, SolveDetails, Solver, SolverConfig};
    // The two cantilever cases have a sixth of the others' DOFs at one grid scale, so they
    // run at twice the scale too: every case then has an instance of 81k–107k DOFs at
    // scale 5 ("the larger cases"), and the smaller ones show where mixed stops paying.
    let twice = Size::Scale(2 * size.k());
    let mut cases = vec![stiffness_contrast(size, 1e4), incompressible(size, 0.49)];
    if cantilevers_twice {
        cases.push(incompressible(twice, 0.49));
    }
    cases.push(time_step(size, 1e2));
    if cantilevers_twice {
        cases.push(time_step(twice, 1e2));
    }
    cases.extend([
        near_axis_normals(size),
        conditioned(size, 1e6, false),
        conditioned(size, 1e8, true),
    ]);
    let mut out = Vec::new();
    for case in cases {
        let e = case.eliminated();
        let r = reference(&e).map_err(|err| format!("{}: reference: {err}", case.name))?;
        // (best seconds, iterations, error, fallback) per solver.
        type Best = Option<(f64, usize, f64, Option<String>)>;
        let mut res: [Best; 2] = [None, None];
        // Both solvers built first, then solved alternately, best of SPEED_REPS after one
        // warm-up solve each: the ratio of one run on a shared 2-core machine is noise.
        let layout = LayoutKey::fresh();
        let mut solvers: Vec<Option<Solver>> = [Precision::F64, Precision::Mixed]
            .into_iter()
            .map(|precision| {
                let params = GpuParams {
                    precision,
                    tol,
                    max_iters: 50_000,
                    coarse,
                    ..Default::default()
                };
                let config = SolverConfig::gpu(precision)
                    .gpu_params(params)
                    .gpu_context(ctx.clone());
                // The warm-up solve (rep 0) builds the device buffers; later reps reuse them.
                Solver::new(config).ok()
            })
            .collect();
        for rep in 0..=SPEED_REPS {
            for (k, sol) in solvers.iter_mut().enumerate() {
                let Some(sol) = sol else { continue };
                let solved =
                    sol.solve_eliminated(layout, &e)
                        .map(|step| match step.stats.details {
                            SolveDetails::Gpu(info) => Some((step.y, *info)),
                            _ => None,
                        });
                if let Ok(Some((y, info))) = solved {
                    if rep > 0 {
                        let best = res[k]
                            .as_ref()
                            .map_or(info.seconds.solve, |b| b.0.min(info.seconds.solve));
                        res[k] = Some((
                            best,
                            info.iterations,
                            relative_error(&y, &r.y),
                            info.fallback.clone(),
                        ));
                    }
                }
            }
        }
        let [a, b] = res;
        out.push(SpeedRow {
            case: case.name.clone(),
            dofs: case.ndof(),
            coarse: coarse.name().into(),
            f64_seconds: a.as_ref().map(|v| v.0),
            mixed_seconds: b.as_ref().map(|v| v.0),
            f64_iterations: a.as_ref().map(|v| v.1),
            mixed_iterations: b.as_ref().map(|v| v.1),
            f64_error: a.as_ref().map(|v| v.2),
            mixed_error: b.as_ref().map(|v| v.2),
            mixed_fallback: b.and_then(|v| v.3),
        });
        if let Some(row) = out.last() {
            progress(row);
        }
    }
    Ok(out)
}
