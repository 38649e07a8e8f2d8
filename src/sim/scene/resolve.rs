//! Resolution of a parsed [`SceneFile`] into a runnable [`Scene`]: every value checked
//! (errors name their key path), bodies assembled, boundary regions selected, motions
//! and obstacles built.

use super::check::Ctx;
use super::mesh_build::{build_mesh, check_planned_nodes};
use super::model::{check_name, BcShape, CellBlock, Motion, NodeBc, Obstacle, Scene, MAX_STEPS};
use super::spec::{
    BcKindSpec, BodySpec, BoundarySpec, CgTolerance, MaterialModel, MotionSpec, MovingSpec,
    ObstacleKind, ObstacleSpec, RegionSpec, SceneFile, SolverSpec,
};
use crate::error::InputError;
use crate::sim::energy::barrier::HalfSpace;
use crate::sim::energy::{ElementSet, Law, Model, NeoHookean, Springs};
use crate::sim::memory::LoadError;
use crate::sim::memory::{self, AllocError, SceneTooLarge};
use crate::sim::mesh::{self, ElementKind, Mesh};

pub(super) fn resolve(spec: SceneFile, file: &str, size: f64) -> Result<Scene, LoadError> {
    let c = Ctx { file };
    let dim = spec.dimension;
    if dim != 2 && dim != 3 {
        return Err(c
            .err("dimension", format!("must be 2 or 3, got {dim}"))
            .into());
    }
    // The one check of the run's `--size` (the resolution multiplier).
    if !(size.is_finite() && size > 0.0) {
        return Err(InputError::new(
            "--size",
            "",
            format!("must be a positive number, got {size}"),
        )
        .into());
    }
    // 1. Time, gravity, output, solver and moving-boundary settings.
    let (h, steps) = time_steps(&c, &spec)?;
    let gravity = match &spec.gravity {
        Some(g) => c.vector("gravity", g, dim)?[..dim].to_vec(),
        None => vec![0.0; dim],
    };
    if spec.output.checkpoint_every == Some(0) {
        return Err(c
            .err("output.checkpoint_every", "must be at least 1")
            .into());
    }
    if spec.output.every == 0 {
        return Err(c.err("output.every", "must be at least 1").into());
    }
    check_solver(&c, &spec.solver)?;
    check_moving(&c, &spec.moving)?;
    if spec.bodies.is_empty() {
        return Err(c.err("bodies", "at least one body is needed").into());
    }
    // 2. Bodies: meshes, materials, masses, element sets; first, whether the address
    // space has room for what the run will allocate (for the generated meshes, before any
    // is built; a Gmsh body counts once it is read).
    let too_large = |e: AllocError, nodes: usize| SceneTooLarge {
        scene: scene_name(&c, spec.name.as_deref(), file).unwrap_or_else(|_| file.to_string()),
        error: e.with_nodes(nodes),
    };
    let planned = check_planned_nodes(
        &c,
        &spec.bodies.iter().map(|b| &b.mesh).collect::<Vec<_>>(),
        dim,
        size,
    )?;
    memory::probe(memory::scene_bytes(dim, planned), memory::SCENE_WHAT)
        .map_err(|e| too_large(e, planned))?;
    let bodies = build_bodies(&c, &spec, dim, size)?;
    let n_nodes = bodies.x0.len() / dim;
    if n_nodes > planned {
        memory::probe(memory::scene_bytes(dim, n_nodes), memory::SCENE_WHAT)
            .map_err(|e| too_large(e, n_nodes))?;
    }
    let char_len = characteristic_length(&c, &spec.solver, &bodies.x0, dim)?;
    // 3. Boundary conditions and obstacles.
    let bcs = build_bcs(&c, &spec, dim, &bodies, char_len)?;
    let obstacles = build_obstacles(
        &c,
        &spec.obstacle,
        dim,
        &bodies.x0,
        char_len,
        bodies.max_young,
    )?;
    // 4. The scene.
    let name = scene_name(&c, spec.name.as_deref(), file)?;
    let Bodies {
        x0,
        v0,
        mass,
        sets,
        cells,
        contact_weight,
        ..
    } = bodies;
    let model = Model::try_new(dim, mass, Some(gravity.clone()), sets)
        .map_err(|e| too_large(e, n_nodes))?;
    Ok(Scene {
        name,
        file: file.to_string(),
        dim,
        time_step: h,
        steps,
        output: spec.output.clone(),
        solver: {
            let nodes = x0.len() / dim;
            let mut solver = SolverSpec {
                linear: spec.solver.linear_choice.resolve(dim, nodes),
                ..spec.solver.clone()
            };
            solver.resolve_preconditioner(dim, nodes);
            solver
        },
        moving: spec.moving.clone(),
        model,
        x0,
        v0,
        cells,
        bcs,
        characteristic_length: char_len,
        gravity,
        obstacles,
        contact_weight,
    })
}

