//! Scene files (TOML) and their resolution into a simulation model.
//!
//! A scene names the dimension, time step, steps (or end time), gravity, bodies (a
//! generated mesh and a material), boundary conditions selected by region (box, plane
//! within a tolerance, node list, all), optionally moving, the linear solver and output.
//! Every key is checked: unknown keys and out-of-range values are [`InputError`]s naming
//! the key path, e.g. `bodies[0].material.poisson`. The built-in scenes in `scenes/` are
//! compiled into the binary and run by name; `size` multiplies every mesh resolution.
//!
//! Units: SI. Tolerances that carry a length are relative to the characteristic length L
//! (the bounding-box diagonal of all bodies at t = 0 unless `solver.characteristic_length`
//! sets it):
//! - Newton stops when ‖Δx‖∞ / h < `solver.newton_tolerance` · L (per second);
//!   default 1e-6 · L/s.
//! - A moving boundary node is satisfied (snapped and eliminated) when
//!   ‖x_k − x̂_k‖ / h < `moving.tolerance` · L (per second); default 1e-3 · L/s.
//!
//! Obstacles (`[[obstacle]]`, the distance barrier of docs/method.md, "Contact with
//! half-spaces"; see [`crate::sim::energy::barrier`]):
//!
//! ```toml
//! [[obstacle]]
//! kind = "half-space"            # the allowed side is n·(x − point) > 0
//! point = [0.0, 0.0, 0.0]
//! normal = [0.0, 1.0, 0.0]       # outward (into the allowed side), need not be unit
//! dhat = 0.005                   # activation distance d̂ in metres; default 1e-2 · L
//! kappa = 1e5                    # barrier stiffness κ in Pa; default: the largest
//!                                # neo-Hookean Young's modulus of the scene (1e5 Pa
//!                                # when every body is mass-spring)
//! motion = { velocity = [0.0, 0.1, 0.0], end = 0.5 }   # optional; translation only
//! ```
//!
//! Each node i carries the contact measure w_i used to weight the barrier: its lumped share
//! of the body's boundary ([`crate::sim::mesh::Mesh::boundary_measure`]: boundary edges in 2D and
//! boundary faces in 3D split equally among their nodes; a rod in 2D or a sheet in 3D is its
//! own boundary, a rod in 3D counts its length as a unit-width strip). At rest on a plane a
//! body presses with about κ·(1 − d/d̂) per unit contact measure, so κ ≈ E puts the resting
//! gap within a few percent of d̂ below d̂ for everyday loads. Every node must start at a
//! positive distance from every obstacle; otherwise the scene is rejected naming the node.
//!
//! Limits, all checked before anything big is allocated: a name of at most
//! [`MAX_NAME_BYTES`] bytes; at most [`mesh::MAX_SCENE_NODES_2D`] or
//! [`mesh::MAX_SCENE_NODES_3D`] nodes over all bodies together (what a run fits in about
//! 100 GB), and [`mesh::MAX_CHOLESKY_NODES_3D`] for a 3D scene solved by Cholesky; several
//! static conditions on one node must agree at the initial configuration
//! ([`joint_targets`]).
//!
//! Layout: `spec` holds the file schema (serde), `resolve` turns a parsed file into a
//! [`Scene`], and `mesh_build` generates or loads each body's mesh.

mod mesh_build;
mod resolve;
mod spec;

pub use spec::{
    BcKindSpec, BodySpec, BoundarySpec, BoxRegion, LinearKind, MaterialModel, MaterialSpec,
    MeshKind, MeshSpec, MotionSpec, MovingSpec, NewtonLoop, ObstacleKind, ObstacleSpec, OutputSpec,
    PlaneRegion, RegionSpec, SceneFile, SolverSpec,
};

use crate::error::InputError;
use crate::sim::energy::barrier::HalfSpace;
use crate::sim::energy::Model;
use crate::sim::mesh::{self, ElementKind};
use resolve::resolve;

/// Most steps a run may take (`steps`, `end_time / time_step`, or `--steps`): one billion.
pub const MAX_STEPS: usize = 1_000_000_000;

