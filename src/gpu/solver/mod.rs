//! Device-resident preconditioned CG (design.md §4).
//!
//! Per iteration three dispatches: `matvec` (q = Ĥp fused with p·q partials), `update_xrz`
//! (α reduced redundantly per workgroup; x, r, z updated; r·z and r·r partials) and
//! `update_p` (ρ, β and the stop decision reduced redundantly per workgroup; p = z + βp).
//! Scalars stay on the device; one submit records a chunk of iterations and one small
//! status read-back follows it; chunk sizes follow the predicted iterations left
//! (see `run_cg`). Success is declared only after
//! the true residual is recomputed in f64 on the host from the downloaded y.
//!
//! Layout: `info` holds the public report types; `host` the host copy of the system (f64
//! residuals, recovery lift); `builder` buffer allocation and kernel compilation; `levels`
//! the device-side operator, CG level, refinement and recovery and their construction;
//! `setup` the per-system uploads and setup kernels; `run` the CG driver (chunks, status
//! reads, Lanczos estimate); `mixed` mixed precision; `inspect` kernel-level access for
//! tests and benchmarks.

mod builder;
mod host;
mod info;
mod inspect;
mod levels;
mod mixed;
mod run;
mod setup;

pub use info::{BufferRecord, GpuSolveInfo, KernelRecord, KernelTime, Resources, StageSeconds};

use super::{DifferenceForm, GpuContext, GpuError, GpuParams, Precision, MAX_WORKGROUPS};
use crate::cg::{CgError, Preconditioner};
use crate::coarse::{Aggregation, CoarseSpace};
use crate::constraints::Frames;
use crate::elimination::{norm2, Eliminated};
use crate::sparse::BlockCsr;
use crate::springs::MassSpring;
use builder::{u32s, AggBuffers, Builder, Real, Shared};
use host::{spring_adjacency, spring_rhs, Host, HostOp};
use levels::{
    blocks_fit, build_level, build_operator, build_recovery, build_refine, bytes_per_iteration,
    Level, Recovery, Refine, Timestamps,
};
use mixed::inner_scale;
use run::Outcome;
use std::collections::BTreeMap;
use std::time::Instant;

/// Uniform parameters shared by every kernel (mirrors `struct Params` in the shaders).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    n_nodes: u32,
    n_rot: u32,
    n_partials: u32,
    n_blocks: u32,
}
const _: () = assert!(std::mem::size_of::<Params>() == 16);

/// Length of the scalar (acc) and state (u32) arrays of the CG (see cg.wgsl).
const N_SCAL: usize = 8;
/// Lanczos coefficients (α, β pairs) recorded per CG run after the scalars (cg.wgsl).
const LANCZOS_HIST: usize = 1024;
/// Length of the `scal` array: the scalars, then the coefficient history.
const SCAL_LEN: usize = N_SCAL + 2 * LANCZOS_HIST;
/// Mixed: f32 CG is abandoned for f64 once κ̃(M⁻¹Ĥ)·ε_f32 exceeds this. There f32 CG's
/// loss of orthogonality costs more iterations than f32 saves (kappa-1e6, κ̃ε = 0.09:
/// 2.3× f64's count; needles, 0.014: 1.6×; see STABILITY.md).
const F32_KAPPA_LIMIT: f64 = 0.05;
const N_STATE: usize = 8;
/// Top three bits of a packed column index hold the column node's mask.
const MAX_NODES: usize = 1 << 29;

