//! [`DeviceCg`]: the device PCG's buffers, launches and bind groups, and its driver.
//!
//! - `kernels`: the shader families (product, updates and scalars, coarse spaces), each
//!   owning its pipelines, selected by preconditioner, coarse space and mode;
//! - `frames`: a constraint set on the device ([`DeviceFrames`]);
//! - `coarse`: the coarse spaces' host side (E of the translations, the aggregates' E⁺)
//!   and the multilevel preconditioner's levels;
//! - `run`: the driver: chunks of iterations, their verification, status reads, restarts
//!   from the true residual;
//! - `segment`: runs that resume a search direction (mixed precision's reliable updates);
//! - `profile`: what one iteration dispatches and moves, and its kernels' device times.

use crate::gpu::blocks::{BlockMatrix, ValuesChunk};
use crate::gpu::kernels::{slots, Real};
use crate::gpu::{GpuContext, GpuError, Launch, Phase, ReadRange, TrafficCount};
use crate::solve::cg::Preconditioner;
use crate::solve::coarse::CoarseSpace;
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::multilevel::DeviceMultilevel;

mod coarse;
mod coarse_start;
mod frames;
mod kernels;
mod levels;
mod profile;
mod run;
mod segment;

use super::aggregates::AggregateIndex;
use super::coarse_factor::CoarseFactor;
use kernels::{Co, Kernels, Mode, PcgParams, Pre, Spec, WORKGROUP};
pub use kernels::{Scalars, PCG_COARSE, PCG_PRODUCT, PCG_UPDATE};

/// Lanczos coefficient pairs a PCG built with history records per solve (the HIST
/// override): enough for κ̃ on any solve that converges in reasonable time.
pub const LANCZOS_HIST: u32 = 1024;

/// Workgroups of the kernels that sum every partial of the reduction before them
/// (update_yr sums the product's p·q for α, update_p the updates' r·z and r·r for β):
/// each of them reads all n/64 partials (on a GPU), so their count bounds that redundant
/// work, while 2,048 workgroups of 64 invocations still fill a large GPU.
const FUSED_GROUPS: u64 = 2048;

/// Bytes of the status read back per chunk: the leading `scal` slots (`acc`) then
/// `state`.
fn status_bytes(acc: Real) -> u64 {
    acc.size() * slots::STATUS_SCAL as u64 + 4 * slots::N_STATE as u64
}

/// Iterations of the first chunk, the shortest and the longest chunk
/// ([`schedule::next_chunk`]).
pub(crate) const FIRST_CHUNK: usize = 8;
/// The longest first chunk of a PCG's first solve, and how many solves back the first chunk of
/// the next one looks ([`DeviceCg::first_chunk`]).
const FIRST_CHUNK_SOLVE: usize = 32;
const RECENT_SOLVES: usize = 4;
const MIN_CHUNK: usize = 2;
const MAX_CHUNK: usize = 256;

/// The factor by which a run whose recurrence met the tolerance must lower the best true
/// residual before it; less ends the solve in `CgError::Stagnation` (see `run`; the
/// same 2× as mixed precision asks of its f32 segments).
const MIN_RESTART_GAIN: f64 = 0.5;

/// Identities of every [`DeviceCg`] and [`DeviceFrames`]: frames built for one CG are
/// refused by another, and `iterate` refuses frames `prepare` did not see.
static NEXT_ID: AtomicU64 = AtomicU64::new(0);

