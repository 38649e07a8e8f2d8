//! The scene file's schema: the serde structs and enums a TOML scene deserializes into,
//! with their defaults. [`super::parse`] reads a file into [`SceneFile`] and resolves it.

use crate::gpu::Precision;
use crate::solve::cg::Preconditioner;
use crate::solve::coarse::CoarseSpace;
use crate::solve::options::MultilevelSetup;
use serde::Deserialize;

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
    /// Write a checkpoint every this many steps (and always at the last completed step);
    /// absent: every frame (`every`). `run --resume` continues from the last one.
    #[serde(default)]
    pub checkpoint_every: Option<usize>,
}

impl Default for OutputSpec {
    fn default() -> Self {
        OutputSpec {
            every: 1,
            vtk: true,
            checkpoint_every: None,
        }
    }
}

fn one() -> usize {
    1
}
fn yes() -> bool {
    true
}

/// Which linear solver runs the eliminated Newton systems: the library's
/// [`crate::SolverKind`] under the scene file's name for it (`[solver] linear`).
pub use crate::engine::solver::SolverKind as LinearKind;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolverSpec {
    /// `linear` as the scene file says it: a solver or "auto" (the default).
    #[serde(rename = "linear", default)]
    pub linear_choice: LinearChoice,
    /// The solver that runs: `linear_choice` resolved for the scene's size when the scene
    /// is read (or set by `run --solver`).
    #[serde(skip, default = "default_linear")]
    pub linear: LinearKind,
    /// CG and GPU: the relative residual ‖b̂ − Ĥy‖/‖b̂‖ each Newton system is solved to:
    /// "adaptive" (the default, inexact Newton) or a number (every system to it).
    #[serde(default)]
    pub cg_tolerance: CgTolerance,
    #[serde(default = "default_cg_iters")]
    pub cg_max_iterations: usize,
    /// `preconditioner` as the scene file says it: a preconditioner or "auto" (the
    /// default).
    #[serde(rename = "preconditioner", default)]
    pub preconditioner_choice: PreconditionerChoice,
    /// The preconditioner that runs: `preconditioner_choice` resolved for the scene's size,
    /// dimension and solver when the scene is read (again after `run --solver` or
    /// `--newton`).
    #[serde(skip)]
    pub preconditioner: Preconditioner,
    /// Multilevel: when its levels are rebuilt ("reuse", the default for scenes: kept
    /// across the Newton systems of a step with the same constraint set while the solves
    /// stay fast; or "every" system).
    #[serde(default = "default_multilevel_setup")]
    pub multilevel_setup: MultilevelSetup,
    /// CG and GPU: coarse correction added to the preconditioner ("aggregates", the
    /// default, "translations" or "none").
    #[serde(default)]
    pub coarse: CoarseSpace,
    /// GPU arithmetic.
    #[serde(default = "default_precision")]
    pub precision: Precision,
    /// Newton stops when ‖Δx‖∞/h < newton_tolerance · L (per second).
    #[serde(default = "default_newton_tol")]
    pub newton_tolerance: f64,
    /// ... and at an iterate whose largest unbalanced free force is at most
    /// force_tolerance of the step's force scale (in (0, 1)).
    #[serde(default = "default_force_tol")]
    pub force_tolerance: f64,
    #[serde(default = "default_newton_iters")]
    pub max_newton_iterations: usize,
    pub characteristic_length: Option<f64>,
    /// Cholesky: fill-reducing ordering ("auto", the default, "amd" or "nested-dissection").
    #[serde(default)]
    pub ordering: crate::CholeskyOrdering,
    /// Where the Newton loop runs: "cpu" (the default; `linear` picks the linear solver)
    /// or "gpu" (element terms, assembly, elimination, CG and line search on the device,
    /// f64; `linear` is not used).
    #[serde(default)]
    pub newton: NewtonLoop,
    /// What a step that ends with an inverted element (J ≤ 0, possible only for the stable
    /// neo-Hookean law) does: "allow" (the default; summary.json counts such steps) or
    /// "fail" (the step fails naming the element).
    #[serde(default)]
    pub inversion: InversionPolicy,
}