/// The GPU solver: pipelines, buffers and bind groups built once; `update` uploads new
/// values for the same pattern and constraint set; `solve` runs device-resident PCG.
pub struct GpuSolver {
    ctx: GpuContext,
    params: GpuParams,
    dim: usize,
    n_nodes: usize,
    wg: u32,
    n_partials: u32,
    masked: bool,
    host: Host,
    // Held for the solver's lifetime: bind groups reference these buffers.
    #[allow(dead_code)]
    shared: Shared,
    level: Level,
    refine: Option<Refine>,
    recovery: Recovery,
    timestamps: Option<Timestamps>,
    buffers: Vec<BufferRecord>,
    kernels: Vec<KernelRecord>,
    dispatches: BTreeMap<String, u64>,
    bytes_per_iteration: u64,
    upload_seconds: f64,
    setup_seconds: f64,
    readbacks: usize,
    gpu_seconds: f64,
    /// Iterations recorded in chunks since the solve began.
    recorded: usize,
    consts: Consts,
    /// Mixed: the f32 operator holds 2^s·Ĥ (this factor; 1 unless Ĥ's diagonal is extreme).
    inner_scale: f64,
    /// Mixed: the f64 CG level of the fallback, built on first use.
    fallback_level: Option<Level>,
    /// Mixed: run the fallback on the CPU even where an f64 GPU level could be built.
    force_cpu_fallback: bool,
    /// Mixed: why and where the last solve fell back to f64.
    last_fallback: Option<String>,
    /// The scalars and coefficient history of the last status read.
    last_scal: Vec<f64>,
    /// The Lanczos coefficients of the current uninterrupted CG sequence.
    lz_alphas: Vec<f64>,
    lz_betas: Vec<f64>,
    /// The next run continues the sequence (set by a reliable update).
    lz_resumed: bool,
    /// Largest κ̃(M⁻¹Ĥ) of the closed sequences of this solve.
    kappa_est: Option<f64>,
    /// Mixed: the error estimate of the extended-precision refinement of the last solve.
    last_error_estimate: Option<f64>,
    /// Mixed: the assembled Ĥ for the double-double residuals (built on first use).
    assembled: Option<BlockCsr>,
    /// ρ_prev (scal[1]) at the last status read: what a reliable update rescales.
    last_rho_prev: f64,
    /// Size of the first chunk of the next `run_cg` (mixed: the length the previous
    /// segment's late rate predicts).
    chunk_hint: Option<usize>,
    /// The fall of ln r·r per iteration over the later half of the last converged run
    /// (mixed: predicts the next segment's length).
    last_rate: Option<f64>,
    /// E⁺ of the coarse correction (k×k, for Ĥ itself), when it is on.
    coarse_einv: Option<Vec<f64>>,
    /// The aggregates of `--coarse aggregates` (assembled Ĥ only).
    aggregation: Option<Aggregation>,
    /// r·r where the next `run_cg` starts, when known (mixed: 1, the unit right-hand side
    /// with x = 0): the first point of its rate history, so the chunk after the first is
    /// predicted instead of doubled.
    start_rr: Option<f64>,
}

#[derive(Clone, Copy)]
struct Consts {
    d: f64,
    wg: f64,
    masked: bool,
    rotated: bool,
    precond: f64,
    /// Coarse correction on the rigid translations in every CG level (fused into the
    /// CG reductions).
    coarse: bool,
    /// Coarse correction on the translations of this many aggregates (coarse.wgsl); 0: off.
    agg: u32,
    /// Difference form of f32 block operators.
    diff: bool,
}

/// Relative move of the softest translation's eigenvalue above which
/// [`DifferenceForm::Auto`] turns the difference form on.
const DIFF_AUTO_THRESHOLD: f64 = 1e-3;

/// Whether the f32 operator of `host` should use the difference form.
fn wants_difference_form(host: &Host, choice: DifferenceForm, acc: Real) -> bool {
    let HostOp::Blocks(h) = &host.op else {
        return false;
    };
    match choice {
        DifferenceForm::Off => false,
        DifferenceForm::On => true,
        DifferenceForm::Auto if acc == Real::F64 => true,
        DifferenceForm::Auto => crate::coarse::softest_translation(h, &host.frames)
            .is_some_and(|lz| f64::from(f32::EPSILON) * host.diag_max() > DIFF_AUTO_THRESHOLD * lz),
    }
}

