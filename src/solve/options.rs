//! Every user-facing option of the solvers, in one home: which solver
//! ([`SolverKind`]), the GPU's arithmetic ([`Precision`]), the preconditioner
//! ([`Preconditioner`]), its coarse space ([`CoarseSpace`]) and the Cholesky oracle's
//! fill-reducing ordering ([`CholeskyOrdering`]) and when the multilevel preconditioner's
//! levels are rebuilt ([`MultilevelSetup`]). Each parses from the name the command line
//! and scene files use and prints as it.

/// Arithmetic of the GPU CG.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 throughout (reductions in f64 where the device has SHADER_F64).
    #[default]
    F32,
    /// f64 throughout; needs SHADER_F64.
    F64,
    /// f32 CG inside f64 iterative refinement; stops on the f64 residual.
    Mixed,
}

impl Precision {
    /// The name used in scene files, options and messages.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
            Precision::Mixed => "mixed",
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" => Ok(Precision::F32),
            "f64" => Ok(Precision::F64),
            "mixed" => Ok(Precision::Mixed),
            _ => Err(format!(
                "unknown precision '{s}' (expected f32, f64 or mixed)"
            )),
        }
    }
}

/// Preconditioner built on the free components of Ĥ (constrained components get 1/D).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preconditioner {
    /// No preconditioning.
    None,
    /// The inverse of diag(Ĥ).
    #[default]
    Jacobi,
    /// The inverse of each node's d×d diagonal block of Ĥ (in the node's frame, masked).
    BlockJacobi,
    /// One symmetric V-cycle over Ĥ's dense blocks on clusters of about 16 nodes and
    /// coarser levels of the clusters' smoothed translations, down to one cluster (see
    /// `solve::multilevel`). The CPU CG and the device PCG in f64; its own coarse levels
    /// replace the coarse space, which it ignores.
    Multilevel,
}

impl Preconditioner {
    /// The name used on the command line, in scenes and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Preconditioner::None => "none",
            Preconditioner::Jacobi => "jacobi",
            Preconditioner::BlockJacobi => "block-jacobi",
            Preconditioner::Multilevel => "multilevel",
        }
    }
}

impl std::str::FromStr for Preconditioner {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(Preconditioner::None),
            "jacobi" => Ok(Preconditioner::Jacobi),
            "block-jacobi" => Ok(Preconditioner::BlockJacobi),
            "multilevel" => Ok(Preconditioner::Multilevel),
            _ => Err(format!(
                "unknown preconditioner '{s}' (expected none, jacobi, block-jacobi or multilevel)"
            )),
        }
    }
}

/// When the multilevel preconditioner's levels (cluster inverses, prolongations, coarse
/// matrices) are rebuilt for a new system of the same pattern and constraint set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MultilevelSetup {
    /// For every system: a solve depends on its own system only.
    #[default]
    Every,
    /// Kept across the systems of a Newton solve: the next system keeps the levels (with
    /// its own finest matrix and smoothing weight) while its solves take at most
    /// [`crate::solve::multilevel::reuse::REBUILD_GROWTH`] times the iterations per decade of
    /// residual reduction of the first solve on them, and rebuilds them when the
    /// constraint set or the pattern changes or a solve on kept levels fails. A
    /// simulation step is one Newton solve ([`crate::Solver::new_newton_solve`]): its first
    /// system builds the levels.
    Reuse,
}

impl MultilevelSetup {
    pub fn name(self) -> &'static str {
        match self {
            MultilevelSetup::Every => "every",
            MultilevelSetup::Reuse => "reuse",
        }
    }
}

impl std::str::FromStr for MultilevelSetup {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "every" => Ok(MultilevelSetup::Every),
            "reuse" => Ok(MultilevelSetup::Reuse),
            _ => Err(format!(
                "unknown multilevel setup '{s}' (expected every or reuse)"
            )),
        }
    }
}

/// The coarse space of the preconditioner.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoarseSpace {
    /// Point-wise preconditioner only.
    None,
    /// Add the coarse correction on the d rigid translations (see the module docs).
    Translations,
    /// Add the coarse correction on the d translations of each aggregate: the nodes are
    /// grouped into connected aggregates of about 64 nodes (at most 128 aggregates) from
    /// Ĥ's graph, so a stiffness-dominated body's smooth modes (bending, not only rigid
    /// motion) are solved on the coarse space too. The default:
    /// on the hard cases at 15k–81k DOFs f64 CG needs 2–5× fewer iterations than with
    /// the translations alone; `slivers` is the exception (STABILITY.md).
    #[default]
    Aggregates,
}

impl CoarseSpace {
    pub fn name(self) -> &'static str {
        match self {
            CoarseSpace::None => "none",
            CoarseSpace::Translations => "translations",
            CoarseSpace::Aggregates => "aggregates",
        }
    }
}

impl std::str::FromStr for CoarseSpace {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(CoarseSpace::None),
            "translations" => Ok(CoarseSpace::Translations),
            "aggregates" => Ok(CoarseSpace::Aggregates),
            _ => Err(format!(
                "unknown coarse space '{s}' (expected none, translations or aggregates)"
            )),
        }
    }
}

/// Which fill-reducing ordering the Cholesky analysis uses.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum CholeskyOrdering {
    /// From 2,000 nodes on, both orderings, keeping the one whose factor needs fewer
    /// flops; AMD below.
    //
    // (The count is `solve::ordering::AUTO_MIN_NODES`; the choice is
    // `solve::ordering::auto_tries_nested_dissection`. Help texts are read on a terminal:
    // no links here.)
    #[default]
    Auto,
    /// Approximate minimum degree (faer) on the scalar pattern of Ĥ.
    Amd,
    /// Nested dissection (METIS) of the node graph, expanded to DOFs.
    NestedDissection,
}

impl CholeskyOrdering {
    /// The name used on the command line, in scenes and in reports.
    pub fn name(self) -> &'static str {
        match self {
            CholeskyOrdering::Auto => "auto",
            CholeskyOrdering::Amd => "amd",
            CholeskyOrdering::NestedDissection => "nested-dissection",
        }
    }
}

impl std::fmt::Display for CholeskyOrdering {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for CholeskyOrdering {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(CholeskyOrdering::Auto),
            "amd" => Ok(CholeskyOrdering::Amd),
            "nested-dissection" => Ok(CholeskyOrdering::NestedDissection),
            _ => Err(format!(
                "unknown ordering '{s}' (expected auto, amd or nested-dissection)"
            )),
        }
    }
}

/// Which solver runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum SolverKind {
    /// Sparse Cholesky (faer LLᵀ) of the assembled Ĥ, f64: the reference.
    Cholesky,
    /// Preconditioned CG on the CPU, f64, matrix-free.
    Cg,
    /// Preconditioned CG on the GPU (wgpu), f32, f64 or mixed precision.
    Gpu,
}

impl SolverKind {
    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            SolverKind::Cholesky => "cholesky",
            SolverKind::Cg => "cg",
            SolverKind::Gpu => "gpu",
        }
    }
}

impl std::fmt::Display for SolverKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for SolverKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cholesky" => Ok(SolverKind::Cholesky),
            "cg" => Ok(SolverKind::Cg),
            "gpu" => Ok(SolverKind::Gpu),
            _ => Err(format!(
                "unknown solver '{s}' (expected cholesky, cg or gpu)"
            )),
        }
    }
}