/// `[solver] inversion`: what a step that ends with an inverted element does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum InversionPolicy {
    /// The step completes; the run's summary counts the steps that ended inverted.
    #[default]
    Allow,
    /// The step fails with one line naming the step and the element.
    Fail,
}

/// `[solver] linear`: a linear solver, or "auto".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LinearChoice {
    /// The sparse Cholesky solver up to [`LinearChoice::AUTO_CHOLESKY_MAX_NODES_2D`] or
    /// [`LinearChoice::AUTO_CHOLESKY_MAX_NODES_3D`] nodes, the CPU CG above (where each
    /// wins on a 2-core machine: BENCHMARKS.md, "The linear solver a scene gets").
    #[default]
    Auto,
    Cholesky,
    Cg,
    Gpu,
}

impl LinearChoice {
    /// The most nodes a 2D scene solves with Cholesky under "auto".
    pub const AUTO_CHOLESKY_MAX_NODES_2D: usize = 1_500;
    /// The most nodes a 3D scene solves with Cholesky under "auto".
    pub const AUTO_CHOLESKY_MAX_NODES_3D: usize = 300;

    /// The most nodes a `dim`-dimensional scene solves with Cholesky under "auto".
    fn auto_cholesky_max(dim: usize) -> usize {
        if dim == 3 {
            Self::AUTO_CHOLESKY_MAX_NODES_3D
        } else {
            Self::AUTO_CHOLESKY_MAX_NODES_2D
        }
    }

    /// The solver this choice runs on a scene of `nodes` nodes in `dim` dimensions.
    pub fn resolve(self, dim: usize, nodes: usize) -> LinearKind {
        match self {
            LinearChoice::Auto => {
                if nodes <= Self::auto_cholesky_max(dim) {
                    LinearKind::Cholesky
                } else {
                    LinearKind::Cg
                }
            }
            LinearChoice::Cholesky => LinearKind::Cholesky,
            LinearChoice::Cg => LinearKind::Cg,
            LinearChoice::Gpu => LinearKind::Gpu,
        }
    }

    /// The explicit choice of `kind` (`run --solver`).
    pub fn of(kind: LinearKind) -> Self {
        match kind {
            LinearKind::Cholesky => LinearChoice::Cholesky,
            LinearKind::Cg => LinearChoice::Cg,
            LinearKind::Gpu => LinearChoice::Gpu,
        }
    }

    /// Why "auto" picked what it did, for the run's report; None for an explicit choice.
    pub fn reason(self, dim: usize, nodes: usize) -> Option<String> {
        (self == LinearChoice::Auto).then(|| {
            let max = Self::auto_cholesky_max(dim);
            let side = if nodes <= max { "≤" } else { ">" };
            format!("linear = \"auto\": {nodes} nodes {side} {max} in {dim}D")
        })
    }
}

/// `[solver] preconditioner`: a preconditioner, or "auto".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum PreconditionerChoice {
    /// The multilevel preconditioner where the CPU CG solves a scene of at least
    /// [`PreconditionerChoice::AUTO_MULTILEVEL_MIN_NODES_2D`] or
    /// [`PreconditionerChoice::AUTO_MULTILEVEL_MIN_NODES_3D`] nodes, Jacobi (with the
    /// scene's coarse correction) otherwise: where each takes fewer linear seconds on a
    /// 2-core machine (BENCHMARKS.md, "The preconditioner a scene gets"). The GPU solvers
    /// get Jacobi.
    #[default]
    Auto,
    None,
    Jacobi,
    BlockJacobi,
    Multilevel,
}

impl std::str::FromStr for PreconditionerChoice {
    type Err = String;
    /// "auto" or a preconditioner's name ([`Preconditioner`]'s parser): as `[solver]
    /// preconditioner` spells it (`run --preconditioner`).
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(PreconditionerChoice::Auto);
        }
        s.parse::<Preconditioner>()
            .map(PreconditionerChoice::of)
            .map_err(|_| {
                format!(
                    "unknown preconditioner '{s}' (expected auto, none, jacobi, block-jacobi or \
                     multilevel)"
                )
            })
    }
}