/// One dispatch: pipeline, workgroups, bind group.
type Kernel<'a> = (wgpu::ComputePipeline, Launch, &'a wgpu::BindGroup);

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
    pub(super) fn new(
        n: usize,
        dim: usize,
        segments: u64,
        chunks: usize,
        hist: u32,
        ty: Scalars,
    ) -> Self {
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
    /// The segmented reductions over every node (rhs, init, ml_dot).
    segments: Launch,
    /// The kernels that sum every partial of the reduction before them (update_yr,
    /// update_p, start_p): at most [`FUSED_GROUPS`] workgroups.
    fused: Launch,
    /// Per values chunk of H: its segmented reductions (matvec, coarse_e) and its
    /// per-row kernels (precond, agg_rows).
    chunk_segments: Vec<Launch>,
    chunk_rows: Vec<Launch>,
    /// One invocation per node (world_y, recover).
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
    /// solve in `CgError::Stagnation`, and so does one not below half the best after a
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
    pub(super) owner: u64,
    /// Its own identity: `iterate` needs the frames `prepare` used.
    pub(super) id: u64,
    /// One bind group per values chunk of H (the kernels that do not read H use the
    /// first).
    pub(super) groups: Vec<wgpu::BindGroup>,
    /// G = ZᵀZ of the translations of every node with a free component (src/solve/coarse.rs,
    /// `translation_gram`): with the E and absolute row sums `prepare` reduces, whether a
    /// translation is pinned by nothing.
    pub(super) gram: crate::solve::coarse::TranslationGram,
    /// The coarse space these frames were built for.
    pub(super) coarse: CoarseSpace,
    /// With `Aggregates`: the aggregate index (`None` when every node is fixed).
    pub(super) agg: Option<AggregateIndex>,
    /// Kept alive with the bind groups (and bound by the multilevel setup's: cg/levels.rs).
    pub(super) _frame: wgpu::Buffer,
    pub(super) _rotations: wgpu::Buffer,
    pub(super) _aggregates: wgpu::Buffer,
    /// The aggregate coarse space's f64 data (shaders/pcg_coarse.wgsl, `coarse`).
    pub(super) coarse_buf: wgpu::Buffer,
    /// With the aggregates: the kernels that form E⁺ from E in `prepare`.
    pub(super) factor: Option<CoarseFactor>,
}

/// What the last constraint set uploaded, kept so that the next one uploads only what
/// differs: a Newton loop's constraint sets differ in the few moving nodes that snapped,
/// the aggregates depend on H's pattern alone, and rotations rarely change.
#[derive(Default)]
pub(super) struct Uploaded {
    pub(super) frame: Option<(Vec<u32>, wgpu::Buffer)>,
    pub(super) rotations: Option<(Vec<u8>, wgpu::Buffer)>,
    pub(super) aggregates: Option<(Vec<u8>, wgpu::Buffer)>,
}

/// E of the translations for the last `prepare`.
#[derive(Debug, Clone)]
pub(super) enum Galerkin {
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

/// What a caller records after every chunk of a solve (after its verification and Δx's
/// recovery, in the same submit) and reads back with every status: the work that needs
/// the solution, done without another round trip when the solve succeeds in the chunk.
/// Its kernels must do nothing unless the chunk's verification met the tolerance
/// (STATE_TRUE_OK of [`DeviceCg::state_buffer`]), since most chunks end unconverged.
pub struct Tail<'a> {
    pub record: &'a dyn Fn(&mut wgpu::CommandEncoder) -> Result<(), GpuError>,
    pub read: &'a [ReadRange<'a>],
}

/// The bytes of a tail's ranges read with the status of the chunk whose verification met
/// the tolerance (the solve's answer).
pub type TailBytes = Vec<Vec<u8>>;

/// The device buffers of the CG (all f64 vectors are n·d, node-major).
struct Buffers {
    /// Per values chunk of H: its parameters and its values.
    params: Vec<wgpu::Buffer>,
    pattern: wgpu::Buffer,
    hvals: Vec<wgpu::Buffer>,
    /// Each values chunk's rows and blocks (the multilevel setup reads H by them).
    hruns: Vec<crate::gpu::blocks::RowRun>,
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
    /// context's traffic: (D·aggregates)² values each way per `prepare`, whatever the
    /// mesh).
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
    /// The tolerance the last solve ran to, once its first status was read.
    last_eta: Option<f64>,
    /// The iterations of the last few solves (the next one's first chunk).
    recent: std::collections::VecDeque<usize>,
    /// What the last constraint set uploaded ([`DeviceCg::frames`]).
    uploaded: std::cell::RefCell<Uploaded>,
    /// Iterations recorded into command buffers and status reads of the current solve.
    recorded: Cell<usize>,
    reads: Cell<usize>,
    /// The multilevel preconditioner's V-cycle, once asked for, and whether its levels
    /// are those of the last `prepare`'s system.
    ml: Option<DeviceMultilevel>,
    ml_ready: bool,
}

