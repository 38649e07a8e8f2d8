//! Seeded random Newton systems with mesh-like block sparsity, for tests, `stickslip
//! generate` and the benchmark.
//!
//! Nodes sit on a grid; each node couples to its grid neighbours (2D: 8-neighbourhood,
//! like a triangle mesh; 3D: the 14 neighbours of a Freudenthal tetrahedral mesh, or the
//! 6 face neighbours). H = M + Σ_edges [K −K; −K K] with random positive semi-definite
//! 2×2/3×3 spring blocks K and a lumped mass M, so H is SPD, like an incremental-potential
//! Hessian (mass + stiffness).

use crate::core::constraints::{Constraint, ConstraintKind, Frames};
use crate::core::sparse::BlockCsr;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Which constraints to put on the nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConstraintMix {
    /// Every kind mixed at random over the nodes, including combinations, redundant rows,
    /// normals within 1e-8 of e_x, axis-aligned slips and prescribed values.
    Random,
    /// A simulation-like set: the x = 0 face sticky, the x = max face prescribed (moved
    /// by a small displacement), the y = 0 face on a tilted plane slip, a few line slips.
    Realistic,
    /// No constraints.
    None,
}

/// Neighbourhood of a node on the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stencil {
    /// 2D: 4 neighbours; 3D: 6.
    Face,
    /// 2D: 8 neighbours (triangle-mesh-like); 3D: 14 (tetrahedral-mesh-like).
    Mesh,
}

#[derive(Debug, Clone, PartialEq)]
pub struct SystemSpec {
    pub dim: usize,
    /// Grid size per axis (the z entry is ignored in 2D).
    pub grid: [usize; 3],
    pub seed: u64,
    pub mix: ConstraintMix,
    pub stencil: Stencil,
    /// Lumped mass per node relative to the spring stiffness (smaller: harder to solve).
    pub mass: f64,
    /// Whether prescribed values (non-homogeneous constraints) appear.
    pub prescribed: bool,
}

impl SystemSpec {
    /// A small random system (tens of nodes) for exhaustive tests.
    pub fn small(dim: usize, seed: u64) -> Self {
        let mut rng = StdRng::seed_from_u64(seed ^ 0x5eed);
        let g = if dim == 2 {
            [rng.random_range(3..8), rng.random_range(3..8), 1]
        } else {
            [
                rng.random_range(2..5),
                rng.random_range(2..5),
                rng.random_range(2..4),
            ]
        };
        SystemSpec {
            dim,
            grid: g,
            seed,
            mix: ConstraintMix::Random,
            stencil: Stencil::Mesh,
            mass: 0.1,
            prescribed: seed % 2 == 0,
        }
    }

    /// A grid with about `nodes` nodes and the realistic constraint mix.
    pub fn with_nodes(dim: usize, nodes: usize, seed: u64) -> Self {
        let grid = if dim == 2 {
            let s = (nodes as f64).sqrt().round().max(2.0) as usize;
            [s, s, 1]
        } else {
            let s = (nodes as f64).cbrt().round().max(2.0) as usize;
            [s, s, s]
        };
        SystemSpec {
            dim,
            grid,
            seed,
            mix: ConstraintMix::Realistic,
            stencil: Stencil::Mesh,
            mass: 0.01,
            prescribed: true,
        }
    }

    pub fn n_nodes(&self) -> usize {
        if self.dim == 2 {
            self.grid[0] * self.grid[1]
        } else {
            self.grid[0] * self.grid[1] * self.grid[2]
        }
    }
}

/// A generated system: H, g, the constraints and their frames.
#[derive(Debug, Clone)]
pub struct GeneratedSystem {
    pub h: BlockCsr,
    pub g: Vec<f64>,
    pub constraints: Vec<Constraint>,
    pub frames: Frames,
    /// Grid coordinates of each node (d per node), for scenes and plots.
    pub coords: Vec<[usize; 3]>,
}