/// The time step and the number of steps (given, or end_time / time_step rounded).
fn time_steps(c: &Ctx, spec: &SceneFile) -> Result<(f64, usize), InputError> {
    let h = c.positive("time_step", spec.time_step)?;
    let steps = match (spec.steps, spec.end_time) {
        (Some(_), Some(_)) => {
            return Err(c.err("end_time", "give either steps or end_time, not both"))
        }
        (Some(0), None) => return Err(c.err("steps", "must be at least 1")),
        (Some(n), None) if n > MAX_STEPS => {
            return Err(c.err("steps", format!("{n} is more than the cap of {MAX_STEPS}")))
        }
        (Some(n), None) => n,
        (None, Some(t)) => {
            let t = c.positive("end_time", t)?;
            let n = (t / h).round();
            // Checked before the cast (`as usize` saturates); NaN is rejected explicitly.
            if n.is_nan() || n > MAX_STEPS as f64 {
                return Err(c.err(
                    "end_time",
                    format!(
                        "end_time / time_step = {:e} steps, more than the cap of {MAX_STEPS}",
                        t / h
                    ),
                ));
            }
            (n as usize).max(1)
        }
        (None, None) => return Err(c.err("steps", "missing: give steps or end_time")),
    };
    Ok((h, steps))
}

fn check_solver(c: &Ctx, s: &SolverSpec) -> Result<(), InputError> {
    if let CgTolerance::Fixed(t) = s.cg_tolerance {
        if !(t > 0.0 && t < 1.0) {
            return Err(c.err(
                "solver.cg_tolerance",
                "must be \"adaptive\" or a number in (0, 1)",
            ));
        }
    }
    if s.cg_max_iterations == 0 {
        return Err(c.err("solver.cg_max_iterations", "must be at least 1"));
    }
    c.positive("solver.newton_tolerance", s.newton_tolerance)?;
    if !(s.force_tolerance > 0.0 && s.force_tolerance < 1.0) {
        return Err(c.err("solver.force_tolerance", "must be a number in (0, 1)"));
    }
    if s.max_newton_iterations == 0 {
        return Err(c.err("solver.max_newton_iterations", "must be at least 1"));
    }
    if let Some(l) = s.characteristic_length {
        c.positive("solver.characteristic_length", l)?;
    }
    Ok(())
}

fn check_moving(c: &Ctx, m: &MovingSpec) -> Result<(), InputError> {
    c.positive("moving.penalty_start", m.penalty_start)?;
    if m.penalty_start > 1e6 {
        return Err(c.err(
            "moving.penalty_start",
            "must be at most 1e6 (the penalty starts at most there and doubles)",
        ));
    }
    if m.penalty_max.is_nan() || m.penalty_max < m.penalty_start || !m.penalty_max.is_finite() {
        return Err(c.err(
            "moving.penalty_max",
            "must be finite and at least moving.penalty_start",
        ));
    }
    c.positive("moving.tolerance", m.tolerance)?;
    Ok(())
}

/// Every body's nodes, masses and elements, concatenated in body order.
struct Bodies {
    x0: Vec<f64>,
    v0: Vec<f64>,
    mass: Vec<f64>,
    sets: Vec<ElementSet>,
    cells: Vec<CellBlock>,
    /// Per body, its node range.
    body_range: Vec<std::ops::Range<usize>>,
    /// Per node, the barrier's contact measure (empty without obstacles).
    contact_weight: Vec<f64>,
    /// The largest Young's modulus (0 for mass-spring bodies only).
    max_young: f64,
}