/// A pattern index past the device CG's u32 words.
fn too_big(what: &str) -> GpuError {
    GpuError::Unsupported(format!("the {what} exceed the device CG's u32 indices"))
}

/// H's pattern as the device CG reads it: row pointers, column indices, then per node
/// the index of its diagonal block, all u32, with where the columns and the diagonals
/// start.
struct PatternWords {
    words: Vec<u32>,
    col_at: u32,
    diag_at: u32,
}

impl PatternWords {
    fn new(row_ptr: &[usize], col_idx: &[usize]) -> Result<Self, GpuError> {
        let n = row_ptr.len().saturating_sub(1);
        let nnz = col_idx.len();
        let mut words: Vec<u32> = Vec::with_capacity(2 * n + 1 + nnz);
        for &v in row_ptr.iter().chain(col_idx) {
            words.push(u32::try_from(v).map_err(|_| too_big("block indices"))?);
        }
        for i in 0..n {
            let row = &col_idx[row_ptr[i]..row_ptr[i + 1]];
            let k = row
                .iter()
                .position(|&j| j == i)
                .ok_or_else(|| GpuError::Mismatch(format!("node {i} has no diagonal block")))?;
            words.push(u32::try_from(row_ptr[i] + k).map_err(|_| too_big("block indices"))?);
        }
        Ok(PatternWords {
            words,
            col_at: u32::try_from(n + 1).map_err(|_| too_big("nodes"))?,
            diag_at: u32::try_from(n + 1 + nnz).map_err(|_| too_big("blocks"))?,
        })
    }
}