/// Half of a grid node's neighbourhood (the other half is the mirror image), as offsets
/// in grid coordinates. 3D `Mesh`: the Kuhn (Freudenthal) tetrahedral mesh's 14
/// neighbours, the main diagonal (1, 1, 1) among them.
pub(crate) fn stencil_offsets(dim: usize, stencil: Stencil) -> &'static [[i64; 3]] {
    match (dim, stencil) {
        (2, Stencil::Face) => &[[1, 0, 0], [0, 1, 0]],
        (2, Stencil::Mesh) => &[[1, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0]],
        (_, Stencil::Face) => &[[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        (_, Stencil::Mesh) => &[
            [1, 0, 0],
            [0, 1, 0],
            [0, 0, 1],
            [1, 1, 0],
            [0, 1, 1],
            [1, 0, 1],
            [1, 1, 1],
        ],
    }
}

/// The nodes of a grid of `grid` nodes per axis (1 along z in 2D) in id order, x fastest:
/// node (x, y, z) has id x + g₀(y + g₁z).
pub(crate) fn grid_coords(grid: [usize; 3]) -> Vec<[usize; 3]> {
    let mut coords = Vec::with_capacity(grid.iter().product());
    for z in 0..grid[2] {
        for y in 0..grid[1] {
            for x in 0..grid[0] {
                coords.push([x, y, z]);
            }
        }
    }
    coords
}

/// The edges of a grid: for each node in id order and each offset in `offs`, the node, the
/// neighbour at that offset and the offset, where the neighbour is inside the grid.
pub(crate) fn grid_edges(grid: [usize; 3], offs: &[[i64; 3]]) -> Vec<(usize, usize, [i64; 3])> {
    let id = |c: [i64; 3]| -> Option<usize> {
        let inside = (0..3).all(|a| c[a] >= 0 && (c[a] as usize) < grid[a]);
        inside.then(|| c[0] as usize + grid[0] * (c[1] as usize + grid[1] * c[2] as usize))
    };
    let mut edges = Vec::new();
    for (i, c) in grid_coords(grid).into_iter().enumerate() {
        for o in offs {
            let m = [c[0] as i64 + o[0], c[1] as i64 + o[1], c[2] as i64 + o[2]];
            if let Some(j) = id(m) {
                edges.push((i, j, *o));
            }
        }
    }
    edges
}

/// Builds the system described by `spec`.
pub fn random_system(spec: &SystemSpec) -> GeneratedSystem {
    let dim = spec.dim;
    let mut rng = StdRng::seed_from_u64(spec.seed);
    let n = spec.n_nodes();
    let gz = if dim == 2 { 1 } else { spec.grid[2] };
    let grid = [spec.grid[0], spec.grid[1], gz];
    let coords = grid_coords(grid);
    let edges: Vec<(usize, usize)> = grid_edges(grid, stencil_offsets(dim, spec.stencil))
        .into_iter()
        .map(|(i, j, _)| (i.min(j), i.max(j)))
        .collect();
    // Pattern.
    let mut rows: Vec<Vec<usize>> = (0..n).map(|i| vec![i]).collect();
    for &(i, j) in &edges {
        rows[i].push(j);
        rows[j].push(i);
    }
    for r in rows.iter_mut() {
        r.sort_unstable();
    }
    let mut h = BlockCsr::from_pattern(dim, &rows);
    let d = dim;
    // Springs: K = s·a aᵀ + ε·s·I (PSD, like a projected spring Hessian).
    for &(i, j) in &edges {
        let s: f64 = rng.random_range(0.5..2.0);
        let a: Vec<f64> = (0..d).map(|_| rng.random_range(-1.0..1.0)).collect();
        let an = a.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-3);
        let mut k = [0.0f64; 9];
        for r in 0..d {
            for c in 0..d {
                // s·(a_r a_c) keeps the block exactly symmetric (same product order for (r,c), (c,r)).
                k[r * d + c] = s * (a[r] * a[c]) / (an * an) + if r == c { 0.1 * s } else { 0.0 };
            }
        }
        for (p, q, sign) in [(i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)] {
            let kb = h.find(p, q).expect("pattern holds every edge");
            for (hv, kv) in h.values[kb * d * d..(kb + 1) * d * d].iter_mut().zip(&k) {
                *hv += sign * kv;
            }
        }
    }
    for i in 0..n {
        let m = spec.mass * rng.random_range(0.5..1.5);
        let kb = h.diag_index(i).expect("diagonal present");
        for a in 0..d {
            h.values[kb * d * d + a * d + a] += m;
        }
    }
    let g: Vec<f64> = (0..n * d).map(|_| rng.random_range(-1.0..1.0)).collect();
    let constraints = match spec.mix {
        ConstraintMix::Random => random_constraints(spec, &mut rng, n),
        ConstraintMix::Realistic => realistic_constraints(spec, &coords, &mut rng),
        ConstraintMix::None => Vec::new(),
    };
    let frames = Frames::build(dim, n, &constraints).expect("generated constraints are valid");
    GeneratedSystem {
        h,
        g,
        constraints,
        frames,
        coords,
    }
}

