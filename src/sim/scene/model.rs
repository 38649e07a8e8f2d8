//! The runnable scene that a scene file resolves to ([`Scene`]): bodies, per-node
//! boundary conditions and their motions, obstacles, and the checks on names and sizes
//! that the command line shares.

use super::spec::{LinearKind, MovingSpec, OutputSpec, SolverSpec};
use crate::sim::energy::barrier::HalfSpace;
use crate::sim::energy::Model;
use crate::sim::mesh::{self, ElementKind};

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
    (
        "crush",
        include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/crush.toml")),
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
    /// Every cell's `kind.nodes()` nodes, cell after cell (one flat array: no heap block
    /// per cell).
    pub nodes: Vec<usize>,
}

impl CellBlock {
    /// The cells.
    pub fn len(&self) -> usize {
        self.nodes.len() / self.kind.nodes()
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Each cell's nodes, in order.
    pub fn cells(&self) -> impl Iterator<Item = &[usize]> {
        self.nodes.chunks_exact(self.kind.nodes())
    }
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
