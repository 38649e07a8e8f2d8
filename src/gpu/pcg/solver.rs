//! The device PCG on an eliminated system from the host: what `solve --solver gpu` runs
//! in every precision (through the facade's engine; mixed precision: solver/mixed.rs). H is uploaded once per pattern into the
//! block layout the device assembly writes ([`HostBlocks`]), in f64 or rounded to f32
//! (with the difference form's row sums, summed in f64, beside it), b̂ with each system;
//! the CG is the device Newton loop's own ([`DeviceCg`]), so the two give the same
//! iterations and bits on the same system in f64. The host keeps H in f64 to recompute
//! the true residual from the downloaded y (success is declared on it) and recovers
//! Δx = Δx_p + V P y with the f64 frames: an f32 iterate is never rotated by f32 frames,
//! so the constrained components of Δx are exactly the prescribed ones.

use super::cg::{DeviceCg, DeviceCgParams, DeviceFrames, Scalars};
use super::host::{blocks_diag_max, Host};
use super::policy;
use crate::core::elimination::{norm2, Eliminated};
use crate::gpu::blocks::{plan_rows, row_sums, values_limit, HostBlocks};
use crate::gpu::context::padded_size;
use crate::gpu::error::MULTILEVEL_ON_CPU;
use crate::gpu::kernels::Real;
use crate::gpu::{
    GpuContext, GpuError, GpuParams, GpuSolveInfo, Precision, SolveOutcome, StageSeconds,
};
use crate::solve::cg::CgError;
use crate::solve::coarse::CoarseSpace;
use crate::solve::multilevel::reuse::KeptLevels;
use crate::solve::multilevel::Hierarchy;
use crate::solve::options::Preconditioner;
use std::sync::Arc;
use std::time::Instant;

mod mixed;

/// The scalar types of a solve of `e` in `params.precision` (mixed: of its f32 level):
/// f64, or f32 with the difference form as `params.f32_difference` decides (refusing f64
/// and mixed without SHADER_F64 and the multilevel preconditioner in f32 and mixed).
fn scalars_for(ctx: &GpuContext, e: &Eliminated, params: &GpuParams) -> Result<Scalars, GpuError> {
    let real = match params.precision {
        Precision::F64 if !ctx.has_f64() => {
            return Err(GpuError::NoF64 {
                adapter: ctx.info.name.clone(),
                precision: params.precision.name(),
            })
        }
        Precision::F64 => Real::F64,
        Precision::F32 if params.preconditioner == Preconditioner::Multilevel => {
            return Err(GpuError::Unsupported(MULTILEVEL_ON_CPU.into()))
        }
        Precision::F32 => Real::F32,
        // Mixed: f32 segments, their residual and y in f64 (solver/mixed.rs).
        Precision::Mixed if !ctx.has_f64() => {
            return Err(GpuError::NoF64 {
                adapter: ctx.info.name.clone(),
                precision: params.precision.name(),
            })
        }
        Precision::Mixed if params.preconditioner == Preconditioner::Multilevel => {
            return Err(GpuError::Unsupported(MULTILEVEL_ON_CPU.into()))
        }
        Precision::Mixed => Real::F32,
    };
    let difference = real == Real::F32
        && params
            .f32_difference
            .wanted(ctx.has_f64(), e.h, e.frames, || blocks_diag_max(e.h));
    Scalars::on(ctx, real, difference)
}

/// Refuses, before anything is allocated, a system whose H, CG buffers and multilevel
/// levels (`hierarchy`, when asked for) exceed the device memory in force, or one of whose
/// level buffers exceeds the adapter's limits (the aggregates' index arrays, a few words
/// per node, come on top). Returns the bytes planned.
fn check_memory(
    ctx: &GpuContext,
    e: &Eliminated,
    params: &GpuParams,
    hierarchy: Option<&Hierarchy>,
    ty: Scalars,
) -> Result<u64, GpuError> {
    let need = memory_plan(ctx, e, params, hierarchy, ty, true)?;
    ctx.check_fits(need, ctx.memory_in_force(params.memory_limit))?;
    Ok(need)
}