/// Longest scene name, in bytes of UTF-8. The name is a folder and the prefix of every
/// frame file (`<name>_00001.vtk`), and file systems allow 255 bytes per path component.
pub const MAX_NAME_BYTES: usize = 100;

/// Checks a scene name: it becomes the default output folder `out/<name>` and the prefix
/// of every frame file, so it must be a plain file name: not empty, at most
/// [`MAX_NAME_BYTES`] bytes, no path separator (`/` or `\\`), no `..`, no NUL or other
/// control character. The error says what is wrong.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("must not be empty".into());
    }
    if name.len() > MAX_NAME_BYTES {
        let head: String = name.chars().take(20).collect();
        return Err(format!(
            "is {} bytes long, more than the cap of {MAX_NAME_BYTES} bytes (it names the output folder and every frame file), got {head:?}...",
            name.len()
        ));
    }
    if name.contains(['/', '\\']) {
        return Err(format!(
            "must be a plain file name without path separators, got {name:?}"
        ));
    }
    if name.contains("..") {
        return Err(format!("must not contain \"..\", got {name:?}"));
    }
    if name.chars().any(char::is_control) {
        return Err(format!("must not contain control characters, got {name:?}"));
    }
    Ok(())
}

/// Fails (saying why) when the sparse Cholesky solver would not fit in memory: a 3D scene
/// of more than [`mesh::MAX_CHOLESKY_NODES_3D`] nodes. CG and the GPU have no cap of their
/// own beyond the scene's ([`mesh::max_scene_nodes`]).
pub fn check_solver_size(dim: usize, nodes: usize, linear: LinearKind) -> Result<(), String> {
    if linear == LinearKind::Cholesky && dim == 3 && nodes > mesh::MAX_CHOLESKY_NODES_3D {
        return Err(format!(
            "the Cholesky solver is capped at {} nodes in 3D (mesh::MAX_CHOLESKY_NODES_3D: its factor grows faster than the mesh, about 76 kB per node at 100k nodes) and this scene has {nodes}; use linear = \"cg\" or \"gpu\"",
            mesh::MAX_CHOLESKY_NODES_3D
        ));
    }
    Ok(())
}

/// The built-in scenes, by name (the files in `scenes/`).
pub const BUILTIN: &[(&str, &str)] = &[
    (
        "default",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/default.toml")),
    ),
    (
        "hanging",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/hanging.toml")),
    ),
    (
        "incline",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/incline.toml")),
    ),
    (
        "bead",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/bead.toml")),
    ),
    (
        "twist",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/twist.toml")),
    ),
    (
        "compress",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/compress.toml")),
    ),
    (
        "slip-line",
        include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/scenes/slip-line.toml"
        )),
    ),
    (
        "drop",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/drop.toml")),
    ),
    (
        "squash",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/squash.toml")),
    ),
];

/// The text of a built-in scene.
pub fn builtin(name: &str) -> Option<&'static str> {
    BUILTIN.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

// ---------------------------------------------------------------------------------------
// Resolved scene.

/// What a boundary condition asks of one node.
#[derive(Debug, Clone, PartialEq)]
pub enum BcShape {
    /// Stay at `anchor` (moved by the motion).
    Sticky { anchor: [f64; 3] },
    /// Stay on nᵀx = c (unit n).
    Plane { normal: [f64; 3], offset: f64 },
    /// Stay on p + span(t) (unit t).
    Line {
        point: [f64; 3],
        direction: [f64; 3],
    },
}

/// A scripted rigid motion x ↦ c + vτ + R(ωτ)(x − c), τ = clamp(t, start, end) − start.
#[derive(Debug, Clone, PartialEq)]
pub struct Motion {
    pub velocity: [f64; 3],
    pub angular_velocity: f64,
    pub axis: [f64; 3],
    pub center: [f64; 3],
    pub start: f64,
    pub end: f64,
}

impl Motion {
    fn tau(&self, t: f64) -> f64 {
        t.clamp(self.start, self.end) - self.start
    }

