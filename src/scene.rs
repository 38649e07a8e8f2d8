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
//! Obstacles (`[[obstacle]]`, seed 003's distance barrier; see [`crate::energy::barrier`]):
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
//! of the body's boundary ([`crate::mesh::Mesh::boundary_measure`]: boundary edges in 2D and
//! boundary faces in 3D split equally among their nodes; a rod in 2D or a sheet in 3D is its
//! own boundary, a rod in 3D counts its length as a unit-width strip). At rest on a plane a
//! body presses with about κ·(1 − d/d̂) per unit contact measure, so κ ≈ E puts the resting
//! gap within a few percent of d̂ below d̂ for everyday loads. Every node must start at a
//! positive distance from every obstacle; otherwise the scene is rejected naming the node.

use crate::cg::Preconditioner;
use crate::energy::barrier::HalfSpace;
use crate::energy::{ElementSet, Model, NeoHookean, Springs};
use crate::error::InputError;
use crate::gpu::Precision;
use crate::mesh::{self, ElementKind, Mesh};
use serde::Deserialize;

/// Most steps a run may take (`steps`, `end_time / time_step`, or `--steps`): one billion.
pub const MAX_STEPS: usize = 1_000_000_000;

/// Checks a scene name: it becomes the default output folder `out/<name>` and the prefix
/// of every frame file, so it must be a plain file name: not empty, no path separator
/// (`/` or `\\`), no `..`, no NUL or other control character. The error says what is wrong.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("must not be empty".into());
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

/// The built-in scenes, by name (the files in `scenes/`).
pub const BUILTIN: &[(&str, &str)] = &[
    ("default", include_str!("../scenes/default.toml")),
    ("hanging", include_str!("../scenes/hanging.toml")),
    ("incline", include_str!("../scenes/incline.toml")),
    ("bead", include_str!("../scenes/bead.toml")),
    ("twist", include_str!("../scenes/twist.toml")),
    ("compress", include_str!("../scenes/compress.toml")),
    ("seed-line", include_str!("../scenes/seed-line.toml")),
    ("drop", include_str!("../scenes/drop.toml")),
    ("squash", include_str!("../scenes/squash.toml")),
];

/// The text of a built-in scene.
pub fn builtin(name: &str) -> Option<&'static str> {
    BUILTIN.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

// ---------------------------------------------------------------------------------------
// File format (serde). Flat structs with optional fields keep every error's key path exact.

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    pub name: Option<String>,
    pub dimension: usize,
    pub time_step: f64,
    pub steps: Option<usize>,
    pub end_time: Option<f64>,
    pub gravity: Option<Vec<f64>>,
    #[serde(default)]
    pub output: OutputSpec,
    #[serde(default)]
    pub solver: SolverSpec,
    #[serde(default)]
    pub moving: MovingSpec,
    pub bodies: Vec<BodySpec>,
    #[serde(default)]
    pub boundary: Vec<BoundarySpec>,
    /// Analytic obstacles for the distance barrier (none: no contact code runs).
    #[serde(default)]
    pub obstacle: Vec<ObstacleSpec>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ObstacleKind {
    /// n·(x − point) ≥ 0.
    HalfSpace,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObstacleSpec {
    pub kind: ObstacleKind,
    /// A point on the boundary plane.
    pub point: Vec<f64>,
    /// Outward normal (into the allowed side); need not be unit length.
    pub normal: Vec<f64>,
    /// Activation distance d̂ (m); default 1e-2 · L.
    pub dhat: Option<f64>,
    /// Barrier stiffness κ (Pa); default: the largest neo-Hookean Young's modulus, else 1e5.
    pub kappa: Option<f64>,
    /// Translation (velocity, start, end) like a moving boundary; no rotation.
    pub motion: Option<MotionSpec>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputSpec {
    /// Write a VTK frame every this many steps (frame 0 is the initial state).
    #[serde(default = "one")]
    pub every: usize,
    /// Write VTK frames at all.
    #[serde(default = "yes")]
    pub vtk: bool,
}

impl Default for OutputSpec {
    fn default() -> Self {
        OutputSpec {
            every: 1,
            vtk: true,
        }
    }
}

fn one() -> usize {
    1
}
fn yes() -> bool {
    true
}

/// Which linear solver runs the eliminated Newton systems.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LinearKind {
    Cholesky,
    Cg,
    Gpu,
}

impl std::str::FromStr for LinearKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cholesky" => Ok(LinearKind::Cholesky),
            "cg" => Ok(LinearKind::Cg),
            "gpu" => Ok(LinearKind::Gpu),
            _ => Err(format!(
                "unknown solver '{s}' (expected cholesky, cg or gpu)"
            )),
        }
    }
}