/// The bytes [`PcgSolver`] allocates for `e` in one precision: H's values, the CG's
/// buffers (with the Lanczos history where `lanczos`) and frames, the multilevel levels
/// (`hierarchy`) and nothing else but the aggregates' arrays.
fn memory_plan(
    ctx: &GpuContext,
    e: &Eliminated,
    params: &GpuParams,
    hierarchy: Option<&Hierarchy>,
    ty: Scalars,
    lanczos: bool,
) -> Result<u64, GpuError> {
    let h = e.h;
    let block = ty.real.size() * (h.dim * h.dim) as u64;
    let plan = plan_rows(
        &h.row_ptr,
        block,
        values_limit(ctx, params.binding_limit),
        "matrix blocks",
        ctx.adapter_name(),
    )?;
    let values: u64 = plan
        .iter()
        .map(|(_, b)| padded_size(b.len() as u64 * block))
        .sum();
    let cg = DeviceCg::device_bytes(
        ctx,
        (h.n, h.col_idx.len(), h.dim),
        plan.len(),
        e.frames.rot_nodes.len(),
        lanczos,
        ty,
    );
    let levels = match hierarchy {
        Some(hi) => {
            super::multilevel_bytes(ctx, &hi.level_sizes(h.dim), h.dim, params.binding_limit)?
        }
        None => 0,
    };
    // The gradient's placeholder: b̂ is given.
    let gradient = padded_size(16);
    Ok(values + cg + levels + gradient)
}

/// The device PCG for eliminated systems given on the host (f64, or f32 with f64 sums
/// where the device has them): built once per block pattern and constraint set;
/// [`PcgSolver::update`] writes new values.
pub struct PcgSolver {
    ctx: GpuContext,
    params: GpuParams,
    ty: Scalars,
    /// σ of the right-hand side σb̂ the device iterates on ([`crate::solve::cg::rhs_scale`]:
    /// a power of two, exact, so f64 gives the same bits as unscaled), y unscaled on
    /// download: an f32 b̂ then neither over- nor underflows.
    rhs_scale: f64,
    host: Host,
    blocks: HostBlocks,
    cg: DeviceCg,
    frames: DeviceFrames,
    /// The multilevel preconditioner's clusters (H's pattern only: kept across updates)
    /// and its levels (kept or rebuilt as `params.multilevel_setup` says).
    levels: KeptLevels,
    upload_seconds: f64,
    setup_seconds: f64,
    /// Mixed precision's f64 side (`cg` is then its f32 level); None in f64 and f32.
    mixed: Option<MixedSide>,
}

/// What a solve counted, for its report ([`PcgSolver::report`]).
struct Tally {
    iterations: usize,
    recorded: usize,
    reads: usize,
    restarts: usize,
    outer: usize,
    relative_residual: f64,
    solve_seconds: f64,
    download_seconds: f64,
    condition_estimate: Option<f64>,
    fallback: Option<String>,
    error_estimate: Option<f64>,
}

/// Mixed precision's f64 side ([`Precision::Mixed`]; solver/mixed.rs runs it).
struct MixedSide {
    /// Ĥ in f64 on the device: each segment's residual product, the f64 fallback's CG and
    /// the corrections of extended-precision refinement. None where it does not fit in
    /// device memory beside the f32 level: the residual is then formed on the host and
    /// the fallback runs on the CPU.
    level: Option<F64Level>,
    /// 2^s: the f32 level holds 2^s Ĥ ([`policy::inner_scale`]).
    inner_scale: f64,
    /// Tests: the fallback runs on the CPU even where the f64 level exists.
    force_cpu_fallback: bool,
    /// Why the last solve left f32, and where it finished.
    last_fallback: Option<String>,
    /// Ĥ assembled for extended refinement's double-double residuals (on first use).
    assembled: Option<crate::core::sparse::BlockCsr>,
    /// Why the f64 level is missing.
    missing: Option<String>,
    /// The kernels that keep stage 1's y and residual on the device (with the level).
    refine: Option<super::refine::Refine>,
}

/// The device PCG in f64 beside mixed precision's f32 level, on the same pattern and
/// frames, with b̂ scaled by `rhs_scale` (as in f64).
struct F64Level {
    blocks: HostBlocks,
    cg: DeviceCg,
    frames: DeviceFrames,
    rhs_scale: f64,
    /// Whether its b̂ is σb̂ (extended refinement solves for other right-hand sides).
    holds_rhs: bool,
}

