//! [`DeviceCg`]: the kernels of shaders/pcg.wgsl, their buffers, launches and bind groups,
//! and the CG driver (chunks, status reads, restarts from the true residual).

use crate::core::constraints::{Frames, NO_ROTATION};
use crate::gpu::blocks::BlockMatrix;
use crate::gpu::kernels::{self, slots, Access, Layout, Real};
use crate::gpu::schedule::{self, ChunkStatus};
use crate::gpu::{GpuContext, GpuError, KernelTime, Launch, TrafficCount};
use crate::solve::cg::{CgError, Preconditioner};
use crate::solve::coarse::CoarseSpace;
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use Access::{Read as R, ReadWrite as W, Uniform as U};

use super::aggregates::{self, AggregateIndex};
use super::coarse_factor::CoarseFactor;
use super::multilevel::{DeviceMultilevel, Finest, Step};
use crate::solve::multilevel::Multilevel;

/// Bind group 0 of shaders/pcg.wgsl, shared by all its entry points.
pub const PCG: Layout = Layout {
    file: "pcg.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/pcg.wgsl")),
    bindings: &[
        ("params", U),
        ("pattern", R),
        ("hvals", R),
        ("grad", R),
        ("frame", R),
        ("rotations", R),
        ("y", W),
        ("r", W),
        ("z", W),
        ("p", W),
        ("q", W),
        ("b", W),
        ("minv", W),
        ("dx", W),
        ("partials", W),
        ("scal", W),
        ("state", W),
        ("aggregates", R),
        ("coarse", W),
        ("pw", W),
        ("rowsum", R),
    ],
};

/// Lanczos coefficient pairs a PCG built with history records per solve (the HIST
/// override): enough for κ̃ on any solve that converges in reasonable time.
pub const LANCZOS_HIST: u32 = 1024;

/// Uniform parameters of every kernel (mirrors `PcgParams` in the WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct PcgParams {
    n_nodes: u32,
    n_partials: u32,
    col_at: u32,
    diag_at: u32,
    /// The values chunk of the dispatch: rows, first block, index.
    row_begin: u32,
    row_end: u32,
    block_first: u32,
    chunk: u32,
}
const _: () = assert!(std::mem::size_of::<PcgParams>() == 32);

/// Workgroup size of every kernel.
const WORKGROUP: u32 = 64;

/// Bytes of the status read back per chunk: the leading `scal` slots (`acc`) then
/// `state`.
fn status_bytes(acc: Real) -> u64 {
    acc.size() * slots::STATUS_SCAL as u64 + 4 * slots::N_STATE as u64
}

/// Iterations of the first chunk, the shortest and the longest chunk
/// ([`schedule::next_chunk`]).
pub(crate) const FIRST_CHUNK: usize = 8;
const MIN_CHUNK: usize = 2;
const MAX_CHUNK: usize = 256;

/// The factor by which a run whose recurrence met the tolerance must lower the best true
/// residual before it; less ends the solve in [`CgError::Stagnation`] (see `run`; the
/// same 2× as mixed precision asks of its f32 segments).
const MIN_RESTART_GAIN: f64 = 0.5;

/// Identities of every [`DeviceCg`] and [`DeviceFrames`]: frames built for one CG are
/// refused by another, and `iterate` refuses frames `prepare` did not see.
static NEXT_ID: AtomicU64 = AtomicU64::new(0);

/// One dispatch: pipeline, workgroups, bind group.
type Kernel<'a> = (&'a wgpu::ComputePipeline, Launch, &'a wgpu::BindGroup);

/// One dispatch of a CG iteration: the kernel, its workgroups and invocations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct DispatchRecord {
    pub kernel: &'static str,
    pub workgroups: u64,
    pub threads: u64,
}

/// The dispatches of one CG iteration and the bytes it must move at the least.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct IterationProfile {
    pub dispatches: Vec<DispatchRecord>,
    pub bytes: u64,
}

/// The bytes of the buffers [`DeviceCg::new`] sizes by the system (one place for both).
struct Sizes {
    /// One n·d vector (y, r, z, p, q, pw, b̂, Δx) of `real`.
    vector: u64,
    /// Both preconditioners: the block-Jacobi inverses (n·d²) and the Jacobi diagonal.
    minv: u64,
    /// The difference form's row sums (n·d², with it; else a placeholder).
    rowsum: u64,
    /// The partial sums, then the sums carried across each boundary between H's chunks
    /// (one segment straddles it), per invocation.
    partials: u64,
    /// The scalars and the Lanczos history.
    scal: u64,
}

/// The vectors of the CG: y, r, z, p, q, pw, b̂ and Δx.
const N_VECTORS: u64 = 8;

impl Sizes {
    fn new(n: usize, dim: usize, segments: u64, chunks: usize, hist: u32, ty: Scalars) -> Self {
        let nd = (n * dim) as u64;
        let (rs, acs) = (ty.real.size(), ty.acc.size());
        Sizes {
            vector: rs * nd,
            minv: rs * (n * dim * dim) as u64 + rs * nd,
            rowsum: if ty.difference {
                rs * (n * dim * dim) as u64
            } else {
                16
            },
            partials: acs
                * (slots::N_PART as u64 * segments
                    + (chunks.saturating_sub(1) as u64)
                        * slots::CARRY_LEN as u64
                        * WORKGROUP as u64),
            scal: acs * (slots::SCAL_HIST + 2 * hist) as u64,
        }
    }
}

/// The scalar types of one PCG: `real` for H, the frames and the vectors (H's own),
/// `acc` for every sum and scalar (f64 wherever the device has SHADER_F64), and whether
/// the product takes the difference form (f32 only; see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Scalars {
    pub real: Real,
    pub acc: Real,
    pub difference: bool,
}

impl Scalars {
    /// f64 throughout: the Newton loop's.
    pub const F64: Scalars = Scalars {
        real: Real::F64,
        acc: Real::F64,
        difference: false,
    };

    /// `real` vectors on `ctx`: f64 sums where it has SHADER_F64, else f32 (refused for
    /// f64 vectors).
    pub fn on(ctx: &GpuContext, real: Real, difference: bool) -> Result<Self, GpuError> {
        let acc = if ctx.has_f64() { Real::F64 } else { Real::F32 };
        if real == Real::F64 && acc == Real::F32 {
            return Err(GpuError::Unsupported(format!(
                "{} has no SHADER_F64: the device PCG cannot run in f64 there",
                ctx.adapter_name()
            )));
        }
        Ok(Scalars {
            real,
            acc,
            difference: difference && real == Real::F32,
        })
    }
}

/// How a run of chunks ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Chunked {
    /// The recurrence met the tolerance, or the iteration limit was reached.
    Stopped,
    /// The caller's watch asked to stop ([`DeviceCg::segment`]).
    Watched,
    /// The run reached the stagnation window's length, or its recurrence residual has
    /// not improved for that long: the true residual decides whether CG goes on.
    Check,
}

/// Looks at a [`DeviceCg::segment`] after each status read, given the iterations so far
/// and ρ of the segment's start ([`SegmentInfo::start_rho`]); true stops it.
pub type Watch<'a> = dyn FnMut(&DeviceCg, usize, f64) -> Result<bool, GpuError> + 'a;

/// [`Watch`] inside `chunks`: the iterations so far.
type ChunkWatch<'a> = dyn FnMut(&DeviceCg, usize) -> Result<bool, GpuError> + 'a;

/// One workgroup (the scalar kernels).
const ONE: Launch = Launch { x: 1, y: 1 };

/// The launches of the CG's kernels, from the device's limits and segment policy.
struct Launches {
    /// The segmented reductions over every node (rhs, init, update_yr).
    segments: Launch,
    /// Per values chunk of H: its segmented reductions (matvec, coarse_e) and its
    /// per-row kernels (precond, agg_rows).
    chunk_segments: Vec<Launch>,
    chunk_rows: Vec<Launch>,
    /// One invocation per node (update_p, recover).
    nodes: Launch,
}

/// Parameters of one [`DeviceCg::solve`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceCgParams {
    /// Success when the true relative residual ‖b̂ − Ĥy‖/‖b̂‖ (f64, on the device) ≤ tol.
    pub tol: f64,
    /// Limit on CG iterations, restarts included.
    pub max_iterations: usize,
    /// Jacobi or block Jacobi (or none).
    pub preconditioner: Preconditioner,
    /// Added to the preconditioner (see the module docs). `Aggregates` needs frames built
    /// for it ([`DeviceCg::frames`]).
    pub coarse: CoarseSpace,
    /// Stagnation: at least every this many iterations (and sooner when the recurrence
    /// residual has not improved for as long) the true residual is computed and CG
    /// restarts from it; a true residual no smaller than the best before it ends the
    /// solve in [`CgError::Stagnation`], and so does one not below half the best after a
    /// run whose recurrence met the tolerance.
    pub stagnation_window: usize,
}

/// What a successful solve reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceCgInfo {
    /// CG iterations, restarts included (0 when b̂ = 0).
    pub iterations: usize,
    /// Restarts from the true residual after the recurrence met the tolerance.
    pub restarts: usize,
    /// Iterations recorded into command buffers (those past the stop are no-ops on the
    /// device but still cost their dispatches).
    pub recorded_iterations: usize,
    /// Status read-backs (one per chunk and per start).
    pub status_reads: usize,
    /// The true relative residual ‖b̂ − Ĥy‖/‖b̂‖ at the returned y (0 when b̂ = 0).
    pub relative_residual: f64,
    /// ‖b̂‖.
    pub rhs_norm: f64,
    /// The relative residual tolerance the solve met.
    pub tolerance: f64,
}

/// How a [`DeviceCg::segment`] starts, always from y = 0 on the b̂ last given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SegmentStart {
    /// p = z (+ the coarse correction): plain CG.
    Fresh,
    /// A reliable update: the last segment's search direction goes on, rescaled by
    /// `pscale` (the old right-hand side's norm over the new one, when each segment solves
    /// for a unit right-hand side), with β = pscale·ρ/`rho_prev` (`rho_prev` the ρ the last
    /// α used, times pscale²). Both must be positive and finite.
    Resume { rho_prev: f64, pscale: f64 },
}

/// How a [`DeviceCg::segment`] ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SegmentEnd {
    /// The recurrence residual met the tolerance: p and ρ are those a resume goes on from.
    Converged,
    /// The iteration limit.
    MaxIterations,
    /// The recurrence residual did not improve for the stagnation window.
    Stagnated,
    /// The caller's watch stopped it.
    Watched,
}