impl std::fmt::Display for LinearKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            LinearKind::Cholesky => "cholesky",
            LinearKind::Cg => "cg",
            LinearKind::Gpu => "gpu",
        })
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolverSpec {
    #[serde(default = "default_linear")]
    pub linear: LinearKind,
    /// CG and GPU: relative residual ‖b̂ − Ĥy‖/‖b̂‖.
    #[serde(default = "default_cg_tol")]
    pub cg_tolerance: f64,
    #[serde(default = "default_cg_iters")]
    pub cg_max_iterations: usize,
    #[serde(default)]
    pub preconditioner: Preconditioner,
    /// GPU arithmetic.
    #[serde(default = "default_precision")]
    pub precision: Precision,
    /// Newton stops when ‖Δx‖∞/h < newton_tolerance · L (per second).
    #[serde(default = "default_newton_tol")]
    pub newton_tolerance: f64,
    #[serde(default = "default_newton_iters")]
    pub max_newton_iterations: usize,
    pub characteristic_length: Option<f64>,
}

fn default_linear() -> LinearKind {
    LinearKind::Cholesky
}
fn default_cg_tol() -> f64 {
    1e-10
}
fn default_cg_iters() -> usize {
    20_000
}
fn default_precision() -> Precision {
    Precision::Mixed
}
fn default_newton_tol() -> f64 {
    1e-6
}
fn default_newton_iters() -> usize {
    400
}

impl Default for SolverSpec {
    fn default() -> Self {
        SolverSpec {
            linear: default_linear(),
            cg_tolerance: default_cg_tol(),
            cg_max_iterations: default_cg_iters(),
            preconditioner: Preconditioner::default(),
            precision: default_precision(),
            newton_tolerance: default_newton_tol(),
            max_newton_iterations: default_newton_iters(),
            characteristic_length: None,
        }
    }
}

/// Moving boundary conditions (design.md §5).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct MovingSpec {
    /// Initial penalty stiffness k_M (dimensionless: relative to the mass term).
    #[serde(default = "default_km")]
    pub penalty_start: f64,
    /// Cap of k_M; a step fails if nodes are still unsatisfied at the cap.
    #[serde(default = "default_km_max")]
    pub penalty_max: f64,
    /// ε: a node is satisfied when ‖x_k − x̂_k‖/h < ε · L (per second).
    #[serde(default = "default_eps")]
    pub tolerance: f64,
    /// Augmented Lagrangian: adds −√m_k λ_kᵀ r_k and updates λ on convergence.
    #[serde(default)]
    pub augmented_lagrangian: bool,
}

fn default_km() -> f64 {
    1e3
}
fn default_km_max() -> f64 {
    1e12
}
fn default_eps() -> f64 {
    1e-3
}