/// Builds every body: mesh, material, lumped masses, contact weights, initial velocity.
/// The node caps are checked over all generated bodies before any mesh is allocated, and
/// again once Gmsh bodies have been counted.
fn build_bodies(c: &Ctx, spec: &SceneFile, dim: usize, size: f64) -> Result<Bodies, InputError> {
    let meshes: Vec<&super::spec::MeshSpec> = spec.bodies.iter().map(|b| &b.mesh).collect();
    // The linear solver's own cap is checked when the run starts (`Stepper::new`): the
    // command line may choose another solver or the device loop.
    check_planned_nodes(c, &meshes, dim, size)?;

    let mut out = Bodies {
        x0: Vec::new(),
        v0: Vec::new(),
        mass: Vec::new(),
        sets: Vec::new(),
        cells: Vec::new(),
        body_range: Vec::new(),
        contact_weight: Vec::new(),
        max_young: 0.0,
    };
    let with_contact = !spec.obstacle.is_empty();
    for (b, body) in spec.bodies.iter().enumerate() {
        let key = format!("bodies[{b}]");
        let mesh = build_mesh(c, &key, &body.mesh, dim, size, out.x0.len() / dim)?;
        let mk = format!("{key}.material");
        let density = c.positive(&format!("{mk}.density"), body.material.density)?;
        let offset = out.x0.len() / dim;
        let (set, young) = build_material(c, &key, body, &mesh, dim, offset)?;
        out.max_young = out.max_young.max(young);
        let m = mesh.lumped_masses(density);
        if with_contact {
            out.contact_weight.extend(mesh.boundary_measure());
        }
        let vel = match &body.velocity {
            Some(v) => c.vector(&format!("{key}.velocity"), v, dim)?,
            None => [0.0; 3],
        };
        let nodes = mesh
            .elements
            .iter()
            .flatten()
            .map(|&i| i + offset)
            .collect();
        out.cells.push(CellBlock {
            kind: mesh.kind,
            nodes,
        });
        for _ in 0..mesh.n_nodes() {
            out.v0.extend_from_slice(&vel[..dim]);
        }
        out.body_range.push(offset..offset + mesh.n_nodes());
        out.x0.extend_from_slice(&mesh.x);
        out.mass.extend(m);
        out.sets.push(set);
    }
    Ok(out)
}

/// The body's element set (node indices shifted by `offset`) and its Young's modulus (0
/// for mass-spring). Each model refuses the other's parameters.
fn build_material(
    c: &Ctx,
    key: &str,
    body: &BodySpec,
    mesh: &Mesh,
    dim: usize,
    offset: usize,
) -> Result<(ElementSet, f64), InputError> {
    let mat = &body.material;
    let mk = format!("{key}.material");
    match mat.model {
        MaterialModel::NeoHookean | MaterialModel::StableNeoHookean => {
            let law = if mat.model == MaterialModel::NeoHookean {
                Law::NeoHookean
            } else {
                Law::StableNeoHookean
            };
            for (name, v) in [("stiffness", mat.stiffness.is_some())] {
                if v {
                    return Err(c.err(
                        format!("{mk}.{name}"),
                        "is a mass-spring parameter; neo-Hookean takes young and poisson",
                    ));
                }
            }
            let young = mat.young.ok_or_else(|| {
                c.err(
                    format!("{mk}.young"),
                    "missing (neo-Hookean needs young and poisson)",
                )
            })?;
            let young = c.positive(&format!("{mk}.young"), young)?;
            let nu = mat.poisson.ok_or_else(|| {
                c.err(
                    format!("{mk}.poisson"),
                    "missing (neo-Hookean needs young and poisson)",
                )
            })?;
            if !(nu > 0.0 && nu < 0.5) {
                return Err(c.err(
                    format!("{mk}.poisson"),
                    format!("must be in (0, 0.5), got {nu}"),
                ));
            }
            let solid = matches!(
                (dim, mesh.kind),
                (2, ElementKind::Triangle) | (3, ElementKind::Tetrahedron)
            );
            if !solid {
                return Err(c.err(
                    format!("{key}.mesh.kind"),
                    format!("neo-Hookean needs a solid mesh (rectangle in 2D, box in 3D), got {:?} in {dim}D", body.mesh.kind),
                ));
            }
            let mut nh = NeoHookean::new(mesh, young, nu, law)
                .map_err(|e| c.err(format!("{key}.mesh"), e))?;
            nh.shift_nodes(offset);
            Ok((ElementSet::NeoHookean(nh), young))
        }
        MaterialModel::MassSpring => {
            for (name, v) in [
                ("young", mat.young.is_some()),
                ("poisson", mat.poisson.is_some()),
            ] {
                if v {
                    return Err(c.err(
                        format!("{mk}.{name}"),
                        "is a neo-Hookean parameter; mass-spring takes stiffness",
                    ));
                }
            }
            let k = mat.stiffness.ok_or_else(|| {
                c.err(
                    format!("{mk}.stiffness"),
                    "missing (mass-spring needs stiffness)",
                )
            })?;
            let k = c.positive(&format!("{mk}.stiffness"), k)?;
            let edges = mesh.edges();
            let mut sp = Springs::new(dim, &mesh.x, edges, k)
                .map_err(|e| c.err(format!("{key}.mesh"), e))?;
            for e in sp.edges.iter_mut() {
                e[0] += offset;
                e[1] += offset;
            }
            Ok((ElementSet::Springs(sp), 0.0))
        }
    }
}