/// What a [`DeviceCg::segment`] reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentInfo {
    pub end: SegmentEnd,
    pub iterations: usize,
    pub recorded_iterations: usize,
    pub status_reads: usize,
    /// The recurrence's relative residual √(r·r)/‖b̂‖ at the end.
    pub recurrence_residual: f64,
    /// ρ of the last α: with `end` = Converged, the `rho_prev` of the next resume (before
    /// its rescaling).
    pub rho: f64,
    /// ρ of the start: resumed, start_rho/`rho_prev` is the β that links this segment's
    /// Lanczos coefficients to the last one's.
    pub start_rho: f64,
    /// ‖b̂‖.
    pub rhs_norm: f64,
}

/// One constraint set on the device (mask and rotation per node) with the bind group that
/// uses it; built by [`DeviceCg::frames`], valid only with the [`DeviceCg`] that built it.
pub struct DeviceFrames {
    owner: u64,
    /// Its own identity: `iterate` needs the frames `prepare` used.
    id: u64,
    /// One bind group per values chunk of H (the kernels that do not read H use the
    /// first).
    groups: Vec<wgpu::BindGroup>,
    /// G = ZᵀZ of the translations of every node with a free component, the first such
    /// node and their count (src/solve/coarse.rs, `translation_gram`): with the E and
    /// absolute row sums `prepare` reduces, whether a translation is pinned by nothing.
    gram: (Vec<f64>, usize, usize),
    /// The coarse space these frames were built for.
    coarse: CoarseSpace,
    /// With `Aggregates`: the aggregate index (`None` when every node is fixed).
    agg: Option<AggregateIndex>,
    /// Kept alive with the bind groups.
    _frame: wgpu::Buffer,
    _rotations: wgpu::Buffer,
    _aggregates: wgpu::Buffer,
    /// The aggregate coarse space's f64 data (shaders/pcg.wgsl, `coarse`).
    coarse_buf: wgpu::Buffer,
    /// With the aggregates: the kernels that form E⁺ from E in `prepare`.
    factor: Option<CoarseFactor>,
}

/// The pipelines of shaders/pcg.wgsl; those the coarse correction changes once per
/// coarse space (`[0]`, `[1]`, `[2]`: none, translations, aggregates: the COARSE
/// override), `init` and `update_yr` once per preconditioner too (none, Jacobi, block
/// Jacobi: the PRECOND override).
struct Pipelines {
    rhs: wgpu::ComputePipeline,
    rhs_given: wgpu::ComputePipeline,
    precond: wgpu::ComputePipeline,
    coarse_e: wgpu::ComputePipeline,
    coarse_e_sum: wgpu::ComputePipeline,
    agg_rows: wgpu::ComputePipeline,
    agg_e: wgpu::ComputePipeline,
    agg_restrict: wgpu::ComputePipeline,
    agg_solve: wgpu::ComputePipeline,
    matvec: wgpu::ComputePipeline,
    world_p: wgpu::ComputePipeline,
    /// The multilevel preconditioner's: pw = V P z (its level-0 product), the r·z
    /// partials after the V-cycle, init and update_yr leaving z to it.
    world_z: wgpu::ComputePipeline,
    ml_dot: wgpu::ComputePipeline,
    ml_start: wgpu::ComputePipeline,
    update_yr_ml: wgpu::ComputePipeline,
    init_ml: wgpu::ComputePipeline,
    scalar_alpha: wgpu::ComputePipeline,
    update_yr: [[wgpu::ComputePipeline; 3]; 3],
    scalar_beta: [wgpu::ComputePipeline; 3],
    update_p: [wgpu::ComputePipeline; 3],
    init: [[wgpu::ComputePipeline; 3]; 3],
    scalar_start: [wgpu::ComputePipeline; 3],
    recover: wgpu::ComputePipeline,
}

/// The bind group layout of shaders/pcg.wgsl and every pipeline of one specialization:
/// what [`DeviceCg::new`] takes from the device's cache ([`GpuContext::cached`]).
struct Kernels {
    layout: wgpu::BindGroupLayout,
    pipes: Pipelines,
}

impl Kernels {
    fn build(dev: &wgpu::Device, ty: Scalars, dim: usize, items: u32, hist: u32) -> Kernels {
        let module = PCG.module(dev, ty.real.name(), ty.acc.name());
        let (layout, pl) = PCG.layouts(dev, "pcg");
        let pipe = |entry: &str, precond: u32, coarse: u32| {
            // SUM_LANES: scalar_start sums three values in one tree, no kernel more; the
            // translations' correction sums r·z, r·r and Zᵀr (2 + D) in one, coarse_e E's
            // D² in trees of five.
            let wide = coarse == 1 || entry.starts_with("coarse_e");
            let lanes = match (wide, dim) {
                (false, _) => 3.0,
                (true, 3) => 5.0,
                (true, _) => 4.0,
            };
            let constants = [
                ("D", dim as f64),
                ("WG", WORKGROUP as f64),
                ("SUM_LANES", lanes),
                ("PRECOND", precond as f64),
                ("COARSE", coarse as f64),
                ("ITEMS", items as f64),
                ("HIST", hist as f64),
                ("DIFF", f64::from(u8::from(ty.difference))),
            ];
            let label = format!("pcg {entry} ({dim}D, preconditioner {precond}, coarse {coarse})");
            kernels::pipeline(dev, &pl, &module, entry, &label, &constants)
        };
        let both = |entry: &str| [0, 1, 2].map(|c| pipe(entry, 0, c));
        let each = |entry: &str| [0, 1, 2].map(|c| [0, 1, 2].map(|k| pipe(entry, k, c)));
        let pipes = Pipelines {
            rhs: pipe("rhs", 0, 0),
            rhs_given: pipe("rhs_given", 0, 0),
            precond: pipe("precond", 0, 0),
            coarse_e: pipe("coarse_e", 0, 0),
            coarse_e_sum: pipe("coarse_e_sum", 0, 0),
            agg_rows: pipe("agg_rows", 0, 2),
            agg_e: pipe("agg_e", 0, 2),
            agg_restrict: pipe("agg_restrict", 0, 2),
            agg_solve: pipe("agg_solve", 0, 2),
            matvec: pipe("matvec", 0, 0),
            world_p: pipe("world_p", 0, 0),
            world_z: pipe("world_z", 0, 0),
            ml_dot: pipe("ml_dot", 3, 0),
            ml_start: pipe("ml_start", 3, 0),
            update_yr_ml: pipe("update_yr", 3, 0),
            init_ml: pipe("init", 3, 0),
            scalar_alpha: pipe("scalar_alpha", 0, 0),
            update_yr: each("update_yr"),
            scalar_beta: both("scalar_beta"),
            update_p: both("update_p"),
            init: each("init"),
            scalar_start: both("scalar_start"),
            recover: pipe("recover", 0, 0),
        };
        Kernels { layout, pipes }
    }
}

/// E of the translations for the last `prepare`.
#[derive(Debug, Clone)]
enum Galerkin {
    /// Reduced on the device (in `scal`), not read back yet.
    OnDevice,
    /// Read back and symmetrized (D², row-major) with its pseudo-inverse, `None` when
    /// every translation is constrained or E is not finite (no correction then, as on
    /// the CPU).
    Read {
        e: Vec<f64>,
        /// 2^-64 · Σ |entries| of the rows of each world axis (D).
        abs: Vec<f64>,
        einv: Option<Vec<f64>>,
    },
}

/// The device buffers of the CG (all f64 vectors are n·d, node-major).
struct Buffers {
    /// Per values chunk of H: its parameters and its values.
    params: Vec<wgpu::Buffer>,
    pattern: wgpu::Buffer,
    hvals: Vec<wgpu::Buffer>,
    grad: wgpu::Buffer,
    y: wgpu::Buffer,
    r: wgpu::Buffer,
    z: wgpu::Buffer,
    p: wgpu::Buffer,
    q: wgpu::Buffer,
    /// V P p, what the matvec multiplies H by.
    pw: wgpu::Buffer,
    b: wgpu::Buffer,
    minv: wgpu::Buffer,
    dx: wgpu::Buffer,
    partials: wgpu::Buffer,
    scal: wgpu::Buffer,
    state: wgpu::Buffer,
    /// `scal` and `state` gathered for one read-back.
    status: wgpu::Buffer,
    /// The difference form's row sums S_i = Σ_j H_ij (a placeholder without it).
    rowsum: wgpu::Buffer,
}

/// The eliminated PCG on a device block matrix, built once per pattern, in H's
/// precision ([`Scalars`]).
/// Per Newton iteration: [`DeviceCg::solve`] (or [`DeviceCg::prepare`] then
/// [`DeviceCg::iterate`]) after every `assemble`; Δx is then in [`DeviceCg::dx_buffer`].
pub struct DeviceCg {
    ctx: GpuContext,
    id: u64,
    ty: Scalars,
    dim: usize,
    n_nodes: usize,
    /// The launches of every kernel.
    launches: Launches,
    /// Partial sums per reduction (its segments).
    n_partials: u32,
    /// The bind group layout and pipelines, shared with every device PCG of the same
    /// specialization on this device.
    kernels: Arc<Kernels>,
    buf: Buffers,
    /// The frames `prepare` last built b̂ and the preconditioner for.
    prepared: Option<u64>,
    /// E of that `prepare`.
    galerkin: Galerkin,
    /// Bytes of the aggregates' E read back and E⁺ written so far (a part of the
    /// context's traffic: none where `prepare` forms E⁺ on the device, (D·aggregates)²
    /// values each way per fallback and per E⁺ from the host, whatever the mesh).
    coarse_traffic: TrafficCount,
    /// The pattern as uploaded (row pointers, column indices, diagonal blocks), for the
    /// aggregates of [`DeviceCg::frames`].
    host_pattern: Vec<u32>,
    /// b̂ comes from the host ([`DeviceCg::prepare_with_rhs`]), not from a gradient.
    given_rhs: bool,
    /// Lanczos pairs recorded per solve (the HIST override; 0: none).
    hist: u32,
    /// The iteration counts at which the last solve's CG runs began (0, then each
    /// restart): where its Lanczos sequence is cut.
    run_starts: Vec<usize>,
    /// The iterations of the last solve.
    last_iterations: usize,
    /// Iterations recorded into command buffers and status reads of the current solve.
    recorded: Cell<usize>,
    reads: Cell<usize>,
    /// The multilevel preconditioner's V-cycle, once asked for, and whether its levels
    /// are those of the last `prepare`'s system.
    ml: Option<DeviceMultilevel>,
    ml_ready: bool,
}