impl Default for MovingSpec {
    fn default() -> Self {
        MovingSpec {
            penalty_start: default_km(),
            penalty_max: default_km_max(),
            tolerance: default_eps(),
            augmented_lagrangian: false,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BodySpec {
    pub mesh: MeshSpec,
    pub material: MaterialSpec,
    /// Initial velocity of every node.
    pub velocity: Option<Vec<f64>>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshKind {
    /// 2D: [0,w]×[0,h] of triangles.
    Rectangle,
    /// 3D: [0,lx]×[0,ly]×[0,lz] of tetrahedra.
    Box,
    /// A chain of springs along x.
    Rod,
    /// Triangulated rectangle (in 3D in the plane z = 0): springs on its edges.
    Sheet,
    /// A Gmsh MSH 4.1 file (`file`): triangles in 2D, tetrahedra in 3D. The file fixes
    /// the resolution (the run's size option does not apply); no `cells` or `size`.
    Gmsh,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshSpec {
    pub kind: MeshKind,
    /// Rectangle/sheet: [w, h]; box: [lx, ly, lz].
    pub size: Option<Vec<f64>>,
    /// Rod length.
    pub length: Option<f64>,
    /// Cells per axis (rod: one number), multiplied by the run's size option.
    #[serde(default)]
    pub cells: Vec<usize>,
    /// Gmsh: the .msh file, relative to the scene file's folder unless absolute.
    pub file: Option<String>,
    /// Translation applied after the rotation.
    pub origin: Option<Vec<f64>>,
    /// Rotation about the z axis (2D: in-plane), degrees.
    pub rotate_degrees: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaterialModel {
    NeoHookean,
    MassSpring,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialSpec {
    pub model: MaterialModel,
    /// Mass per unit length, area or volume of the mesh's elements.
    pub density: f64,
    /// Neo-Hookean: Young's modulus (Pa).
    pub young: Option<f64>,
    /// Neo-Hookean: Poisson ratio in (0, 0.5).
    pub poisson: Option<f64>,
    /// Mass-spring: k in newtons (a strain ε stores ½ k l₀ ε²).
    pub stiffness: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BcKindSpec {
    Sticky,
    Plane,
    Line,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoundarySpec {
    pub kind: BcKindSpec,
    pub region: RegionSpec,
    /// Restrict the region to one body (default: all bodies).
    pub body: Option<usize>,
    /// Plane: normal (need not be unit length).
    pub normal: Option<Vec<f64>>,
    /// Plane: nᵀx = offset with n as given. Default: the plane through each node.
    pub offset: Option<f64>,
    /// Line: direction (need not be unit length); the line passes through each node.
    pub direction: Option<Vec<f64>>,
    pub motion: Option<MotionSpec>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegionSpec {
    #[serde(rename = "box")]
    pub bbox: Option<BoxRegion>,
    pub plane: Option<PlaneRegion>,
    pub nodes: Option<Vec<usize>>,
    pub all: Option<bool>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxRegion {
    pub min: Vec<f64>,
    pub max: Vec<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaneRegion {
    pub normal: Vec<f64>,
    /// nᵀx = offset with n as given (default 0).
    #[serde(default)]
    pub offset: f64,
    /// Distance tolerance (default 1e-9 · L).
    pub tolerance: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionSpec {
    pub velocity: Option<Vec<f64>>,
    /// Radians per second about `axis` (3D) through `center`.
    pub angular_velocity: Option<f64>,
    pub axis: Option<Vec<f64>>,
    pub center: Option<Vec<f64>>,
    /// Active time range [start, end] (seconds); outside it the target holds still.
    #[serde(default)]
    pub start: f64,
    pub end: Option<f64>,
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
    let kxv = crate::linalg::cross3(k, v);
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

struct Ctx<'a> {
    file: &'a str,
}

impl Ctx<'_> {
    fn err(&self, key: impl Into<String>, problem: impl Into<String>) -> InputError {
        InputError::new(self.file, key, problem)
    }

    fn positive(&self, key: &str, v: f64) -> Result<f64, InputError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(self.err(key, format!("must be positive and finite, got {v}")))
        }
    }

    fn vector(&self, key: &str, v: &[f64], dim: usize) -> Result<[f64; 3], InputError> {
        if v.len() != dim {
            return Err(self.err(key, format!("must have {dim} components, got {}", v.len())));
        }
        let mut out = [0.0; 3];
        for (a, &x) in v.iter().enumerate() {
            if !x.is_finite() {
                return Err(self.err(format!("{key}[{a}]"), "must be finite"));
            }
            out[a] = x;
        }
        Ok(out)
    }

    fn unit(&self, key: &str, v: &[f64], dim: usize) -> Result<[f64; 3], InputError> {
        let mut u = self.vector(key, v, dim)?;
        let n = mesh::dot3(&u, &u).sqrt();
        if n.is_nan() || n <= 0.0 || !n.is_finite() {
            return Err(self.err(key, "must be a nonzero vector"));
        }
        for x in u.iter_mut() {
            *x /= n;
        }
        Ok(u)
    }
}

fn resolve(spec: SceneFile, file: &str, size: f64) -> Result<Scene, InputError> {
    let c = Ctx { file };
    let dim = spec.dimension;
    if dim != 2 && dim != 3 {
        return Err(c.err("dimension", format!("must be 2 or 3, got {dim}")));
    }
    // The one check of the run's `--size` (the resolution multiplier).
    if !(size.is_finite() && size > 0.0) {
        return Err(InputError::new(
            "--size",
            "",
            format!("must be a positive number, got {size}"),
        ));
    }
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
    let gravity = match &spec.gravity {
        Some(g) => c.vector("gravity", g, dim)?[..dim].to_vec(),
        None => vec![0.0; dim],
    };
    if spec.output.every == 0 {
        return Err(c.err("output.every", "must be at least 1"));
    }
    let s = &spec.solver;
    if !(s.cg_tolerance > 0.0 && s.cg_tolerance < 1.0) {
        return Err(c.err("solver.cg_tolerance", "must be in (0, 1)"));
    }
    if s.cg_max_iterations == 0 {
        return Err(c.err("solver.cg_max_iterations", "must be at least 1"));
    }
    c.positive("solver.newton_tolerance", s.newton_tolerance)?;
    if s.max_newton_iterations == 0 {
        return Err(c.err("solver.max_newton_iterations", "must be at least 1"));
    }
    if let Some(l) = s.characteristic_length {
        c.positive("solver.characteristic_length", l)?;
    }
    let m = &spec.moving;
    c.positive("moving.penalty_start", m.penalty_start)?;
    if m.penalty_start > 1e6 {
        return Err(c.err(
            "moving.penalty_start",
            "must be at most 1e6 (seed 003: start below 1e6 and double)",
        ));
    }
    if m.penalty_max.is_nan() || m.penalty_max < m.penalty_start || !m.penalty_max.is_finite() {
        return Err(c.err(
            "moving.penalty_max",
            "must be finite and at least moving.penalty_start",
        ));
    }
    c.positive("moving.tolerance", m.tolerance)?;
    if spec.bodies.is_empty() {
        return Err(c.err("bodies", "at least one body is needed"));
    }

    // Bodies: meshes, materials, masses, element sets.
    let mut x0 = Vec::new();
    let mut v0 = Vec::new();
    let mut mass = Vec::new();
    let mut sets = Vec::new();
    let mut cells = Vec::new();
    let mut body_range = Vec::new();
    let with_contact = !spec.obstacle.is_empty();
    let mut contact_weight = Vec::new();
    let mut max_young = 0.0f64;
    for (b, body) in spec.bodies.iter().enumerate() {
        let key = format!("bodies[{b}]");
        let mut mesh = build_mesh(&c, &key, &body.mesh, dim, size)?;
        let mat = &body.material;
        let mk = format!("{key}.material");
        let density = c.positive(&format!("{mk}.density"), mat.density)?;
        let offset = x0.len() / dim;
        let set = match mat.model {
            MaterialModel::NeoHookean => {
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
                max_young = max_young.max(young);
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
                let nh = NeoHookean::new(&mesh, young, nu)
                    .map_err(|e| c.err(format!("{key}.mesh"), e))?;
                let mut nh = nh;
                shift_elements(&mut nh.elements, offset);
                ElementSet::NeoHookean(nh)
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
                ElementSet::Springs(sp)
            }
        };
        let m = mesh.lumped_masses(density);
        if with_contact {
            contact_weight.extend(mesh.boundary_measure());
        }
        let vel = match &body.velocity {
            Some(v) => c.vector(&format!("{key}.velocity"), v, dim)?,
            None => [0.0; 3],
        };
        shift_elements(&mut mesh.elements, offset);
        cells.push(CellBlock {
            kind: mesh.kind,
            cells: mesh.elements.clone(),
        });
        for i in 0..mesh.n_nodes() {
            v0.extend_from_slice(&vel[..dim]);
            let _ = i;
        }
        body_range.push(offset..offset + mesh.n_nodes());
        x0.extend_from_slice(&mesh.x);
        mass.extend(m);
        sets.push(set);
    }
    let all_mesh = Mesh {
        dim,
        x: x0.clone(),
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

    // Boundary conditions: regions select nodes; each selected node gets its shape.
    let mut bcs = Vec::new();
    for (k, bc) in spec.boundary.iter().enumerate() {
        let key = format!("boundary[{k}]");
        let range = match bc.body {
            Some(b) if b >= body_range.len() => {
                return Err(c.err(
                    format!("{key}.body"),
                    format!("there are {} bodies (numbered from 0)", body_range.len()),
                ))
            }
            Some(b) => body_range[b].clone(),
            None => 0..x0.len() / dim,
        };
        let nodes = select(&c, &key, &bc.region, dim, &x0, range, char_len)?;
        let motion = match &bc.motion {
            None => None,
            Some(m) => Some(build_motion(&c, &format!("{key}.motion"), m, dim, bc.kind)?),
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
            let p = point(&x0, dim, node);
            let shape = match bc.kind {
                BcKindSpec::Sticky => BcShape::Sticky { anchor: p },
                BcKindSpec::Plane => {
                    let raw = bc.normal.as_ref().ok_or_else(|| {
                        c.err(
                            format!("{key}.normal"),
                            "missing (a plane boundary needs a normal)",
                        )
                    })?;
                    let nraw = c.vector(&format!("{key}.normal"), raw, dim)?;
                    let len = mesh::dot3(&nraw, &nraw).sqrt();
                    let n = c.unit(&format!("{key}.normal"), raw, dim)?;
                    let offset = match bc.offset {
                        Some(o) if !o.is_finite() => {
                            return Err(c.err(format!("{key}.offset"), "must be finite"))
                        }
                        Some(o) => o / len,
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
            };
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
    let obstacles = build_obstacles(&c, &spec.obstacle, dim, &x0, char_len, max_young)?;
    let model = Model::new(dim, mass, Some(gravity.clone()), sets);
    let name = spec.name.clone().unwrap_or_else(|| {
        std::path::Path::new(file)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "scene".into())
    });
    // The name becomes a folder and file names: no separators, no `..`.
    if let Err(problem) = check_name(&name) {
        let problem = if spec.name.is_some() {
            problem
        } else {
            format!("(taken from the file name) {problem}; give a `name`")
        };
        return Err(c.err("name", problem));
    }
    Ok(Scene {
        name,
        file: file.to_string(),
        dim,
        time_step: h,
        steps,
        output: spec.output.clone(),
        solver: spec.solver.clone(),
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

fn shift_elements(els: &mut [Vec<usize>], offset: usize) {
    for e in els.iter_mut() {
        for i in e.iter_mut() {
            *i += offset;
        }
    }
}

fn point(x: &[f64], dim: usize, i: usize) -> [f64; 3] {
    let mut p = [0.0; 3];
    p[..dim].copy_from_slice(&x[i * dim..(i + 1) * dim]);
    p
}

/// `cells · size`, rounded, at least 1; None when it is above [`mesh::MAX_NODES`] (checked
/// before the cast: `as usize` would saturate).
fn scaled(cells: usize, size: f64) -> Option<usize> {
    let n = (cells as f64 * size).round();
    if n <= mesh::MAX_NODES as f64 {
        Some((n as usize).max(1))
    } else {
        None
    }
}

fn build_mesh(c: &Ctx, key: &str, m: &MeshSpec, dim: usize, size: f64) -> Result<Mesh, InputError> {
    let mk = format!("{key}.mesh");
    if m.kind == MeshKind::Gmsh {
        return gmsh_mesh(c, &mk, m, dim);
    }
    if m.file.is_some() {
        return Err(c.err(format!("{mk}.file"), "only a gmsh mesh takes a file"));
    }
    let want_cells = match m.kind {
        MeshKind::Rod => 1,
        MeshKind::Rectangle | MeshKind::Sheet => 2,
        MeshKind::Box => 3,
        MeshKind::Gmsh => 0,
    };
    if m.cells.len() != want_cells {
        return Err(c.err(
            format!("{mk}.cells"),
            format!("must have {want_cells} entries for a {:?} mesh", m.kind).to_lowercase(),
        ));
    }
    if let Some(k) = m.cells.iter().position(|&n| n == 0) {
        return Err(c.err(format!("{mk}.cells[{k}]"), "must be at least 1"));
    }
    // Node and element counts in checked arithmetic, against the per-body cap.
    let too_big = || {
        let by = if size == 1.0 {
            String::new()
        } else {
            format!(" times --size {size}")
        };
        c.err(
            format!("{mk}.cells"),
            format!(
                "{:?}{by} gives more than {} nodes, the cap per body (mesh::MAX_NODES)",
                m.cells,
                mesh::MAX_NODES
            ),
        )
    };
    let cells: Vec<usize> = m
        .cells
        .iter()
        .map(|&n| scaled(n, size))
        .collect::<Option<_>>()
        .ok_or_else(too_big)?;
    if mesh::grid_counts(&cells, 1).is_none() {
        return Err(too_big());
    }
    let size_vec = |n: usize| -> Result<Vec<f64>, InputError> {
        let s = m
            .size
            .as_ref()
            .ok_or_else(|| c.err(format!("{mk}.size"), format!("missing ({n} lengths)")))?;
        if s.len() != n {
            return Err(c.err(
                format!("{mk}.size"),
                format!("must have {n} entries, got {}", s.len()),
            ));
        }
        for (a, &v) in s.iter().enumerate() {
            c.positive(&format!("{mk}.size[{a}]"), v)?;
        }
        Ok(s.clone())
    };
    let mut mesh = match m.kind {
        MeshKind::Rectangle => {
            if dim != 2 {
                return Err(c.err(
                    format!("{mk}.kind"),
                    "a rectangle is a 2D mesh (use box or sheet in 3D)",
                ));
            }
            let s = size_vec(2)?;
            mesh::rectangle(2, [s[0], s[1]], [cells[0], cells[1]])
        }
        MeshKind::Sheet => {
            let s = size_vec(2)?;
            mesh::rectangle(dim, [s[0], s[1]], [cells[0], cells[1]])
        }
        MeshKind::Box => {
            if dim != 3 {
                return Err(c.err(
                    format!("{mk}.kind"),
                    "a box is a 3D mesh (use rectangle in 2D)",
                ));
            }
            let s = size_vec(3)?;
            mesh::cuboid([s[0], s[1], s[2]], [cells[0], cells[1], cells[2]])
        }
        MeshKind::Rod => {
            let l = m
                .length
                .ok_or_else(|| c.err(format!("{mk}.length"), "missing (a rod needs a length)"))?;
            let l = c.positive(&format!("{mk}.length"), l)?;
            mesh::rod(dim, l, cells[0])
        }
        MeshKind::Gmsh => unreachable!("handled above"),
    };
    if m.kind != MeshKind::Rod && m.length.is_some() {
        return Err(c.err(
            format!("{mk}.length"),
            "only a rod takes a length (use size)",
        ));
    }
    if m.kind == MeshKind::Rod && m.size.is_some() {
        return Err(c.err(format!("{mk}.size"), "a rod takes a length, not a size"));
    }
    let origin = match &m.origin {
        Some(o) => c.vector(&format!("{mk}.origin"), o, dim)?,
        None => [0.0; 3],
    };
    let angle = match m.rotate_degrees {
        Some(a) if !a.is_finite() => {
            return Err(c.err(format!("{mk}.rotate_degrees"), "must be finite"))
        }
        Some(a) => a.to_radians(),
        None => 0.0,
    };
    mesh.transform(angle, &origin);
    Ok(mesh)
}

/// Loads `mesh.file` (Gmsh), then applies rotation and origin like the generated meshes.
fn gmsh_mesh(c: &Ctx, mk: &str, m: &MeshSpec, dim: usize) -> Result<Mesh, InputError> {
    for (name, given) in [
        ("cells", !m.cells.is_empty()),
        ("size", m.size.is_some()),
        ("length", m.length.is_some()),
    ] {
        if given {
            return Err(c.err(
                format!("{mk}.{name}"),
                "does not apply to a gmsh mesh (the file fixes it)",
            ));
        }
    }
    let f = m.file.as_ref().ok_or_else(|| {
        c.err(
            format!("{mk}.file"),
            "missing (a gmsh mesh needs a .msh file)",
        )
    })?;
    let path = std::path::Path::new(f);
    let path = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::path::Path::new(c.file)
            .parent()
            .map(|d| d.join(path))
            .unwrap_or_else(|| path.to_path_buf())
    };
    let shown = path.display().to_string();
    let bytes = std::fs::read(&path)
        .map_err(|e| c.err(format!("{mk}.file"), format!("{shown}: cannot read: {e}")))?;
    let mut mesh = mesh::gmsh(dim, &bytes)
        .map_err(|e| c.err(format!("{mk}.file"), format!("{shown}: {e}")))?;
    let origin = match &m.origin {
        Some(o) => c.vector(&format!("{mk}.origin"), o, dim)?,
        None => [0.0; 3],
    };
    let angle = match m.rotate_degrees {
        Some(a) if !a.is_finite() => {
            return Err(c.err(format!("{mk}.rotate_degrees"), "must be finite"))
        }
        Some(a) => a.to_radians(),
        None => 0.0,
    };
    mesh.transform(angle, &origin);
    Ok(mesh)
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
        let len = mesh::dot3(&nraw, &nraw).sqrt();
        let n = c.unit(&format!("{rk}.plane.normal"), &p.normal, dim)?;
        if !p.offset.is_finite() {
            return Err(c.err(format!("{rk}.plane.offset"), "must be finite"));
        }
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
        let off = p.offset / len;
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