    /// Image of point p (given at τ = 0) at time t.
    pub fn apply(&self, p: &[f64; 3], t: f64) -> [f64; 3] {
        let tau = self.tau(t);
        let mut r = [0.0; 3];
        for a in 0..3 {
            r[a] = p[a] - self.center[a];
        }
        if self.angular_velocity != 0.0 {
            r = rotate(&r, &self.axis, self.angular_velocity * tau);
        }
        let mut out = [0.0; 3];
        for a in 0..3 {
            out[a] = self.center[a] + self.velocity[a] * tau + r[a];
        }
        out
    }

    /// Translation at time t (slip boundaries move by translation only).
    pub fn shift(&self, t: f64) -> [f64; 3] {
        let tau = self.tau(t);
        [
            self.velocity[0] * tau,
            self.velocity[1] * tau,
            self.velocity[2] * tau,
        ]
    }
}

/// Rodrigues rotation of v about unit axis k by angle θ.
fn rotate(v: &[f64; 3], k: &[f64; 3], theta: f64) -> [f64; 3] {
    let (s, c) = theta.sin_cos();
    let kxv = crate::core::linalg::cross3(k, v);
    let kv = mesh::dot3(k, v);
    let mut o = [0.0; 3];
    for a in 0..3 {
        o[a] = v[a] * c + kxv[a] * s + k[a] * kv * (1.0 - c);
    }
    o
}

/// A boundary condition on one node.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeBc {
    pub node: usize,
    pub shape: BcShape,
    pub motion: Option<Motion>,
    /// Names the scene entry, e.g. `boundary[2]`.
    pub label: String,
}

impl NodeBc {
    /// The shape at time t.
    pub fn shape_at(&self, t: f64) -> BcShape {
        let Some(m) = &self.motion else {
            return self.shape.clone();
        };
        match &self.shape {
            BcShape::Sticky { anchor } => BcShape::Sticky {
                anchor: m.apply(anchor, t),
            },
            BcShape::Plane { normal, offset } => {
                let s = m.shift(t);
                BcShape::Plane {
                    normal: *normal,
                    offset: offset + mesh::dot3(normal, &s),
                }
            }
            BcShape::Line { point, direction } => {
                let s = m.shift(t);
                BcShape::Line {
                    point: [point[0] + s[0], point[1] + s[1], point[2] + s[2]],
                    direction: *direction,
                }
            }
        }
    }
}

/// Where a node with several static conditions is held: the point of their intersection
/// nearest its initial position, and the directions it stays free to move along.
#[derive(Debug, Clone, PartialEq)]
pub struct JointTarget {
    pub node: usize,
    /// The nearest point of the intersection to the node's initial position.
    pub point: [f64; 3],
    /// Orthonormal free directions of the intersection (none: the node is held at `point`).
    pub free: Vec<[f64; 3]>,
}

impl JointTarget {
    /// Moves a node onto the intersection: x ← p + Σ_f f fᵀ(x − p).
    pub fn project(&self, d: usize, xi: &mut [f64]) {
        let mut y = self.point;
        for f in &self.free {
            let s: f64 = (0..d).map(|a| f[a] * (xi[a] - self.point[a])).sum();
            for a in 0..d {
                y[a] += s * f[a];
            }
        }
        xi[..d].copy_from_slice(&y[..d]);
    }
}

/// Absolute floor of the consistency tolerance for a scene's conditions:
/// [`CONSISTENCY_RTOL`](crate::core::constraints::CONSISTENCY_RTOL) relative to the scene's
/// length scale (L plus the largest |coordinate|), so that coordinates and offsets that
/// agree up to rounding (a node at 0.30000000000000004 on the plane x = 0.3) are
/// consistent while conditions that disagree by a visible distance are not.
pub fn consistency_floor(x0: &[f64], characteristic_length: f64) -> f64 {
    let xmax = x0.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    crate::core::constraints::CONSISTENCY_RTOL * (characteristic_length + xmax)
}