impl MixedSide {
    /// The f64 level where it fits beside the `planned` bytes of the f32 level.
    fn new(
        ctx: &GpuContext,
        e: &Eliminated,
        params: &GpuParams,
        planned: u64,
        inner_scale: f64,
        f32_level: &DeviceCg,
    ) -> Result<Self, GpuError> {
        let need = memory_plan(ctx, e, params, None, Scalars::F64, false);
        let fits = need.and_then(|need| {
            ctx.check_fits(planned + need, ctx.memory_in_force(params.memory_limit))
        });
        let (level, missing) = match fits {
            Ok(()) => {
                let blocks = HostBlocks::upload(ctx, e.h, Real::F64, params.binding_limit)?;
                let cg = DeviceCg::new(ctx, blocks.matrix(), None, false, false)?;
                let frames = cg.frames(e.frames, params.coarse)?;
                let level = F64Level {
                    blocks,
                    cg,
                    frames,
                    rhs_scale: 1.0,
                    holds_rhs: false,
                };
                (Some(level), None)
            }
            Err(e) if e.does_not_fit() => (None, Some(e.to_string())),
            Err(e) => return Err(e),
        };
        let refine = match &level {
            Some(l) => Some(super::refine::Refine::new(ctx, &l.cg, f32_level)?),
            None => None,
        };
        Ok(MixedSide {
            level,
            refine,
            inner_scale,
            force_cpu_fallback: false,
            last_fallback: None,
            assembled: None,
            missing,
        })
    }
}

/// H with every value times `s` (a power of two: exact), or H itself for s = 1.
fn scaled(
    h: &crate::core::sparse::BlockCsr,
    s: f64,
) -> std::borrow::Cow<'_, crate::core::sparse::BlockCsr> {
    if s == 1.0 {
        return std::borrow::Cow::Borrowed(h);
    }
    let mut m = h.clone();
    m.values.iter_mut().for_each(|v| *v *= s);
    std::borrow::Cow::Owned(m)
}

impl PcgSolver {
    /// Uploads `e`'s H, frames and b̂ and builds the CG (mixed: its f32 level, and the f64
    /// level where it fits). Refuses f64 and mixed on a device without SHADER_F64, the
    /// multilevel preconditioner in f32 and mixed, a system over
    /// the device memory and (as the CPU CG) one that a rigid translation
    /// leaves singular. With the multilevel preconditioner the host builds its levels
    /// (the CPU CG's [`crate::solve::multilevel::Multilevel`], clusters partitioned once
    /// per pattern) and uploads them, for every system or, with
    /// [`crate::MultilevelSetup::Reuse`], when the kept ones no longer serve: setup time.
    /// The device puts D = I on the constrained components whatever `e.diag` holds: b̂,
    /// and so r, z and p, vanish there, so y is the same; the host's true residual uses
    /// `e.diag`.
    pub fn new(ctx: &GpuContext, e: &Eliminated, params: &GpuParams) -> Result<Self, GpuError> {
        let mut s = Self::build(ctx, e, params, None)?;
        s.prepare(e, None)?;
        Ok(s)
    }

    /// [`PcgSolver::new`] with the multilevel clusters and levels of `levels`, which the
    /// solvers of every constraint set of one mesh share (the facade's engine): the mesh
    /// is partitioned once, and the levels are kept or rebuilt as one sequence decides,
    /// whichever solver a system goes to. Use [`PcgSolver::update_sharing`] and
    /// [`PcgSolver::solve_sharing`] with the same `levels` afterwards.
    pub fn sharing(
        ctx: &GpuContext,
        e: &Eliminated,
        params: &GpuParams,
        levels: &mut KeptLevels,
    ) -> Result<Self, GpuError> {
        let hierarchy = (params.preconditioner == Preconditioner::Multilevel)
            .then(|| levels.hierarchy_for(e.h));
        let mut s = Self::build(ctx, e, params, hierarchy)?;
        s.prepare(e, Some(levels))?;
        Ok(s)
    }