fn check_params(ctx: &GpuContext, p: &GpuParams) -> Result<(), GpuError> {
    if p.precision != Precision::F32 && !ctx.has_f64() {
        return Err(GpuError::NoF64 {
            adapter: ctx.info.name.clone(),
            precision: p.precision,
        });
    }
    let wg = p.workgroup_size;
    if !wg.is_power_of_two()
        || !(32..=256).contains(&wg)
        || wg > ctx.limits.max_compute_workgroup_size_x
    {
        return Err(GpuError::Unsupported(format!(
            "workgroup size {wg} (expected a power of two in 32..=256 within the adapter's limit {})",
            ctx.limits.max_compute_workgroup_size_x
        )));
    }
    if let Some(g) = p.workgroups {
        if !(1..=MAX_WORKGROUPS).contains(&g) {
            return Err(GpuError::Unsupported(format!(
                "workgroups {g} (expected 1..={MAX_WORKGROUPS}: the partial sums of a reduction)"
            )));
        }
    }
    // Written to reject NaN too.
    if !(p.tol > 0.0 && p.tol.is_finite()) || p.first_chunk == 0 || p.max_chunk < p.first_chunk {
        return Err(GpuError::Unsupported(
            "tol must be positive and 0 < first_chunk <= max_chunk".into(),
        ));
    }
    if !(p.inner_tol > 0.0 && p.inner_tol < 1.0) {
        return Err(GpuError::Unsupported(format!(
            "inner_tol (the mixed reliable-update factor) must lie in (0, 1), not {}",
            p.inner_tol
        )));
    }
    if let Some(et) = p.error_tol {
        if !(et > 0.0 && et.is_finite()) {
            return Err(GpuError::Unsupported(format!(
                "error_tol must be positive and finite, not {et}"
            )));
        }
        if p.precision != Precision::Mixed {
            return Err(GpuError::Unsupported(
                "error_tol is a mixed-precision option (extended-precision refinement)".into(),
            ));
        }
    }
    Ok(())
}