impl PreconditionerChoice {
    /// The explicit choice of `p`.
    pub fn of(p: Preconditioner) -> Self {
        match p {
            Preconditioner::None => PreconditionerChoice::None,
            Preconditioner::Jacobi => PreconditionerChoice::Jacobi,
            Preconditioner::BlockJacobi => PreconditionerChoice::BlockJacobi,
            Preconditioner::Multilevel => PreconditionerChoice::Multilevel,
        }
    }

    /// The fewest nodes of a 2D scene whose CPU CG takes the multilevel preconditioner
    /// under "auto".
    pub const AUTO_MULTILEVEL_MIN_NODES_2D: usize = 8_000;
    /// The fewest nodes of a 3D scene whose CPU CG takes the multilevel preconditioner
    /// under "auto".
    pub const AUTO_MULTILEVEL_MIN_NODES_3D: usize = 8_000;

    /// The fewest nodes of a `dim`-dimensional scene that takes multilevel under "auto".
    fn auto_multilevel_min(dim: usize) -> usize {
        if dim == 3 {
            Self::AUTO_MULTILEVEL_MIN_NODES_3D
        } else {
            Self::AUTO_MULTILEVEL_MIN_NODES_2D
        }
    }

    /// Whether "auto" takes the multilevel preconditioner for this solver and size.
    fn auto_multilevel(dim: usize, nodes: usize, linear: LinearKind, newton: NewtonLoop) -> bool {
        newton == NewtonLoop::Cpu
            && linear == LinearKind::Cg
            && nodes >= Self::auto_multilevel_min(dim)
    }

    /// The preconditioner this choice runs on a scene of `nodes` nodes in `dim`
    /// dimensions solved by `linear` in the `newton` loop.
    pub fn resolve(
        self,
        dim: usize,
        nodes: usize,
        linear: LinearKind,
        newton: NewtonLoop,
    ) -> Preconditioner {
        match self {
            PreconditionerChoice::Auto => {
                if Self::auto_multilevel(dim, nodes, linear, newton) {
                    Preconditioner::Multilevel
                } else {
                    Preconditioner::Jacobi
                }
            }
            PreconditionerChoice::None => Preconditioner::None,
            PreconditionerChoice::Jacobi => Preconditioner::Jacobi,
            PreconditionerChoice::BlockJacobi => Preconditioner::BlockJacobi,
            PreconditionerChoice::Multilevel => Preconditioner::Multilevel,
        }
    }

    /// Why "auto" picked what it did, for the run's report; None for an explicit choice
    /// or a solver without a preconditioner (Cholesky).
    pub fn reason(
        self,
        dim: usize,
        nodes: usize,
        linear: LinearKind,
        newton: NewtonLoop,
    ) -> Option<String> {
        if self != PreconditionerChoice::Auto {
            return None;
        }
        if newton == NewtonLoop::Gpu || linear == LinearKind::Gpu {
            return Some("preconditioner = \"auto\": jacobi on the GPU".to_string());
        }
        if linear != LinearKind::Cg {
            return None;
        }
        let min = Self::auto_multilevel_min(dim);
        let side = if nodes >= min { "≥" } else { "<" };
        Some(format!(
            "preconditioner = \"auto\": {nodes} nodes {side} {min} in {dim}D"
        ))
    }
}

/// The CG tolerance of the Newton systems (`[solver] cg_tolerance`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum CgTolerance {
    /// Inexact Newton: each system's tolerance follows the Eisenstat–Walker forcing
    /// sequence of `sim::integrator::forcing`, between
    /// [`CgTolerance::ADAPTIVE_LOOSEST`] and [`CgTolerance::ADAPTIVE_TIGHTEST`]; a step
    /// converges only on a direction solved to the tightest.
    #[default]
    Adaptive,
    /// Every system to this relative residual, in (0, 1).
    Fixed(f64),
}