/// L: given, or the bounding-box diagonal of every node at t = 0 (which must be positive).
fn characteristic_length(
    c: &Ctx,
    s: &SolverSpec,
    x0: &[f64],
    dim: usize,
) -> Result<f64, InputError> {
    let all_mesh = Mesh {
        dim,
        x: x0.to_vec(),
        kind: ElementKind::Segment,
        elements: Vec::new(),
    };
    let char_len = match s.characteristic_length {
        Some(l) => l,
        None => all_mesh.bbox_diagonal(),
    };
    if char_len.is_nan() || char_len <= 0.0 {
        return Err(c.err("bodies", "all nodes coincide (zero characteristic length)"));
    }
    Ok(char_len)
}

/// Boundary conditions: each `[[boundary]]` region selects nodes and each selected node
/// gets its shape. A node with a moving condition carries only that one; several static
/// conditions on one node must agree at the initial configuration.
fn build_bcs(
    c: &Ctx,
    spec: &SceneFile,
    dim: usize,
    bodies: &Bodies,
    char_len: f64,
) -> Result<Vec<NodeBc>, InputError> {
    let x0 = &bodies.x0;
    let mut bcs = Vec::new();
    for (k, bc) in spec.boundary.iter().enumerate() {
        let key = format!("boundary[{k}]");
        let range = match bc.body {
            Some(b) if b >= bodies.body_range.len() => {
                return Err(c.err(
                    format!("{key}.body"),
                    format!(
                        "there are {} bodies (numbered from 0)",
                        bodies.body_range.len()
                    ),
                ))
            }
            Some(b) => bodies.body_range[b].clone(),
            None => 0..x0.len() / dim,
        };
        let nodes = select(c, &key, &bc.region, dim, x0, range, char_len)?;
        let motion = match &bc.motion {
            None => None,
            Some(m) => Some(build_motion(c, &format!("{key}.motion"), m, dim, bc.kind)?),
        };
        for (name, present, kinds) in [
            ("normal", bc.normal.is_some(), BcKindSpec::Plane),
            ("offset", bc.offset.is_some(), BcKindSpec::Plane),
            ("direction", bc.direction.is_some(), BcKindSpec::Line),
        ] {
            if present && bc.kind != kinds {
                return Err(c.err(
                    format!("{key}.{name}"),
                    format!("does not apply to a {:?} boundary", bc.kind).to_lowercase(),
                ));
            }
        }
        for &node in &nodes {
            let shape = node_shape(c, &key, bc, point(x0, dim, node), dim)?;
            bcs.push(NodeBc {
                node,
                shape,
                motion: motion.clone(),
                label: key.clone(),
            });
        }
    }
    // A node with a moving condition must carry only that one (its set changes per step).
    for b in bcs.iter().filter(|b| b.motion.is_some()) {
        if bcs.iter().filter(|o| o.node == b.node).count() > 1 {
            return Err(c.err(
                b.label.clone(),
                format!("node {} has a moving condition and another condition; a moving node takes exactly one", b.node),
            ));
        }
    }
    // Several static conditions on one node must agree at the initial configuration
    // (the same test as bc.json; the stepper projects such a node onto their intersection).
    super::model::joint_targets(dim, x0, &bcs, char_len).map_err(|e| c.err(e.label, e.problem))?;
    Ok(bcs)
}

