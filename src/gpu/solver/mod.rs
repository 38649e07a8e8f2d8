//! The precision kernels: device-resident preconditioned CG in f32, f64 and mixed
//! precision, and on the matrix-free mass-spring operator (docs/method.md, "The GPU CG
//! loop"). No solve of the product runs them: every precision of an assembled system goes
//! to the device PCG of [`crate::gpu::pcg`] through the facade. They stay for the
//! matrix-free operator and for the measurements that compare the two kernel sets; their
//! host-side pieces (`host`, `policy`, `info`) serve the device PCG too.
//!
//! Per iteration three dispatches: `matvec` (q = Ĥp fused with p·q partials), `update_xrz`
//! (α reduced redundantly per workgroup; x, r, z updated; r·z and r·r partials) and
//! `update_p` (ρ, β and the stop decision reduced redundantly per workgroup; p = z + βp).
//! An operator whose per-block arrays exceed the storage binding limit runs its matvec as
//! one dispatch per row chunk (`builder::plan_chunks`), the same product bit for bit.
//! Scalars stay on the device; one submit records a chunk of iterations and one small
//! status read-back follows it; chunk sizes follow the predicted iterations left
//! (see `run_cg`). Success is declared only after
//! the true residual is recomputed in f64 on the host from the downloaded y.
//!
//! Layout: `info` holds the public report types; `host` the host copy of the system (f64
//! residuals, the recovery); `builder` buffer allocation, kernel compilation and bind
//! groups (from the layouts of `gpu::kernels`); `levels` the device-side operator, CG
//! level (buffers, kernels) and refinement and their construction; `device` what the
//! solver builds on the device, once; `setup` the per-system uploads and setup kernels;
//! `run` the CG driver (chunks, status reads, Lanczos estimate); `mixed` mixed precision
//! and `policy` its decisions (plain CPU code); `telemetry` the records behind the
//! reports; `inspect` kernel-level access for tests and benchmarks.

mod builder;
mod device;
pub(crate) mod host;
mod info;
mod inspect;
mod levels;
mod mixed;
mod plan;
pub(crate) mod policy;
mod run;
mod setup;
mod state;
mod telemetry;

pub use info::{
    BufferRecord, GpuSolveInfo, KernelRecord, KernelTime, Resources, SolveOutcome, StageSeconds,
};

use super::{GpuContext, GpuError, GpuParams, Precision};
use crate::cases::springs::MassSpring;
use crate::core::constraints::Frames;
use crate::core::elimination::{norm2, Eliminated};
use crate::solve::cg::CgError;
use crate::solve::coarse::Aggregation;
use crate::solve::options::Preconditioner;
use builder::Real;
use device::{Built, Device};
use host::{spring_rhs, Host, HostOp};
use levels::bytes_per_iteration;
pub use plan::{DOES_NOT_FIT, MULTILEVEL_ON_CPU};
use state::{MixedState, Outcome, RunState};
use std::time::Instant;
use telemetry::Telemetry;

/// What `solve_plain` and `solve_mixed` hand back to `solve`.
#[derive(Default)]
struct Solved {
    iterations: usize,
    /// Mixed: f32 segments (reliable updates).
    outer: usize,
    restarts: usize,
    solve_seconds: f64,
    download_seconds: f64,
    y: Vec<f64>,
    dx: Vec<f64>,
}

/// The coarse space's host data.
struct CoarseHost {
    /// The aggregates of `--coarse aggregates` (assembled Ĥ only).
    aggregation: Option<Aggregation>,
    /// E⁺ of the coarse correction (k×k, for Ĥ itself), when it is on.
    einv: Option<Vec<f64>>,
}

/// The GPU solver: pipelines, buffers and bind groups built once; `update` uploads new
/// values for the same pattern and constraint set; `solve` runs device-resident PCG.
pub struct GpuSolver {
    ctx: GpuContext,
    params: GpuParams,
    /// The system in f64 on the host: true residuals and the recovery.
    host: Host,
    coarse: CoarseHost,
    /// Buffers and compiled kernels with their bind groups.
    dev: Device,
    /// The CG driver's state between status reads.
    run: RunState,
    /// Mixed precision's state (its decisions: `policy`).
    mixed: MixedState,
    /// What the reports say was allocated, dispatched and timed.
    tel: Telemetry,
    /// σ of the plain CG's right-hand side σb̂ ([`crate::solve::cg::rhs_scale`]; 1 for
    /// mixed precision, which scales its own inner systems): y is unscaled on download.
    rhs_scale: f64,
}