/// System data the builder turns into buffers.
enum SystemRef<'s> {
    Blocks(&'s BlockCsr),
    Springs(&'s MassSpring),
}

impl GpuSolver {
    /// Builds the solver for an assembled eliminated system.
    pub fn new(ctx: &GpuContext, e: &Eliminated, params: &GpuParams) -> Result<Self, GpuError> {
        crate::cg::check_pinned(e)?;
        let host = Host::new(
            HostOp::Blocks(e.h.clone()),
            e.frames.clone(),
            e.rhs.clone(),
            e.diag.clone(),
        );
        Self::build(ctx, host, params)
    }

    /// Builds the matrix-free solver of a mass-spring system (H = M + h²ΣK_e is never
    /// assembled) with gradient g and the given constraint frames; D = I.
    pub fn new_mass_spring(
        ctx: &GpuContext,
        ms: &MassSpring,
        g: &[f64],
        frames: &Frames,
        params: &GpuParams,
    ) -> Result<Self, GpuError> {
        if frames.dim != ms.dim || frames.n_nodes != ms.n_nodes() || g.len() != ms.ndof() {
            return Err(GpuError::Mismatch(
                "the mass-spring system, its gradient and the frames disagree in size".into(),
            ));
        }
        let host = Host::new(
            HostOp::Springs(ms.clone()),
            frames.clone(),
            spring_rhs(ms, g, frames),
            vec![1.0; ms.ndof()],
        );
        Self::build(ctx, host, params)
    }

    fn build(ctx: &GpuContext, host: Host, params: &GpuParams) -> Result<Self, GpuError> {
        check_params(ctx, params)?;
        let t0 = Instant::now();
        let f = &host.frames;
        let d = f.dim;
        let n = f.n_nodes;
        if n == 0 || n >= MAX_NODES {
            return Err(GpuError::Unsupported(format!(
                "{n} nodes (the GPU solver takes 1 to {} nodes)",
                MAX_NODES - 1
            )));
        }
        let wg = params.workgroup_size;
        let max_groups = ctx.limits.max_compute_workgroups_per_dimension as usize;
        if n.div_ceil(wg as usize) > max_groups {
            return Err(GpuError::Unsupported(format!(
                "{n} nodes need more than {max_groups} workgroups of {wg}"
            )));
        }
        let n_partials =
            (n.div_ceil(wg as usize)).clamp(1, ctx.workgroups(params.workgroups)) as u32;
        let masked = f.has_constraints();
        let rotated = f.has_rotation();
        let acc = if ctx.has_f64() { Real::F64 } else { Real::F32 };
        let mut bld = Builder::new(ctx);
        let sys = match &host.op {
            HostOp::Blocks(h) => SystemRef::Blocks(h),
            HostOp::Springs(ms) => SystemRef::Springs(ms),
        };
        let n_blocks = match sys {
            SystemRef::Blocks(h) => h.nnz_blocks(),
            SystemRef::Springs(ms) => ms.edges.len(),
        };
        let prm = Params {
            n_nodes: n as u32,
            n_rot: f.rot_nodes.len() as u32,
            n_partials,
            n_blocks: n_blocks as u32,
        };
        let params_buf = bld.init(
            "params",
            bytemuck::bytes_of(&prm),
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        )?;
        let mask_packed = |j: usize| -> u32 {
            if masked {
                (j as u32) | ((f.mask[j] as u32) << 29)
            } else {
                j as u32
            }
        };
        let (row_ptr, col, diag_row_ptr, diag_col) = match sys {
            SystemRef::Blocks(h) => (
                bld.storage("row_ptr", &u32s(h.row_ptr.iter().map(|&v| v as u32)))?,
                bld.storage("col_idx", &u32s(h.col_idx.iter().map(|&j| mask_packed(j))))?,
                None,
                None,
            ),
            SystemRef::Springs(ms) => {
                let (ptr, adj) = spring_adjacency(ms);
                (
                    bld.storage("spring_adj_ptr", &u32s(ptr))?,
                    bld.storage("spring_adj", &u32s(adj))?,
                    Some(bld.storage("diag_row_ptr", &u32s(0..=n as u32))?),
                    Some(bld.storage("diag_col", &u32s((0..n).map(mask_packed)))?),
                )
            }
        };
        // Aggregates need H's blocks (E from one pass over them): matrix-free springs keep
        // the rigid translations. No aggregate (every node fixed): no correction.
        let aggregation = match (&host.op, params.coarse) {
            (HostOp::Blocks(h), CoarseSpace::Aggregates) => {
                Some(Aggregation::build(h, f)).filter(|a| a.count > 0)
            }
            _ => None,
        };
        let agg_buffers = match &aggregation {
            Some(a) => {
                let (ptr, nodes) = a.lists();
                Some(AggBuffers {
                    of_node: bld.storage("aggregate_of_node", &u32s(a.of_node.iter().copied()))?,
                    ptr: bld.storage("aggregate_ptr", &u32s(ptr))?,
                    nodes: bld.storage("aggregate_nodes", &u32s(nodes))?,
                })
            }
            None => None,
        };
        let shared = Shared {
            agg: agg_buffers,
            params: params_buf,
            row_ptr,
            col,
            mask: if masked {
                Some(bld.storage("mask", &u32s(f.mask.iter().map(|&m| m as u32)))?)
            } else {
                None
            },
            rot_index: if rotated {
                Some(bld.storage("rot_index", &u32s(f.rot_index.iter().copied()))?)
            } else {
                None
            },
            rot_nodes: if rotated {
                Some(bld.storage("rot_nodes", &u32s(f.rot_nodes.iter().copied()))?)
            } else {
                None
            },
            diag_row_ptr,
            diag_col,
            placeholder: bld.storage("placeholder", &[0u8; 16])?,
        };
        let inner_real = match params.precision {
            Precision::F64 => Real::F64,
            _ => Real::F32,
        };
        let consts = Consts {
            d: d as f64,
            wg: wg as f64,
            masked,
            rotated,
            precond: match params.preconditioner {
                Preconditioner::None => 0.0,
                Preconditioner::Jacobi => 1.0,
                Preconditioner::BlockJacobi => 2.0,
            },
            coarse: params.coarse == CoarseSpace::Translations
                || (params.coarse == CoarseSpace::Aggregates && aggregation.is_none()),
            agg: aggregation.as_ref().map_or(0, |a| a.count as u32),
            diff: inner_real == Real::F32
                && wants_difference_form(&host, params.f32_difference, acc),
        };
        let op = build_operator(&mut bld, &shared, &host, inner_real, acc, &consts)?;
        let level = build_level(
            &mut bld,
            &shared,
            op,
            &host,
            acc,
            &consts,
            params.preconditioner,
        )?;
        let refine = if params.precision == Precision::Mixed {
            let op64 = if blocks_fit(ctx, &host, Real::F64)
                && std::env::var_os("STICKSLIP_MIXED_HOST_RESIDUAL").is_none()
            {
                Some(build_operator(
                    &mut bld,
                    &shared,
                    &host,
                    Real::F64,
                    acc,
                    &consts,
                )?)
            } else {
                None
            };
            Some(build_refine(
                &mut bld, &shared, op64, &level, &host, &consts,
            )?)
        } else {
            None
        };
        let y_buf = match &refine {
            Some(r) => &r.y64,
            None => &level.x,
        };
        let recovery = build_recovery(
            &mut bld,
            &shared,
            y_buf,
            if refine.is_some() {
                Real::F64
            } else {
                inner_real
            },
            if refine.is_some() {
                refine.as_ref().and_then(|r| {
                    r.op.as_ref()
                        .map_or(r.rotations64.as_ref(), |o| o.rotations.as_ref())
                })
            } else {
                level.op.rotations.as_ref()
            },
            &consts,
            n * d,
        )?;
        let timestamps = if ctx.has_timestamps() {
            let set = ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("chunk timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: 2,
            });
            let resolve = bld.buffer(
                "timestamp_resolve",
                16,
                wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            )?;
            Some(Timestamps {
                set,
                resolve,
                period_ns: ctx.queue.get_timestamp_period() as f64,
            })
        } else {
            None
        };
        ctx.check("allocating GPU buffers")?;
        let bytes_per_iteration =
            bytes_per_iteration(&host, &level, &consts, params.preconditioner);
        let host_diag_max = host.diag_max();
        let mut s = GpuSolver {
            ctx: ctx.clone(),
            params: params.clone(),
            dim: d,
            n_nodes: n,
            wg,
            n_partials,
            masked,
            host,
            shared,
            level,
            refine,
            recovery,
            timestamps,
            buffers: bld.buffers,
            kernels: bld.kernels,
            dispatches: BTreeMap::new(),
            bytes_per_iteration,
            upload_seconds: 0.0,
            setup_seconds: 0.0,
            readbacks: 0,
            gpu_seconds: 0.0,
            recorded: 0,
            consts,
            inner_scale: if params.precision == Precision::Mixed {
                inner_scale(host_diag_max)
            } else {
                1.0
            },
            fallback_level: None,
            force_cpu_fallback: false,
            last_fallback: None,
            last_rho_prev: 1.0,
            chunk_hint: None,
            last_rate: None,
            start_rr: None,
            coarse_einv: None,
            aggregation,
            last_error_estimate: None,
            assembled: None,
            last_scal: vec![0.0; SCAL_LEN],
            lz_alphas: Vec::new(),
            lz_betas: Vec::new(),
            lz_resumed: false,
            kappa_est: None,
        };
        s.upload_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        s.upload_values()?;
        s.upload_seconds += t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        s.device_setup()?;
        s.setup_seconds = t2.elapsed().as_secs_f64();
        Ok(s)
    }

    /// New values for the same pattern and constraint set (a later Newton iteration):
    /// uploads H, b̂ and D only, then rotates and rebuilds the preconditioner on the device.
    pub fn update(&mut self, e: &Eliminated) -> Result<(), GpuError> {
        let t0 = Instant::now();
        let h = match &mut self.host.op {
            HostOp::Blocks(h) => h,
            HostOp::Springs(_) => {
                return Err(GpuError::Mismatch(
                    "this solver is matrix-free; use update_mass_spring".into(),
                ))
            }
        };
        if e.h.dim != h.dim || e.h.row_ptr != h.row_ptr || e.h.col_idx != h.col_idx {
            return Err(GpuError::Mismatch(
                "the Hessian's block pattern changed; build a new solver".into(),
            ));
        }
        let f = &self.host.frames;
        if e.frames.mask != f.mask || e.frames.rot_index != f.rot_index {
            return Err(GpuError::Mismatch(
                "the constraint set changed; build a new solver".into(),
            ));
        }
        h.values.copy_from_slice(&e.h.values);
        // The double-double residuals must see the new Ĥ (rebuilt on first use).
        self.assembled = None;
        self.host.frames = e.frames.clone();
        self.host.rhs.copy_from_slice(&e.rhs);
        self.host.diag.copy_from_slice(&e.diag);
        self.upload_values()?;
        self.upload_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        self.device_setup()?;
        self.setup_seconds = t1.elapsed().as_secs_f64();
        Ok(())
    }

    /// New positions (and gradient) of the same mass-spring system and constraint set.
    pub fn update_mass_spring(&mut self, ms: &MassSpring, g: &[f64]) -> Result<(), GpuError> {
        let t0 = Instant::now();
        match &mut self.host.op {
            HostOp::Springs(old) => {
                if old.edges != ms.edges || old.dim != ms.dim || old.masses.len() != ms.masses.len()
                {
                    return Err(GpuError::Mismatch(
                        "the springs changed; build a new solver".into(),
                    ));
                }
                *old = ms.clone();
            }
            HostOp::Blocks(_) => {
                return Err(GpuError::Mismatch(
                    "this solver holds an assembled Hessian; use update".into(),
                ))
            }
        }
        if g.len() != ms.ndof() {
            return Err(GpuError::Mismatch(
                "the gradient has the wrong length".into(),
            ));
        }
        self.host.rhs = spring_rhs(ms, g, &self.host.frames);
        self.upload_values()?;
        self.upload_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        self.device_setup()?;
        self.setup_seconds = t1.elapsed().as_secs_f64();
        Ok(())
    }

    fn record(&mut self, name: &'static str) {
        *self.dispatches.entry(name.to_string()).or_default() += 1;
    }

    fn node_groups(&self) -> u32 {
        (self.n_nodes as u32).div_ceil(self.wg)
    }

    fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    fn wait(&self) -> Result<(), GpuError> {
        self.ctx
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Device(format!("waiting for the GPU: {e}")))
    }

    /// Maps `staging`, copies `bytes` out and unmaps it.
    fn read(&mut self, staging: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>, GpuError> {
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, 0..bytes, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .map_err(|_| GpuError::Device("buffer mapping was dropped".into()))?
            .map_err(|e| GpuError::Device(format!("mapping a read-back buffer: {e}")))?;
        let out = {
            let view = staging
                .get_mapped_range(0..bytes)
                .map_err(|e| GpuError::Device(format!("reading a mapped buffer: {e}")))?;
            view.to_vec()
        };
        staging.unmap();
        self.readbacks += 1;
        self.ctx.check("reading back")?;
        Ok(out)
    }

    /// Recovers dx = V P y on the device and downloads y and dx (dx gets the lift in f64).
    fn download_solution(&mut self) -> Result<(Vec<f64>, Vec<f64>), GpuError> {
        let nd = (self.n_nodes * self.dim) as u64;
        let rs = self.recovery.real.size();
        let y_buf = match &self.refine {
            Some(r) => r.y64.clone(),
            None => self.level.x.clone(),
        };
        let mut enc = self.encoder("recovery");
        let mut names = Vec::new();
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("recovery pass"),
                timestamp_writes: None,
            });
            let groups = self.node_groups();
            if let Some((k, bg)) = &self.recovery.recover {
                pass.set_pipeline(&k.pipeline);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(groups, 1, 1);
                names.push(k.name);
            }
            if let Some((k, bg)) = &self.recovery.rotate {
                let nr = self.host.frames.rot_nodes.len() as u32;
                pass.set_pipeline(&k.pipeline);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(nr.div_ceil(self.wg), 1, 1);
                names.push(k.name);
            }
        }
        if self.recovery.recover.is_none() {
            // No constraints: dx = y, no masking work.
            enc.copy_buffer_to_buffer(&y_buf, 0, &self.recovery.dx, 0, nd * rs);
        }
        enc.copy_buffer_to_buffer(&y_buf, 0, &self.recovery.staging, 0, nd * rs);
        enc.copy_buffer_to_buffer(
            &self.recovery.dx,
            0,
            &self.recovery.staging,
            nd * rs,
            nd * rs,
        );
        self.ctx.queue.submit([enc.finish()]);
        for n in names {
            self.record(n);
        }
        let staging = self.recovery.staging.clone();
        let bytes = self.read(&staging, 2 * nd * rs)?;
        let half = (nd * rs) as usize;
        let y = self.recovery.real.values(&bytes[..half]);
        let mut dx = self.recovery.real.values(&bytes[half..]);
        self.host.add_lift(&mut dx);
        Ok((y, dx))
    }

    /// Solves Ĥ y = b̂; returns y (frame coordinates), Δx = Δx_p + V y and the report.
    pub fn solve(&mut self) -> Result<(Vec<f64>, Vec<f64>, GpuSolveInfo), GpuError> {
        self.readbacks = 0;
        self.gpu_seconds = 0.0;
        self.recorded = 0;
        self.last_fallback = None;
        self.last_error_estimate = None;
        self.lz_alphas.clear();
        self.lz_betas.clear();
        self.lz_resumed = false;
        self.kappa_est = None;
        let t0 = Instant::now();
        let bnorm = norm2(&self.host.rhs);
        let mut notes = Vec::new();
        if !self.ctx.has_f64() {
            notes.push("no SHADER_F64: reductions accumulate in f32".to_string());
        }
        let nd = self.host.ndof();
        let (iterations, outer, restarts, solve_s, dl_s, y, dx) = if bnorm == 0.0 {
            // Ĥ is SPD: the solution is y = 0 and Δx the lift.
            let mut dx = vec![0.0; nd];
            self.host.add_lift(&mut dx);
            notes.push("b̂ = 0: y = 0 without iterating".into());
            (0, 0, 0, 0.0, 0.0, vec![0.0; nd], dx)
        } else if self.refine.is_some() {
            self.solve_mixed(bnorm, &mut notes)?
        } else {
            let f32_only = self.params.precision == Precision::F32;
            self.solve_plain(bnorm).map_err(|e| match e {
                GpuError::Cg(
                    c @ (CgError::NonPositiveCurvature { .. } | CgError::Stagnation { .. }),
                ) if f32_only => GpuError::InF32(c),
                other => other,
            })?
        };
        let _ = t0;
        self.lanczos_close();
        let rel = self.host.relative_residual(&y);
        let bpi = self.bytes_per_iteration;
        let moved = bpi as f64 * iterations as f64;
        let gpu_seconds = self.timestamps.as_ref().map(|_| self.gpu_seconds);
        let info = GpuSolveInfo {
            adapter: self.ctx.info.name.clone(),
            precision: self.params.precision,
            coarse: match (&self.coarse_einv, &self.aggregation) {
                (Some(e), _) if e.iter().all(|&v| v == 0.0) => format!(
                    "{} (inactive: every translation is constrained)",
                    self.params.coarse.name()
                ),
                (_, Some(a)) => format!("aggregates ({})", a.count),
                _ if self.consts.coarse => "translations".into(),
                _ => self.params.coarse.name().into(),
            },
            f32_difference: self.level.op.rowsum.is_some(),
            iterations,
            recorded_iterations: self.recorded.max(iterations),
            outer_refinements: outer,
            restarts,
            relative_residual: rel,
            seconds: StageSeconds {
                upload: self.upload_seconds,
                setup: self.setup_seconds,
                solve: solve_s,
                download: dl_s,
            },
            gpu_seconds,
            bytes_per_iteration: bpi,
            achieved_gb_per_s: if solve_s > 0.0 {
                moved / solve_s / 1e9
            } else {
                0.0
            },
            achieved_gb_per_s_gpu: gpu_seconds.filter(|&s| s > 0.0).map(|s| moved / s / 1e9),
            dispatches_per_iteration: 3,
            workgroups: self.n_partials,
            readbacks: self.readbacks,
            fallback: self.last_fallback.clone(),
            error_estimate: self.last_error_estimate,
            condition_estimate: self.kappa_est,
            notes,
        };
        Ok((y, dx, info))
    }

    #[allow(clippy::type_complexity)]
    fn solve_plain(
        &mut self,
        bnorm: f64,
    ) -> Result<(usize, usize, usize, f64, f64, Vec<f64>, Vec<f64>), GpuError> {
        let tol = self.params.tol;
        let thresh = (tol * bnorm).powi(2);
        let t0 = Instant::now();
        let mut total = 0usize;
        let mut restarts = 0usize;
        let mut dl = 0.0;
        let mut keep = false;
        loop {
            self.start(keep, thresh)?;
            let (out, it) = self.run_cg(self.params.max_iters - total, total, thresh)?;
            total += it;
            let td = Instant::now();
            let (y, dx) = self.download_solution()?;
            dl += td.elapsed().as_secs_f64();
            let rel = self.host.relative_residual(&y);
            match out {
                Outcome::Converged if rel <= tol => {
                    let solve = t0.elapsed().as_secs_f64() - dl;
                    return Ok((total, 0, restarts, solve, dl, y, dx));
                }
                Outcome::Converged
                    if restarts < self.params.max_restarts && total < self.params.max_iters =>
                {
                    // The recurrence drifted from the true residual: restart from y.
                    restarts += 1;
                    keep = true;
                }
                Outcome::MaxIters => {
                    return Err(CgError::MaxIterations {
                        iterations: total,
                        relative_residual: rel,
                        tol,
                    }
                    .into())
                }
                _ => {
                    return Err(CgError::Stagnation {
                        iterations: total,
                        relative_residual: rel,
                        tol,
                    }
                    .into())
                }
            }
        }
    }

    /// Forces the f64 fallback of mixed precision onto the CPU (src/cg.rs) even where the
    /// GPU could run it (for tests and comparisons).
    pub fn force_cpu_fallback(&mut self, yes: bool) {
        self.force_cpu_fallback = yes;
    }

    /// Why and where the last mixed solve fell back to f64 (also after an error).
    pub fn last_fallback(&self) -> Option<&str> {
        self.last_fallback.as_deref()
    }

    /// What the solver allocated, compiled and dispatched.
    pub fn resources(&self) -> Resources {
        Resources {
            buffers: self.buffers.clone(),
            kernels: self.kernels.clone(),
            dispatches: self.dispatches.clone(),
        }
    }

    pub fn adapter_name(&self) -> &str {
        &self.ctx.info.name
    }

    pub fn params(&self) -> &GpuParams {
        &self.params
    }

    /// Number of partial sums (= workgroups of the reduction kernels).
    pub fn n_partials(&self) -> u32 {
        self.n_partials
    }

    /// Whether this solver's kernels run the masking code.
    pub fn is_masked(&self) -> bool {
        self.masked
    }

    fn download(
        &mut self,
        mut enc: wgpu::CommandEncoder,
        buf: &wgpu::Buffer,
        real: Real,
        len: usize,
    ) -> Result<Vec<f64>, GpuError> {
        let bytes = real.size() * len as u64;
        let staging = self.ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("test download staging"),
            size: bytes.max(16).div_ceil(16) * 16,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        enc.copy_buffer_to_buffer(buf, 0, &staging, 0, bytes);
        self.ctx.queue.submit([enc.finish()]);
        let b = self.read(&staging, bytes)?;
        Ok(real.values(&b))
    }
}