    fn build(
        ctx: &GpuContext,
        e: &Eliminated,
        params: &GpuParams,
        hierarchy: Option<Arc<Hierarchy>>,
    ) -> Result<Self, GpuError> {
        let ty = scalars_for(ctx, e, params)?;
        crate::solve::cg::check_pinned(e)?;
        let host = Host::new(e.h.clone(), e.frames.clone(), e.rhs.clone(), e.diag.clone());
        // The clusters (H's pattern only) first: their levels count in the memory check.
        let hierarchy = (params.preconditioner == Preconditioner::Multilevel).then(|| {
            hierarchy
                .filter(|h| h.fits(e.h))
                .unwrap_or_else(|| Arc::new(Hierarchy::new(e.h)))
        });
        let planned = check_memory(ctx, e, params, hierarchy.as_deref(), ty)?;
        let levels = match hierarchy {
            Some(h) => KeptLevels::with_hierarchy(params.multilevel_setup, h),
            None => KeptLevels::new(params.multilevel_setup),
        };
        let t0 = Instant::now();
        let mixed = params.precision == Precision::Mixed;
        let inner_scale = if mixed {
            policy::inner_scale(blocks_diag_max(e.h))
        } else {
            1.0
        };
        let h = scaled(e.h, inner_scale);
        let blocks = HostBlocks::upload(ctx, &h, ty.real, params.binding_limit)?;
        let cg = DeviceCg::new(ctx, blocks.matrix(), None, true, ty.difference)?;
        if ty.difference {
            cg.write_row_sums(&row_sums(&h))?;
        }
        let frames = cg.frames(e.frames, params.coarse)?;
        let mixed = if mixed {
            Some(MixedSide::new(ctx, e, params, planned, inner_scale, &cg)?)
        } else {
            None
        };
        Ok(PcgSolver {
            mixed,
            ctx: ctx.clone(),
            params: params.clone(),
            ty,
            rhs_scale: 1.0,
            host,
            blocks,
            cg,
            frames,
            levels,
            upload_seconds: t0.elapsed().as_secs_f64(),
            setup_seconds: 0.0,
        })
    }

    /// b̂ and the preconditioner (and coarse matrix) of the current values on the device,
    /// the multilevel levels from `shared` or the solver's own.
    fn prepare(&mut self, e: &Eliminated, shared: Option<&mut KeptLevels>) -> Result<(), GpuError> {
        let t = Instant::now();
        let bn = norm2(&self.host.rhs);
        let sigma = crate::solve::cg::rhs_scale(bn);
        let by = |f: f64| -> Vec<f64> { self.host.rhs.iter().map(|v| v * f).collect() };
        if let Some(m) = &mut self.mixed {
            // The f32 level solves for unit right-hand sides (each segment writes its
            // own); the f64 level holds σb̂ as an f64 solve would.
            let unit = by(if bn > 0.0 { 1.0 / bn } else { 0.0 });
            let rhs = by(sigma);
            self.rhs_scale = 1.0;
            self.cg.prepare_with_rhs(&self.frames, &unit)?;
            if self.params.coarse != CoarseSpace::None {
                let h = scaled(e.h, m.inner_scale);
                self.cg.set_galerkin_from_host(&self.frames, &h, e.frames)?;
            }
            if let Some(l) = &mut m.level {
                l.rhs_scale = sigma;
                l.cg.prepare_with_rhs(&l.frames, &rhs)?;
                l.holds_rhs = true;
            }
        } else {
            self.rhs_scale = sigma;
            let scaled = by(sigma);
            self.cg.prepare_with_rhs(&self.frames, &scaled)?;
            if self.ty.real == Real::F32 && self.params.coarse != CoarseSpace::None {
                self.cg
                    .set_galerkin_from_host(&self.frames, e.h, e.frames)?;
            }
        }
        if self.params.preconditioner == Preconditioner::Multilevel {
            let (ml, _) = shared.unwrap_or(&mut self.levels).for_system(e);
            self.cg
                .set_multilevel(&ml, e.frames, self.params.binding_limit)?;
        }
        if self.mixed.is_none() {
            // The solve's pipelines are compiled here, in the setup, not inside the first
            // solve's seconds (a no-op once compiled).
            self.cg
                .compile_solve_pipelines(&self.frames, &self.cg_params());
        }
        // The setup kernels' time, not just their recording.
        self.ctx.wait("the PCG's setup")?;
        self.setup_seconds = t.elapsed().as_secs_f64();
        Ok(())
    }

    /// The device memory [`PcgSolver::new`] allocates for `e` with `params` (what its
    /// refusal compares with the memory in force), the aggregates' index arrays and values
    /// aside: a few words per node. With the multilevel preconditioner this partitions
    /// the mesh (METIS), as `new` does.
    pub fn memory_needed(
        ctx: &GpuContext,
        e: &Eliminated,
        params: &GpuParams,
    ) -> Result<u64, GpuError> {
        let ty = scalars_for(ctx, e, params)?;
        let hierarchy =
            (params.preconditioner == Preconditioner::Multilevel).then(|| Hierarchy::new(e.h));
        let own = memory_plan(ctx, e, params, hierarchy.as_ref(), ty, true)?;
        // Mixed precision adds its f64 level where it fits (see `MixedSide`).
        let f64_level = if params.precision == Precision::Mixed {
            memory_plan(ctx, e, params, None, Scalars::F64, false)?
        } else {
            0
        };
        Ok(own + f64_level)
    }