impl GpuSolver {
    /// Builds the solver for an assembled eliminated system.
    pub fn new(ctx: &GpuContext, e: &Eliminated, params: &GpuParams) -> Result<Self, GpuError> {
        crate::solve::cg::check_pinned(e)?;
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

    /// Allocates and compiles (`Device::build`), then uploads the values and runs the
    /// setup kernels.
    fn build(ctx: &GpuContext, host: Host, params: &GpuParams) -> Result<Self, GpuError> {
        if params.preconditioner == Preconditioner::Multilevel {
            return Err(GpuError::Unsupported(MULTILEVEL_ON_CPU.into()));
        }
        let t0 = Instant::now();
        let Built {
            device,
            aggregation,
            buffers,
            kernels,
        } = Device::build(ctx, &host, params)?;
        let bpi = bytes_per_iteration(&host, &device.level, &device.consts, params.preconditioner);
        let mixed = MixedState::new(params.precision == Precision::Mixed, host.diag_max());
        let mut s = GpuSolver {
            ctx: ctx.clone(),
            params: params.clone(),
            host,
            coarse: CoarseHost {
                aggregation,
                einv: None,
            },
            dev: device,
            run: RunState::new(),
            mixed,
            tel: Telemetry::new(buffers, kernels, bpi),
            rhs_scale: 1.0,
        };
        s.tel.upload_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        s.upload_values()?;
        s.tel.upload_seconds += t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        s.device_setup()?;
        s.tel.setup_seconds = t2.elapsed().as_secs_f64();
        Ok(s)
    }

    /// Sets the relative residual tolerance of the next solves (an inexact Newton loop
    /// tightens or loosens it per system); refuses a value outside (0, 1).
    pub fn set_tol(&mut self, tol: f64) -> Result<(), GpuError> {
        self.params.tol = crate::gpu::params::checked_tol(tol)?;
        Ok(())
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
        self.mixed.assembled = None;
        self.host.frames = e.frames.clone();
        self.host.rhs.copy_from_slice(&e.rhs);
        self.host.diag.copy_from_slice(&e.diag);
        self.upload_values()?;
        self.tel.upload_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        self.device_setup()?;
        self.tel.setup_seconds = t1.elapsed().as_secs_f64();
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
        self.tel.upload_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        self.device_setup()?;
        self.tel.setup_seconds = t1.elapsed().as_secs_f64();
        Ok(())
    }

    fn record(&mut self, name: &'static str) {
        self.tel.record(name);
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
        self.ctx.note_download(bytes);
        self.tel.readbacks += 1;
        self.ctx.check("reading back")?;
        Ok(out)
    }

    /// Downloads y (the f64 iterate of mixed precision, else the CG's x) and recovers
    /// Δx = Δx_p + V P y on the host in f64. Why not on the device: an f32 iterate would be
    /// rotated by f32 frames there, and V_i's rounding (ε_f32) would leak into the
    /// constrained directions, breaking BΔx = p by ~1e-8·‖Δx‖; with the f64 frames the
    /// constrained components are exactly the lift's and the rest miss by f64 rounding.
    fn download_solution(&mut self) -> Result<(Vec<f64>, Vec<f64>), GpuError> {
        let nd = self.host.ndof();
        let (y_buf, real) = match &self.dev.refine {
            Some(r) => (r.y64.clone(), Real::F64),
            None => (self.dev.level.buf.x.clone(), self.dev.level.real),
        };
        let bytes = nd as u64 * real.size();
        let mut enc = self.encoder("download solution");
        enc.copy_buffer_to_buffer(&y_buf, 0, &self.dev.solution_staging, 0, bytes);
        self.ctx.queue.submit([enc.finish()]);
        let staging = self.dev.solution_staging.clone();
        let mut y = real.values(&self.read(&staging, bytes)?);
        if self.rhs_scale != 1.0 {
            for v in &mut y {
                *v /= self.rhs_scale;
            }
        }
        let dx = self.host.recover(&y);
        Ok((y, dx))
    }

    /// Solves Ĥ y = b̂; returns y (frame coordinates), Δx = Δx_p + V y and the report.
    pub fn solve(&mut self) -> Result<SolveOutcome, GpuError> {
        self.tel.start_solve();
        self.mixed.start_solve();
        self.run.start_solve();
        let bnorm = norm2(&self.host.rhs);
        let mut notes = Vec::new();
        if !self.ctx.has_f64() {
            notes.push("no SHADER_F64: reductions accumulate in f32".to_string());
        }
        let nd = self.host.ndof();
        let solved = if bnorm == 0.0 {
            // Ĥ is SPD: the solution is y = 0 and Δx the lift.
            let y = vec![0.0; nd];
            notes.push("b̂ = 0: y = 0 without iterating".into());
            Solved {
                dx: self.host.recover(&y),
                y,
                ..Solved::default()
            }
        } else if self.dev.refine.is_some() {
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
        self.lanczos_close();
        let Solved {
            iterations,
            outer,
            restarts,
            solve_seconds: solve_s,
            download_seconds: dl_s,
            y,
            dx,
        } = solved;
        let rel = self.host.relative_residual(&y);
        let bpi = self.tel.bytes_per_iteration;
        let moved = bpi as f64 * iterations as f64;
        let gpu_seconds = self.dev.timestamps.as_ref().map(|_| self.tel.gpu_seconds);
        let info = GpuSolveInfo {
            adapter: self.ctx.info.name.clone(),
            precision: self.params.precision,
            coarse: match (&self.coarse.einv, &self.coarse.aggregation) {
                (Some(e), _) if e.iter().all(|&v| v == 0.0) => format!(
                    "{} (inactive: every translation is constrained)",
                    self.params.coarse.name()
                ),
                (_, Some(a)) => format!("aggregates ({})", a.count),
                _ if self.dev.consts.coarse => "translations".into(),
                _ => self.params.coarse.name().into(),
            },
            f32_difference: self.dev.level.op.rowsum.is_some(),
            iterations,
            recorded_iterations: self.tel.recorded.max(iterations),
            outer_refinements: outer,
            restarts,
            relative_residual: rel,
            seconds: StageSeconds {
                upload: self.tel.upload_seconds,
                setup: self.tel.setup_seconds,
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
            // matvec once per row chunk of the operator's blocks.
            dispatches_per_iteration: 2 + self.dev.level.k.matvec_p.len(),
            workgroups: self.dev.n_partials,
            readbacks: self.tel.readbacks,
            fallback: self.mixed.last_fallback.clone(),
            error_estimate: self.mixed.last_error_estimate,
            condition_estimate: self.run.kappa_est,
            notes,
        };
        Ok(SolveOutcome { y, dx, info })
    }

    fn solve_plain(&mut self, bnorm: f64) -> Result<Solved, GpuError> {
        let tol = self.params.tol;
        // The device iterates on σb̂ (see `upload_values`).
        let thresh = (tol * bnorm * self.rhs_scale).powi(2);
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
                    return Ok(Solved {
                        iterations: total,
                        outer: 0,
                        restarts,
                        solve_seconds: t0.elapsed().as_secs_f64() - dl,
                        download_seconds: dl,
                        y,
                        dx,
                    });
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
        self.mixed.force_cpu_fallback = yes;
    }

    /// Why and where the last mixed solve fell back to f64 (also after an error).
    pub fn last_fallback(&self) -> Option<&str> {
        self.mixed.last_fallback.as_deref()
    }

    /// What the solver allocated, compiled and dispatched.
    pub fn resources(&self) -> Resources {
        self.tel.resources()
    }

    pub fn adapter_name(&self) -> &str {
        &self.ctx.info.name
    }

    pub fn params(&self) -> &GpuParams {
        &self.params
    }

    /// Number of partial sums (= workgroups of the reduction kernels).
    pub fn n_partials(&self) -> u32 {
        self.dev.n_partials
    }

    /// Whether this solver's kernels run the masking code.
    pub fn is_masked(&self) -> bool {
        self.dev.consts.masked
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