impl Launches {
    /// The launches of `n` nodes in `segments` reduction segments, with H's values in
    /// `chunks`, as the device's segment policy and limits allow.
    fn new(ctx: &GpuContext, n: usize, segments: u64, chunks: &[ValuesChunk]) -> Self {
        let policy = ctx.segments();
        let limits = ctx.launch();
        let seg_len = (WORKGROUP * policy.items) as usize;
        Launches {
            segments: policy.launch(&limits, segments, WORKGROUP),
            fused: policy.launch_capped(&limits, segments, FUSED_GROUPS, WORKGROUP),
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
        }
    }
}

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
        let dev = &ctx.device;

        let PatternWords {
            words: pattern,
            col_at,
            diag_at,
        } = PatternWords::new(row_ptr, col_idx)?;
        // The segmented reductions: partials per segment, workgroups by the device.
        let policy = ctx.segments();
        let segments = policy.segments(n as u64, WORKGROUP);
        let n_partials = u32::try_from(segments).map_err(|_| too_big("nodes"))?;
        let chunks = h.chunks;
        let launches = Launches::new(&ctx, n, segments, chunks);

        // Pipelines, compiled once per device and specialization.
        let hist = if lanczos { LANCZOS_HIST } else { 0 };
        PCG_UPDATE.check_adapter(&ctx)?;
        let key = format!(
            "pcg pipelines: {}/{}, difference {}, {dim}D, {} items, history {hist}",
            ty.real.name(),
            ty.acc.name(),
            ty.difference,
            policy.items
        );
        let spec = Spec {
            ty,
            dim,
            items: policy.items,
            hist,
        };
        let kernels = ctx.cached(&key, || Kernels::build(dev, &spec))?;

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
            hruns: chunks
                .iter()
                .map(|c| (c.rows.clone(), c.blocks.clone()))
                .collect(),
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
            last_eta: None,
            recent: std::collections::VecDeque::new(),
            uploaded: Default::default(),
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
    pub(super) fn read_vector(&self, buf: &wgpu::Buffer, what: &str) -> Result<Vec<f64>, GpuError> {
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
    pub(super) fn lanczos_pairs(&self, n: usize) -> Result<Vec<f64>, GpuError> {
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
    pub(super) fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }
    /// Records `kernels` (pipeline, workgroups, bind group) in one compute pass of
    /// `phase`.
    pub(super) fn pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        label: &str,
        phase: Phase,
        kernels: &[Kernel],
    ) {
        let mut cp = self.ctx.compute_pass(enc, label, Some(phase));
        let mut bound: Option<&wgpu::BindGroup> = None;
        for (pipe, launch, group) in kernels {
            if bound.is_none_or(|b| !std::ptr::eq(b, *group)) {
                cp.set_bind_group(0, group);
                bound = Some(group);
            }
            cp.set_pipeline(pipe);
            cp.dispatch(*launch);
        }
    }

    /// `pipe` once per values chunk of H, in row order, each with its chunk's launch and
    /// bind group.
    pub(super) fn per_chunk<'a>(
        pipe: wgpu::ComputePipeline,
        launches: &'a [Launch],
        frames: &'a DeviceFrames,
    ) -> impl Iterator<Item = Kernel<'a>> {
        launches
            .iter()
            .zip(&frames.groups)
            .map(move |(l, g)| (pipe.clone(), *l, g))
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
    pub(super) fn write_rhs(&mut self, frames: &DeviceFrames, rhs: &[f64]) -> Result<(), GpuError> {
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
    pub(super) fn check_prepared(&self, frames: &DeviceFrames) -> Result<(), GpuError> {
        if self.prepared != Some(frames.id) {
            return Err(GpuError::Mismatch(
                "the device CG was not prepared with these frames (call prepare first)".into(),
            ));
        }
        Ok(())
    }
    pub(super) fn prepare_kernels(
        &mut self,
        frames: &DeviceFrames,
        given: bool,
    ) -> Result<(), GpuError> {
        self.own(frames)?;
        let mut enc = self.encoder("pcg prepare");
        let l = &self.launches;
        let (up, co) = (&self.kernels.update, &self.kernels.coarse);
        let dev = &self.ctx;
        let g0 = &frames.groups[0];
        // The failure flag belongs to this prepare (the factorization sets it).
        let flag = 4 * slots::STATE_COARSE_FAILED as u64;
        enc.clear_buffer(&self.buf.state, flag, Some(4));
        let mut kernels: Vec<Kernel> = vec![(up.rhs(dev, given), l.segments, g0)];
        kernels.extend(Self::per_chunk(up.precond(dev), &l.chunk_rows, frames));
        kernels.extend(Self::per_chunk(co.coarse_e(dev), &l.chunk_segments, frames));
        kernels.push((co.coarse_e_sum(dev), ONE, g0));
        if let Some(a) = &frames.agg {
            kernels.extend(Self::per_chunk(co.agg_rows(dev), &l.chunk_rows, frames));
            let e = self.ctx.launch().grid((a.k * a.k) as u64, WORKGROUP);
            kernels.push((co.agg_e(dev), e, g0));
        }
        if let Some(f) = &frames.factor {
            kernels.extend(f.kernels().map(|(p, l, g)| (p.clone(), l, g)));
        }
        self.pass(&mut enc, "pcg prepare", Phase::Elimination, &kernels);
        self.ctx.submit(enc);
        self.ctx.check("preparing the device PCG")?;
        self.prepared = Some(frames.id);
        self.galerkin = Galerkin::OnDevice;
        self.ml_ready = false;
        Ok(())
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

/// The preconditioner's kernels (PRECOND).
fn pre_of(p: Preconditioner) -> Pre {
    match p {
        Preconditioner::None => Pre::None,
        Preconditioner::Jacobi => Pre::Jacobi,
        Preconditioner::BlockJacobi => Pre::BlockJacobi,
        Preconditioner::Multilevel => Pre::Multilevel,
    }
}

/// The preconditioner and coarse correction of `params` on these frames. The multilevel
/// preconditioner has coarse levels of its own and takes no coarse space (as on the CPU);
/// the aggregates with every node fixed have no aggregate and add nothing.
fn overrides(params: &DeviceCgParams, frames: &DeviceFrames) -> (Pre, Co) {
    let pre = pre_of(params.preconditioner);
    let co = match (pre, params.coarse) {
        (Pre::Multilevel, _) | (_, CoarseSpace::None) => Co::None,
        (_, CoarseSpace::Translations) => Co::Translations,
        (_, CoarseSpace::Aggregates) if frames.agg.is_none() => Co::None,
        (_, CoarseSpace::Aggregates) => Co::Aggregates,
    };
    (pre, co)
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
    pre: Pre,
    co: Co,
    /// The scalars before E that the run starts from.
    scal: [f64; slots::SCAL_E as usize],
}