/// The constraint set of boundary `key` at a node starting at `p`: sticky at p; a plane
/// through p (or at the given offset); a line through p (in 2D, the plane whose normal is
/// perpendicular to it).
fn node_shape(
    c: &Ctx,
    key: &str,
    bc: &BoundarySpec,
    p: [f64; 3],
    dim: usize,
) -> Result<BcShape, InputError> {
    Ok(match bc.kind {
        BcKindSpec::Sticky => BcShape::Sticky { anchor: p },
        BcKindSpec::Plane => {
            let raw = bc.normal.as_ref().ok_or_else(|| {
                c.err(
                    format!("{key}.normal"),
                    "missing (a plane boundary needs a normal)",
                )
            })?;
            let nraw = c.vector(&format!("{key}.normal"), raw, dim)?;
            let len = c.length(&format!("{key}.normal"), &nraw[..dim])?;
            let n = c.unit(&format!("{key}.normal"), raw, dim)?;
            let offset = match bc.offset {
                Some(o) => c.along(&format!("{key}.offset"), o, len)?,
                None => mesh::dot3(&n, &p),
            };
            BcShape::Plane { normal: n, offset }
        }
        BcKindSpec::Line => {
            let raw = bc.direction.as_ref().ok_or_else(|| {
                c.err(
                    format!("{key}.direction"),
                    "missing (a line boundary needs a direction)",
                )
            })?;
            let t = c.unit(&format!("{key}.direction"), raw, dim)?;
            if dim == 2 {
                // In 2D a line is a plane with the perpendicular normal.
                let n = [-t[1], t[0], 0.0];
                BcShape::Plane {
                    normal: n,
                    offset: mesh::dot3(&n, &p),
                }
            } else {
                BcShape::Line {
                    point: p,
                    direction: t,
                }
            }
        }
    })
}

/// The scene's name: given, or the file's stem. It becomes a folder and file names: no
/// separators, no `..`.
fn scene_name(c: &Ctx, given: Option<&str>, file: &str) -> Result<String, InputError> {
    let name = given.map(str::to_string).unwrap_or_else(|| {
        std::path::Path::new(file)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "scene".into())
    });
    if let Err(problem) = check_name(&name) {
        let problem = if given.is_some() {
            problem
        } else {
            format!("(taken from the file name) {problem}; give a `name`")
        };
        return Err(c.err("name", problem));
    }
    Ok(name)
}

/// Resolves `[[obstacle]]` entries and checks that the initial configuration is
/// penetration-free (every node at a positive signed distance from every obstacle).
fn build_obstacles(
    c: &Ctx,
    specs: &[ObstacleSpec],
    dim: usize,
    x0: &[f64],
    char_len: f64,
    max_young: f64,
) -> Result<Vec<Obstacle>, InputError> {
    let mut out = Vec::with_capacity(specs.len());
    for (j, o) in specs.iter().enumerate() {
        let key = format!("obstacle[{j}]");
        let ObstacleKind::HalfSpace = o.kind;
        let p = c.vector(&format!("{key}.point"), &o.point, dim)?;
        let n = c.unit(&format!("{key}.normal"), &o.normal, dim)?;
        let dhat = match o.dhat {
            Some(v) => c.positive(&format!("{key}.dhat"), v)?,
            None => 1e-2 * char_len,
        };
        let kappa = match o.kappa {
            Some(v) => c.positive(&format!("{key}.kappa"), v)?,
            None if max_young > 0.0 => max_young,
            None => 1e5,
        };
        let motion = match &o.motion {
            None => None,
            Some(m) => {
                if m.angular_velocity.is_some_and(|w| w != 0.0) {
                    return Err(c.err(
                        format!("{key}.motion.angular_velocity"),
                        "an obstacle moves by translation only",
                    ));
                }
                Some(build_motion(
                    c,
                    &format!("{key}.motion"),
                    m,
                    dim,
                    BcKindSpec::Plane,
                )?)
            }
        };
        let plane = HalfSpace {
            normal: n,
            offset: mesh::dot3(&n, &p),
            dhat,
            kappa,
        };
        for i in 0..x0.len() / dim {
            let d = plane.distance(&x0[i * dim..(i + 1) * dim]);
            if d.is_nan() || d <= 0.0 {
                return Err(c.err(
                    key,
                    format!(
                        "node {i} starts at signed distance {d:e} m from this half-space; the initial configuration must be penetration-free (distance > 0)"
                    ),
                ));
            }
        }
        out.push(Obstacle {
            label: key,
            plane,
            motion,
        });
    }
    Ok(out)
}

fn point(x: &[f64], dim: usize, i: usize) -> [f64; 3] {
    let mut p = [0.0; 3];
    p[..dim].copy_from_slice(&x[i * dim..(i + 1) * dim]);
    p
}