/// The nodes that carry several static (non-moving) conditions, each with the
/// intersection of its conditions at the initial configuration. The conditions of such a
/// node must agree: they go through the same rank and consistency test as bc.json
/// ([`Frames::build_with_tolerance`](crate::core::constraints::Frames::build_with_tolerance)),
/// written for the displacement from the node's initial position, with the floor
/// [`consistency_floor`]. Contradictory ones (a sticky node and a plane it is not on, two
/// parallel planes apart) are an error naming the node and the boundary entries. Moving
/// conditions are not looked at: a moving node carries exactly one condition.
pub fn joint_targets(
    dim: usize,
    x0: &[f64],
    bcs: &[NodeBc],
    characteristic_length: f64,
) -> Result<Vec<JointTarget>, crate::core::constraints::ConstraintError> {
    use crate::core::constraints::{Constraint, ConstraintKind, Frames};
    let n_nodes = x0.len() / dim;
    let mut count = vec![0u32; n_nodes];
    for b in bcs.iter().filter(|b| b.motion.is_none()) {
        count[b.node] += 1;
    }
    let mut cs = Vec::new();
    for b in bcs
        .iter()
        .filter(|b| b.motion.is_none() && count[b.node] > 1)
    {
        let i = b.node;
        let mut p = [0.0; 3];
        p[..dim].copy_from_slice(&x0[i * dim..(i + 1) * dim]);
        let kind = match &b.shape {
            BcShape::Sticky { anchor } => ConstraintKind::Sticky {
                displacement: Some((0..dim).map(|a| anchor[a] - p[a]).collect()),
            },
            BcShape::Plane { normal, offset } => ConstraintKind::Plane {
                normal: normal[..dim].to_vec(),
                offset: offset - mesh::dot3(normal, &p),
            },
            BcShape::Line { point, direction } => ConstraintKind::Line {
                direction: direction[..dim].to_vec(),
                offset: Some((0..dim).map(|a| point[a] - p[a]).collect()),
            },
        };
        cs.push(Constraint {
            node: i,
            kind,
            label: b.label.clone(),
        });
    }
    if cs.is_empty() {
        return Ok(Vec::new());
    }
    let floor = consistency_floor(x0, characteristic_length);
    let frames = Frames::build_with_tolerance(dim, n_nodes, &cs, floor).map_err(|mut e| {
        // Say where the node is: the conditions are compared at its initial position.
        if let Some(i) = e.node {
            e.problem = format!(
                "{} at the node's initial position {:?}; the conditions on one node must agree there (to {floor:.1e} m)",
                e.problem,
                &x0[i * dim..(i + 1) * dim]
            );
        }
        e
    })?;
    let mut out = Vec::new();
    let mut nodes: Vec<usize> = cs.iter().map(|c| c.node).collect();
    nodes.sort_unstable();
    nodes.dedup();
    for i in nodes {
        let mut point = [0.0; 3];
        for a in 0..dim {
            point[a] = x0[i * dim + a] + frames.lift[i * dim + a];
        }
        let free = (0..dim)
            .filter(|&a| frames.is_free(i, a))
            .map(|a| {
                let mut f = [0.0; 3];
                match frames.rotation(i) {
                    Some(v) => (0..dim).for_each(|k| f[k] = v[k * dim + a]),
                    None => f[a] = 1.0,
                }
                f
            })
            .collect();
        out.push(JointTarget {
            node: i,
            point,
            free,
        });
    }
    Ok(out)
}

/// A half-space obstacle as resolved from the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Obstacle {
    /// Names the scene entry, e.g. `obstacle[0]`.
    pub label: String,
    /// The half-space at t = 0.
    pub plane: HalfSpace,
    pub motion: Option<Motion>,
}

impl Obstacle {
    /// The half-space at time t (a translation moves the plane along its normal only).
    pub fn at(&self, t: f64) -> HalfSpace {
        let mut p = self.plane;
        if let Some(m) = &self.motion {
            p.offset += mesh::dot3(&p.normal, &m.shift(t));
        }
        p
    }
}

/// Cells of one body for output.
#[derive(Debug, Clone)]
pub struct CellBlock {
    pub kind: ElementKind,
    pub cells: Vec<Vec<usize>>,
}