/// A small dense SPD system with a prescribed spectrum: H = Q Λ Qᵀ on `nodes` nodes of
/// dimension `dim` (every block present), Λ log-spaced over [1, κ], Q a seeded random
/// orthogonal matrix, no constraints. Its eigenvectors are spread over every DOF, so the
/// Jacobi preconditioner leaves the conditioning about where it is: a test case for what
/// an iterative solver does at a given κ that no grid structure hides or helps.
pub fn dense_spd(dim: usize, nodes: usize, kappa: f64, seed: u64) -> GeneratedSystem {
    let m = dim * nodes;
    let mut rng = StdRng::seed_from_u64(seed);
    let a = nalgebra::DMatrix::from_fn(m, m, |_, _| rng.random_range(-1.0..1.0));
    let q = a.qr().q();
    let lam = nalgebra::DVector::from_fn(m, |k, _| kappa.powf(k as f64 / (m.max(2) - 1) as f64));
    let dense = &q * nalgebra::DMatrix::from_diagonal(&lam) * q.transpose();
    let rows: Vec<Vec<usize>> = (0..nodes).map(|_| (0..nodes).collect()).collect();
    let mut h = BlockCsr::from_pattern(dim, &rows);
    for i in 0..nodes {
        for j in 0..nodes {
            let kb = h.find(i, j).expect("every block is in the pattern");
            for r in 0..dim {
                for c in 0..dim {
                    let (u, v) = (i * dim + r, j * dim + c);
                    // The mean of the two rounded triangles: exactly symmetric.
                    h.values[kb * dim * dim + r * dim + c] = 0.5 * (dense[(u, v)] + dense[(v, u)]);
                }
            }
        }
    }
    let g = (0..m).map(|_| rng.random_range(-1.0..1.0)).collect();
    GeneratedSystem {
        h,
        g,
        constraints: Vec::new(),
        frames: Frames::unconstrained(dim, nodes),
        coords: (0..nodes).map(|i| [i, 0, 0]).collect(),
    }
}

fn rand_vec(rng: &mut StdRng, d: usize) -> Vec<f64> {
    loop {
        let v: Vec<f64> = (0..d).map(|_| rng.random_range(-1.0..1.0)).collect();
        if v.iter().map(|x| x * x).sum::<f64>() > 0.05 {
            return v;
        }
    }
}

fn random_constraints(spec: &SystemSpec, rng: &mut StdRng, n: usize) -> Vec<Constraint> {
    let d = spec.dim;
    let mut out = Vec::new();
    let val = |rng: &mut StdRng| -> f64 {
        if spec.prescribed {
            rng.random_range(-0.1..0.1)
        } else {
            0.0
        }
    };
    let mut push = |node: usize, kind: ConstraintKind| {
        let label = format!("constraints[{}]", out.len());
        out.push(Constraint { node, kind, label });
    };
    // Keep at least a few free nodes so the system is not trivial.
    for node in 0..n {
        let pick = rng.random_range(0..14);
        match pick {
            0 => push(
                node,
                ConstraintKind::Sticky {
                    displacement: spec.prescribed.then(|| (0..d).map(|_| val(rng)).collect()),
                },
            ),
            1 | 2 => {
                let normal = rand_vec(rng, d);
                let offset = val(rng);
                push(node, ConstraintKind::Plane { normal, offset })
            }
            3 => {
                // Normal within 1e-8 of e_x.
                let mut normal = vec![0.0; d];
                normal[0] = 1.0;
                for v in normal.iter_mut().skip(1) {
                    *v = rng.random_range(-1e-8..1e-8);
                }
                let offset = val(rng);
                push(node, ConstraintKind::Plane { normal, offset })
            }
            4 => {
                // Axis-aligned (masked without rotation), not unit length.
                let mut normal = vec![0.0; d];
                normal[rng.random_range(0..d)] = rng.random_range(0.5..3.0);
                let offset = val(rng);
                push(node, ConstraintKind::Plane { normal, offset })
            }
            5 => {
                let direction = rand_vec(rng, d);
                let offset = spec.prescribed.then(|| (0..d).map(|_| val(rng)).collect());
                push(node, ConstraintKind::Line { direction, offset })
            }
            6 => {
                // General rows of full row rank (1 or 2 rows in 3D, 1 in 2D).
                let k = if d == 3 { rng.random_range(1..3) } else { 1 };
                let rows: Vec<Vec<f64>> = (0..k).map(|_| rand_vec(rng, d)).collect();
                let values = (0..k).map(|_| val(rng)).collect();
                push(node, ConstraintKind::Rows { rows, values })
            }
            7 => {
                // Redundant: the same plane twice (scaled), consistent values.
                let normal = rand_vec(rng, d);
                let offset = val(rng);
                let s = rng.random_range(0.5..2.0);
                push(
                    node,
                    ConstraintKind::Plane {
                        normal: normal.clone(),
                        offset,
                    },
                );
                push(
                    node,
                    ConstraintKind::Rows {
                        rows: vec![normal.iter().map(|v| v * s).collect()],
                        values: vec![offset * s],
                    },
                )
            }
            8 if d == 3 => {
                // Two planes make a line; a third row that combines them is redundant.
                let n1 = rand_vec(rng, d);
                let n2 = rand_vec(rng, d);
                let (c1, c2) = (val(rng), val(rng));
                let combo: Vec<f64> = n1.iter().zip(&n2).map(|(a, b)| a + 2.0 * b).collect();
                push(
                    node,
                    ConstraintKind::Plane {
                        normal: n1,
                        offset: c1,
                    },
                );
                push(
                    node,
                    ConstraintKind::Plane {
                        normal: n2,
                        offset: c2,
                    },
                );
                push(
                    node,
                    ConstraintKind::Rows {
                        rows: vec![combo],
                        values: vec![c1 + 2.0 * c2],
                    },
                )
            }
            _ => {}
        }
    }
    out
}