impl CgTolerance {
    /// The loosest tolerance of the adaptive policy (the first Newton iteration of a step).
    pub const ADAPTIVE_LOOSEST: f64 = 1e-4;
    /// The tightest tolerance of the adaptive policy: its floor, and the tolerance of the
    /// direction on which a step is declared converged.
    pub const ADAPTIVE_TIGHTEST: f64 = 1e-6;

    /// The loosest tolerance this policy asks for.
    pub fn loosest(self) -> f64 {
        match self {
            CgTolerance::Adaptive => Self::ADAPTIVE_LOOSEST,
            CgTolerance::Fixed(t) => t,
        }
    }

    /// The tolerance of the direction on which a step may be declared converged.
    pub fn tightest(self) -> f64 {
        match self {
            CgTolerance::Adaptive => Self::ADAPTIVE_TIGHTEST,
            CgTolerance::Fixed(t) => t,
        }
    }

    /// "adaptive", or the number.
    pub fn name(self) -> String {
        match self {
            CgTolerance::Adaptive => "adaptive".into(),
            CgTolerance::Fixed(t) => format!("{t:e}"),
        }
    }
}

impl std::str::FromStr for CgTolerance {
    type Err = String;
    /// "adaptive" or a number in (0, 1).
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "adaptive" {
            return Ok(CgTolerance::Adaptive);
        }
        match s.parse::<f64>() {
            Ok(t) if t > 0.0 && t < 1.0 => Ok(CgTolerance::Fixed(t)),
            _ => Err(format!(
                "expected \"adaptive\" or a number in (0, 1), got \"{s}\""
            )),
        }
    }
}

impl serde::Serialize for CgTolerance {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            CgTolerance::Adaptive => s.serialize_str("adaptive"),
            CgTolerance::Fixed(t) => s.serialize_f64(*t),
        }
    }
}