mod coarse_start;
mod segment;

impl DeviceCg {
    /// Pipelines and buffers for the block matrix `h` (its values are read in place by
    /// every solve: write new ones there, then [`DeviceCg::prepare`]), in its precision
    /// with the device's sums ([`Scalars::on`]). `grad` is the gradient g (of H's
    /// precision) from which [`DeviceCg::prepare`] forms b̂ = −P Vᵀ g; without it b̂ is
    /// given ([`DeviceCg::prepare_with_rhs`]).
    ///
    /// With `lanczos` the CG records its first [`LANCZOS_HIST`] Lanczos coefficient pairs
    /// for [`DeviceCg::condition_estimate`]. With `difference` (f32 values only) the
    /// product takes the difference form, whose row sums the caller writes
    /// ([`DeviceCg::write_row_sums`]) with every new H.
    pub fn new(
        ctx: &GpuContext,
        h: BlockMatrix<'_>,
        grad: Option<&wgpu::Buffer>,
        lanczos: bool,
        difference: bool,
    ) -> Result<Self, GpuError> {
        let real = if h.f64 { Real::F64 } else { Real::F32 };
        let ty = Scalars::on(ctx, real, difference)?;
        let ctx = ctx.clone();
        let dim = h.dim;
        let (row_ptr, col_idx) = (h.row_ptr, h.col_idx);
        let n = row_ptr.len().saturating_sub(1);
        let nnz = col_idx.len();
        let dev = &ctx.device;

        // The pattern as u32: row pointers, column indices, per node its diagonal block.
        let too_big = |what: &str| {
            GpuError::Unsupported(format!("the {what} exceed the device CG's u32 indices"))
        };
        let mut pattern: Vec<u32> = Vec::with_capacity(2 * n + 1 + nnz);
        for &v in row_ptr.iter().chain(col_idx) {
            pattern.push(u32::try_from(v).map_err(|_| too_big("block indices"))?);
        }
        for i in 0..n {
            let row = &col_idx[row_ptr[i]..row_ptr[i + 1]];
            let k = row
                .iter()
                .position(|&j| j == i)
                .ok_or_else(|| GpuError::Mismatch(format!("node {i} has no diagonal block")))?;
            pattern.push(u32::try_from(row_ptr[i] + k).map_err(|_| too_big("block indices"))?);
        }
        let col_at = u32::try_from(n + 1).map_err(|_| too_big("nodes"))?;
        let diag_at = u32::try_from(n + 1 + nnz).map_err(|_| too_big("blocks"))?;
        // The segmented reductions: partials per segment, workgroups by the device.
        let policy = ctx.segments();
        let limits = ctx.launch();
        let segments = policy.segments(n as u64, WORKGROUP);
        let n_partials = u32::try_from(segments).map_err(|_| too_big("nodes"))?;
        let chunks = h.chunks;
        let seg_len = (WORKGROUP * policy.items) as usize;
        let launches = Launches {
            segments: policy.launch(&limits, segments, WORKGROUP),
            chunk_segments: chunks
                .iter()
                .map(|c| {
                    let s = c.rows.end.div_ceil(seg_len) - c.rows.start / seg_len;
                    policy.launch(&limits, s as u64, WORKGROUP)
                })
                .collect(),
            chunk_rows: chunks
                .iter()
                .map(|c| limits.grid(c.rows.len() as u64, WORKGROUP))
                .collect(),
            // An invocation per node on a GPU; a CPU adapter's few workgroups loop.
            nodes: policy.launch(&limits, (n as u64).div_ceil(WORKGROUP as u64), WORKGROUP),
        };

        // Pipelines, compiled once per device and specialization.
        let hist = if lanczos { LANCZOS_HIST } else { 0 };
        PCG.check_adapter(&ctx)?;
        let key = format!(
            "pcg pipelines: {}/{}, difference {}, {dim}D, {} items, history {hist}",
            ty.real.name(),
            ty.acc.name(),
            ty.difference,
            policy.items
        );
        let kernels = ctx.cached(&key, || Kernels::build(dev, ty, dim, policy.items, hist))?;

        // Buffers, limits checked first.
        let sz = Sizes::new(n, dim, segments, chunks.len(), hist, ty);
        let zeroed = |label: &str, bytes: u64| ctx.storage_zeroed(label, bytes);
        let vector = |label: &str| zeroed(label, sz.vector);
        let pattern_buf = ctx.storage_with("pcg pattern", bytemuck::cast_slice(&pattern))?;
        let mut params = Vec::with_capacity(chunks.len());
        for (c, ch) in chunks.iter().enumerate() {
            let p = PcgParams {
                n_nodes: u32::try_from(n).map_err(|_| too_big("nodes"))?,
                n_partials,
                col_at,
                diag_at,
                row_begin: ch.rows.start as u32,
                row_end: ch.rows.end as u32,
                block_first: ch.blocks.start as u32,
                chunk: c as u32,
            };
            params.push(ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("pcg params of values chunk {c}")),
                contents: bytemuck::bytes_of(&p),
                usage: wgpu::BufferUsages::UNIFORM,
            }));
        }
        let buf = Buffers {
            params,
            pattern: pattern_buf,
            hvals: chunks.iter().map(|c| c.buffer.clone()).collect(),
            grad: match grad {
                Some(g) => g.clone(),
                None => zeroed("pcg gradient (b̂ is given)", 16)?,
            },
            y: vector("pcg y")?,
            r: vector("pcg r")?,
            z: vector("pcg z")?,
            p: vector("pcg p")?,
            q: vector("pcg q")?,
            pw: vector("pcg p in the world frame")?,
            b: vector("pcg rhs")?,
            minv: zeroed("pcg preconditioner", sz.minv)?,
            dx: vector("pcg dx")?,
            partials: zeroed("pcg partial sums", sz.partials)?,
            scal: zeroed("pcg scalars", sz.scal)?,
            state: zeroed("pcg state", 4 * slots::N_STATE as u64)?,
            status: zeroed("pcg status", status_bytes(ty.acc))?,
            rowsum: zeroed("pcg row sums of the difference form", sz.rowsum)?,
        };
        ctx.check("building the device PCG")?;
        Ok(DeviceCg {
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            ctx,
            ty,
            dim,
            n_nodes: n,
            launches,
            n_partials,
            kernels,
            buf,
            prepared: None,
            galerkin: Galerkin::OnDevice,
            coarse_traffic: TrafficCount::default(),
            host_pattern: pattern,
            given_rhs: grad.is_none(),
            hist,
            run_starts: Vec::new(),
            last_iterations: 0,
            recorded: Cell::new(0),
            reads: Cell::new(0),
            ml: None,
            ml_ready: false,
        })
    }

    /// The device memory [`DeviceCg::new`] and [`DeviceCg::frames`] take beside H's values
    /// and the gradient, for `n` block rows and `nnz` blocks in `dim` with H in `chunks`
    /// buffers and `rotated` rotated nodes (the aggregates' index arrays and values, a few
    /// words per node, not counted: frames without them take two 16-byte placeholders,
    /// counted), in the precision `ty`: what a caller adds to H's bytes to refuse a system
    /// that does not fit before anything is allocated.
    pub fn device_bytes(
        ctx: &GpuContext,
        (n, nnz, dim): (usize, usize, usize),
        chunks: usize,
        rotated: usize,
        lanczos: bool,
        ty: Scalars,
    ) -> u64 {
        let p = crate::gpu::context::padded_size;
        let segments = ctx.segments().segments(n as u64, WORKGROUP);
        let hist = if lanczos { LANCZOS_HIST } else { 0 };
        let sz = Sizes::new(n, dim, segments, chunks, hist, ty);
        let pattern = 4 * (2 * n as u64 + 1 + nnz as u64);
        // The frame words and the rotations, one buffer each.
        let frames = p(8 * n as u64) + p(ty.real.size() * (rotated * dim * dim) as u64);
        p(pattern)
            + N_VECTORS * p(sz.vector)
            + p(sz.minv)
            + p(sz.rowsum)
            + p(sz.partials)
            + p(sz.scal)
            + p(4 * slots::N_STATE as u64)
            + p(status_bytes(ty.acc))
            + chunks as u64 * p(std::mem::size_of::<PcgParams>() as u64)
            + frames
            + 2 * p(16)
    }

    /// The world-frame Δx of the last successful solve (n·d `real`, node-major).
    pub fn dx_buffer(&self) -> &wgpu::Buffer {
        &self.buf.dx
    }

    /// The scalar types this PCG runs in.
    pub fn scalars(&self) -> Scalars {
        self.ty
    }

    /// Δx read back to the host (a full read-back: for tests and diagnostics, not the loop).
    pub fn read_dx(&self) -> Result<Vec<f64>, GpuError> {
        self.read_vector(&self.buf.dx, "reading back the Newton step")
    }

    /// One n·d `real` vector read back as f64.
    fn read_vector(&self, buf: &wgpu::Buffer, what: &str) -> Result<Vec<f64>, GpuError> {
        let nd = (self.n_nodes * self.dim) as u64;
        let bytes = self.ctx.download(buf, 0, self.ty.real.size() * nd, what)?;
        Ok(self.ty.real.values(&bytes))
    }

    /// The difference form's row sums S_i = Σ_j H_ij (node-major, d² per node, row-major,
    /// summed in f64 from the values just written to H:
    /// [`crate::gpu::blocks::row_sums`]); refused by a PCG
    /// built without the form.
    pub fn write_row_sums(&self, sums: &[f64]) -> Result<(), GpuError> {
        let d = self.dim;
        if !self.ty.difference || sums.len() != self.n_nodes * d * d {
            return Err(GpuError::Mismatch(format!(
                "row sums: {} values for a PCG {} the difference form on {} nodes",
                sums.len(),
                if self.ty.difference {
                    "with"
                } else {
                    "without"
                },
                self.n_nodes
            )));
        }
        self.ctx
            .write_buffer(&self.buf.rowsum, 0, &self.ty.real.bytes(sums));
        Ok(())
    }

    /// κ̃(M⁻¹Ĥ) of the last solve from its Lanczos coefficients (a PCG built with
    /// `lanczos`): the largest over its runs (cut at restarts) of at least 2 iterations
    /// within the first [`LANCZOS_HIST`]; `None` without one (a read-back).
    pub fn condition_estimate(&self) -> Result<Option<f64>, GpuError> {
        let n = self.last_iterations.min(self.hist as usize);
        if n < 2 {
            return Ok(None);
        }
        let h = self.lanczos_pairs(n)?;
        let mut ends: Vec<usize> = self.run_starts.iter().skip(1).copied().collect();
        ends.push(self.last_iterations);
        let mut kappa: Option<f64> = None;
        for (&a, &b) in self.run_starts.iter().zip(&ends) {
            let b = b.min(n);
            if b < a + 2 {
                continue;
            }
            let alphas: Vec<f64> = (a..b).map(|j| h[2 * j]).collect();
            let betas: Vec<f64> = (a..b - 1).map(|j| h[2 * j + 1]).collect();
            if let Some(k) = crate::solve::cg::lanczos_condition(&alphas, &betas) {
                kappa = Some(kappa.map_or(k, |c| c.max(k)));
            }
        }
        Ok(kappa)
    }

    /// The first `n` (α_j, β_{j+1}) pairs of the current run's Lanczos history,
    /// interleaved (a PCG built with `lanczos`; at most [`LANCZOS_HIST`]).
    fn lanczos_pairs(&self, n: usize) -> Result<Vec<f64>, GpuError> {
        let n = n.min(self.hist as usize);
        if n == 0 {
            return Ok(Vec::new());
        }
        let acc = self.ty.acc;
        let bytes = self.ctx.download(
            &self.buf.scal,
            acc.size() * slots::SCAL_HIST as u64,
            acc.size() * 2 * n as u64,
            "reading back the Lanczos coefficients",
        )?;
        Ok(acc.values(&bytes))
    }

    /// The Lanczos coefficients of the current run's first `iterations` (at most
    /// [`LANCZOS_HIST`]): α_0..α_{k−1} and β_1..β_{k−1}.
    pub fn lanczos_history(&self, iterations: usize) -> Result<(Vec<f64>, Vec<f64>), GpuError> {
        let h = self.lanczos_pairs(iterations)?;
        let k = h.len() / 2;
        let alphas = (0..k).map(|j| h[2 * j]).collect();
        let betas = (0..k.saturating_sub(1)).map(|j| h[2 * j + 1]).collect();
        Ok((alphas, betas))
    }

    /// The preconditioner the last `prepare` built, read back in the CPU CG's layout
    /// ([`crate::solve::cg::BuiltPreconditioner::data`]): the Jacobi diagonal (n·d) or the
    /// block-Jacobi inverses (n·d², row-major per node); empty for none and the multilevel
    /// preconditioner. For tests of the one block-Jacobi specification.
    pub fn preconditioner_data(&self, pc: Preconditioner) -> Result<Vec<f64>, GpuError> {
        let (n, d) = (self.n_nodes, self.dim);
        let (first, len) = match pc {
            Preconditioner::Jacobi => (n * d * d, n * d),
            Preconditioner::BlockJacobi => (0, n * d * d),
            _ => return Ok(Vec::new()),
        };
        let rs = self.ty.real.size();
        let bytes = self.ctx.download(
            &self.buf.minv,
            rs * first as u64,
            rs * len as u64,
            "reading back the preconditioner",
        )?;
        Ok(self.ty.real.values(&bytes))
    }

    /// The solution y of Ĥ y = b̂ (frame coordinates, n·d) read back.
    pub fn read_y(&self) -> Result<Vec<f64>, GpuError> {
        self.read_vector(&self.buf.y, "reading back the PCG's solution")
    }

    /// Uploads one constraint set (mask per node, rotation per rotated node) and builds
    /// its bind group, once: callers keep it for as long as the constraints hold. With
    /// `coarse` = `Aggregates` also the aggregates of the pattern and their index arrays
    /// ([`aggregates`]); frames built for another coarse space refuse it in `iterate`.
    /// Refuses frames of another mesh and prescribed (non-zero) constraint values, which
    /// a Newton step never has.
    pub fn frames(&self, f: &Frames, coarse: CoarseSpace) -> Result<DeviceFrames, GpuError> {
        let (n, d) = (self.n_nodes, self.dim);
        if f.dim != d || f.n_nodes != n {
            return Err(GpuError::Mismatch(format!(
                "the constraints are for {} nodes in {}D, the mesh has {n} in {d}D",
                f.n_nodes, f.dim
            )));
        }
        if !f.homogeneous && !self.given_rhs {
            return Err(GpuError::Unsupported(
                "the device PCG forms b̂ from a gradient for homogeneous constraints only \
                 (a Newton step prescribes no displacement)"
                    .into(),
            ));
        }
        if f.mask.len() != n
            || f.rot_index.len() != n
            || f.rotations.len() != d * d * f.rot_nodes.len()
        {
            return Err(GpuError::Mismatch(
                "the constraint frames' arrays disagree with their node count".into(),
            ));
        }
        let mut frame = Vec::with_capacity(2 * n);
        for i in 0..n {
            let ri = f.rot_index[i];
            if ri != NO_ROTATION && ri as usize >= f.rot_nodes.len() {
                return Err(GpuError::Mismatch(format!(
                    "node {i} names rotation {ri} of {}",
                    f.rot_nodes.len()
                )));
            }
            frame.push(f.mask[i] as u32);
            frame.push(ri);
        }
        let frame_buf = self
            .ctx
            .storage_with("pcg frames", bytemuck::cast_slice(&frame))?;
        let rot_buf = self
            .ctx
            .storage_with("pcg rotations", &self.ty.real.bytes(&f.rotations))?;
        let agg = match coarse {
            CoarseSpace::Aggregates => {
                let (row_ptr, col_idx) = self.usize_pattern();
                aggregates::aggregate_index(&row_ptr, &col_idx, f)?
            }
            _ => None,
        };
        let mut agg = agg;
        // The index words live on the device only: taken, not kept on the host.
        let (agg_words, coarse_bytes) = match agg.as_mut() {
            Some(a) => (
                std::mem::take(&mut a.words),
                self.ty.acc.size() * a.values as u64,
            ),
            None => (vec![0u32; 4], 16),
        };
        let agg_buf = self
            .ctx
            .storage_with("pcg aggregates", bytemuck::cast_slice(&agg_words))?;
        let coarse_buf = self.ctx.storage_zeroed("pcg coarse space", coarse_bytes)?;
        let factor = match &agg {
            Some(a) => Some(CoarseFactor::new(
                &self.ctx,
                d,
                self.ty.acc,
                a,
                &coarse_buf,
                &self.buf.state,
            )?),
            None => None,
        };
        let b = &self.buf;
        let mut groups = Vec::with_capacity(b.hvals.len());
        for (params, hvals) in b.params.iter().zip(&b.hvals) {
            let bufs: [&wgpu::Buffer; 21] = [
                params,
                &b.pattern,
                hvals,
                &b.grad,
                &frame_buf,
                &rot_buf,
                &b.y,
                &b.r,
                &b.z,
                &b.p,
                &b.q,
                &b.b,
                &b.minv,
                &b.dx,
                &b.partials,
                &b.scal,
                &b.state,
                &agg_buf,
                &coarse_buf,
                &b.pw,
                &b.rowsum,
            ];
            groups.push(kernels::bind_group(
                &self.ctx.device,
                &self.kernels.layout,
                "pcg bind group",
                &bufs,
            ));
        }
        self.ctx.check("uploading the constraint frames")?;
        Ok(DeviceFrames {
            owner: self.id,
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            groups,
            gram: crate::solve::coarse::translation_gram(f),
            coarse,
            agg,
            _frame: frame_buf,
            _rotations: rot_buf,
            _aggregates: agg_buf,
            coarse_buf,
            factor,
        })
    }

    /// The block pattern's row pointers and column indices as `usize` (from the uploaded
    /// u32 copy; only while aggregates are built).
    fn usize_pattern(&self) -> (Vec<usize>, Vec<usize>) {
        let n = self.n_nodes;
        let p = &self.host_pattern;
        let row_ptr: Vec<usize> = p[..=n].iter().map(|&v| v as usize).collect();
        let nnz = row_ptr[n];
        let col_idx = p[n + 1..n + 1 + nnz].iter().map(|&v| v as usize).collect();
        (row_ptr, col_idx)
    }

    fn own(&self, frames: &DeviceFrames) -> Result<(), GpuError> {
        if frames.owner != self.id {
            return Err(GpuError::Mismatch(
                "these device frames were built by another device CG".into(),
            ));
        }
        Ok(())
    }

    fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// Records `kernels` (pipeline, workgroups, bind group) in one compute pass.
    fn pass(enc: &mut wgpu::CommandEncoder, label: &str, kernels: &[Kernel]) {
        let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        let mut bound: Option<&wgpu::BindGroup> = None;
        for &(pipe, launch, group) in kernels {
            if bound.is_none_or(|b| !std::ptr::eq(b, group)) {
                cp.set_bind_group(0, group, &[]);
                bound = Some(group);
            }
            cp.set_pipeline(pipe);
            launch.dispatch(&mut cp);
        }
    }

    /// `pipe` once per values chunk of H, in row order, each with its chunk's launch and
    /// bind group.
    fn per_chunk<'a>(
        pipe: &'a wgpu::ComputePipeline,
        launches: &'a [Launch],
        frames: &'a DeviceFrames,
    ) -> impl Iterator<Item = Kernel<'a>> {
        launches
            .iter()
            .zip(&frames.groups)
            .map(move |(l, g)| (pipe, *l, g))
    }

    /// b̂ = −P Vᵀ g, the preconditioners (Jacobi and block Jacobi both) and E = ZᵀĤZ of
    /// the translations from the current assembly; call after every `assemble` (or
    /// constraint change). No read-back: E (D² values) is read by the first `iterate`
    /// that uses the coarse correction.
    pub fn prepare(&mut self, frames: &DeviceFrames) -> Result<(), GpuError> {
        if self.given_rhs {
            return Err(GpuError::Mismatch(
                "this device PCG has no gradient: b̂ is given (prepare_with_rhs)".into(),
            ));
        }
        self.prepare_kernels(frames, false)
    }

    /// [`DeviceCg::prepare`] with b̂ given (frame coordinates, zero in the constrained
    /// components, n·d) for a PCG built without a gradient.
    pub fn prepare_with_rhs(&mut self, frames: &DeviceFrames, rhs: &[f64]) -> Result<(), GpuError> {
        self.write_rhs(frames, rhs)?;
        self.prepare_kernels(frames, true)
    }

    /// Writes a given b̂ (refused for a PCG that forms it from its gradient).
    fn write_rhs(&mut self, frames: &DeviceFrames, rhs: &[f64]) -> Result<(), GpuError> {
        if !self.given_rhs {
            return Err(GpuError::Mismatch(
                "this device PCG forms b̂ from its gradient (prepare)".into(),
            ));
        }
        if rhs.len() != self.n_nodes * self.dim {
            return Err(GpuError::Mismatch(format!(
                "b̂ has {} entries, the system {}",
                rhs.len(),
                self.n_nodes * self.dim
            )));
        }
        self.own(frames)?;
        self.ctx
            .write_buffer(&self.buf.b, 0, &self.ty.real.bytes(rhs));
        Ok(())
    }

    /// Refuses frames that the last `prepare` did not see.
    fn check_prepared(&self, frames: &DeviceFrames) -> Result<(), GpuError> {
        if self.prepared != Some(frames.id) {
            return Err(GpuError::Mismatch(
                "the device CG was not prepared with these frames (call prepare first)".into(),
            ));
        }
        Ok(())
    }

    /// E⁺ of the aggregates written from the host for the iterations of the current
    /// `prepare`, in place of the device's (whose failure flag it clears).
    fn write_aggregate_einv(&mut self, frames: &DeviceFrames, einv: &[f64]) {
        let Some(a) = &frames.agg else { return };
        let acc = self.ty.acc;
        self.ctx.write_buffer(
            &frames.coarse_buf,
            acc.size() * a.einv_at as u64,
            &acc.bytes(einv),
        );
        self.ctx.write_buffer(
            &self.buf.state,
            4 * slots::STATE_COARSE_FAILED as u64,
            &[0u8; 4],
        );
        self.coarse_traffic.host_to_device_bytes += acc.size() * einv.len() as u64;
    }

    fn prepare_kernels(&mut self, frames: &DeviceFrames, given: bool) -> Result<(), GpuError> {
        self.own(frames)?;
        let mut enc = self.encoder("pcg prepare");
        let l = &self.launches;
        let p = &self.kernels.pipes;
        let g0 = &frames.groups[0];
        let rhs = if given { &p.rhs_given } else { &p.rhs };
        // The failure flag belongs to this prepare (the factorization sets it).
        let flag = 4 * slots::STATE_COARSE_FAILED as u64;
        enc.clear_buffer(&self.buf.state, flag, Some(4));
        let mut kernels: Vec<Kernel> = vec![(rhs, l.segments, g0)];
        kernels.extend(Self::per_chunk(&p.precond, &l.chunk_rows, frames));
        kernels.extend(Self::per_chunk(&p.coarse_e, &l.chunk_segments, frames));
        kernels.push((&p.coarse_e_sum, ONE, g0));
        if let Some(a) = &frames.agg {
            kernels.extend(Self::per_chunk(&p.agg_rows, &l.chunk_rows, frames));
            let e = self.ctx.launch().grid((a.k * a.k) as u64, WORKGROUP);
            kernels.push((&p.agg_e, e, g0));
        }
        if let Some(f) = &frames.factor {
            kernels.extend(f.kernels());
        }
        Self::pass(&mut enc, "pcg prepare", &kernels);
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check("preparing the device PCG")?;
        self.prepared = Some(frames.id);
        self.galerkin = Galerkin::OnDevice;
        self.ml_ready = false;
        Ok(())
    }

    /// The multilevel preconditioner of the system just prepared (built on the host from
    /// the same H and constraints `frames` were built from: [`Multilevel::new`]),
    /// uploaded for the iterations with [`Preconditioner::Multilevel`]; call after every
    /// `prepare`. A hierarchy met before keeps its buffers and only the values move; the
    /// same generation of levels ([`Multilevel::generation`]: kept levels refreshed) moves
    /// only its smoothing weights.
    ///
    /// The cluster inverses go in buffers of consecutive clusters under the adapter's
    /// binding limit, lowered to `binding_limit` where given (tests of the split path): the
    /// smoothings run once per buffer, with the same sums as one buffer.
    pub fn set_multilevel(
        &mut self,
        ml: &Multilevel,
        frames: &Frames,
        binding_limit: Option<u64>,
    ) -> Result<(), GpuError> {
        if frames.n_nodes != self.n_nodes {
            return Err(GpuError::Mismatch(format!(
                "the constraints have {} nodes, the device PCG {}",
                frames.n_nodes, self.n_nodes
            )));
        }
        if self.ty != Scalars::F64 {
            return Err(GpuError::Unsupported(
                "the multilevel preconditioner runs in f64 only".into(),
            ));
        }
        if self.ml.is_none() {
            self.ml = Some(DeviceMultilevel::new(&self.ctx, self.dim)?);
        }
        let finest = Finest {
            r: &self.buf.r,
            z: &self.buf.z,
            q: &self.buf.q,
            state: &self.buf.state,
        };
        if let Some(dm) = self.ml.as_mut() {
            dm.set(ml, frames, finest, binding_limit)?;
        }
        self.ml_ready = true;
        Ok(())
    }

    /// Clusters per level of the multilevel preconditioner on the device, finest first
    /// (empty before [`DeviceCg::set_multilevel`]).
    pub fn multilevel_clusters(&self) -> Vec<usize> {
        self.ml
            .as_ref()
            .map(DeviceMultilevel::cluster_counts)
            .unwrap_or_default()
    }

    /// Buffers of cluster inverses per level of the multilevel preconditioner on the
    /// device, finest first (empty before [`DeviceCg::set_multilevel`]).
    pub fn multilevel_inverse_buffers(&self) -> Vec<usize> {
        self.ml
            .as_ref()
            .map(DeviceMultilevel::inverse_chunk_counts)
            .unwrap_or_default()
    }

    /// The fallback where `prepare` could not factor E of the aggregates on the device:
    /// E read back, pseudo-inverted on the host as the CPU does
    /// ([`crate::solve::coarse::aggregates_einv_from_galerkin`], whose fallback is the
    /// eigen pseudo-inverse of the whole of E) and E⁺ written back (zero where E has no
    /// usable part: no correction then).
    fn upload_aggregate_einv(&mut self, frames: &DeviceFrames) -> Result<(), GpuError> {
        let Some(a) = frames.agg.as_ref() else {
            return Ok(());
        };
        let e = self.read_coarse(
            frames,
            a.e_at,
            a.k * a.k,
            "reading back the aggregates' coarse matrix E = ZᵀĤZ",
        )?;
        let einv =
            crate::solve::coarse::aggregates_einv_from_galerkin(self.dim, a.count, e, &a.gram)
                .unwrap_or_else(|| vec![0.0; a.k * a.k]);
        self.coarse_traffic.device_to_host_bytes += self.ty.acc.size() * (a.k * a.k) as u64;
        self.write_aggregate_einv(frames, &einv);
        Ok(())
    }

    /// The aggregates' E and E⁺ moved between host and device so far (part of the
    /// context's [`GpuContext::traffic`]).
    pub fn coarse_traffic(&self) -> TrafficCount {
        self.coarse_traffic
    }

    /// E of the last `prepare` read back and pseudo-inverted, with its rows' absolute sums
    /// (once per `prepare`).
    fn read_galerkin(&mut self) -> Result<(), GpuError> {
        if let Galerkin::Read { .. } = self.galerkin {
            return Ok(());
        }
        let d = self.dim;
        let what = "reading back the coarse matrix E = ZᵀĤZ";
        let len = (slots::SCAL_EABS - slots::SCAL_E) as usize + d;
        let acc = self.ty.acc;
        let bytes = self.ctx.download(
            &self.buf.scal,
            acc.size() * slots::SCAL_E as u64,
            acc.size() * len as u64,
            what,
        )?;
        let v = acc.values(&bytes);
        let mut e = v[..d * d].to_vec();
        let abs = v[(slots::SCAL_EABS - slots::SCAL_E) as usize..].to_vec();
        // As src/solve/coarse.rs: the mean of E and Eᵀ, then the pseudo-inverse.
        for a in 0..d {
            for b in 0..a {
                let m = 0.5 * (e[a * d + b] + e[b * d + a]);
                e[a * d + b] = m;
                e[b * d + a] = m;
            }
        }
        let einv = crate::solve::coarse::pseudo_inverse(d, &e);
        self.galerkin = Galerkin::Read { e, abs, einv };
        Ok(())
    }

    /// The coarse matrix E = ZᵀĤZ of the last `prepare` computed on the host in f64 from
    /// `h` (the values this PCG holds, before rounding) and the frames `f` these frames
    /// were built from, in place of the device's reduction: an f32 PCG sums blocks rounded
    /// to f32, whose rounding (ε_f32‖H‖ per row) swamps a free body's mass term, the very
    /// part of E the correction is for. The translations' absolute row sums (the check of
    /// a pinned body) stay the device's. Call after every `prepare`.
    pub fn set_galerkin_from_host(
        &mut self,
        frames: &DeviceFrames,
        h: &crate::core::sparse::BlockCsr,
        f: &crate::core::constraints::Frames,
    ) -> Result<(), GpuError> {
        self.own(frames)?;
        self.check_prepared(frames)?;
        let d = self.dim;
        self.read_galerkin()?;
        if let Galerkin::Read { e, einv, .. } = &mut self.galerkin {
            let (host_e, _) = crate::solve::coarse::translations_galerkin_from_blocks(h, f);
            *einv = crate::solve::coarse::pseudo_inverse(d, &host_e);
            *e = host_e;
        }
        if let Some(a) = &frames.agg {
            let (row_ptr, col_idx) = self.usize_pattern();
            let agg = crate::solve::coarse::Aggregation::from_pattern(&row_ptr, &col_idx, f);
            let einv = crate::solve::coarse::aggregates_einv_from_blocks(h, f, &agg)
                .unwrap_or_else(|| vec![0.0; a.k * a.k]);
            self.write_aggregate_einv(frames, &einv);
        }
        Ok(())
    }

    /// Refuses a system that a rigid translation of the free nodes leaves singular to
    /// working precision, by the CPU CG's test ([`crate::solve::coarse::is_unpinned`]),
    /// with every free node as one group (the CPU tests each connected group).
    fn check_pinned(&mut self, frames: &DeviceFrames) -> Result<(), GpuError> {
        self.read_galerkin()?;
        let (g, first, count) = &frames.gram;
        if *count == 0 {
            return Ok(());
        }
        if let Galerkin::Read { e, abs, .. } = &self.galerkin {
            let t = crate::solve::coarse::group_translation(self.dim, e, g, abs, *first, *count);
            if let Some(t) = t.filter(crate::solve::coarse::is_unpinned) {
                return Err(CgError::Unpinned(t).into());
            }
        }
        Ok(())
    }

    /// E = ZᵀĤZ of the translations (D², row-major, symmetrized) and its pseudo-inverse
    /// (`None`: no correction) as the last `iterate` read them (every solve reads E for
    /// its check of the translations); `None` before one. For tests and diagnostics.
    pub fn coarse_matrix(&self) -> Option<(&[f64], Option<&[f64]>)> {
        match &self.galerkin {
            Galerkin::Read { e, einv, .. } => Some((e, einv.as_deref())),
            Galerkin::OnDevice => None,
        }
    }

    /// Whether the last `iterate` found no usable E of the translations (every translation
    /// constrained, or E not finite): the translations' correction then adds nothing.
    pub fn translations_inactive(&self) -> bool {
        matches!(self.galerkin, Galerkin::Read { einv: None, .. })
    }

    /// E⁺ of the aggregates (K×K, row-major) as the last `prepare` formed it (or the
    /// host's, after a fallback or [`DeviceCg::set_galerkin_from_host`]); `None` for
    /// frames without aggregates. For tests and diagnostics (a read-back).
    pub fn aggregate_einv(&self, frames: &DeviceFrames) -> Result<Option<Vec<f64>>, GpuError> {
        self.own(frames)?;
        let Some(a) = &frames.agg else {
            return Ok(None);
        };
        let einv = self.read_coarse(
            frames,
            a.einv_at,
            a.k * a.k,
            "reading back the aggregates' E⁺",
        )?;
        Ok(Some(einv))
    }

    /// `len` values of the frames' coarse buffer (`acc`) from index `at`.
    fn read_coarse(
        &self,
        frames: &DeviceFrames,
        at: usize,
        len: usize,
        what: &str,
    ) -> Result<Vec<f64>, GpuError> {
        let acc = self.ty.acc;
        let bytes = self.ctx.download(
            &frames.coarse_buf,
            acc.size() * at as u64,
            acc.size() * len as u64,
            what,
        )?;
        Ok(acc.values(&bytes))
    }

    /// Records the status copies (`scal`, `state` into `status`) after the work of `enc`,
    /// submits, and reads the 128 status bytes back (one wait).
    fn submit_and_read(
        &self,
        mut enc: wgpu::CommandEncoder,
        what: &str,
    ) -> Result<ChunkStatus, GpuError> {
        let acc = self.ty.acc;
        let sb = acc.size() * slots::STATUS_SCAL as u64;
        enc.copy_buffer_to_buffer(&self.buf.scal, 0, &self.buf.status, 0, sb);
        enc.copy_buffer_to_buffer(
            &self.buf.state,
            0,
            &self.buf.status,
            sb,
            4 * slots::N_STATE as u64,
        );
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check(what)?;
        let bytes = self
            .ctx
            .download(&self.buf.status, 0, status_bytes(acc), what)?;
        self.reads.set(self.reads.get() + 1);
        let scal = acc.values(&bytes[..sb as usize]);
        Ok(ChunkStatus::read(
            &scal,
            &schedule::state_words(&bytes[sb as usize..]),
        ))
    }

    /// Clears the four stop flags (the iteration count stays): the next CG dispatches run.
    fn clear_flags(&self) {
        self.ctx
            .write_buffer(&self.buf.state, 0, &[0u8; 4 * slots::STATE_ITERS as usize]);
    }

    /// CG from y = 0 on the b̂ and preconditioner of the last [`DeviceCg::prepare`] with
    /// these frames, until the true residual ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol, then Δx = V P y into
    /// [`DeviceCg::dx_buffer`].
    ///
    /// The recurrence residual decides when to look: once it meets the tolerance, the true
    /// residual is computed in f64 on the device (q = Ĥy, r = b̂ − q); if it misses, CG
    /// restarts from y with that residual. Iterations are recorded in chunks, one status
    /// read-back each (the first chunk 8 iterations, then as many as the residual's rate of
    /// fall predicts, at least 2, at most double the last and 256: [`schedule::next_chunk`],
    /// the schedule of `solve`'s CG too).
    pub fn iterate(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<DeviceCgInfo, GpuError> {
        self.iterate_to(frames, params, &mut |_| params.tol)
    }

    /// [`DeviceCg::iterate`] with the tolerance chosen from ‖b̂‖ once it is known (read
    /// back with the start's status): `tolerance(‖b̂‖)` replaces `params.tol`.
    pub fn iterate_to(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        tolerance: &mut dyn FnMut(f64) -> f64,
    ) -> Result<DeviceCgInfo, GpuError> {
        self.run(frames, params, tolerance, false)
    }

    /// [`DeviceCg::iterate`] from the y the last iterate left (a restart: r = b̂ − Ĥy),
    /// for a caller whose own check of y missed the tolerance.
    pub fn iterate_from_current(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<DeviceCgInfo, GpuError> {
        self.run(frames, params, &mut |_| params.tol, true)
    }

    /// What every run checks and sets up before its start: the frames, the tolerance, the
    /// preconditioner's state (E⁺ of the translations or the aggregates on the device),
    /// and the scalars it starts from (written by the caller).
    fn begin(&mut self, frames: &DeviceFrames, params: &DeviceCgParams) -> Result<Begun, GpuError> {
        self.own(frames)?;
        self.check_prepared(frames)?;
        let tol = check_tol(params.tol)?;
        let (pre, co) = overrides(params, frames)?;
        if pre != 3
            && params.coarse == CoarseSpace::Aggregates
            && frames.coarse != CoarseSpace::Aggregates
        {
            return Err(GpuError::Mismatch(
                "the device CG's aggregates need frames built for them (DeviceCg::frames)".into(),
            ));
        }
        if pre == 3 && !(self.ml_ready && self.ml.as_ref().is_some_and(DeviceMultilevel::is_set)) {
            return Err(GpuError::Mismatch(
                "the multilevel preconditioner was not set for this system (call \
                 set_multilevel after prepare)"
                    .into(),
            ));
        }
        self.check_pinned(frames)?;
        self.recorded.set(0);
        self.reads.set(0);
        // Every slot before E: the scalars, c and E⁺ (zero without the correction, or
        // when every translation is constrained: then c = 0 and so is the correction).
        let mut scal = [0.0f64; slots::SCAL_E as usize];
        scal[slots::SCAL_TOL2 as usize] = tol * tol;
        if co == 1 {
            self.read_galerkin()?;
            if let Galerkin::Read {
                einv: Some(einv), ..
            } = &self.galerkin
            {
                let at = slots::SCAL_EINV as usize;
                scal[at..at + einv.len()].copy_from_slice(einv);
            }
        }
        Ok(Begun { tol, pre, co, scal })
    }

    fn run(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        tolerance: &mut dyn FnMut(f64) -> f64,
        from_current: bool,
    ) -> Result<DeviceCgInfo, GpuError> {
        let Begun { pre, co, scal, .. } = self.begin(frames, params)?;
        let max = params.max_iterations;
        self.ctx
            .write_buffer(&self.buf.scal, 0, &self.ty.acc.bytes(&scal));
        self.clear_state();

        // Start: from y = 0, so q = Ĥy = 0 without a product, or from the current y.
        let record = |cg: &DeviceCg| {
            let mut enc = cg.encoder("pcg start");
            let mut kernels: Vec<Kernel> = Vec::new();
            if from_current {
                kernels.extend(cg.product_of_y(&mut enc, frames));
            } else {
                enc.clear_buffer(&cg.buf.y, 0, None);
                enc.clear_buffer(&cg.buf.q, 0, None);
            }
            kernels.extend(cg.start(frames, pre, co));
            Self::pass(&mut enc, "pcg start", &kernels);
            enc
        };
        let mut st = self.start_status(frames, co, "starting the device PCG", &record)?;
        st.error(0)?;
        self.run_starts = vec![0];
        let bb = st.bb;
        let rhs_norm = bb.sqrt();
        let tol = check_tol(tolerance(rhs_norm))?;
        let tol2 = tol * tol;
        self.ctx.write_buffer(
            &self.buf.scal,
            self.ty.acc.size() * slots::SCAL_TOL2 as u64,
            &self.ty.acc.bytes(&[tol2]),
        );
        let relative = |rr: f64| {
            if bb == 0.0 {
                if rr == 0.0 {
                    0.0
                } else {
                    1.0
                }
            } else {
                rr.sqrt() / rhs_norm
            }
        };
        // The smallest true residual so far: a check that does not improve on it ends the
        // solve in stagnation (the recurrence residual of f64 CG goes on falling long
        // after the true one has stopped at its rounding floor).
        let mut best_true = f64::INFINITY;
        // Each pass of this loop starts from a status whose r·r is the true residual.
        loop {
            let rel = relative(st.rr);
            if rel <= tol {
                break;
            }
            if st.iterations >= max {
                return Err(CgError::MaxIterations {
                    iterations: st.iterations,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            if st.converged {
                // The device's r·r ≤ tol²‖b̂‖² held where the host's quotient missed tol
                // by rounding: go on iterating.
                self.clear_flags();
            }
            let ended = self.chunks(frames, (pre, co), params, tol2 * bb, &mut st, None)?;
            // The true residual at y: q = Ĥy (y copied into p), r = b̂ − q, p = z.
            self.clear_flags();
            let mut enc = self.encoder("pcg true residual");
            let mut kernels = self.product_of_y(&mut enc, frames);
            kernels.extend(self.start(frames, pre, co));
            Self::pass(&mut enc, "pcg true residual", &kernels);
            st = self.submit_and_read(enc, "the device PCG's true residual")?;
            st.error(0)?;
            let rel = relative(st.rr);
            // A run that ends on no better a true residual than the best before it is at
            // the rounding floor, whether its recurrence met the tolerance or the
            // stagnation window ended it: another restart would only repeat it. A run whose
            // recurrence met the tolerance must also halve the best: away from the floor
            // the true residual falls with the recurrence, at the floor it only creeps
            // (f32's for hundreds of iterations) while the recurrence falls on past it.
            let gain = match ended {
                Chunked::Stopped if st.iterations < max => MIN_RESTART_GAIN,
                _ => 1.0,
            };
            if rel > tol && rel >= gain * best_true {
                return Err(CgError::Stagnation {
                    iterations: st.iterations,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            best_true = best_true.min(rel);
            self.run_starts.push(st.iterations);
        }
        // The last true residual met the tolerance: it began no run.
        if self.run_starts.len() > 1 {
            self.run_starts.pop();
        }
        self.last_iterations = st.iterations;
        if !self.given_rhs {
            let mut enc = self.encoder("pcg recovery");
            Self::pass(
                &mut enc,
                "pcg recovery",
                &[(
                    &self.kernels.pipes.recover,
                    self.launches.nodes,
                    &frames.groups[0],
                )],
            );
            self.ctx.queue.submit([enc.finish()]);
            self.ctx.check("recovering the device Newton step")?;
        }
        Ok(DeviceCgInfo {
            iterations: st.iterations,
            restarts: self.run_starts.len() - 1,
            recorded_iterations: self.recorded.get(),
            status_reads: self.reads.get(),
            relative_residual: relative(st.rr),
            rhs_norm,
            tolerance: tol,
        })
    }

    /// q = Ĥx for a given x (frame coordinates, n·d) with these frames, read back: the
    /// product every iteration runs, for tests of the operator. Overwrites y (an
    /// `iterate` starts afresh from y = 0).
    pub fn apply(&mut self, frames: &DeviceFrames, x: &[f64]) -> Result<Vec<f64>, GpuError> {
        self.own(frames)?;
        if x.len() != self.n_nodes * self.dim {
            return Err(GpuError::Mismatch(format!(
                "x has {} entries, the system {}",
                x.len(),
                self.n_nodes * self.dim
            )));
        }
        self.ctx
            .write_buffer(&self.buf.y, 0, &self.ty.real.bytes(x));
        // No stop flag: the product runs.
        self.clear_state();
        let mut enc = self.encoder("pcg product");
        let kernels = self.product_of_y(&mut enc, frames);
        Self::pass(&mut enc, "pcg product", &kernels);
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check("the device PCG's product")?;
        self.read_vector(&self.buf.q, "reading back the product")
    }

    /// q = Ĥy: y copied into p (recorded in `enc`), then the kernels of pw = V P p and the
    /// product.
    fn product_of_y<'a>(
        &'a self,
        enc: &mut wgpu::CommandEncoder,
        frames: &'a DeviceFrames,
    ) -> Vec<Kernel<'a>> {
        enc.copy_buffer_to_buffer(&self.buf.y, 0, &self.buf.p, 0, None);
        let mut k = vec![(
            &self.kernels.pipes.world_p,
            self.launches.nodes,
            &frames.groups[0],
        )];
        k.extend(Self::per_chunk(
            &self.kernels.pipes.matvec,
            &self.launches.chunk_segments,
            frames,
        ));
        k
    }

    /// The kernels of a (re)start from the q = Ĥy in `q`: r, z, p, ρ and the true r·r; with
    /// the coarse correction `update_p` (β = 0) then completes p = z + Z E⁺Zᵀr.
    fn start<'a>(&'a self, frames: &'a DeviceFrames, pre: usize, co: usize) -> Vec<Kernel<'a>> {
        let p = &self.kernels.pipes;
        let g0 = &frames.groups[0];
        let l = &self.launches;
        if pre == 3 {
            let mut k = vec![(&p.init_ml, l.segments, g0)];
            k.extend(self.vcycle(frames).into_iter().map(|(_, k)| k));
            k.push((&p.ml_start, l.segments, g0));
            k.push((&p.scalar_start[0], ONE, g0));
            return k;
        }
        let mut k = vec![(&p.init[co][pre], l.segments, g0)];
        k.extend(self.aggregate_correction(frames, co));
        k.push((&p.scalar_start[co], ONE, g0));
        if co != 0 {
            k.push((&p.update_p[co], l.nodes, g0));
        }
        k
    }

    /// With the aggregates (`co` = 2): w = Zᵀr (a workgroup per aggregate) and c = E⁺w (a
    /// workgroup per coarse row).
    fn aggregate_correction<'a>(&'a self, frames: &'a DeviceFrames, co: usize) -> Vec<Kernel<'a>> {
        let (p, limits) = (&self.kernels.pipes, self.ctx.launch());
        // A workgroup per aggregate (coarse row) on a GPU; a CPU adapter's few loop over
        // them, each still summed by one workgroup in the same order.
        let policy = self.ctx.segments();
        match (&frames.agg, co) {
            (Some(a), 2) => vec![
                (
                    &p.agg_restrict,
                    policy.launch(&limits, a.count as u64, WORKGROUP),
                    &frames.groups[0],
                ),
                (
                    &p.agg_solve,
                    policy.launch(&limits, a.k as u64, WORKGROUP),
                    &frames.groups[0],
                ),
            ],
            _ => Vec::new(),
        }
    }

    /// The dispatches of z = M⁻¹r with the multilevel preconditioner (r and z the PCG's),
    /// named: the V-cycle's, with level 0's product the PCG's own (pw = V P z, then q = Ĥz).
    fn vcycle<'a>(&'a self, frames: &'a DeviceFrames) -> Vec<(&'static str, Kernel<'a>)> {
        let Some(ml) = &self.ml else {
            return Vec::new();
        };
        let mut out = Vec::new();
        for step in ml.steps() {
            match step {
                Step::Kernel(name, pipe, launch, group) => out.push((name, (pipe, launch, group))),
                Step::FinestProduct => {
                    out.push((
                        "ml world_z",
                        (
                            &self.kernels.pipes.world_z,
                            self.launches.nodes,
                            &frames.groups[0],
                        ),
                    ));
                    out.extend(
                        Self::per_chunk(
                            &self.kernels.pipes.matvec,
                            &self.launches.chunk_segments,
                            frames,
                        )
                        .map(|k| ("ml matvec", k)),
                    );
                }
            }
        }
        out
    }

    /// The dispatches of one CG iteration, named.
    fn iteration<'a>(
        &'a self,
        frames: &'a DeviceFrames,
        pre: usize,
        co: usize,
    ) -> Vec<(&'static str, Kernel<'a>)> {
        let (p, l) = (&self.kernels.pipes, &self.launches);
        let g0 = &frames.groups[0];
        let mut one: Vec<(&'static str, Kernel)> =
            Self::per_chunk(&p.matvec, &l.chunk_segments, frames)
                .map(|k| ("matvec", k))
                .collect();
        if pre == 3 {
            one.extend([
                ("scalar_alpha", (&p.scalar_alpha, ONE, g0)),
                ("update_yr", (&p.update_yr_ml, l.segments, g0)),
            ]);
            one.extend(self.vcycle(frames));
            one.extend([
                ("ml_dot", (&p.ml_dot, l.segments, g0)),
                ("scalar_beta", (&p.scalar_beta[0], ONE, g0)),
                ("update_p", (&p.update_p[0], l.nodes, g0)),
            ]);
            return one;
        }
        one.extend([
            ("scalar_alpha", (&p.scalar_alpha, ONE, g0)),
            ("update_yr", (&p.update_yr[co][pre], l.segments, g0)),
        ]);
        let agg = self.aggregate_correction(frames, co);
        one.extend(["agg_restrict", "agg_solve"].into_iter().zip(agg));
        one.extend([
            ("scalar_beta", (&p.scalar_beta[co], ONE, g0)),
            ("update_p", (&p.update_p[co], l.nodes, g0)),
        ]);
        one
    }

    /// What one CG iteration launches with these frames and parameters, and the bytes it
    /// must move at the least (every array its kernels read or write, once per kernel):
    /// the floor against which a measured time per iteration is a bandwidth.
    pub fn iteration_profile(
        &self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<IterationProfile, GpuError> {
        let (pre, co) = overrides(params, frames)?;
        let dispatches = self
            .iteration(frames, pre, co)
            .into_iter()
            .map(|(name, (_, l, _))| DispatchRecord {
                kernel: name,
                workgroups: l.workgroups(),
                threads: l.threads(WORKGROUP),
            })
            .collect();
        let (n, d) = (self.n_nodes as u64, self.dim as u64);
        let nnz = self.host_pattern[self.n_nodes] as u64;
        let rs = self.ty.real.size();
        let vec = rs * n * d;
        let partials = self.ty.acc.size() * self.n_partials as u64;
        // matvec: H, its column indices and row pointers, the frames, pw, p, q (and the
        // difference form's row sums).
        let rowsum = if self.ty.difference {
            rs * n * d * d
        } else {
            0
        };
        let matvec = nnz * (rs * d * d + 4) + 4 * (n + 1) + 8 * n + 3 * vec + rowsum;
        // update_yr: y and r read and written, p, q and the preconditioner read, z written.
        let minv = [0, vec, rs * n * d * d, 0][pre];
        let update_yr = 7 * vec + minv + 8 * n * u64::from(co == 1);
        // update_p: z and p read, p and pw written, the frames (and each node's aggregate).
        let update_p = 4 * vec + [8 * n, 8 * n, 12 * n][co];
        let agg = frames.agg.as_ref().filter(|_| co == 2).map_or(0, |a| {
            let k = a.k as u64;
            // restrict: r, the frames and the node lists; solve: E⁺ and w.
            vec + 12 * n + self.ty.acc.size() * (k * k + 2 * k)
        });
        // The V-cycle: its own kernels, two more level-0 products (pw = V P z first) and
        // ml_dot (r and z read).
        let ml = match (&self.ml, pre) {
            (Some(m), 3) => m.bytes_per_cycle() + 2 * (matvec + 2 * vec + 8 * n) + 2 * vec,
            _ => 0,
        };
        Ok(IterationProfile {
            dispatches,
            bytes: matvec + update_yr + update_p + agg + ml + 2 * partials,
        })
    }

    /// Device time of each dispatch of one CG iteration with these frames and parameters,
    /// in seconds (fastest and mean over `reps` iterations), from timestamp queries
    /// around each dispatch in its own compute pass; `None` without TIMESTAMP_QUERY.
    /// Runs from y = 0 with no stopping test; the next iterate starts afresh.
    pub fn profile_iteration(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        reps: usize,
    ) -> Result<Option<Vec<KernelTime>>, GpuError> {
        if !self.ctx.has_timestamps() {
            return Ok(None);
        }
        self.own(frames)?;
        let (pre, co) = overrides(params, frames)?;
        if co == 2 {
            // No start status here: the factorization's flag is read on its own.
            let flag = 4 * slots::STATE_COARSE_FAILED as u64;
            let what = "reading the coarse factorization's flag";
            let word = self.ctx.download(&self.buf.state, flag, 4, what)?;
            if schedule::state_words(&word)[0] != 0 {
                self.upload_aggregate_einv(frames)?;
            }
        }
        // Tolerance 0: no stop flag is ever set, so every dispatch does its work.
        self.ctx.write_buffer(
            &self.buf.scal,
            0,
            &vec![0u8; (self.ty.acc.size() * slots::SCAL_E as u64) as usize],
        );
        self.clear_state();
        let mut enc = self.encoder("pcg profile start");
        enc.clear_buffer(&self.buf.y, 0, None);
        enc.clear_buffer(&self.buf.q, 0, None);
        Self::pass(&mut enc, "pcg profile start", &self.start(frames, pre, co));
        self.ctx.queue.submit([enc.finish()]);
        let one = self.iteration(frames, pre, co);
        let n_q = 2 * one.len() as u32;
        let dev = &self.ctx.device;
        let set = dev.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("pcg profile timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: n_q,
        });
        let resolve = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pcg profile resolve"),
            size: 8 * n_q as u64,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let period_s = self.ctx.queue.get_timestamp_period() as f64 * 1e-9;
        let mut best = vec![f64::INFINITY; one.len()];
        let mut sum = vec![0.0f64; one.len()];
        for _ in 0..reps.max(1) {
            let mut enc = self.encoder("pcg profile");
            for (j, &(_, (pipe, launch, group))) in one.iter().enumerate() {
                let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("pcg profile pass"),
                    timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                        query_set: &set,
                        beginning_of_pass_write_index: Some(2 * j as u32),
                        end_of_pass_write_index: Some(2 * j as u32 + 1),
                    }),
                });
                cp.set_bind_group(0, group, &[]);
                cp.set_pipeline(pipe);
                launch.dispatch(&mut cp);
            }
            enc.resolve_query_set(&set, 0..n_q, &resolve, 0);
            self.ctx.queue.submit([enc.finish()]);
            let bytes =
                self.ctx
                    .download(&resolve, 0, 8 * n_q as u64, "reading back timestamps")?;
            let t: Vec<u64> = bytes
                .chunks_exact(8)
                .map(|c| {
                    let mut w = [0u8; 8];
                    w.copy_from_slice(c);
                    u64::from_le_bytes(w)
                })
                .collect();
            for j in 0..one.len() {
                let dt = t[2 * j + 1].saturating_sub(t[2 * j]) as f64 * period_s;
                best[j] = best[j].min(dt);
                sum[j] += dt;
            }
        }
        Ok(Some(
            one.iter()
                .zip(best.into_iter().zip(sum))
                .map(|(&(name, _), (best_s, sum_s))| KernelTime {
                    name: name.to_string(),
                    best_s,
                    mean_s: sum_s / reps.max(1) as f64,
                })
                .collect(),
        ))
    }

    /// CG iterations in chunks from the current state until the recurrence residual meets
    /// `thresh` (on r·r), `params.max_iterations` are done in all, or the stagnation
    /// window asks for the true residual; `st` is the last status.
    fn chunks(
        &self,
        frames: &DeviceFrames,
        (pre, co): (usize, usize),
        params: &DeviceCgParams,
        thresh: f64,
        st: &mut ChunkStatus,
        mut watch: Option<&mut ChunkWatch>,
    ) -> Result<Chunked, GpuError> {
        let mut k = FIRST_CHUNK;
        let max = params.max_iterations;
        let window = params.stagnation_window.max(1);
        let start = st.iterations;
        // The smallest recurrence r·r so far and where it was reached.
        let (mut best, mut best_at) = (st.rr, st.iterations);
        // (iterations, ln r·r) at each status read of this run.
        let mut hist: Vec<(usize, f64)> = Vec::new();
        if st.rr > 0.0 && st.rr.is_finite() {
            hist.push((st.iterations, st.rr.ln()));
        }
        loop {
            let kk = k.min(max.saturating_sub(st.iterations));
            if kk == 0 {
                return Ok(Chunked::Stopped);
            }
            if st.iterations - start >= window {
                return Ok(Chunked::Check);
            }
            let kk = kk.min(window - (st.iterations - start));
            let one: Vec<Kernel> = self
                .iteration(frames, pre, co)
                .into_iter()
                .map(|(_, k)| k)
                .collect();
            let kernels: Vec<Kernel> = (0..kk).flat_map(|_| one.iter().copied()).collect();
            self.recorded.set(self.recorded.get() + kk);
            let mut enc = self.encoder("pcg chunk");
            Self::pass(&mut enc, "pcg chunk", &kernels);
            *st = self.submit_and_read(enc, "a device PCG chunk")?;
            st.error(0)?;
            if st.converged {
                return Ok(Chunked::Stopped);
            }
            if let Some(w) = watch.as_deref_mut() {
                if w(self, st.iterations)? {
                    return Ok(Chunked::Watched);
                }
            }
            if st.rr < best {
                (best, best_at) = (st.rr, st.iterations);
            } else if st.iterations - best_at >= window {
                return Ok(Chunked::Check);
            }
            if st.rr > 0.0 && st.rr.is_finite() {
                hist.push((st.iterations, st.rr.ln()));
            }
            k = schedule::next_chunk(&hist, thresh, kk, MIN_CHUNK, MAX_CHUNK);
        }
    }

    /// [`DeviceCg::prepare`] then [`DeviceCg::iterate`]: Δx of the current assembly.
    pub fn solve(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<DeviceCgInfo, GpuError> {
        self.prepare(frames)?;
        self.iterate(frames, params)
    }
}

impl DeviceFrames {
    /// The number of aggregates of the coarse space these frames were built for (`None`
    /// without the aggregates, or when every node is fixed).
    pub fn aggregate_count(&self) -> Option<usize> {
        self.agg.as_ref().map(|a| a.count)
    }
}

/// The PRECOND override of a preconditioner.
fn precond_index(p: Preconditioner) -> Result<usize, GpuError> {
    match p {
        Preconditioner::None => Ok(0),
        Preconditioner::Jacobi => Ok(1),
        Preconditioner::BlockJacobi => Ok(2),
        Preconditioner::Multilevel => Ok(3),
    }
}

/// The PRECOND and COARSE overrides of `params` on these frames. The multilevel
/// preconditioner has coarse levels of its own and takes no coarse space (as on the CPU).
fn overrides(params: &DeviceCgParams, frames: &DeviceFrames) -> Result<(usize, usize), GpuError> {
    let pre = precond_index(params.preconditioner)?;
    let co = if pre == 3 {
        0
    } else {
        coarse_index(params.coarse, frames)
    };
    Ok((pre, co))
}

/// A CG tolerance must be positive and finite (written to reject NaN too).
fn check_tol(tol: f64) -> Result<f64, GpuError> {
    if tol > 0.0 && tol.is_finite() {
        Ok(tol)
    } else {
        Err(GpuError::Unsupported(format!(
            "the CG tolerance must be positive and finite, not {tol}"
        )))
    }
}

/// A run's checked setup ([`DeviceCg::begin`]).
struct Begun {
    tol: f64,
    pre: usize,
    co: usize,
    /// The scalars before E that the run starts from.
    scal: [f64; slots::SCAL_E as usize],
}

/// The COARSE override of a coarse space on these frames (aggregates with every node
/// fixed: no aggregate, no correction).
fn coarse_index(c: CoarseSpace, frames: &DeviceFrames) -> usize {
    match c {
        CoarseSpace::None => 0,
        CoarseSpace::Translations => 1,
        CoarseSpace::Aggregates if frames.agg.is_none() => 0,
        CoarseSpace::Aggregates => 2,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shader is well typed in every precision the PCG instantiates: f64, and f32
    /// vectors with f64 or (a device without SHADER_F64) f32 accumulators.
    #[test]
    fn every_precision_parses() {
        for (real, acc) in [("f64", "f64"), ("f32", "f64"), ("f32", "f32")] {
            let m = kernels::check::module(&PCG, real, acc);
            naga::valid::Validator::new(
                naga::valid::ValidationFlags::all(),
                naga::valid::Capabilities::all(),
            )
            .validate(&m)
            .unwrap_or_else(|e| panic!("pcg.wgsl ({real}/{acc}): {e:?}"));
        }
    }

    /// Bind group 0 is [`PCG`]'s bindings in order with their access, the params
    /// struct has Rust's size, and every aggregate header constant has Rust's value (the
    /// CG's slots come from the prelude, `gpu::kernels::slots`).
    #[test]
    fn layout_params_and_headers_match_the_wgsl() {
        let m = kernels::check::layout(&PCG, "PcgParams", std::mem::size_of::<PcgParams>(), &[]);
        use aggregates::header as h;
        let agg = [
            ("AGG_COUNT", h::COUNT),
            ("AGG_K", h::K),
            ("AGG_OF", h::OF),
            ("AGG_PTR", h::PTR),
            ("AGG_NODES", h::NODES),
            ("AGG_SLOT_PTR", h::SLOT_PTR),
            ("AGG_SLOT_OF", h::SLOT_OF),
            ("AGG_PAIR_PTR", h::PAIR_PTR),
            ("AGG_PAIR_SLOTS", h::PAIR_SLOTS),
            ("AGG_PAIR_OF", h::PAIR_OF),
            ("AGG_E", h::E),
            ("AGG_EINV", h::EINV),
            ("AGG_W", h::W),
            ("AGG_C", h::C),
        ];
        for (name, want) in agg {
            let (_, c) = m
                .constants
                .iter()
                .find(|(_, c)| c.name.as_deref() == Some(name))
                .unwrap_or_else(|| panic!("no const {name}"));
            match m.global_expressions[c.init] {
                naga::Expression::Literal(naga::Literal::U32(v)) => assert_eq!(v, want, "{name}"),
                ref e => panic!("{name} = {e:?}"),
            }
        }
        for e in [
            "rhs",
            "precond",
            "matvec",
            "scalar_alpha",
            "update_yr",
            "scalar_beta",
            "update_p",
            "init",
            "scalar_start",
            "recover",
            "coarse_e",
            "coarse_e_sum",
            "agg_rows",
            "agg_e",
            "agg_restrict",
            "agg_solve",
        ] {
            assert!(
                m.entry_points.iter().any(|p| p.name == e),
                "no entry point {e}"
            );
        }
    }
}