fn realistic_constraints(
    spec: &SystemSpec,
    coords: &[[usize; 3]],
    rng: &mut StdRng,
) -> Vec<Constraint> {
    let d = spec.dim;
    let mut out = Vec::new();
    let xmax = spec.grid[0] - 1;
    // A tilted slip plane for the y = 0 face: normal (−sin θ, cos θ, 0), θ = 30°.
    let th = 30f64.to_radians();
    let tilted = {
        let mut n = vec![-th.sin(), th.cos()];
        if d == 3 {
            n.push(0.0);
        }
        n
    };
    for (i, c) in coords.iter().enumerate() {
        let label = || format!("constraints[{}]", out.len());
        if c[0] == 0 {
            out.push(Constraint {
                node: i,
                kind: ConstraintKind::Sticky { displacement: None },
                label: label(),
            });
        } else if c[0] == xmax {
            let mut disp = vec![0.0; d];
            if spec.prescribed {
                disp[0] = 0.01;
            }
            out.push(Constraint {
                node: i,
                kind: ConstraintKind::Sticky {
                    displacement: Some(disp),
                },
                label: label(),
            });
        } else if c[1] == 0 {
            out.push(Constraint {
                node: i,
                kind: ConstraintKind::Plane {
                    normal: tilted.clone(),
                    offset: 0.0,
                },
                label: label(),
            });
        } else if rng.random_range(0..200) == 0 {
            out.push(Constraint {
                node: i,
                kind: ConstraintKind::Line {
                    direction: rand_vec(rng, d),
                    offset: None,
                },
                label: label(),
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_hessian_is_symmetric_and_seeded() {
        let a = random_system(&SystemSpec::small(3, 11));
        let b = random_system(&SystemSpec::small(3, 11));
        assert_eq!(a.h, b.h);
        assert!(a.h.check_symmetric().is_ok());
        assert!(!a.constraints.is_empty());
    }

    #[test]
    fn dense_spd_has_the_asked_condition_number() {
        let s = dense_spd(3, 8, 1e8, 1);
        assert!(s.h.check_symmetric().is_ok());
        let n = s.h.ndof();
        let mut a = nalgebra::DMatrix::<f64>::zeros(n, n);
        for i in 0..s.h.n {
            for k in s.h.row_ptr[i]..s.h.row_ptr[i + 1] {
                let j = s.h.col_idx[k];
                for r in 0..3 {
                    for c in 0..3 {
                        a[(3 * i + r, 3 * j + c)] = s.h.values[k * 9 + r * 3 + c];
                    }
                }
            }
        }
        let ev = a.symmetric_eigenvalues();
        let (lo, hi) = ev
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
        // The smallest eigenvalue, 1, carries the rounding of Q Λ Qᵀ: ε·κ·(a few) = 1e-7
        // relative; 1e-6 leaves a factor of 10.
        assert!(
            (hi / 1e8 - 1.0).abs() <= 1e-12 && (lo - 1.0).abs() <= 1e-6,
            "{lo} {hi}"
        );
    }
}