    /// Sets the relative residual tolerance of the next solves; refuses a value outside
    /// (0, 1).
    pub fn set_tol(&mut self, tol: f64) -> Result<(), GpuError> {
        self.params.tol = crate::gpu::params::checked_tol(tol)?;
        Ok(())
    }

    /// New values for the same pattern and constraint set (a later Newton iteration).
    pub fn update(&mut self, e: &Eliminated) -> Result<(), GpuError> {
        self.update_values(e)?;
        self.prepare(e, None)
    }

    /// [`PcgSolver::update`] with the levels shared by the solvers of a mesh
    /// ([`PcgSolver::sharing`]).
    pub fn update_sharing(
        &mut self,
        e: &Eliminated,
        levels: &mut KeptLevels,
    ) -> Result<(), GpuError> {
        self.update_values(e)?;
        self.prepare(e, Some(levels))
    }

    fn update_values(&mut self, e: &Eliminated) -> Result<(), GpuError> {
        let t0 = Instant::now();
        let f = &self.host.frames;
        if e.frames.mask != f.mask || e.frames.rot_index != f.rot_index {
            return Err(GpuError::Mismatch(
                "the constraint set changed; build a new solver".into(),
            ));
        }
        let s = self.mixed.as_ref().map_or(1.0, |m| m.inner_scale);
        let h = scaled(e.h, s);
        self.blocks.write(&self.ctx, &h)?;
        if self.ty.difference {
            self.cg.write_row_sums(&row_sums(&h))?;
        }
        // New rotations of the same constraint set (a slip plane turned) need new frames.
        let turned = e.frames.rotations != f.rotations;
        if turned {
            self.frames = self.cg.frames(e.frames, self.params.coarse)?;
        }
        if let Some(m) = &mut self.mixed {
            m.assembled = None;
            if let Some(l) = &mut m.level {
                l.blocks.write(&self.ctx, e.h)?;
                if turned {
                    l.frames = l.cg.frames(e.frames, self.params.coarse)?;
                }
            }
        }
        self.host.h.values.copy_from_slice(&e.h.values);
        self.host.frames = e.frames.clone();
        self.host.rhs.copy_from_slice(&e.rhs);
        self.host.diag.copy_from_slice(&e.diag);
        self.upload_seconds = t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Solves Ĥ y = b̂; returns y (frame coordinates), Δx = Δx_p + V y and the report. A
    /// solve that fails on kept multilevel levels runs again on levels built for it.
    pub fn solve(&mut self) -> Result<SolveOutcome, GpuError> {
        self.solve_with_levels(None)
    }

    /// [`PcgSolver::solve`] with the levels shared by the solvers of a mesh
    /// ([`PcgSolver::sharing`]).
    pub fn solve_sharing(&mut self, levels: &mut KeptLevels) -> Result<SolveOutcome, GpuError> {
        self.solve_with_levels(Some(levels))
    }

    fn solve_with_levels(
        &mut self,
        mut shared: Option<&mut KeptLevels>,
    ) -> Result<SolveOutcome, GpuError> {
        if self.mixed.is_some() {
            return self.solve_mixed();
        }
        let multilevel = self.params.preconditioner == Preconditioner::Multilevel;
        let first = self.solve_once().map_err(|e| self.in_precision(e));
        let levels = match shared.as_deref_mut() {
            Some(l) => l,
            None => &mut self.levels,
        };
        let outcome = match first {
            Err(_) if multilevel && levels.failed() => {
                let t = Instant::now();
                let e = self.host.eliminated();
                let (ml, _) = levels.for_system(&e);
                self.cg
                    .set_multilevel(&ml, &self.host.frames, self.params.binding_limit)?;
                self.setup_seconds += t.elapsed().as_secs_f64();
                self.solve_once().map_err(|e| self.in_precision(e))
            }
            other => other,
        }?;
        if multilevel {
            let levels = match shared {
                Some(l) => l,
                None => &mut self.levels,
            };
            levels.solved(outcome.info.iterations, self.params.tol);
        }
        Ok(outcome)
    }

    /// An f32 solve's loss of curvature or stagnation is f32's ([`GpuError::InF32`]: f64
    /// or mixed may still solve the system).
    fn in_precision(&self, e: GpuError) -> GpuError {
        match e {
            GpuError::Cg(
                c @ (CgError::NonPositiveCurvature { .. } | CgError::Stagnation { .. }),
            ) if self.params.precision == Precision::F32 => GpuError::InF32(c),
            other => other,
        }
    }

    /// The device CG's parameters of a solve.
    fn cg_params(&self) -> DeviceCgParams {
        DeviceCgParams {
            tol: self.params.tol,
            max_iterations: self.params.max_iters,
            preconditioner: self.params.preconditioner,
            coarse: self.params.coarse,
            stagnation_window: self.params.stagnation_window,
        }
    }

    fn solve_once(&mut self) -> Result<SolveOutcome, GpuError> {
        let tol = self.params.tol;
        let bnorm = norm2(&self.host.rhs);
        let mut notes = Vec::new();
        if self.ty.acc == Real::F32 {
            notes.push("no SHADER_F64: reductions accumulate in f32".to_string());
        }
        let t0 = Instant::now();
        let cg_params = self.cg_params();
        let (mut iterations, mut restarts, mut recorded, mut reads) = (0, 0, 0, 0);
        let mut download = 0.0;
        let mut kappa: Option<f64> = None;
        let mut run = cg_params;
        let mut first = true;
        let (y, rel) = loop {
            let remaining = self.params.max_iters.saturating_sub(iterations);
            run.max_iterations = remaining;
            let info = if first {
                self.cg.iterate(&self.frames, &run)
            } else {
                self.cg.iterate_from_current(&self.frames, &run)
            }
            .map_err(|e| match e {
                GpuError::Cg(CgError::MaxIterations {
                    iterations: it,
                    relative_residual,
                    tol: t,
                }) => GpuError::Cg(CgError::MaxIterations {
                    iterations: iterations + it,
                    relative_residual,
                    tol: t,
                }),
                other => other,
            })?;
            first = false;
            iterations += info.iterations;
            restarts += info.restarts;
            recorded += info.recorded_iterations;
            reads += info.status_reads + 1;
            if let Some(k) = self.cg.condition_estimate()? {
                kappa = Some(kappa.map_or(k, |c: f64| c.max(k)));
            }
            let td = Instant::now();
            let mut y = self.cg.read_y()?;
            if self.rhs_scale != 1.0 {
                for v in &mut y {
                    *v /= self.rhs_scale;
                }
            }
            download += td.elapsed().as_secs_f64();
            let rel = self.host.relative_residual(&y);
            if rel <= tol || bnorm == 0.0 {
                break (y, rel);
            }
            // The device's f64 residual met tol where the host's, summed in another
            // order, misses it by rounding: go on from y to a tighter device tolerance.
            if restarts >= self.params.max_restarts || iterations >= self.params.max_iters {
                return Err(CgError::Stagnation {
                    iterations,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            restarts += 1;
            run.tol = (run.tol * 0.5 * tol / rel).max(f64::MIN_POSITIVE);
        };
        if bnorm == 0.0 {
            notes.push("b̂ = 0: y = 0 without iterating".into());
        }
        let solve_s = t0.elapsed().as_secs_f64() - download;
        let dx = self.host.recover(&y);
        let info = self.report(
            &cg_params,
            Tally {
                iterations,
                recorded,
                reads,
                restarts,
                outer: 0,
                relative_residual: rel,
                solve_seconds: solve_s,
                download_seconds: download,
                condition_estimate: kappa,
                fallback: None,
                error_estimate: None,
            },
            notes,
        )?;
        Ok(SolveOutcome { y, dx, info })
    }

    /// The report of a solve: its tally, the iteration's profile (dispatches and the bytes
    /// it must move, of `cg_params` on the main level), the coarse space as it ran.
    fn report(
        &self,
        cg_params: &DeviceCgParams,
        t: Tally,
        notes: Vec<String>,
    ) -> Result<GpuSolveInfo, GpuError> {
        let profile = self.cg.iteration_profile(&self.frames, cg_params)?;
        let bpi = profile.bytes;
        let moved = bpi as f64 * t.iterations as f64;
        let joined = |v: Vec<usize>| {
            v.iter()
                .map(|c| c.to_string())
                .collect::<Vec<_>>()
                .join("/")
        };
        let buffers = self.cg.multilevel_inverse_buffers();
        let coarse = match (self.params.coarse, self.frames.aggregate_count()) {
            _ if self.params.preconditioner == Preconditioner::Multilevel => {
                let split = if buffers.iter().any(|&b| b > 1) {
                    format!("; inverses in {} buffers", joined(buffers))
                } else {
                    String::new()
                };
                format!(
                    "the multilevel levels ({} clusters{split})",
                    joined(self.cg.multilevel_clusters())
                )
            }
            (CoarseSpace::Aggregates, Some(k)) => format!("aggregates ({k})"),
            (CoarseSpace::Translations, _) if self.cg.translations_inactive() => format!(
                "{} (inactive: every translation is constrained)",
                self.params.coarse.name()
            ),
            (c, _) => c.name().into(),
        };
        let info = GpuSolveInfo {
            adapter: self.ctx.info.name.clone(),
            precision: self.params.precision,
            coarse,
            f32_difference: self.ty.difference,
            iterations: t.iterations,
            recorded_iterations: t.recorded.max(t.iterations),
            outer_refinements: t.outer,
            restarts: t.restarts,
            relative_residual: t.relative_residual,
            seconds: StageSeconds {
                upload: self.upload_seconds,
                setup: self.setup_seconds,
                solve: t.solve_seconds,
                download: t.download_seconds,
            },
            gpu_seconds: None,
            bytes_per_iteration: bpi,
            achieved_gb_per_s: if t.solve_seconds > 0.0 {
                moved / t.solve_seconds / 1e9
            } else {
                0.0
            },
            achieved_gb_per_s_gpu: None,
            dispatches_per_iteration: profile.dispatches.len(),
            workgroups: profile
                .dispatches
                .iter()
                .map(|d| d.workgroups)
                .max()
                .unwrap_or(1)
                .min(u32::MAX as u64) as u32,
            threads_per_dispatch: profile
                .dispatches
                .iter()
                .map(|d| d.threads)
                .max()
                .unwrap_or(0),
            readbacks: t.reads,
            fallback: t.fallback,
            error_estimate: t.error_estimate,
            condition_estimate: t.condition_estimate,
            notes,
        };
        Ok(info)
    }

    /// Device time of each dispatch of one CG iteration (see
    /// [`DeviceCg::profile_iteration`]); `None` without TIMESTAMP_QUERY.
    pub fn profile_kernels(
        &mut self,
        reps: usize,
    ) -> Result<Option<Vec<crate::gpu::KernelTime>>, GpuError> {
        let params = DeviceCgParams {
            tol: self.params.tol,
            max_iterations: self.params.max_iters,
            preconditioner: self.params.preconditioner,
            coarse: self.params.coarse,
            stagnation_window: self.params.stagnation_window,
        };
        self.cg.profile_iteration(&self.frames, &params, reps)
    }

    /// q = Ĥx with the solver's H and constraint frames, read back (the product of every
    /// iteration; for tests of the operator).
    pub fn apply_operator(&mut self, x: &[f64]) -> Result<Vec<f64>, GpuError> {
        self.cg.apply(&self.frames, x)
    }

    /// The preconditioner of the current system as the device built it, in the CPU CG's
    /// layout (see [`DeviceCg::preconditioner_data`]; mixed: its f32 level's).
    pub fn preconditioner_data(&self) -> Result<Vec<f64>, GpuError> {
        self.cg.preconditioner_data(self.params.preconditioner)
    }

    /// The buffers H's values are split over on the device, one per row chunk (each within
    /// a storage binding): the solver's own level's, and mixed precision's f64 level's
    /// where it has one.
    pub fn values_chunks(&self) -> (usize, Option<usize>) {
        let f64_level = self.mixed.as_ref().and_then(|m| m.level.as_ref());
        (
            self.blocks.chunk_count(),
            f64_level.map(|l| l.blocks.chunk_count()),
        )
    }

    /// Whether the f32 product takes the difference form.
    pub fn difference_form(&self) -> bool {
        self.ty.difference
    }

    pub fn adapter_name(&self) -> &str {
        &self.ctx.info.name
    }

    /// Buffers of cluster inverses per multilevel level, finest first (empty without the
    /// multilevel preconditioner).
    pub fn multilevel_inverse_buffers(&self) -> Vec<usize> {
        self.cg.multilevel_inverse_buffers()
    }

    pub fn params(&self) -> &GpuParams {
        &self.params
    }
}