fn select(
    c: &Ctx,
    key: &str,
    r: &RegionSpec,
    dim: usize,
    x: &[f64],
    range: std::ops::Range<usize>,
    char_len: f64,
) -> Result<Vec<usize>, InputError> {
    let given = [
        r.bbox.is_some(),
        r.plane.is_some(),
        r.nodes.is_some(),
        r.all.is_some(),
    ]
    .iter()
    .filter(|&&b| b)
    .count();
    if given != 1 {
        return Err(c.err(
            format!("{key}.region"),
            "give exactly one of box, plane, nodes, all",
        ));
    }
    let rk = format!("{key}.region");
    let nodes: Vec<usize> = if let Some(b) = &r.bbox {
        let lo = c.vector(&format!("{rk}.box.min"), &b.min, dim)?;
        let hi = c.vector(&format!("{rk}.box.max"), &b.max, dim)?;
        range
            .filter(|&i| (0..dim).all(|a| x[i * dim + a] >= lo[a] && x[i * dim + a] <= hi[a]))
            .collect()
    } else if let Some(p) = &r.plane {
        let nraw = c.vector(&format!("{rk}.plane.normal"), &p.normal, dim)?;
        let len = c.length(&format!("{rk}.plane.normal"), &nraw[..dim])?;
        let n = c.unit(&format!("{rk}.plane.normal"), &p.normal, dim)?;
        let off = c.along(&format!("{rk}.plane.offset"), p.offset, len)?;
        let tol = match p.tolerance {
            Some(t) if !(t >= 0.0 && t.is_finite()) => {
                return Err(c.err(
                    format!("{rk}.plane.tolerance"),
                    "must be non-negative and finite",
                ))
            }
            Some(t) => t,
            None => 1e-9 * char_len,
        };
        range
            .filter(|&i| (mesh::dot3(&n, &point(x, dim, i)) - off).abs() <= tol)
            .collect()
    } else if let Some(list) = &r.nodes {
        for (k, &i) in list.iter().enumerate() {
            if !range.contains(&i) {
                return Err(c.err(
                    format!("{rk}.nodes[{k}]"),
                    format!("node {i} is out of range ({}..{})", range.start, range.end),
                ));
            }
        }
        let mut l = list.clone();
        l.sort_unstable();
        l.dedup();
        l
    } else {
        if r.all != Some(true) {
            return Err(c.err(format!("{rk}.all"), "must be true when given"));
        }
        range.collect()
    };
    if nodes.is_empty() {
        return Err(c.err(rk, "selects no node"));
    }
    Ok(nodes)
}

fn build_motion(
    c: &Ctx,
    key: &str,
    m: &MotionSpec,
    dim: usize,
    kind: BcKindSpec,
) -> Result<Motion, InputError> {
    let velocity = match &m.velocity {
        Some(v) => c.vector(&format!("{key}.velocity"), v, dim)?,
        None => [0.0; 3],
    };
    let omega = m.angular_velocity.unwrap_or(0.0);
    if !omega.is_finite() {
        return Err(c.err(format!("{key}.angular_velocity"), "must be finite"));
    }
    if omega != 0.0 && kind != BcKindSpec::Sticky {
        return Err(c.err(
            format!("{key}.angular_velocity"),
            "rotating slip boundaries are not supported: a plane or line boundary moves by velocity only",
        ));
    }
    let axis = if dim == 2 {
        if m.axis.is_some() {
            return Err(c.err(
                format!("{key}.axis"),
                "in 2D the rotation is in-plane; give no axis",
            ));
        }
        [0.0, 0.0, 1.0]
    } else if omega != 0.0 {
        let a = m.axis.as_ref().ok_or_else(|| {
            c.err(
                format!("{key}.axis"),
                "missing (a 3D rotation needs an axis)",
            )
        })?;
        c.unit(&format!("{key}.axis"), a, 3)?
    } else {
        [0.0, 0.0, 1.0]
    };
    let center = match &m.center {
        Some(p) => c.vector(&format!("{key}.center"), p, dim)?,
        None if omega != 0.0 => {
            return Err(c.err(
                format!("{key}.center"),
                "missing (a rotation needs a center)",
            ))
        }
        None => [0.0; 3],
    };
    if !m.start.is_finite() || m.start < 0.0 {
        return Err(c.err(format!("{key}.start"), "must be a non-negative time"));
    }
    let end = match m.end {
        Some(e) if e.is_nan() || e <= m.start => {
            return Err(c.err(format!("{key}.end"), "must be after start"))
        }
        Some(e) => e,
        None => f64::INFINITY,
    };
    Ok(Motion {
        velocity,
        angular_velocity: omega,
        axis,
        center,
        start: m.start,
        end,
    })
}