/// A scene ready to run.
#[derive(Debug, Clone)]
pub struct Scene {
    pub name: String,
    pub file: String,
    pub dim: usize,
    pub time_step: f64,
    pub steps: usize,
    pub output: OutputSpec,
    pub solver: SolverSpec,
    pub moving: MovingSpec,
    pub model: Model,
    pub x0: Vec<f64>,
    pub v0: Vec<f64>,
    pub cells: Vec<CellBlock>,
    pub bcs: Vec<NodeBc>,
    /// L: the length unit of the tolerances.
    pub characteristic_length: f64,
    pub gravity: Vec<f64>,
    /// Half-space obstacles (empty: the scene has no contact).
    pub obstacles: Vec<Obstacle>,
    /// Per node, the contact measure w_i of the barrier (empty when there are no obstacles).
    pub contact_weight: Vec<f64>,
}

impl Scene {
    pub fn has_moving(&self) -> bool {
        self.bcs.iter().any(|b| b.motion.is_some())
    }

    pub fn has_obstacles(&self) -> bool {
        !self.obstacles.is_empty()
    }
}

/// Parses a scene file's text. `file` names it in errors; `size` multiplies every mesh
/// resolution (cells), rounded, at least 1.
pub fn parse(text: &str, file: &str, size: f64) -> Result<Scene, InputError> {
    let de = toml::Deserializer::parse(text).map_err(|e| toml_error(file, text, &e, ""))?;
    let spec: SceneFile = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        toml_error(file, text, &inner, &path)
    })?;
    resolve(spec, file, size)
}