impl<'de> Deserialize<'de> for CgTolerance {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = CgTolerance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("\"adaptive\" or a number in (0, 1)")
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<CgTolerance, E> {
                Ok(CgTolerance::Fixed(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<CgTolerance, E> {
                Ok(CgTolerance::Fixed(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<CgTolerance, E> {
                Ok(CgTolerance::Fixed(v as f64))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<CgTolerance, E> {
                match v {
                    "adaptive" => Ok(CgTolerance::Adaptive),
                    _ => Err(E::invalid_value(serde::de::Unexpected::Str(v), &self)),
                }
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// Where the Newton loop of a time step runs (`[solver] newton`, `run --newton`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum NewtonLoop {
    /// Element terms, assembly and line search on the CPU; the linear solve by `linear`.
    #[default]
    Cpu,
    /// The whole Newton step on the GPU in f64: only scalars cross the bus per iteration.
    Gpu,
}

impl NewtonLoop {
    pub fn name(self) -> &'static str {
        match self {
            NewtonLoop::Cpu => "cpu",
            NewtonLoop::Gpu => "gpu",
        }
    }
}

impl SolverSpec {
    /// Resolves `preconditioner_choice` for a scene of `nodes` nodes in `dim` dimensions
    /// with the solver and Newton loop set now.
    pub fn resolve_preconditioner(&mut self, dim: usize, nodes: usize) {
        self.preconditioner =
            self.preconditioner_choice
                .resolve(dim, nodes, self.linear, self.newton);
    }

    /// Why `[solver] preconditioner = "auto"` chose `preconditioner`, for the report.
    pub fn preconditioner_reason(&self, dim: usize, nodes: usize) -> Option<String> {
        self.preconditioner_choice
            .reason(dim, nodes, self.linear, self.newton)
    }

    /// The library solver configuration this scene's solver settings ask for.
    pub fn config(&self) -> crate::SolverConfig {
        match self.linear {
            LinearKind::Cholesky => crate::SolverConfig::cholesky(),
            LinearKind::Cg => crate::SolverConfig::cg(),
            LinearKind::Gpu => crate::SolverConfig::gpu(self.precision),
        }
        .tol(self.cg_tolerance.loosest())
        .max_iters(self.cg_max_iterations)
        .preconditioner(self.preconditioner)
        .multilevel_setup(self.multilevel_setup)
        .coarse(self.coarse)
        .ordering(self.ordering)
    }
}

fn default_linear() -> LinearKind {
    LinearKind::Cholesky
}
fn default_cg_iters() -> usize {
    20_000
}
fn default_precision() -> Precision {
    Precision::Mixed
}
fn default_multilevel_setup() -> MultilevelSetup {
    MultilevelSetup::Reuse
}
fn default_newton_tol() -> f64 {
    1e-6
}
fn default_force_tol() -> f64 {
    1e-4
}
fn default_newton_iters() -> usize {
    400
}

impl Default for SolverSpec {
    fn default() -> Self {
        SolverSpec {
            linear_choice: LinearChoice::Auto,
            linear: default_linear(),
            cg_tolerance: CgTolerance::Adaptive,
            cg_max_iterations: default_cg_iters(),
            preconditioner_choice: PreconditionerChoice::Auto,
            preconditioner: Preconditioner::default(),
            multilevel_setup: default_multilevel_setup(),
            coarse: CoarseSpace::default(),
            precision: default_precision(),
            newton_tolerance: default_newton_tol(),
            force_tolerance: default_force_tol(),
            max_newton_iterations: default_newton_iters(),
            characteristic_length: None,
            ordering: crate::CholeskyOrdering::Auto,
            newton: NewtonLoop::Cpu,
            inversion: InversionPolicy::Allow,
        }
    }
}

/// Moving boundary conditions (docs/method.md, "Moving boundary conditions").
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
    /// 2D: `[0,w]×[0,h]` of triangles.
    Rectangle,
    /// 3D: `[0,lx]×[0,ly]×[0,lz]` of tetrahedra.
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
    /// The classical neo-Hookean law, μ/2 (I_C − d) − μ ln J + λ/2 (ln J)², with the Lamé
    /// parameters of (young, poisson); elements never invert.
    NeoHookean,
    /// The stable neo-Hookean law of Smith, de Goes and Kim (2018), with remapped
    /// parameters; defined for inverted elements.
    StableNeoHookean,
    MassSpring,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialSpec {
    pub model: MaterialModel,
    /// Mass per unit length, area or volume of the mesh's elements.
    pub density: f64,
    /// Neo-Hookean (either law): Young's modulus (Pa).
    pub young: Option<f64>,
    /// Neo-Hookean (either law): Poisson ratio in (0, 0.5).
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_picks_cholesky_up_to_the_measured_sizes() {
        let auto = LinearChoice::Auto;
        assert_eq!(auto.resolve(3, 300), LinearKind::Cholesky);
        assert_eq!(auto.resolve(3, 301), LinearKind::Cg);
        assert_eq!(auto.resolve(2, 1_500), LinearKind::Cholesky);
        assert_eq!(auto.resolve(2, 1_501), LinearKind::Cg);
        assert_eq!(LinearChoice::Gpu.resolve(2, 10), LinearKind::Gpu);
        assert_eq!(
            LinearChoice::Cholesky.resolve(3, 1 << 20),
            LinearKind::Cholesky
        );
        let why = auto.reason(3, 525).expect("auto says why");
        assert!(why.contains("525 nodes > 300 in 3D"), "{why}");
        assert_eq!(LinearChoice::Cg.reason(3, 525), None);
        for k in [LinearKind::Cholesky, LinearKind::Cg, LinearKind::Gpu] {
            assert_eq!(LinearChoice::of(k).resolve(3, 1_000_000), k);
        }
    }

    /// "auto" takes multilevel for the CPU CG from the measured sizes, Jacobi below them
    /// and on the GPU; an explicit choice is itself whatever the size.
    #[test]
    fn auto_picks_multilevel_for_the_cpu_cg_from_the_measured_sizes() {
        let auto = PreconditionerChoice::Auto;
        let (cg, cpu) = (LinearKind::Cg, NewtonLoop::Cpu);
        assert_eq!(auto.resolve(3, 7_999, cg, cpu), Preconditioner::Jacobi);
        assert_eq!(auto.resolve(3, 8_000, cg, cpu), Preconditioner::Multilevel);
        assert_eq!(auto.resolve(2, 7_999, cg, cpu), Preconditioner::Jacobi);
        assert_eq!(auto.resolve(2, 8_000, cg, cpu), Preconditioner::Multilevel);
        for (linear, newton) in [
            (LinearKind::Gpu, NewtonLoop::Cpu),
            (LinearKind::Cg, NewtonLoop::Gpu),
            (LinearKind::Cholesky, NewtonLoop::Cpu),
        ] {
            assert_eq!(
                auto.resolve(3, 1 << 20, linear, newton),
                Preconditioner::Jacobi
            );
        }
        assert_eq!(
            PreconditionerChoice::BlockJacobi.resolve(3, 1 << 20, cg, cpu),
            Preconditioner::BlockJacobi
        );
        assert_eq!(
            PreconditionerChoice::Multilevel.resolve(2, 10, cg, cpu),
            Preconditioner::Multilevel
        );
        let why = auto.reason(3, 44_541, cg, cpu).expect("auto says why");
        assert!(why.contains("44541 nodes ≥ 8000 in 3D"), "{why}");
        let why = auto.reason(2, 2_401, cg, cpu).expect("auto says why");
        assert!(why.contains("2401 nodes < 8000 in 2D"), "{why}");
        assert_eq!(auto.reason(3, 99, LinearKind::Cholesky, cpu), None);
        assert_eq!(
            PreconditionerChoice::Jacobi.reason(3, 44_541, cg, cpu),
            None
        );
    }

    #[test]
    fn scene_solver_keys_parse() {
        let spec: SolverSpec = toml::from_str("").expect("defaults");
        assert_eq!(spec.linear_choice, LinearChoice::Auto);
        assert_eq!(spec.cg_tolerance, CgTolerance::Adaptive);
        let spec: SolverSpec =
            toml::from_str("linear = \"cg\"\ncg_tolerance = 1e-9").expect("explicit");
        assert_eq!(spec.linear_choice, LinearChoice::Cg);
        assert_eq!(spec.cg_tolerance, CgTolerance::Fixed(1e-9));
        let spec: SolverSpec = toml::from_str("cg_tolerance = \"adaptive\"").expect("word");
        assert_eq!(spec.cg_tolerance, CgTolerance::Adaptive);
        for bad in [
            "cg_tolerance = \"tight\"",
            "cg_tolerance = true",
            "linear = \"lu\"",
        ] {
            let e = toml::from_str::<SolverSpec>(bad)
                .expect_err(bad)
                .to_string();
            assert!(e.contains("adaptive") || e.contains("auto"), "{bad}: {e}");
        }
        // Scenes keep the multilevel levels across Newton systems unless told otherwise.
        assert_eq!(spec.multilevel_setup, MultilevelSetup::Reuse);
        assert_eq!(spec.preconditioner_choice, PreconditionerChoice::Auto);
        let spec: SolverSpec =
            toml::from_str("preconditioner = \"block-jacobi\"").expect("explicit");
        assert_eq!(
            spec.preconditioner_choice,
            PreconditionerChoice::BlockJacobi
        );
        let e = toml::from_str::<SolverSpec>("preconditioner = \"ilu\"")
            .expect_err("unknown preconditioner")
            .to_string();
        assert!(e.contains("auto") && e.contains("multilevel"), "{e}");
        let spec: SolverSpec = toml::from_str("multilevel_setup = \"every\"").expect("every");
        assert_eq!(spec.multilevel_setup, MultilevelSetup::Every);
        assert_eq!(spec.config().multilevel_setup, MultilevelSetup::Every);
        let e = toml::from_str::<SolverSpec>("multilevel_setup = \"sometimes\"")
            .expect_err("unknown setup")
            .to_string();
        assert!(e.contains("every") && e.contains("reuse"), "{e}");
        assert_eq!("1e-4".parse::<CgTolerance>(), Ok(CgTolerance::Fixed(1e-4)));
        for bad in ["0", "1", "-1e-3", "nan", "loose"] {
            let e = bad.parse::<CgTolerance>().expect_err(bad);
            assert!(e.contains("adaptive") && !e.contains('\n'), "{bad}: {e}");
        }
    }
}