fn toml_error(file: &str, text: &str, e: &toml::de::Error, path: &str) -> InputError {
    let mut msg = e.message().trim().to_string();
    if let Some(span) = e.span() {
        let line = text[..span.start.min(text.len())].matches('\n').count() + 1;
        msg = format!("{msg} (line {line})");
    }
    let entry = if path.is_empty() || path == "." {
        String::new()
    } else {
        path.to_string()
    };
    InputError::new(file, entry, msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    const OK: &str = r#"
dimension = 2
time_step = 0.01
steps = 3
[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 0.5], cells = [4, 2] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100 }
"#;

    #[test]
    fn every_builtin_scene_parses() {
        for (name, text) in BUILTIN {
            let s = parse(text, name, 1.0).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert!(s.steps > 0);
        }
    }

    #[test]
    fn minimal_scene_parses() {
        let s = parse(OK, "ok.toml", 1.0).expect("valid");
        assert_eq!(s.x0.len(), 2 * 15);
        let s2 = parse(OK, "ok.toml", 2.0).expect("valid");
        assert_eq!(s2.x0.len(), 2 * 45);
    }

    fn entry_of(text: &str) -> InputError {
        parse(text, "bad.toml", 1.0).expect_err("must fail")
    }

    #[test]
    fn bad_values_name_their_key() {
        let e = entry_of(&OK.replace("poisson = 0.3", "poisson = 0.5"));
        assert_eq!(e.entry, "bodies[0].material.poisson");
        assert!(e.problem.contains("(0, 0.5)"));
        let e = entry_of(&OK.replace("young = 1e4", "young = -1"));
        assert_eq!(e.entry, "bodies[0].material.young");
        let e = entry_of(&OK.replace("time_step = 0.01", "time_step = 0"));
        assert_eq!(e.entry, "time_step");
        let e = entry_of(&OK.replace("cells = [4, 2]", "cells = [4]"));
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        let e = entry_of(&format!(
            "{OK}\n[[boundary]]\nkind = \"plane\"\nregion = {{ all = true }}\n"
        ));
        assert_eq!(e.entry, "boundary[0].normal");
        let e = entry_of(&format!(
            "{OK}\n[[boundary]]\nkind = \"sticky\"\nregion = {{ nodes = [99] }}\n"
        ));
        assert_eq!(e.entry, "boundary[0].region.nodes[0]");
    }

    #[test]
    fn unknown_keys_and_types_name_their_key() {
        let e = entry_of(&OK.replace("poisson = 0.3", "poison = 0.3"));
        assert_eq!(e.entry, "bodies[0].material.poison");
        assert!(e.problem.contains("poison"), "{e}");
        let e = entry_of(&OK.replace("steps = 3", "steps = 3\nfoo = 1"));
        assert!(e.problem.contains("foo"), "{e}");
        let e = entry_of(&OK.replace("time_step = 0.01", "time_step = \"fast\""));
        assert_eq!(e.entry, "time_step");
        let e = entry_of(&OK.replace("neo-hookean", "rubber"));
        assert_eq!(e.entry, "bodies[0].material.model");
        let e = entry_of("dimension = 2\ntime_step = [");
        assert!(e.problem.contains("line"), "{e}");
        // One line, naming the file and the key.
        let e = entry_of(&OK.replace("poisson = 0.3", "poisson = 0.7"));
        let line = e.to_string();
        assert!(
            !line.contains('\n') && line.starts_with("bad.toml: bodies[0].material.poisson: "),
            "{line}"
        );
    }

    const BOX: &str = r#"
dimension = 3
time_step = 0.01
steps = 3
[[bodies]]
mesh = { kind = "box", size = [1.0, 0.5, 0.5], cells = [4, 2, 2] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100 }
"#;

    #[test]
    fn huge_meshes_are_input_errors_not_overflows() {
        // --size 1e7 on a box: (4e7+1)(2e7+1)² nodes overflows usize.
        let e = parse(BOX, "box.toml", 1e7).expect_err("too big");
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        assert!(
            e.problem.contains("--size") && e.problem.contains("cap"),
            "{e}"
        );
        // Every builtin scene, at a size that overflows.
        for (name, text) in BUILTIN {
            let e = parse(text, name, 1e300).expect_err(name);
            assert!(e.entry.ends_with(".mesh.cells"), "{name}: {e}");
        }
        // Over the cap without overflow, and from the file alone (size 1).
        let e = entry_of(&BOX.replace("cells = [4, 2, 2]", "cells = [1000, 1000, 100]"));
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        assert!(!e.problem.contains("--size"), "{e}");
        let e = entry_of(&OK.replace("cells = [4, 2]", "cells = [18446744073709551615, 2]"));
        assert_eq!(e.entry, "bodies[0].mesh.cells");
        // Within the cap it still parses.
        let s = parse(BOX, "box.toml", 2.0).expect("valid");
        assert_eq!(s.x0.len(), 3 * 9 * 5 * 5);
    }

    #[test]
    fn step_counts_are_capped() {
        let e = entry_of(&OK.replace("steps = 3", "end_time = 1e300"));
        assert_eq!(e.entry, "end_time");
        assert!(e.problem.contains("cap"), "{e}");
        let e = entry_of(&OK.replace("steps = 3", "steps = 1000000001"));
        assert_eq!(e.entry, "steps");
        let e = entry_of(&OK.replace("steps = 3", "steps = 18446744073709551615"));
        assert_eq!(e.entry, "steps");
        let s = parse(&OK.replace("steps = 3", "end_time = 0.1"), "ok.toml", 1.0).expect("ok");
        assert_eq!(s.steps, 10);
        let s = parse(
            &OK.replace("steps = 3", &format!("steps = {MAX_STEPS}")),
            "ok.toml",
            1.0,
        )
        .expect("at the cap");
        assert_eq!(s.steps, MAX_STEPS);
    }

    #[test]
    fn size_is_checked_once_naming_the_option() {
        for size in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = parse(OK, "ok.toml", size).expect_err("bad size");
            assert_eq!(e.file, "--size", "{e}");
            assert!(
                e.to_string()
                    .starts_with("--size: must be a positive number"),
                "{e}"
            );
        }
    }

    #[test]
    fn names_must_be_plain_file_names() {
        for bad in ["", "a/b", "/abs", "..", "../up", "a\\b", "x..y", "a\nb"] {
            let text = format!("name = {bad:?}\n{OK}");
            let e = entry_of(&text);
            assert_eq!(e.entry, "name", "{bad:?}: {e}");
        }
        for good in ["scene", "my-scene_2", "a.b", "drop v2"] {
            let s = parse(&format!("name = {good:?}\n{OK}"), "ok.toml", 1.0).expect(good);
            assert_eq!(s.name, good);
        }
        // A name taken from the file stem is checked too ("...toml" has the stem "..").
        let e = parse(OK, "dir/...toml", 1.0).expect_err("stem ..");
        assert_eq!(e.entry, "name");
        assert_eq!(parse(OK, "dir/ok.toml", 1.0).expect("ok").name, "ok");
    }
}
