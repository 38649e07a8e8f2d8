//! Device-resident preconditioned CG (design.md §4).
//!
//! Per iteration three dispatches: `matvec` (q = Ĥp fused with p·q partials), `update_xrz`
//! (α reduced redundantly per workgroup; x, r, z updated; r·z and r·r partials) and
//! `update_p` (ρ, β and the stop decision reduced redundantly per workgroup; p = z + βp).
//! Scalars stay on the device; one submit records a chunk of iterations and one small
//! status read-back follows it; chunk sizes follow the predicted iterations left
//! (see `run_cg`). Success is declared only after
//! the true residual is recomputed in f64 on the host from the downloaded y.

use super::kernels;
use super::{GpuContext, GpuError, GpuParams, Precision};
use crate::cg::{CgError, Preconditioner};
use crate::constraints::Frames;
use crate::elimination::{
    apply_eliminated, norm2, relative_residual_from, rotate_block, Eliminated,
};
use crate::sparse::BlockCsr;
use crate::springs::MassSpring;
use std::collections::BTreeMap;
use std::time::Instant;
use wgpu::util::DeviceExt;

/// Scalar type of a kernel instance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Real {
    F32,
    F64,
}

impl Real {
    fn name(self) -> &'static str {
        match self {
            Real::F32 => "f32",
            Real::F64 => "f64",
        }
    }
    fn size(self) -> u64 {
        match self {
            Real::F32 => 4,
            Real::F64 => 8,
        }
    }
    fn bytes(self, v: &[f64]) -> Vec<u8> {
        match self {
            Real::F32 => {
                let w: Vec<f32> = v.iter().map(|&x| x as f32).collect();
                bytemuck::cast_slice(&w).to_vec()
            }
            Real::F64 => bytemuck::cast_slice(v).to_vec(),
        }
    }
    fn values(self, b: &[u8]) -> Vec<f64> {
        match self {
            Real::F32 => b
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
                .collect(),
            Real::F64 => b
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect(),
        }
    }
}

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

/// One allocated buffer.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct BufferRecord {
    pub label: String,
    pub bytes: u64,
}

/// One compiled kernel instance.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct KernelRecord {
    pub name: String,
    pub entry: String,
    pub real: String,
    pub acc: String,
    pub constants: Vec<(String, f64)>,
}

/// What the solver allocated, compiled and dispatched: "model only what a scene needs".
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Resources {
    pub buffers: Vec<BufferRecord>,
    pub kernels: Vec<KernelRecord>,
    /// Dispatches recorded per kernel name since the solver was built.
    pub dispatches: BTreeMap<String, u64>,
}

impl Resources {
    pub fn has_buffer(&self, label: &str) -> bool {
        self.buffers.iter().any(|b| b.label == label)
    }
    pub fn dispatches_of(&self, name: &str) -> u64 {
        self.dispatches.get(name).copied().unwrap_or(0)
    }
    pub fn total_bytes(&self) -> u64 {
        self.buffers.iter().map(|b| b.bytes).sum()
    }
}

/// Device time of one kernel (see `GpuSolver::profile_kernels`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct KernelTime {
    pub name: String,
    pub best_s: f64,
    pub mean_s: f64,
}

/// Wall-clock split of a solve.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct StageSeconds {
    pub upload: f64,
    pub setup: f64,
    pub solve: f64,
    pub download: f64,
}

/// What a successful GPU solve did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GpuSolveInfo {
    pub adapter: String,
    pub precision: Precision,
    /// CG iterations, all restarts and inner solves together.
    pub iterations: usize,
    /// Iterations recorded into command buffers (the chunks); those past convergence are
    /// no-ops on the device but still cost their dispatches. ≥ `iterations`.
    pub recorded_iterations: usize,
    /// Mixed precision: f32 segments, each ended by a reliable update (the true residual
    /// recomputed in f64 and put in place of the f32 one); 0 otherwise.
    pub outer_refinements: usize,
    pub restarts: usize,
    /// ‖b̂ − Ĥy‖/‖b̂‖ recomputed in f64 on the host from the downloaded y.
    pub relative_residual: f64,
    pub seconds: StageSeconds,
    /// Device time of the CG chunks from timestamp queries, where the adapter has them.
    pub gpu_seconds: Option<f64>,
    /// Bytes one CG iteration must move: matrix (or element) data, indices, vectors.
    pub bytes_per_iteration: u64,
    /// bytes_per_iteration · iterations / seconds.solve.
    pub achieved_gb_per_s: f64,
    /// The same over gpu_seconds.
    pub achieved_gb_per_s_gpu: Option<f64>,
    pub dispatches_per_iteration: usize,
    /// Status and result read-backs of this solve.
    pub readbacks: usize,
    /// Mixed: why the solve fell back to f64 CG and where that ran (None: it did not).
    pub fallback: Option<String>,
    /// Mixed, when extended-precision refinement ran (f64 CG stagnated above `tol`, or
    /// `error_tol` was set): its estimate of the relative error ‖y − y*‖/‖y*‖, y* the exact
    /// solution of Ĥ as assembled in f64 on the host (the device's rotated blocks and the
    /// matrix-free residual round differently: their solutions differ by about κε). After a
    /// stagnation, success was claimed on this estimate being ≤ min(tol, error_tol),
    /// because the f64 residual cannot resolve `tol` (its rounding floor ε‖Ĥ‖‖y‖/‖b̂‖ is
    /// above it), so `relative_residual` may exceed `tol`. It is an estimate from the
    /// contraction of consecutive corrections (as LAPACK's refinement error bounds), not
    /// a proof. None: success means relative_residual ≤ tol.
    pub error_estimate: Option<f64>,
    /// κ̃(M⁻¹Ĥ), M the preconditioner, from the Lanczos coefficients of the CG runs (the
    /// largest over uninterrupted runs; an underestimate that tightens as CG runs; the
    /// f32 runs of mixed see the f32 operator). None when no run had 2 iterations.
    pub condition_estimate: Option<f64>,
    pub notes: Vec<String>,
}

/// The host copy of the system, for the true f64 residual and the recovery lift.
enum HostOp {
    Blocks(BlockCsr),
    Springs(MassSpring),
}

struct Host {
    op: HostOp,
    frames: Frames,
    rhs: Vec<f64>,
    diag: Vec<f64>,
    /// Reusable f64 scratch for the host products: Ĥy (d·n) and the work of the product
    /// (2·d·n); its contents between calls do not matter.
    scratch: Vec<f64>,
}

/// out = Ĥ y in f64 for the host operator; `work` has length 2·d·n (contents ignored).
fn host_apply(op: &HostOp, f: &Frames, diag: &[f64], y: &[f64], out: &mut [f64], work: &mut [f64]) {
    match op {
        HostOp::Blocks(h) => apply_eliminated(h, f, diag, y, out, work),
        HostOp::Springs(ms) => {
            let w = &mut work[..y.len()];
            w.copy_from_slice(y);
            f.apply_mask(w);
            f.from_frame_in_place(w);
            ms.apply(w, out);
            f.to_frame_in_place(out);
            let d = f.dim;
            for (i, &m) in f.mask.iter().enumerate() {
                for a in 0..d {
                    if m & (1 << a) != 0 {
                        out[i * d + a] = diag[i * d + a] * y[i * d + a];
                    }
                }
            }
        }
    }
}

impl Host {
    fn new(op: HostOp, frames: Frames, rhs: Vec<f64>, diag: Vec<f64>) -> Self {
        let scratch = vec![0.0; 3 * rhs.len()];
        Host {
            op,
            frames,
            rhs,
            diag,
            scratch,
        }
    }

    fn ndof(&self) -> usize {
        self.rhs.len()
    }

    /// out = Ĥ y in f64 (no per-call allocation once the scratch has its size).
    fn apply(&mut self, y: &[f64], out: &mut [f64]) {
        let n = y.len();
        let Host {
            op,
            frames,
            diag,
            scratch,
            ..
        } = self;
        if scratch.len() < 3 * n {
            scratch.resize(3 * n, 0.0);
        }
        host_apply(op, frames, diag, y, out, &mut scratch[..2 * n]);
    }

    /// Largest |diagonal entry| of H (its diagonal blocks, before rotation and masking).
    fn diag_max(&self) -> f64 {
        let (d, blocks): (usize, Vec<f64>) = match &self.op {
            HostOp::Blocks(h) => {
                let dd = h.dim * h.dim;
                let mut v = Vec::with_capacity(h.n * dd);
                for i in 0..h.n {
                    if let Some(k) = h.diag_index(i) {
                        v.extend_from_slice(&h.values[k * dd..(k + 1) * dd]);
                    }
                }
                (h.dim, v)
            }
            HostOp::Springs(ms) => (ms.dim, spring_diag_blocks(ms, &self.frames)),
        };
        blocks
            .chunks_exact(d * d)
            .flat_map(|b| (0..d).map(move |a| b[a * d + a].abs()))
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    }

    /// ‖b̂ − Ĥy‖ / ‖b̂‖ in f64, as [`Eliminated::relative_residual`].
    fn relative_residual(&mut self, y: &[f64]) -> f64 {
        let n = y.len();
        let Host {
            op,
            frames,
            rhs,
            diag,
            scratch,
        } = self;
        if scratch.len() < 3 * n {
            scratch.resize(3 * n, 0.0);
        }
        let (hy, work) = scratch.split_at_mut(n);
        host_apply(op, frames, diag, y, hy, &mut work[..2 * n]);
        relative_residual_from(rhs, hy)
    }

    /// Δx = V P y + Δx_p with dx_free = V P y computed on the device.
    fn add_lift(&self, dx_free: &mut [f64]) {
        if !self.frames.homogeneous {
            for (v, l) in dx_free.iter_mut().zip(&self.frames.lift) {
                *v += l;
            }
        }
    }
}

#[derive(Clone, Copy)]
enum Bind {
    Uniform,
    Ro,
    Rw,
}

struct Kernel {
    name: &'static str,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

/// Allocation and compilation with bookkeeping and limit checks.
struct Builder<'a> {
    ctx: &'a GpuContext,
    buffers: Vec<BufferRecord>,
    kernels: Vec<KernelRecord>,
    modules: BTreeMap<(String, &'static str, &'static str), wgpu::ShaderModule>,
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

impl<'a> Builder<'a> {
    fn new(ctx: &'a GpuContext) -> Self {
        Builder {
            ctx,
            buffers: Vec::new(),
            kernels: Vec::new(),
            modules: BTreeMap::new(),
        }
    }

    fn check_size(
        &self,
        label: &str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<(), GpuError> {
        let l = &self.ctx.limits;
        let too_large = |limit: u64, what: &'static str| GpuError::BufferTooLarge {
            label: label.to_string(),
            bytes,
            limit,
            what,
            adapter: self.ctx.info.name.clone(),
        };
        if bytes > l.max_buffer_size {
            return Err(too_large(l.max_buffer_size, "buffer"));
        }
        if usage.contains(wgpu::BufferUsages::STORAGE) && bytes > l.max_storage_buffer_binding_size
        {
            return Err(too_large(
                l.max_storage_buffer_binding_size,
                "storage binding",
            ));
        }
        Ok(())
    }

    fn buffer(
        &mut self,
        label: &str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<wgpu::Buffer, GpuError> {
        // Bindings must not be empty; round up to whole 16-byte units.
        let bytes = bytes.max(16).div_ceil(16) * 16;
        self.check_size(label, bytes, usage)?;
        let b = self.ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes,
            usage,
            mapped_at_creation: false,
        });
        self.buffers.push(BufferRecord {
            label: label.to_string(),
            bytes,
        });
        Ok(b)
    }

    fn init(
        &mut self,
        label: &str,
        data: &[u8],
        usage: wgpu::BufferUsages,
    ) -> Result<wgpu::Buffer, GpuError> {
        let mut padded;
        let contents = if data.len() < 16 || data.len() % 4 != 0 {
            padded = data.to_vec();
            padded.resize(data.len().max(16).div_ceil(4) * 4, 0);
            &padded[..]
        } else {
            data
        };
        self.check_size(label, contents.len() as u64, usage)?;
        let b = self
            .ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            });
        self.buffers.push(BufferRecord {
            label: label.to_string(),
            bytes: contents.len() as u64,
        });
        Ok(b)
    }

    fn storage(&mut self, label: &str, data: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        self.init(label, data, STORAGE)
    }

    fn staging(&mut self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        self.buffer(
            label,
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn kernel(
        &mut self,
        name: &'static str,
        file: &'static str,
        src: &'static str,
        real: Real,
        acc: Real,
        entry: &'static str,
        binds: &[Bind],
        constants: &[(&str, f64)],
    ) -> Result<Kernel, GpuError> {
        let dev = &self.ctx.device;
        let key = (file.to_string(), real.name(), acc.name());
        if !self.modules.contains_key(&key) {
            let code = format!("{}{}", kernels::prelude(real.name(), acc.name()), src);
            let m = dev.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(&format!("{file} ({}/{})", real.name(), acc.name())),
                source: wgpu::ShaderSource::Wgsl(code.into()),
            });
            self.modules.insert(key.clone(), m);
        }
        let module = &self.modules[&key];
        let entries: Vec<wgpu::BindGroupLayoutEntry> = binds
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: match b {
                        Bind::Uniform => wgpu::BufferBindingType::Uniform,
                        Bind::Ro => wgpu::BufferBindingType::Storage { read_only: true },
                        Bind::Rw => wgpu::BufferBindingType::Storage { read_only: false },
                    },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            })
            .collect();
        let layout = dev.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(&format!("{name} layout")),
            entries: &entries,
        });
        let pl = dev.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(&format!("{name} pipeline layout")),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(&format!("{name} ({})", real.name())),
            layout: Some(&pl),
            module,
            entry_point: Some(entry),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                zero_initialize_workgroup_memory: true,
            },
            cache: None,
        });
        self.ctx.check(&format!("building kernel {name}"))?;
        self.kernels.push(KernelRecord {
            name: name.to_string(),
            entry: entry.to_string(),
            real: real.name().to_string(),
            acc: acc.name().to_string(),
            constants: constants.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        });
        Ok(Kernel {
            name,
            pipeline,
            layout,
        })
    }

    fn bind(&self, k: &Kernel, label: &str, bufs: &[&wgpu::Buffer]) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = bufs
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout: &k.layout,
                entries: &entries,
            })
    }
}

/// Type-independent data of the system on the device.
struct Shared {
    params: wgpu::Buffer,
    /// Block pattern (assembled) or spring adjacency (matrix-free), columns packed with masks.
    row_ptr: wgpu::Buffer,
    col: wgpu::Buffer,
    mask: Option<wgpu::Buffer>,
    rot_index: Option<wgpu::Buffer>,
    rot_nodes: Option<wgpu::Buffer>,
    /// Springs: the identity pattern of the host-computed diagonal blocks.
    diag_row_ptr: Option<wgpu::Buffer>,
    diag_col: Option<wgpu::Buffer>,
    /// Bound where a kernel's specialization never touches the binding.
    placeholder: wgpu::Buffer,
}

impl Shared {
    fn mask_or(&self) -> &wgpu::Buffer {
        self.mask.as_ref().unwrap_or(&self.placeholder)
    }
}

/// Values per block in each of the three block planes (see matvec.wgsl): D = 3 splits the
/// row-major 3×3 block as (e0..e3), (e4..e7), (e8); D = 2 keeps the 2×2 block in plane 0.
fn plane_widths(d: usize) -> [usize; 3] {
    if d == 3 {
        [4, 4, 1]
    } else {
        [4, 0, 0]
    }
}

/// Row-major d×d blocks → the three planes.
fn to_planes(d: usize, values: &[f64]) -> [Vec<f64>; 3] {
    let w = plane_widths(d);
    let dd = d * d;
    let n = values.len() / dd;
    let mut out = [
        Vec::with_capacity(n * w[0]),
        Vec::with_capacity(n * w[1]),
        Vec::with_capacity(n * w[2]),
    ];
    for b in values.chunks_exact(dd) {
        let mut o = 0;
        for (p, &wp) in out.iter_mut().zip(&w) {
            p.extend_from_slice(&b[o..o + wp]);
            o += wp;
        }
    }
    out
}

/// The three planes → row-major d×d blocks.
fn from_planes(d: usize, n_blocks: usize, planes: &[Vec<f64>; 3]) -> Vec<f64> {
    let w = plane_widths(d);
    let mut out = Vec::with_capacity(n_blocks * d * d);
    for k in 0..n_blocks {
        for (p, &wp) in planes.iter().zip(&w) {
            out.extend_from_slice(&p[k * wp..(k + 1) * wp]);
        }
    }
    out
}

/// Allocates the three block planes `{label}`, `{label}_b`, `{label}_c` (each checked
/// against the binding limit on its own; unused planes take 16 bytes).
fn plane_buffers(
    bld: &mut Builder,
    label: &str,
    d: usize,
    n_blocks: usize,
    real: Real,
) -> Result<[wgpu::Buffer; 3], GpuError> {
    let w = plane_widths(d);
    // An unused plane still binds as one vec4<real> (32 bytes for f64).
    let bytes = |wp: usize| ((n_blocks * wp) as u64 * real.size()).max(4 * real.size());
    Ok([
        bld.buffer(label, bytes(w[0]), STORAGE)?,
        bld.buffer(&format!("{label}_b"), bytes(w[1]), STORAGE)?,
        bld.buffer(&format!("{label}_c"), bytes(w[2]), STORAGE)?,
    ])
}

enum OpData {
    Blocks {
        /// Block planes (see `plane_widths`).
        blocks: [wgpu::Buffer; 3],
        rotate: Option<(Kernel, wgpu::BindGroup)>,
    },
    Springs {
        pos: wgpu::Buffer,
        springs: wgpu::Buffer,
        mass: wgpu::Buffer,
        /// Host-rotated diagonal blocks of VᵀHV (as planes), for the preconditioner build.
        diag_blocks: [wgpu::Buffer; 3],
    },
}

/// Ĥ in one scalar type.
struct Operator {
    real: Real,
    data: OpData,
    dvals: Option<wgpu::Buffer>,
    rotations: Option<wgpu::Buffer>,
    matvec: Kernel,
}

/// One CG in one scalar type.
struct Level {
    real: Real,
    acc: Real,
    op: Operator,
    x: wgpu::Buffer,
    r: wgpu::Buffer,
    #[allow(dead_code)]
    z: wgpu::Buffer,
    p: wgpu::Buffer,
    q: wgpu::Buffer,
    b: wgpu::Buffer,
    minv: wgpu::Buffer,
    scal: wgpu::Buffer,
    state: wgpu::Buffer,
    k_update_p: Kernel,
    k_update_xrz: Kernel,
    k_init: Kernel,
    bg_cg: wgpu::BindGroup,
    bg_mv_p: wgpu::BindGroup,
    bg_mv_x: wgpu::BindGroup,
    precond: Option<(Kernel, wgpu::BindGroup)>,
    status_staging: wgpu::Buffer,
}

/// Mixed precision: the f64 outer loop.
struct Refine {
    /// The f64 operator; `None` when its blocks exceed the storage binding limit, and then
    /// the outer residual is computed on the host from the downloaded y.
    op: Option<Operator>,
    /// f64 rotations for the recovery when `op` is `None`.
    rotations64: Option<wgpu::Buffer>,
    b64: wgpu::Buffer,
    y64: wgpu::Buffer,
    partials64: wgpu::Buffer,
    /// [1/‖r‖, 2^s·‖r‖]: the inner right-hand side's normalization and the correction's
    /// scale back (see refine.wgsl).
    factors: wgpu::Buffer,
    k_residual: Kernel,
    k_scale_rhs: Kernel,
    k_accumulate: Kernel,
    bg_mv: Option<wgpu::BindGroup>,
    bg_refine: wgpu::BindGroup,
    staging: wgpu::Buffer,
}

struct Recovery {
    real: Real,
    dx: wgpu::Buffer,
    recover: Option<(Kernel, wgpu::BindGroup)>,
    rotate: Option<(Kernel, wgpu::BindGroup)>,
    staging: wgpu::Buffer,
}

struct Timestamps {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    period_ns: f64,
}

/// Result of one CG run (until convergence of the recurrence, the budget or stagnation).
enum Outcome {
    Converged,
    MaxIters,
    Stagnated,
}

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
    /// Size of the first chunk of the next `run_cg` (mixed: the previous segment's length).
    chunk_hint: Option<usize>,
    /// r·r where the next `run_cg` starts, when known (mixed: 1, the unit right-hand side
    /// with x = 0): the first point of its rate history, so the chunk after the first is
    /// predicted instead of doubled.
    start_rr: Option<f64>,
}

fn u32s(v: impl IntoIterator<Item = u32>) -> Vec<u8> {
    let w: Vec<u32> = v.into_iter().collect();
    bytemuck::cast_slice(&w).to_vec()
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

/// b̂ = −P Vᵀ(g + H Δx_p) for the matrix-free system.
fn spring_rhs(ms: &MassSpring, g: &[f64], frames: &Frames) -> Vec<f64> {
    crate::elimination::eliminated_rhs(g, frames, |x, y| ms.apply(x, y))
}

/// Diagonal blocks V_iᵀ H_ii V_i of the spring Hessian, computed on the host (O(springs)).
fn spring_diag_blocks(ms: &MassSpring, frames: &Frames) -> Vec<f64> {
    let d = ms.dim;
    let n = ms.n_nodes();
    let mut out = vec![0.0; n * d * d];
    for i in 0..n {
        for a in 0..d {
            out[i * d * d + a * d + a] = ms.masses[i];
        }
    }
    let h2 = ms.h * ms.h;
    for (e, &[i, j]) in ms.edges.iter().enumerate() {
        let k = ms.spring_hessian(e);
        for node in [i, j] {
            for c in 0..d * d {
                out[node * d * d + c] += h2 * k[c];
            }
        }
    }
    let mut tmp = [0.0f64; 9];
    for i in 0..n {
        if let Some(v) = frames.rotation(i) {
            rotate_block(
                d,
                &out[i * d * d..(i + 1) * d * d],
                Some(v),
                Some(v),
                &mut tmp[..d * d],
            );
            out[i * d * d..(i + 1) * d * d].copy_from_slice(&tmp[..d * d]);
        }
    }
    out
}

/// Node adjacency of the springs: per node, (other node, spring) pairs.
fn spring_adjacency(ms: &MassSpring) -> (Vec<u32>, Vec<u32>) {
    let n = ms.n_nodes();
    let mut count = vec![0u32; n + 1];
    for &[i, j] in &ms.edges {
        count[i + 1] += 1;
        count[j + 1] += 1;
    }
    for i in 0..n {
        count[i + 1] += count[i];
    }
    let mut fill = count.clone();
    let mut adj = vec![0u32; 2 * count[n] as usize];
    for (e, &[i, j]) in ms.edges.iter().enumerate() {
        for (a, b) in [(i, j), (j, i)] {
            let k = fill[a] as usize;
            adj[2 * k] = b as u32;
            adj[2 * k + 1] = e as u32;
            fill[a] += 1;
        }
    }
    (count, adj)
}

fn spring_data(ms: &MassSpring) -> Vec<f64> {
    let h2 = ms.h * ms.h;
    ms.rest_lengths
        .iter()
        .zip(&ms.stiffness)
        .flat_map(|(&l, &k)| [l, h2 * k])
        .collect()
}

/// System data the builder turns into buffers.
enum SystemRef<'s> {
    Blocks(&'s BlockCsr),
    Springs(&'s MassSpring),
}

impl GpuSolver {
    /// Builds the solver for an assembled eliminated system.
    pub fn new(ctx: &GpuContext, e: &Eliminated, params: &GpuParams) -> Result<Self, GpuError> {
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
        let n_partials = (n.div_ceil(wg as usize)).clamp(1, 256) as u32;
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
        let shared = Shared {
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
            start_rr: None,
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

    /// Writes Ĥ's values into `op`, multiplied by `scale` (a power of two: exact) except
    /// for the geometry (positions, rest lengths, rotations).
    fn write_operator(&self, op: &Operator, scale: f64) {
        let q = &self.ctx.queue;
        let host = &self.host;
        let sc = |v: &[f64]| -> Vec<f64> {
            if scale == 1.0 {
                v.to_vec()
            } else {
                v.iter().map(|x| x * scale).collect()
            }
        };
        match (&op.data, &host.op) {
            (OpData::Blocks { blocks, .. }, HostOp::Blocks(h)) => {
                for (buf, v) in blocks.iter().zip(to_planes(h.dim, &sc(&h.values))) {
                    if !v.is_empty() {
                        q.write_buffer(buf, 0, &op.real.bytes(&v));
                    }
                }
            }
            (
                OpData::Springs {
                    pos,
                    springs,
                    mass,
                    diag_blocks,
                },
                HostOp::Springs(ms),
            ) => {
                q.write_buffer(pos, 0, &op.real.bytes(&ms.positions));
                let mut sd = spring_data(ms);
                for v in sd.iter_mut().skip(1).step_by(2) {
                    *v *= scale;
                }
                q.write_buffer(springs, 0, &op.real.bytes(&sd));
                q.write_buffer(mass, 0, &op.real.bytes(&sc(&ms.masses)));
                let diag = sc(&spring_diag_blocks(ms, &host.frames));
                for (buf, v) in diag_blocks.iter().zip(to_planes(ms.dim, &diag)) {
                    if !v.is_empty() {
                        q.write_buffer(buf, 0, &op.real.bytes(&v));
                    }
                }
            }
            _ => unreachable!("operator kind follows the host system"),
        }
        if let Some(dv) = &op.dvals {
            q.write_buffer(dv, 0, &op.real.bytes(&sc(&host.diag)));
        }
        if let Some(rot) = &op.rotations {
            q.write_buffer(rot, 0, &op.real.bytes(&host.frames.rotations));
        }
    }

    fn upload_values(&mut self) -> Result<(), GpuError> {
        self.write_operator(&self.level.op, self.inner_scale);
        if let Some(fl) = &self.fallback_level {
            self.write_operator(&fl.op, 1.0);
        }
        match &self.refine {
            Some(rf) => {
                match &rf.op {
                    Some(op) => self.write_operator(op, 1.0),
                    None => {
                        if let Some(rot) = &rf.rotations64 {
                            self.ctx.queue.write_buffer(
                                rot,
                                0,
                                &Real::F64.bytes(&self.host.frames.rotations),
                            );
                        }
                    }
                }
                self.ctx
                    .queue
                    .write_buffer(&rf.b64, 0, &Real::F64.bytes(&self.host.rhs));
            }
            None => {
                let l = &self.level;
                self.ctx
                    .queue
                    .write_buffer(&l.b, 0, &l.real.bytes(&self.host.rhs));
            }
        }
        self.ctx.check("uploading the system")
    }

    fn record(&mut self, name: &'static str) {
        *self.dispatches.entry(name.to_string()).or_default() += 1;
    }

    fn node_groups(&self) -> u32 {
        (self.n_nodes as u32).div_ceil(self.wg)
    }

    /// Rotation of the H blocks (slip nodes only) and the preconditioner build.
    fn device_setup(&mut self) -> Result<(), GpuError> {
        self.setup_levels(true, true)
    }

    /// Rotation and preconditioner build of the main levels (`main`: the CG level and the
    /// refinement operator) and/or of the f64 fallback level where it exists.
    fn setup_levels(&mut self, main: bool, fallback: bool) -> Result<(), GpuError> {
        let mut enc = self.encoder("setup");
        let mut names = Vec::new();
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("setup pass"),
                timestamp_writes: None,
            });
            let groups = self.node_groups();
            let main_ops = std::iter::once(&self.level.op)
                .chain(self.refine.as_ref().and_then(|r| r.op.as_ref()))
                .filter(|_| main);
            let fb = self.fallback_level.as_ref().filter(|_| fallback);
            let ops = main_ops.chain(fb.map(|l| &l.op));
            for op in ops {
                if let OpData::Blocks {
                    rotate: Some((k, bg)),
                    ..
                } = &op.data
                {
                    pass.set_pipeline(&k.pipeline);
                    pass.set_bind_group(0, bg, &[]);
                    pass.dispatch_workgroups(groups, 1, 1);
                    names.push(k.name);
                }
            }
            let pre = std::iter::once(&self.level)
                .filter(|_| main)
                .chain(fb)
                .filter_map(|l| l.precond.as_ref());
            for (k, bg) in pre {
                pass.set_pipeline(&k.pipeline);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(groups, 1, 1);
                names.push(k.name);
            }
        }
        self.ctx.queue.submit([enc.finish()]);
        for n in names {
            self.record(n);
        }
        self.wait()?;
        self.ctx.check("device setup")
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

    /// Resets the CG scalars: ρ_prev, the convergence threshold, the direction scale kept
    /// by `init` (0: p = 0), flags cleared.
    fn reset_scalars(&self, thresh: f64, rho_prev: f64, pscale: f64) {
        let l = &self.level;
        let mut s = vec![0.0f64; N_SCAL];
        s[1] = rho_prev;
        s[5] = thresh;
        s[6] = pscale;
        self.ctx.queue.write_buffer(&l.scal, 0, &l.acc.bytes(&s));
        self.ctx
            .queue
            .write_buffer(&l.state, 0, &[0u8; 4 * N_STATE]);
    }

    fn dispatch(&mut self, pass: &mut wgpu::ComputePass<'_>, which: Which, groups: u32) {
        let (k, bg) = match which {
            Which::UpdateP => (&self.level.k_update_p, &self.level.bg_cg),
            Which::UpdateXrz => (&self.level.k_update_xrz, &self.level.bg_cg),
            Which::Init => (&self.level.k_init, &self.level.bg_cg),
            Which::MatvecP => (&self.level.op.matvec, &self.level.bg_mv_p),
            Which::MatvecX => (&self.level.op.matvec, &self.level.bg_mv_x),
        };
        pass.set_pipeline(&k.pipeline);
        pass.set_bind_group(0, bg, &[]);
        pass.dispatch_workgroups(groups, 1, 1);
        let name = k.name;
        self.record(name);
    }

    /// Starts CG at the current x (zeroed first unless `keep_x`): q = Ĥx, r = b − q,
    /// z = M⁻¹r, then the first update_p (p = z).
    fn start(&mut self, keep_x: bool, thresh: f64) -> Result<(), GpuError> {
        self.begin(thresh, Begin::Restart { keep_x })
    }

    /// Mixed precision's reliable update: CG goes on from the new right-hand side b (the
    /// true residual, renormalized) with x = 0, r = b, and the search direction kept,
    /// rescaled by `pscale` (= ‖r_old‖/‖r_new‖, the ratio of the two normalizations);
    /// `rho_prev` is ρ_prev in the new normalization. Restarting instead (p = 0) throws the
    /// Krylov space away and costs mixed 40% more iterations than f64 CG (64k nodes).
    fn resume(&mut self, thresh: f64, rho_prev: f64, pscale: f64) -> Result<(), GpuError> {
        self.begin(thresh, Begin::Resume { rho_prev, pscale })
    }

    /// The common start of a CG run: scalars, then init and the first update_p. A restart
    /// computes q = Ĥx; a resume has x = 0, so it clears q instead of a product.
    fn begin(&mut self, thresh: f64, how: Begin) -> Result<(), GpuError> {
        let (label, what) = match how {
            Begin::Restart { .. } => ("cg start", "starting CG"),
            Begin::Resume { .. } => ("cg reliable update", "reliable update"),
        };
        let mut enc = self.encoder(label);
        match how {
            Begin::Restart { keep_x } => {
                self.reset_scalars(thresh, 1.0, 0.0);
                self.lz_resumed = false;
                if !keep_x {
                    enc.clear_buffer(&self.level.x, 0, None);
                }
            }
            Begin::Resume { rho_prev, pscale } => {
                self.reset_scalars(thresh, rho_prev, pscale);
                self.lz_resumed = true;
                enc.clear_buffer(&self.level.x, 0, None);
                enc.clear_buffer(&self.level.q, 0, None);
            }
        }
        {
            let mut pass = enc
                .begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(label),
                    timestamp_writes: None,
                })
                .forget_lifetime();
            let g = self.n_partials;
            if matches!(how, Begin::Restart { .. }) {
                self.dispatch(&mut pass, Which::MatvecX, g);
            }
            self.dispatch(&mut pass, Which::Init, g);
            self.dispatch(&mut pass, Which::UpdateP, g);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check(what)
    }

    /// Records `k` iterations in one submit, then reads the status back.
    fn chunk(&mut self, k: usize) -> Result<Status, GpuError> {
        self.recorded += k;
        let mut enc = self.encoder("cg chunk");
        {
            let tw = self
                .timestamps
                .as_ref()
                .map(|t| wgpu::ComputePassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: Some(0),
                    end_of_pass_write_index: Some(1),
                });
            let mut pass = enc
                .begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("cg chunk pass"),
                    timestamp_writes: tw,
                })
                .forget_lifetime();
            let g = self.n_partials;
            for _ in 0..k {
                self.dispatch(&mut pass, Which::MatvecP, g);
                self.dispatch(&mut pass, Which::UpdateXrz, g);
                self.dispatch(&mut pass, Which::UpdateP, g);
            }
        }
        let l = &self.level;
        // The scalars and the coefficient history (16 KiB in f64: no extra read-back).
        let sb = l.acc.size() * SCAL_LEN as u64;
        enc.copy_buffer_to_buffer(&l.scal, 0, &l.status_staging, 0, sb);
        enc.copy_buffer_to_buffer(&l.state, 0, &l.status_staging, sb, 4 * N_STATE as u64);
        if let Some(t) = &self.timestamps {
            enc.resolve_query_set(&t.set, 0..2, &t.resolve, 0);
            enc.copy_buffer_to_buffer(
                &t.resolve,
                0,
                &l.status_staging,
                sb + 4 * N_STATE as u64,
                16,
            );
        }
        self.ctx.queue.submit([enc.finish()]);
        let total = sb + 4 * N_STATE as u64 + 16;
        let staging = self.level.status_staging.clone();
        let bytes = self.read(&staging, total)?;
        let scal = self.level.acc.values(&bytes[..sb as usize]);
        let st: Vec<u32> = bytes[sb as usize..sb as usize + 4 * N_STATE]
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if let Some(t) = &self.timestamps {
            let o = sb as usize + 4 * N_STATE;
            let t0 = u64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
            let t1 = u64::from_le_bytes(bytes[o + 8..o + 16].try_into().expect("8 bytes"));
            self.gpu_seconds += t1.saturating_sub(t0) as f64 * t.period_ns * 1e-9;
        }
        self.last_rho_prev = scal[1];
        let st_out = Status {
            rr: scal[4],
            pq: scal[2],
            iterations: st[2] as usize,
            converged: st[3] != 0,
            curvature: st[1] != 0,
            breakdown: st[4] != 0,
        };
        self.last_scal = scal;
        Ok(st_out)
    }

    /// Appends the Lanczos coefficients of the run that just ended (from the last status
    /// read) to the current sequence: continued across a reliable update (joined by the
    /// β of its first update_p), else after closing the previous sequence.
    fn lanczos_collect(&mut self, iterations: usize) {
        let resumed = std::mem::take(&mut self.lz_resumed);
        if !resumed || self.lz_alphas.is_empty() {
            self.lanczos_close();
        } else {
            self.lz_betas.push(self.last_scal[7]);
        }
        let n = iterations.min(LANCZOS_HIST);
        let h = &self.last_scal[N_SCAL..];
        self.lz_alphas.extend((0..n).map(|j| h[2 * j]));
        self.lz_betas
            .extend((0..n.saturating_sub(1)).map(|j| h[2 * j + 1]));
        if iterations > LANCZOS_HIST {
            // Truncated: the next run cannot continue this sequence.
            self.lanczos_close();
        }
    }

    /// Ends the current coefficient sequence, keeping the largest estimate so far.
    fn lanczos_close(&mut self) {
        if let Some(k) = crate::cg::lanczos_condition(&self.lz_alphas, &self.lz_betas) {
            self.kappa_est = Some(self.kappa_est.map_or(k, |c: f64| c.max(k)));
        }
        self.lz_alphas.clear();
        self.lz_betas.clear();
    }

    /// κ̃(M⁻¹Ĥ) of the current sequence and the earlier ones.
    fn kappa_now(&self) -> Option<f64> {
        let cur = crate::cg::lanczos_condition(&self.lz_alphas, &self.lz_betas);
        match (cur, self.kappa_est) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        }
    }

    /// Runs CG from the state `start` left until the recurrence residual² ≤ `thresh`,
    /// the budget, or stagnation. Returns the outcome and the iterations done.
    ///
    /// Chunk sizing: the first chunks double from `first_chunk`; once two status reads
    /// exist, the next chunk is the number of iterations predicted to reach `thresh` at the
    /// residual reduction rate observed over the later half of the run so far, clamped to
    /// [first_chunk, min(2·previous, max_chunk)]. Iterations recorded past convergence are
    /// then at most about one prediction error (or `first_chunk`), not half the run.
    fn run_cg(
        &mut self,
        budget: usize,
        done_before: usize,
        thresh: f64,
    ) -> Result<(Outcome, usize), GpuError> {
        let res = self.run_cg_chunks(budget, done_before, thresh);
        if let Ok((_, it)) = &res {
            self.lanczos_collect(*it);
        } else {
            self.lz_resumed = false;
        }
        res
    }

    fn run_cg_chunks(
        &mut self,
        budget: usize,
        done_before: usize,
        thresh: f64,
    ) -> Result<(Outcome, usize), GpuError> {
        let floor = self.params.first_chunk;
        let cap = self.params.max_chunk;
        let mut k = self.chunk_hint.take().unwrap_or(floor).clamp(floor, cap);
        let mut best = f64::INFINITY;
        let mut best_at = 0usize;
        let mut iters = 0usize;
        // (iterations, ln r·r) at each status read.
        let mut hist: Vec<(usize, f64)> = Vec::new();
        if let Some(rr0) = self.start_rr.take().filter(|v| *v > 0.0 && v.is_finite()) {
            hist.push((0, rr0.ln()));
        }
        loop {
            let kk = k.min(budget.saturating_sub(iters));
            if kk == 0 {
                return Ok((Outcome::MaxIters, iters));
            }
            let st = self.chunk(kk)?;
            iters = st.iterations;
            if st.breakdown {
                return Err(CgError::Breakdown {
                    iteration: done_before + iters,
                }
                .into());
            }
            if st.curvature {
                return Err(CgError::NonPositiveCurvature {
                    iteration: done_before + iters + 1,
                    curvature: st.pq,
                }
                .into());
            }
            if st.converged {
                return Ok((Outcome::Converged, iters));
            }
            if st.rr < best {
                best = st.rr;
                best_at = iters;
            } else if iters - best_at >= self.params.stagnation_window {
                return Ok((Outcome::Stagnated, iters));
            }
            if st.rr > 0.0 && st.rr.is_finite() {
                hist.push((iters, st.rr.ln()));
            }
            k = next_chunk(&hist, thresh, kk, floor, cap);
        }
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

    /// Mixed precision, in three stages, each entered only when the one before cannot go on:
    /// 1. f32 CG with reliable updates (f64 accumulation of y, f64 true residuals);
    /// 2. f64 CG (GPU, else CPU), warm-started from y, when f32 meets non-positive
    ///    curvature, breaks down, or a segment reduces the true residual less than 2×;
    /// 3. extended-precision refinement when f64 CG stagnates on its residual's rounding
    ///    floor (and, with `error_tol`, after success, until the error estimate is met).
    #[allow(clippy::type_complexity)]
    fn solve_mixed(
        &mut self,
        bnorm: f64,
        notes: &mut Vec<String>,
    ) -> Result<(usize, usize, usize, f64, f64, Vec<f64>, Vec<f64>), GpuError> {
        let tol = self.params.tol;
        let t0 = Instant::now();
        let mut total = 0usize;
        let mut dl = 0.0;
        if self.refine.as_ref().is_some_and(|r| r.op.is_none()) {
            notes.push(
                "mixed: the f64 blocks exceed the adapter's storage binding limit; only the f32 \
                 blocks live on the device and the outer f64 residual is computed on the host"
                    .into(),
            );
        }
        if self.inner_scale != 1.0 {
            notes.push(format!(
                "mixed: Ĥ's diagonal is extreme; the f32 operator holds 2^{} Ĥ (exact) and the \
                 corrections are scaled back in f64",
                self.inner_scale.log2()
            ));
        }
        self.clear_y64();
        let mut outer = 0usize;
        let mut prev = f64::INFINITY;
        // (ρ_prev, ‖r‖) of a converged f32 segment: the next one resumes from its direction.
        let mut keep: Option<(f64, f64)> = None;
        // Iterations of the last segment: the next one's first chunk (one status read-back
        // per segment instead of a doubling series).
        let mut seg_len: Option<usize> = None;
        let reason: String = loop {
            let rel = self.outer_residual()? / bnorm;
            if rel <= tol {
                let td = Instant::now();
                let (y, dx) = self.download_solution()?;
                dl += td.elapsed().as_secs_f64();
                let true_rel = self.host.relative_residual(&y);
                if true_rel <= tol {
                    let (total, y, dx) = self.certify(total, &mut dl, notes, y, dx)?;
                    let solve = t0.elapsed().as_secs_f64() - dl;
                    return Ok((total, outer, 0, solve, dl, y, dx));
                }
                notes.push(format!(
                    "device f64 residual {rel:e} but host residual {true_rel:e}; refining further"
                ));
            }
            if !rel.is_finite() {
                self.clear_y64();
                break format!("the f64 residual is not finite after outer step {outer}");
            }
            if outer > 0 && rel > 0.5 * prev {
                break format!(
                    "outer step {outer}: the f32 inner solve reduced the f64 residual only from \
                     {prev:.3e} to {rel:.3e} (less than 2×)"
                );
            }
            if outer >= self.params.max_outer || total >= self.params.max_iters {
                let td = Instant::now();
                let (y, _) = self.download_solution()?;
                dl += td.elapsed().as_secs_f64();
                let _ = dl;
                let true_rel = self.host.relative_residual(&y);
                return Err(if total >= self.params.max_iters {
                    CgError::MaxIterations {
                        iterations: total,
                        relative_residual: true_rel,
                        tol,
                    }
                } else {
                    CgError::Stagnation {
                        iterations: total,
                        relative_residual: true_rel,
                        tol,
                    }
                }
                .into());
            }
            prev = rel;
            // f32 CG on 2^s Ĥ d̃ = r/‖r‖ (unit right-hand side) until its recurrence residual
            // has dropped by δ = inner_tol; then y += 2^s‖r‖d̃ in f64, the true residual is
            // recomputed in f64 and replaces the f32 one (a reliable update, as in QUDA's
            // mixed-precision CG), and CG goes on with its search direction kept. Only
            // after an f32 segment that did not converge (stagnation, budget) does the next
            // segment restart from p = 0.
            let rn = rel * bnorm;
            let delta = self.params.inner_tol;
            let thresh = delta * delta;
            match keep.take() {
                Some((rho_prev, rn_prev)) if rn > 0.0 => {
                    let ps = rn_prev / rn;
                    self.resume(thresh, rho_prev * ps * ps, ps)?;
                }
                _ => self.start(false, thresh)?,
            }
            self.chunk_hint = seg_len;
            self.start_rr = Some(1.0);
            match self.run_cg(self.params.max_iters - total, total, thresh) {
                Ok((out, it)) => {
                    total += it;
                    outer += 1;
                    self.accumulate();
                    if matches!(out, Outcome::Converged) {
                        keep = Some((self.last_rho_prev, rn));
                        seg_len = Some(it.max(1));
                    }
                    if let Some(k) = self.kappa_now() {
                        let ke = k * f64::from(f32::EPSILON);
                        if ke > F32_KAPPA_LIMIT {
                            break format!(
                                "outer step {outer}: κ̃(M⁻¹Ĥ) ≈ {k:.2e} from the f32 CG's \
                                 Lanczos coefficients; κ̃·ε_f32 = {ke:.2} > {F32_KAPPA_LIMIT}, \
                                 where f32 CG loses orthogonality and costs more iterations \
                                 than it saves"
                            );
                        }
                    }
                }
                Err(GpuError::Cg(CgError::NonPositiveCurvature {
                    iteration,
                    curvature,
                })) => {
                    total = total.max(iteration.saturating_sub(1));
                    outer += 1;
                    // x is the last iterate before the rejected step: keep its progress.
                    self.accumulate();
                    break format!(
                        "outer step {outer}: the f32 inner CG met non-positive curvature \
                         pᵀĤp = {curvature:e} at iteration {iteration} (f32 rounding; f64 CG \
                         checks Ĥ again)"
                    );
                }
                Err(GpuError::Cg(CgError::Breakdown { iteration })) => {
                    total = total.max(iteration);
                    outer += 1;
                    break format!(
                        "outer step {outer}: the f32 inner CG broke down (non-finite value) at \
                         iteration {iteration}"
                    );
                }
                Err(e) => return Err(e),
            }
        };
        // Fallback: f64 CG for the rest of the solve, warm-started from the f64 iterate.
        let on_gpu = self.refine.as_ref().is_some_and(|r| r.op.is_some())
            && !self.force_cpu_fallback
            && match self.ensure_fallback_level() {
                Ok(()) => true,
                Err(e @ GpuError::BufferTooLarge { .. }) => {
                    notes.push(format!("f64 fallback level does not fit on the GPU: {e}"));
                    false
                }
                Err(e) => return Err(e),
            };
        let place = if on_gpu {
            "f64 CG on the GPU"
        } else {
            "f64 CG on the CPU (src/cg.rs)"
        };
        let msg = format!("{reason}; finished by {place}, warm-started from the f64 iterate");
        notes.push(format!("mixed fell back to f64: {msg}"));
        self.last_fallback = Some(msg);
        let fb = if on_gpu {
            self.fallback_gpu(total, &mut dl)
        } else {
            self.fallback_cpu(total, &mut dl)
        };
        let (all, restarts, y, dx) = match fb {
            Ok((it, restarts, y, dx)) => {
                let (all, y, dx) = self.certify(total + it, &mut dl, notes, y, dx)?;
                (all, restarts, y, dx)
            }
            Err(GpuError::Cg(CgError::Stagnation {
                iterations,
                relative_residual,
                ..
            })) if on_gpu && matches!(self.host.op, HostOp::Blocks(_)) => {
                notes.push(format!(
                    "f64 CG stagnated at relative residual {relative_residual:.3e} (its \
                     rounding floor); extended-precision refinement (double-double residuals \
                     on the host, f64 CG corrections on the GPU) goes on"
                ));
                // The residual cannot show tol: the error estimate must be ≤ tol instead
                // (and ≤ error_tol when that is asked for too).
                let target = self
                    .params
                    .error_tol
                    .map_or(self.params.tol, |et| et.min(self.params.tol));
                let (it, y, dx) = self.refine_extended(iterations, &mut dl, notes, target)?;
                (iterations + it, 0, y, dx)
            }
            Err(e) => return Err(e),
        };
        let solve = t0.elapsed().as_secs_f64() - dl;
        Ok((all, outer, restarts, solve, dl, y, dx))
    }

    /// Mixed with `error_tol`: after the residual criterion is met, extended-precision
    /// refinement goes on until the estimated relative error is ≤ error_tol. Without it,
    /// returns its inputs.
    fn certify(
        &mut self,
        total: usize,
        dl: &mut f64,
        notes: &mut Vec<String>,
        y: Vec<f64>,
        dx: Vec<f64>,
    ) -> Result<(usize, Vec<f64>, Vec<f64>), GpuError> {
        let Some(target) = self.params.error_tol else {
            return Ok((total, y, dx));
        };
        if !matches!(self.host.op, HostOp::Blocks(_)) {
            return Err(GpuError::Unsupported(
                "error_tol needs an assembled Hessian (not a mass-spring operator)".into(),
            ));
        }
        if self.refine.as_ref().is_some_and(|r| r.op.is_none()) {
            return Err(GpuError::Unsupported(
                "error_tol needs the f64 operator on the GPU, and its blocks exceed the \
                 adapter's storage binding limit"
                    .into(),
            ));
        }
        self.ensure_fallback_level()?;
        notes.push(format!(
            "error_tol {target:e}: extended-precision refinement estimates and reduces the error"
        ));
        let (it, y, dx) = self.refine_extended(total, dl, notes, target)?;
        Ok((total + it, y, dx))
    }

    /// Mixed precision's last stage, after f64 CG stagnated above `tol`: iterative
    /// refinement y ← y + d with r = b̂ − Ĥy in double-double on the host
    /// ([`BlockCsr::residual_dd`]) and Ĥd = r solved by f64 CG on the GPU. Each step
    /// contracts the error by the inner solve's relative error η (≈ κε), so y converges to
    /// the solution of the f64 Ĥ while κε < 1, past the f64 residual's rounding floor.
    /// Success is claimed when the estimated error ‖d‖/‖y‖·ρ/(1 − ρ) (ρ the observed
    /// contraction of consecutive corrections) is ≤ tol; a contraction ρ ≥ 1/2 ends it with
    /// `Stagnation`. Returns the iterations of its inner solves, y and Δx.
    fn refine_extended(
        &mut self,
        done: usize,
        dl: &mut f64,
        notes: &mut Vec<String>,
        target: f64,
    ) -> Result<(usize, Vec<f64>, Vec<f64>), GpuError> {
        let nd = self.host.ndof();
        let y64 = self
            .refine
            .as_ref()
            .expect("mixed has a refinement level")
            .y64
            .clone();
        let td = Instant::now();
        let mut y = self.download(self.encoder("download y"), &y64, Real::F64, nd)?;
        *dl += td.elapsed().as_secs_f64();
        if self.assembled.is_none() {
            let HostOp::Blocks(h) = &self.host.op else {
                return Err(GpuError::Unsupported(
                    "extended-precision refinement needs an assembled Hessian".into(),
                ));
            };
            let e = Eliminated {
                h,
                frames: &self.host.frames,
                rhs: Vec::new(),
                diag: self.host.diag.clone(),
            };
            self.assembled = Some(e.assemble());
        }
        let a = self.assembled.take().expect("assembled above");
        let res =
            self.on_fallback_level(|s| s.refine_extended_run(&a, &mut y, done, notes, target));
        self.assembled = Some(a);
        let (its, est) = res?;
        self.last_error_estimate = Some(est);
        self.ctx.queue.write_buffer(&y64, 0, &Real::F64.bytes(&y));
        let td = Instant::now();
        let (y, dx) = self.download_solution()?;
        *dl += td.elapsed().as_secs_f64();
        Ok((its, y, dx))
    }

    fn refine_extended_run(
        &mut self,
        a: &BlockCsr,
        y: &mut [f64],
        done: usize,
        notes: &mut Vec<String>,
        target: f64,
    ) -> Result<(usize, f64), GpuError> {
        // Corrections within a few ulps of y are rounding: y is then the f64 Ĥ's solution
        // to working precision.
        const ROUNDING: f64 = 8.0 * f64::EPSILON;
        const MAX_STEPS: usize = 10;
        // The inner CG's recurrence target: far below the f64 residual floor, so the
        // correction is as accurate as f64 CG makes it.
        const INNER_TOL: f64 = 1e-12;
        let tol = self.params.tol;
        let nd = y.len();
        let bnorm = norm2(&self.host.rhs);
        let mut its = 0usize;
        let mut prev: Option<f64> = None;
        for step in 1..=MAX_STEPS {
            let r = a.residual_dd(&self.host.rhs, y);
            let rn = norm2(&r);
            let rel = rn / bnorm;
            if rn == 0.0 {
                notes.push(format!(
                    "extended step {step}: the residual is exactly zero"
                ));
                return Ok((its, 0.0));
            }
            let scaled: Vec<f64> = r.iter().map(|v| v / rn).collect();
            self.ctx
                .queue
                .write_buffer(&self.level.b, 0, &Real::F64.bytes(&scaled));
            self.start(false, INNER_TOL * INNER_TOL)?;
            let budget = self.params.max_iters.saturating_sub(done + its);
            let (out, it) = self.run_cg(budget, done + its, INNER_TOL * INNER_TOL)?;
            its += it;
            // A correction from a stagnated inner CG is still used (it is the best f64 CG
            // reaches), but it may underestimate the error: no claim on its step.
            let inner_converged = matches!(out, Outcome::Converged);
            if matches!(out, Outcome::MaxIters) {
                return Err(CgError::MaxIterations {
                    iterations: done + its,
                    relative_residual: rel,
                    tol,
                }
                .into());
            }
            let x_buf = self.level.x.clone();
            let x = self.download(self.encoder("download correction"), &x_buf, Real::F64, nd)?;
            let mut d2 = 0.0f64;
            for (v, xk) in y.iter_mut().zip(&x) {
                let d = rn * xk;
                *v += d;
                d2 += d * d;
            }
            let yn = norm2(y);
            if !(d2.is_finite() && yn.is_finite()) {
                return Err(CgError::Breakdown {
                    iteration: done + its,
                }
                .into());
            }
            let eta = if yn > 0.0 { d2.sqrt() / yn } else { 0.0 };
            let (rho, est) = match prev {
                _ if !inner_converged => (f64::NAN, f64::INFINITY),
                // Rounding-level corrections count only after one observed contraction.
                Some(_) if eta <= ROUNDING => (0.0, ROUNDING),
                Some(pe) if pe > 0.0 => {
                    let rho = eta / pe;
                    // Floored at the rounding of y itself: no f64 vector is closer than that.
                    let est = eta * rho / (1.0 - rho).max(f64::MIN_POSITIVE);
                    (rho, est.max(ROUNDING))
                }
                _ => (f64::NAN, f64::INFINITY),
            };
            notes.push(format!(
                "extended step {step}: residual (double-double) {rel:.3e}, correction \
                 ‖d‖/‖y‖ {eta:.3e}, contraction {rho:.2e}, error estimate {est:.2e} \
                 ({it} f64 CG iterations)"
            ));
            if est <= target {
                return Ok((its, est));
            }
            if rho >= 0.5 {
                break;
            }
            prev = Some(eta);
        }
        // The residual of the iterate that is returned.
        let rel = norm2(&a.residual_dd(&self.host.rhs, y)) / bnorm;
        Err(CgError::Stagnation {
            iterations: done + its,
            relative_residual: rel,
            tol,
        }
        .into())
    }

    fn clear_y64(&mut self) {
        let rf = self.refine.as_ref().expect("mixed has a refinement level");
        let mut enc = self.encoder("mixed reset");
        enc.clear_buffer(&rf.y64, 0, None);
        self.ctx.queue.submit([enc.finish()]);
    }

    /// y64 += 2^s·‖r‖·x32 (the factors written by `outer_residual`).
    fn accumulate(&mut self) {
        let rf = self.refine.as_ref().expect("mixed has a refinement level");
        let mut enc = self.encoder("mixed accumulate");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("accumulate pass"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&rf.k_accumulate.pipeline);
            pass.set_bind_group(0, &rf.bg_refine, &[]);
            pass.dispatch_workgroups(((self.n_nodes * self.dim) as u32).div_ceil(self.wg), 1, 1);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.record("accumulate");
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

    /// Builds the f64 CG level of the fallback (once; kept across solves and updates).
    fn ensure_fallback_level(&mut self) -> Result<(), GpuError> {
        if self.fallback_level.is_some() {
            return Ok(());
        }
        let ctx = self.ctx.clone();
        let mut bld = Builder::new(&ctx);
        let acc = self.level.acc;
        let op = build_operator(
            &mut bld,
            &self.shared,
            &self.host,
            Real::F64,
            acc,
            &self.consts,
        )?;
        let level = build_level(
            &mut bld,
            &self.shared,
            op,
            &self.host,
            acc,
            &self.consts,
            self.params.preconditioner,
        )?;
        ctx.check("allocating the f64 fallback level")?;
        self.buffers
            .extend(bld.buffers.into_iter().map(|b| BufferRecord {
                label: format!("fallback_{}", b.label),
                bytes: b.bytes,
            }));
        self.kernels.extend(bld.kernels);
        self.fallback_level = Some(level);
        if let Some(fl) = &self.fallback_level {
            self.write_operator(&fl.op, 1.0);
        }
        self.setup_levels(false, true)
    }

    /// Runs `f` with the f64 fallback level in the CG's place, then puts both back.
    fn on_fallback_level<T>(
        &mut self,
        f: impl FnOnce(&mut Self) -> Result<T, GpuError>,
    ) -> Result<T, GpuError> {
        let Some(mut fb) = self.fallback_level.take() else {
            return Err(GpuError::Device("the f64 fallback level is missing".into()));
        };
        std::mem::swap(&mut self.level, &mut fb);
        let r = f(self);
        std::mem::swap(&mut self.level, &mut fb);
        self.fallback_level = Some(fb);
        r
    }

    /// The fallback on the GPU: the f64 level takes the CG's place for the run.
    fn fallback_gpu(
        &mut self,
        done: usize,
        dl: &mut f64,
    ) -> Result<(usize, usize, Vec<f64>, Vec<f64>), GpuError> {
        self.on_fallback_level(|s| s.fallback_gpu_run(done, dl))
    }

    fn fallback_gpu_run(
        &mut self,
        done: usize,
        dl: &mut f64,
    ) -> Result<(usize, usize, Vec<f64>, Vec<f64>), GpuError> {
        let tol = self.params.tol;
        let thresh = (tol * norm2(&self.host.rhs)).powi(2);
        let nd = self.host.ndof() as u64;
        let y64 = self
            .refine
            .as_ref()
            .expect("mixed has a refinement level")
            .y64
            .clone();
        self.ctx
            .queue
            .write_buffer(&self.level.b, 0, &Real::F64.bytes(&self.host.rhs));
        let mut enc = self.encoder("fallback warm start");
        enc.copy_buffer_to_buffer(&y64, 0, &self.level.x, 0, nd * 8);
        self.ctx.queue.submit([enc.finish()]);
        let mut total = 0usize;
        let mut restarts = 0usize;
        loop {
            self.start(true, thresh)?;
            let budget = self.params.max_iters.saturating_sub(done + total);
            let (out, it) = self.run_cg(budget, done + total, thresh)?;
            total += it;
            let mut enc = self.encoder("fallback result");
            enc.copy_buffer_to_buffer(&self.level.x, 0, &y64, 0, nd * 8);
            self.ctx.queue.submit([enc.finish()]);
            let td = Instant::now();
            let (y, dx) = self.download_solution()?;
            *dl += td.elapsed().as_secs_f64();
            let rel = self.host.relative_residual(&y);
            match out {
                Outcome::Converged if rel <= tol => return Ok((total, restarts, y, dx)),
                Outcome::Converged
                    if restarts < self.params.max_restarts
                        && done + total < self.params.max_iters =>
                {
                    restarts += 1;
                }
                Outcome::MaxIters => {
                    return Err(CgError::MaxIterations {
                        iterations: done + total,
                        relative_residual: rel,
                        tol,
                    }
                    .into())
                }
                _ => {
                    return Err(CgError::Stagnation {
                        iterations: done + total,
                        relative_residual: rel,
                        tol,
                    }
                    .into())
                }
            }
        }
    }

    /// The fallback on the CPU: `cg::solve_with` from the downloaded f64 iterate.
    fn fallback_cpu(
        &mut self,
        done: usize,
        dl: &mut f64,
    ) -> Result<(usize, usize, Vec<f64>, Vec<f64>), GpuError> {
        let nd = self.host.ndof();
        let y64 = self
            .refine
            .as_ref()
            .expect("mixed has a refinement level")
            .y64
            .clone();
        let td = Instant::now();
        let y0 = self.download(self.encoder("download y"), &y64, Real::F64, nd)?;
        *dl += td.elapsed().as_secs_f64();
        let HostOp::Blocks(h) = &self.host.op else {
            return Err(GpuError::Unsupported(
                "the CPU fallback of mixed precision needs an assembled Hessian".into(),
            ));
        };
        let e = Eliminated {
            h,
            frames: &self.host.frames,
            rhs: self.host.rhs.clone(),
            diag: self.host.diag.clone(),
        };
        let pc = self.params.preconditioner;
        let pre = crate::cg::BuiltPreconditioner::new(&e, pc);
        let cp = crate::cg::CgParams {
            tol: self.params.tol,
            max_iters: self.params.max_iters.saturating_sub(done),
            preconditioner: pc,
            stagnation_window: self.params.stagnation_window,
            max_restarts: self.params.max_restarts,
            ..Default::default()
        };
        let warm = y0.iter().all(|v| v.is_finite()).then_some(&y0[..]);
        let (y, info) = crate::cg::solve_with(&e, &pre, warm, &cp).map_err(|err| match err {
            CgError::NonPositiveCurvature {
                iteration,
                curvature,
            } => CgError::NonPositiveCurvature {
                iteration: iteration + done,
                curvature,
            },
            CgError::Stagnation {
                iterations,
                relative_residual,
                tol,
            } => CgError::Stagnation {
                iterations: iterations + done,
                relative_residual,
                tol,
            },
            CgError::MaxIterations {
                iterations,
                relative_residual,
                tol,
            } => CgError::MaxIterations {
                iterations: iterations + done,
                relative_residual,
                tol,
            },
            CgError::Breakdown { iteration } => CgError::Breakdown {
                iteration: iteration + done,
            },
        })?;
        self.ctx.queue.write_buffer(&y64, 0, &Real::F64.bytes(&y));
        let td = Instant::now();
        let (_, dx) = self.download_solution()?;
        *dl += td.elapsed().as_secs_f64();
        Ok((info.iterations, info.restarts, y, dx))
    }

    /// ‖b̂ − Ĥy‖ in f64 (on the device, or on the host when the f64 blocks do not fit);
    /// also sets the inner CG's right-hand side to r/‖r‖ and the factors
    /// [1/‖r‖, 2^s·‖r‖] of the refinement kernels.
    fn outer_residual(&mut self) -> Result<f64, GpuError> {
        let g = self.n_partials;
        let nd = self.host.ndof();
        let scale = self.inner_scale;
        let factors = |rn: f64| -> Vec<u8> {
            let inv = if rn > 0.0 && (1.0 / rn).is_finite() {
                1.0 / rn
            } else {
                1.0
            };
            Real::F64.bytes(&[inv, scale / inv])
        };
        let rf = self.refine.as_ref().expect("mixed has a refinement level");
        let (Some(op), Some(bg_mv)) = (&rf.op, &rf.bg_mv) else {
            // Host path: download y (f64), r = b̂ − Ĥy in f64, upload f32(r/‖r‖).
            let y64 = rf.y64.clone();
            let fb = rf.factors.clone();
            let y = self.download(self.encoder("download y"), &y64, Real::F64, nd)?;
            let mut r = vec![0.0; nd];
            self.host.apply(&y, &mut r);
            // r = b̂ − Ĥy in place.
            for (v, b) in r.iter_mut().zip(&self.host.rhs) {
                *v = b - *v;
            }
            let rn = norm2(&r);
            let f = factors(rn);
            let inv = Real::F64.values(&f)[0];
            r.iter_mut().for_each(|v| *v *= inv);
            self.ctx
                .queue
                .write_buffer(&self.level.b, 0, &Real::F32.bytes(&r));
            self.ctx.queue.write_buffer(&fb, 0, &f);
            return Ok(rn);
        };
        let mut enc = self.encoder("mixed residual");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("residual pass"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&op.matvec.pipeline);
            pass.set_bind_group(0, bg_mv, &[]);
            pass.dispatch_workgroups(g, 1, 1);
            pass.set_pipeline(&rf.k_residual.pipeline);
            pass.set_bind_group(0, &rf.bg_refine, &[]);
            pass.dispatch_workgroups(g, 1, 1);
        }
        enc.copy_buffer_to_buffer(&rf.partials64, 0, &rf.staging, 0, 8 * g as u64);
        self.ctx.queue.submit([enc.finish()]);
        let name = op.matvec.name;
        let staging = rf.staging.clone();
        self.record(name);
        self.record("residual");
        let bytes = self.read(&staging, 8 * g as u64)?;
        // Fixed-order sum of the per-workgroup partials: deterministic.
        let s: f64 = Real::F64.values(&bytes).iter().sum();
        let rn = s.max(0.0).sqrt();
        let rf = self.refine.as_ref().expect("mixed has a refinement level");
        self.ctx.queue.write_buffer(&rf.factors, 0, &factors(rn));
        let mut enc = self.encoder("mixed scale rhs");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("scale rhs pass"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&rf.k_scale_rhs.pipeline);
            pass.set_bind_group(0, &rf.bg_refine, &[]);
            pass.dispatch_workgroups((nd as u32).div_ceil(self.wg), 1, 1);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.record("scale_rhs");
        Ok(rn)
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

    // ---- Kernel-level access for tests (each kernel against its CPU reference). ----

    /// q = Ĥ y with the CG's operator kernel (in the CG's precision).
    pub fn apply_operator(&mut self, y: &[f64]) -> Result<Vec<f64>, GpuError> {
        let l = &self.level;
        self.ctx.queue.write_buffer(&l.p, 0, &l.real.bytes(y));
        self.ctx
            .queue
            .write_buffer(&l.state, 0, &[0u8; 4 * N_STATE]);
        let mut enc = self.encoder("apply operator");
        {
            let mut pass = enc
                .begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("apply operator pass"),
                    timestamp_writes: None,
                })
                .forget_lifetime();
            let g = self.n_partials;
            self.dispatch(&mut pass, Which::MatvecP, g);
        }
        let q = self.level.q.clone();
        self.download(enc, &q, self.level.real, y.len())
    }

    /// Device time per CG kernel in seconds (fastest and mean of `reps` iterations; the
    /// fastest is the figure least disturbed by other load on a shared CPU adapter), from timestamp
    /// queries around each dispatch in its own compute pass: `matvec` (or `spring_matvec`),
    /// `update_xrz`, `update_p`, and for mixed precision the f64 `matvec_f64` and
    /// `residual`. Runs from y = 0 without a stopping test; `None` without TIMESTAMP_QUERY.
    pub fn profile_kernels(&mut self, reps: usize) -> Result<Option<Vec<KernelTime>>, GpuError> {
        let Some(period) = self.timestamps.as_ref().map(|t| t.period_ns) else {
            return Ok(None);
        };
        let reps = reps.max(1);
        if self.refine.is_some() {
            let rhs = Real::F32.bytes(&self.host.rhs);
            self.ctx.queue.write_buffer(&self.level.b, 0, &rhs);
        }
        self.start(false, -1.0)?;
        let dev = &self.ctx.device;
        let n_q = 10u32;
        let set = dev.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("profile timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: n_q,
        });
        let qb = 8 * n_q as u64;
        let resolve = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("profile resolve"),
            size: qb,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let staging = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("profile staging"),
            size: qb,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut names: Vec<String> = vec![
            self.level.op.matvec.name.to_string(),
            "update_xrz".into(),
            "update_p".into(),
        ];
        if self.refine.as_ref().is_some_and(|r| r.op.is_some()) {
            names.push(format!("{}_f64", self.level.op.matvec.name));
            names.push("residual".into());
        }
        let mut best = vec![f64::INFINITY; names.len()];
        let mut sum = vec![0.0f64; names.len()];
        let g = self.n_partials;
        for _ in 0..reps {
            let mut enc = self.encoder("profile");
            let mut slot = 0u32;
            let pass_for = |enc: &mut wgpu::CommandEncoder, slot: &mut u32| {
                let tw = wgpu::ComputePassTimestampWrites {
                    query_set: &set,
                    beginning_of_pass_write_index: Some(*slot),
                    end_of_pass_write_index: Some(*slot + 1),
                };
                *slot += 2;
                enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("profile pass"),
                    timestamp_writes: Some(tw),
                })
                .forget_lifetime()
            };
            for which in [Which::MatvecP, Which::UpdateXrz, Which::UpdateP] {
                let mut pass = pass_for(&mut enc, &mut slot);
                self.dispatch(&mut pass, which, g);
            }
            if let Some((rf, op, bg_mv)) = self
                .refine
                .as_ref()
                .and_then(|rf| Some((rf, rf.op.as_ref()?, rf.bg_mv.as_ref()?)))
            {
                let mut pass = pass_for(&mut enc, &mut slot);
                pass.set_pipeline(&op.matvec.pipeline);
                pass.set_bind_group(0, bg_mv, &[]);
                pass.dispatch_workgroups(g, 1, 1);
                drop(pass);
                let mut pass = pass_for(&mut enc, &mut slot);
                pass.set_pipeline(&rf.k_residual.pipeline);
                pass.set_bind_group(0, &rf.bg_refine, &[]);
                pass.dispatch_workgroups(g, 1, 1);
            }
            enc.resolve_query_set(&set, 0..slot, &resolve, 0);
            enc.copy_buffer_to_buffer(&resolve, 0, &staging, 0, 8 * slot as u64);
            self.ctx.queue.submit([enc.finish()]);
            let bytes = self.read(&staging, 8 * slot as u64)?;
            let t: Vec<u64> = bytes
                .chunks_exact(8)
                .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect();
            for j in 0..names.len() {
                let dt = t[2 * j + 1].saturating_sub(t[2 * j]) as f64 * period * 1e-9;
                best[j] = best[j].min(dt);
                sum[j] += dt;
            }
        }
        Ok(Some(
            names
                .into_iter()
                .zip(best.into_iter().zip(sum))
                .map(|(name, (best_s, sum_s))| KernelTime {
                    name,
                    best_s,
                    mean_s: sum_s / reps as f64,
                })
                .collect(),
        ))
    }

    /// The device's Ĥ blocks after rotation (assembled systems only), unmasked, f64.
    pub fn rotated_blocks(&mut self) -> Result<Option<Vec<f64>>, GpuError> {
        let (bufs, real, d, nb) = match (&self.level.op.data, &self.host.op) {
            (OpData::Blocks { blocks, .. }, HostOp::Blocks(h)) => {
                (blocks.clone(), self.level.op.real, h.dim, h.nnz_blocks())
            }
            _ => return Ok(None),
        };
        let w = plane_widths(d);
        let mut planes: [Vec<f64>; 3] = Default::default();
        for ((buf, &wp), out) in bufs.iter().zip(&w).zip(planes.iter_mut()) {
            if wp > 0 {
                let enc = self.encoder("download blocks");
                *out = self.download(enc, buf, real, nb * wp)?;
            }
        }
        Ok(Some(from_planes(d, nb, &planes)))
    }

    /// The preconditioner data built on the device: 1/diag (Jacobi, d·n values) or the
    /// inverse diagonal blocks (block-Jacobi, d²·n), like `BuiltPreconditioner::data`.
    pub fn preconditioner_data(&mut self) -> Result<Vec<f64>, GpuError> {
        let d = self.dim;
        let len = match self.params.preconditioner {
            Preconditioner::None => return Ok(Vec::new()),
            Preconditioner::Jacobi => self.n_nodes * d,
            Preconditioner::BlockJacobi => self.n_nodes * d * d,
        };
        let enc = self.encoder("download preconditioner");
        let b = self.level.minv.clone();
        self.download(enc, &b, self.level.real, len)
    }

    /// Δx = Δx_p + V P y through the device's recovery kernels.
    pub fn recover_on_device(&mut self, y: &[f64]) -> Result<Vec<f64>, GpuError> {
        let rr = self.recovery.real;
        match &self.refine {
            Some(r) => self.ctx.queue.write_buffer(&r.y64, 0, &rr.bytes(y)),
            None => self.ctx.queue.write_buffer(&self.level.x, 0, &rr.bytes(y)),
        }
        Ok(self.download_solution()?.1)
    }

    /// Runs `k` PCG iterations from y = 0 (no stopping test) and returns (x, r, p).
    #[allow(clippy::type_complexity)]
    pub fn iterate(&mut self, k: usize) -> Result<(Vec<f64>, Vec<f64>, Vec<f64>), GpuError> {
        if let Some(rf) = &self.refine {
            // Mixed: the inner CG's right-hand side is b̂ rounded to f32.
            let rhs = Real::F32.bytes(&self.host.rhs);
            let _ = rf;
            self.ctx.queue.write_buffer(&self.level.b, 0, &rhs);
        }
        self.start(false, -1.0)?;
        let _ = self.chunk(k)?;
        let nd = self.n_nodes * self.dim;
        let real = self.level.real;
        let (x, r, p) = (
            self.level.x.clone(),
            self.level.r.clone(),
            self.level.p.clone(),
        );
        let xs = self.download(self.encoder("x"), &x, real, nd)?;
        let rs = self.download(self.encoder("r"), &r, real, nd)?;
        let ps = self.download(self.encoder("p"), &p, real, nd)?;
        Ok((xs, rs, ps))
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

/// The power of two 2^s that brings H's largest diagonal entry to [1, 2) when it lies
/// outside [2^-20, 2^20] (else 1): the f32 operator of mixed precision holds 2^s·Ĥ, which
/// is exact in floating point and keeps f32 far from underflow and overflow.
fn inner_scale(diag_max: f64) -> f64 {
    if !(diag_max > 0.0 && diag_max.is_finite()) {
        return 1.0;
    }
    let e = diag_max.log2().floor();
    if e.abs() <= 20.0 {
        1.0
    } else {
        (-e).exp2()
    }
}

/// Size of the next chunk from the status history (see `GpuSolver::run_cg`).
fn next_chunk(hist: &[(usize, f64)], thresh: f64, prev: usize, floor: usize, cap: usize) -> usize {
    let grow = (2 * prev).min(cap).max(floor);
    let Some(&(it, lr)) = hist.last() else {
        return grow;
    };
    // The rate over the later half of the run: early CG iterations are not representative,
    // and a single chunk's rate is noisy (the CG residual is not monotone).
    let Some(&(it0, lr0)) = hist.iter().rev().find(|&&(i, _)| 2 * i <= it) else {
        return grow;
    };
    let rate = (lr0 - lr) / (it - it0) as f64;
    // Written to reject NaN too.
    if rate.is_nan() || rate <= 0.0 || thresh.is_nan() || thresh <= 0.0 {
        return grow;
    }
    let need = (lr - thresh.ln()) / rate;
    if !need.is_finite() {
        return grow;
    }
    (need.max(0.0).ceil() as usize).clamp(floor, grow)
}

/// How `GpuSolver::begin` starts a CG run.
#[derive(Clone, Copy)]
enum Begin {
    /// From the current x (or zero), p = 0.
    Restart { keep_x: bool },
    /// Mixed's reliable update: x = 0, p kept and rescaled.
    Resume { rho_prev: f64, pscale: f64 },
}

#[derive(Clone, Copy)]
enum Which {
    UpdateP,
    UpdateXrz,
    Init,
    MatvecP,
    MatvecX,
}

struct Status {
    rr: f64,
    pq: f64,
    iterations: usize,
    converged: bool,
    curvature: bool,
    breakdown: bool,
}

#[derive(Clone, Copy)]
struct Consts {
    d: f64,
    wg: f64,
    masked: bool,
    rotated: bool,
    precond: f64,
}

fn flag(b: bool) -> f64 {
    if b {
        1.0
    } else {
        0.0
    }
}

fn build_operator(
    bld: &mut Builder,
    sh: &Shared,
    host: &Host,
    real: Real,
    acc: Real,
    c: &Consts,
) -> Result<Operator, GpuError> {
    use Bind::*;
    let f = &host.frames;
    let nd = host.ndof() as u64;
    let rn = real.name();
    let dvals = if c.masked {
        Some(bld.buffer(&format!("dvals_{rn}"), nd * real.size(), STORAGE)?)
    } else {
        None
    };
    let rotations = if c.rotated {
        Some(bld.buffer(
            &format!("rotations_{rn}"),
            f.rotations.len() as u64 * real.size(),
            STORAGE,
        )?)
    } else {
        None
    };
    let (data, matvec) = match &host.op {
        HostOp::Blocks(h) => {
            let blocks = plane_buffers(bld, &format!("blocks_{rn}"), h.dim, h.nnz_blocks(), real)?;
            let rotate = match (&rotations, &sh.rot_index, &sh.rot_nodes) {
                (Some(rot), Some(ri), Some(rnod)) => {
                    let k = bld.kernel(
                        "rotate_blocks",
                        "rotate_blocks.wgsl",
                        kernels::ROTATE_BLOCKS,
                        real,
                        acc,
                        "rotate_blocks",
                        &[Uniform, Ro, Ro, Ro, Ro, Ro, Rw, Rw, Rw],
                        &[("D", c.d), ("WG", c.wg)],
                    )?;
                    let bg = bld.bind(
                        &k,
                        "rotate_blocks bind group",
                        &[
                            &sh.params,
                            ri,
                            rnod,
                            rot,
                            &sh.row_ptr,
                            &sh.col,
                            &blocks[0],
                            &blocks[1],
                            &blocks[2],
                        ],
                    );
                    Some((k, bg))
                }
                _ => None,
            };
            let mv = bld.kernel(
                "matvec",
                "matvec.wgsl",
                kernels::MATVEC,
                real,
                acc,
                "matvec",
                &[Uniform, Ro, Ro, Ro, Ro, Ro, Ro, Rw, Rw, Ro, Ro, Ro],
                &[("D", c.d), ("WG", c.wg), ("MASKED", flag(c.masked))],
            )?;
            (OpData::Blocks { blocks, rotate }, mv)
        }
        HostOp::Springs(ms) => {
            let n = ms.n_nodes() as u64;
            let pos = bld.buffer(&format!("positions_{rn}"), nd * real.size(), STORAGE)?;
            let springs = bld.buffer(
                &format!("springs_{rn}"),
                2 * ms.edges.len() as u64 * real.size(),
                STORAGE,
            )?;
            let mass = bld.buffer(&format!("masses_{rn}"), n * real.size(), STORAGE)?;
            let diag_blocks =
                plane_buffers(bld, &format!("diag_blocks_{rn}"), ms.dim, n as usize, real)?;
            let mv = bld.kernel(
                "spring_matvec",
                "springs.wgsl",
                kernels::SPRINGS,
                real,
                acc,
                "spring_matvec",
                &[Uniform, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Ro, Rw, Rw, Ro],
                &[
                    ("D", c.d),
                    ("WG", c.wg),
                    ("MASKED", flag(c.masked)),
                    ("ROTATE", flag(c.rotated)),
                ],
            )?;
            (
                OpData::Springs {
                    pos,
                    springs,
                    mass,
                    diag_blocks,
                },
                mv,
            )
        }
    };
    Ok(Operator {
        real,
        data,
        dvals,
        rotations,
        matvec,
    })
}

/// Whether the block planes of an assembled operator in `real` fit the adapter's limits.
fn blocks_fit(ctx: &GpuContext, host: &Host, real: Real) -> bool {
    let HostOp::Blocks(h) = &host.op else {
        return true;
    };
    let limit = ctx
        .limits
        .max_storage_buffer_binding_size
        .min(ctx.limits.max_buffer_size);
    plane_widths(h.dim)
        .iter()
        .all(|&w| (h.nnz_blocks() * w) as u64 * real.size() <= limit)
}

/// Bind group of the operator kernel with input `p`, output `q`.
#[allow(clippy::too_many_arguments)]
fn bind_operator(
    bld: &Builder,
    sh: &Shared,
    op: &Operator,
    label: &str,
    p: &wgpu::Buffer,
    q: &wgpu::Buffer,
    partials: &wgpu::Buffer,
    state: &wgpu::Buffer,
) -> wgpu::BindGroup {
    let ph = &sh.placeholder;
    let dv = op.dvals.as_ref().unwrap_or(ph);
    match &op.data {
        OpData::Blocks { blocks, .. } => bld.bind(
            &op.matvec,
            label,
            &[
                &sh.params,
                &sh.row_ptr,
                &sh.col,
                &blocks[0],
                sh.mask_or(),
                dv,
                p,
                q,
                partials,
                state,
                &blocks[1],
                &blocks[2],
            ],
        ),
        OpData::Springs {
            pos, springs, mass, ..
        } => bld.bind(
            &op.matvec,
            label,
            &[
                &sh.params,
                &sh.row_ptr,
                &sh.col,
                pos,
                springs,
                mass,
                sh.rot_index.as_ref().unwrap_or(ph),
                op.rotations.as_ref().unwrap_or(ph),
                sh.mask_or(),
                dv,
                p,
                q,
                partials,
                state,
            ],
        ),
    }
}

fn build_level(
    bld: &mut Builder,
    sh: &Shared,
    op: Operator,
    host: &Host,
    acc: Real,
    c: &Consts,
    pc: Preconditioner,
) -> Result<Level, GpuError> {
    use Bind::*;
    let real = op.real;
    let rn = real.name();
    let nd = host.ndof() as u64;
    let vb = nd * real.size();
    let x = bld.buffer(&format!("x_{rn}"), vb, STORAGE)?;
    let r = bld.buffer(&format!("r_{rn}"), vb, STORAGE)?;
    let z = bld.buffer(&format!("z_{rn}"), vb, STORAGE)?;
    let p = bld.buffer(&format!("p_{rn}"), vb, STORAGE)?;
    let q = bld.buffer(&format!("q_{rn}"), vb, STORAGE)?;
    let b = bld.buffer(&format!("b_{rn}"), vb, STORAGE)?;
    let n = host.frames.n_nodes as u64;
    let d = host.frames.dim as u64;
    let minv = match pc {
        Preconditioner::None => None,
        Preconditioner::Jacobi => Some(bld.buffer(
            &format!("precond_jacobi_{rn}"),
            n * d * real.size(),
            STORAGE,
        )?),
        Preconditioner::BlockJacobi => Some(bld.buffer(
            &format!("precond_block_{rn}"),
            n * d * d * real.size(),
            STORAGE,
        )?),
    };
    let g = host.ndof().div_ceil(c.wg as usize).clamp(1, 256) as u64;
    // n_partials is computed from nodes, not DOFs; allocate for the larger bound.
    let partials = bld.buffer("partials", 3 * g.max(256) * acc.size(), STORAGE)?;
    let scal = bld.buffer("cg_scalars", SCAL_LEN as u64 * acc.size(), STORAGE)?;
    let state = bld.buffer("cg_state", 4 * N_STATE as u64, STORAGE)?;
    let status_staging = bld.staging(
        "status_staging",
        SCAL_LEN as u64 * acc.size() + 4 * N_STATE as u64 + 16,
    )?;
    let cg_consts = [
        ("D", c.d),
        ("WG", c.wg),
        ("PRECOND", c.precond),
        ("HIST", LANCZOS_HIST as f64),
    ];
    let cg_binds = [Uniform, Rw, Rw, Rw, Rw, Ro, Ro, Ro, Rw, Rw, Rw];
    let k_update_p = bld.kernel(
        "update_p",
        "cg.wgsl",
        kernels::CG,
        real,
        acc,
        "update_p",
        &cg_binds,
        &cg_consts,
    )?;
    let k_update_xrz = bld.kernel(
        "update_xrz",
        "cg.wgsl",
        kernels::CG,
        real,
        acc,
        "update_xrz",
        &cg_binds,
        &cg_consts,
    )?;
    let k_init = bld.kernel(
        "init",
        "cg.wgsl",
        kernels::CG,
        real,
        acc,
        "init",
        &cg_binds,
        &cg_consts,
    )?;
    let minv_b = minv.as_ref().unwrap_or(&sh.placeholder);
    let bg_cg = bld.bind(
        &k_update_p,
        "cg bind group",
        &[
            &sh.params, &x, &r, &z, &p, &q, &b, minv_b, &partials, &scal, &state,
        ],
    );
    let bg_mv_p = bind_operator(
        bld,
        sh,
        &op,
        "matvec p->q bind group",
        &p,
        &q,
        &partials,
        &state,
    );
    let bg_mv_x = bind_operator(
        bld,
        sh,
        &op,
        "matvec x->q bind group",
        &x,
        &q,
        &partials,
        &state,
    );
    let precond = match &minv {
        None => None,
        Some(mb) => {
            let k = bld.kernel(
                "precond_build",
                "precond.wgsl",
                kernels::PRECOND,
                real,
                acc,
                "build",
                &[Uniform, Ro, Ro, Ro, Ro, Ro, Rw, Ro, Ro],
                &[
                    ("D", c.d),
                    ("WG", c.wg),
                    ("MASKED", flag(c.masked)),
                    ("PRECOND", c.precond),
                ],
            )?;
            let dv = op.dvals.as_ref().unwrap_or(&sh.placeholder);
            let bg = match &op.data {
                OpData::Blocks { blocks, .. } => bld.bind(
                    &k,
                    "precond bind group",
                    &[
                        &sh.params,
                        &sh.row_ptr,
                        &sh.col,
                        &blocks[0],
                        sh.mask_or(),
                        dv,
                        mb,
                        &blocks[1],
                        &blocks[2],
                    ],
                ),
                OpData::Springs { diag_blocks, .. } => bld.bind(
                    &k,
                    "precond bind group",
                    &[
                        &sh.params,
                        sh.diag_row_ptr
                            .as_ref()
                            .expect("springs have a diagonal pattern"),
                        sh.diag_col
                            .as_ref()
                            .expect("springs have a diagonal pattern"),
                        &diag_blocks[0],
                        sh.mask_or(),
                        dv,
                        mb,
                        &diag_blocks[1],
                        &diag_blocks[2],
                    ],
                ),
            };
            Some((k, bg))
        }
    };
    Ok(Level {
        real,
        acc,
        op,
        x,
        r,
        z,
        p,
        q,
        b,
        minv: minv.unwrap_or_else(|| sh.placeholder.clone()),
        scal,
        state,
        k_update_p,
        k_update_xrz,
        k_init,
        bg_cg,
        bg_mv_p,
        bg_mv_x,
        precond,
        status_staging,
    })
}

fn build_refine(
    bld: &mut Builder,
    sh: &Shared,
    op: Option<Operator>,
    level: &Level,
    host: &Host,
    c: &Consts,
) -> Result<Refine, GpuError> {
    use Bind::*;
    let nd = host.ndof() as u64;
    let b64 = bld.buffer("b_f64", nd * 8, STORAGE)?;
    let y64 = bld.buffer("y_f64", nd * 8, STORAGE)?;
    let q64 = bld.buffer("q_f64", nd * 8, STORAGE)?;
    let partials64 = bld.buffer("partials_f64", 256 * 8, STORAGE)?;
    let zero_state = bld.buffer("refine_state", 4 * N_STATE as u64, STORAGE)?;
    let staging = bld.staging("refine_staging", 256 * 8)?;
    let factors = bld.buffer("refine_factors_f64", 2 * 8, STORAGE)?;
    let consts = [("D", c.d), ("WG", c.wg)];
    let binds = [Uniform, Ro, Rw, Rw, Rw, Ro, Rw, Ro];
    let k_residual = bld.kernel(
        "residual",
        "refine.wgsl",
        kernels::REFINE,
        Real::F64,
        Real::F64,
        "residual",
        &binds,
        &consts,
    )?;
    let k_scale_rhs = bld.kernel(
        "scale_rhs",
        "refine.wgsl",
        kernels::REFINE,
        Real::F64,
        Real::F64,
        "scale_rhs",
        &binds,
        &consts,
    )?;
    let k_accumulate = bld.kernel(
        "accumulate",
        "refine.wgsl",
        kernels::REFINE,
        Real::F64,
        Real::F64,
        "accumulate",
        &binds,
        &consts,
    )?;
    let bg_refine = bld.bind(
        &k_residual,
        "refine bind group",
        &[
            &sh.params,
            &b64,
            &q64,
            &level.b,
            &partials64,
            &level.x,
            &y64,
            &factors,
        ],
    );
    let bg_mv = op.as_ref().map(|op| {
        bind_operator(
            bld,
            sh,
            op,
            "matvec f64 y->q bind group",
            &y64,
            &q64,
            &partials64,
            &zero_state,
        )
    });
    let rotations64 = match (&op, host.frames.has_rotation()) {
        (None, true) => Some(bld.buffer(
            "rotations_f64",
            host.frames.rotations.len() as u64 * 8,
            STORAGE,
        )?),
        _ => None,
    };
    Ok(Refine {
        op,
        rotations64,
        b64,
        y64,
        partials64,
        factors,
        k_residual,
        k_scale_rhs,
        k_accumulate,
        bg_mv,
        bg_refine,
        staging,
    })
}

#[allow(clippy::too_many_arguments)]
fn build_recovery(
    bld: &mut Builder,
    sh: &Shared,
    y: &wgpu::Buffer,
    real: Real,
    rotations: Option<&wgpu::Buffer>,
    c: &Consts,
    nd: usize,
) -> Result<Recovery, GpuError> {
    use Bind::*;
    let dx = bld.buffer(
        &format!("dx_{}", real.name()),
        nd as u64 * real.size(),
        STORAGE,
    )?;
    let staging = bld.staging("solution_staging", 2 * nd as u64 * real.size())?;
    let acc = real;
    let recover = match &sh.mask {
        Some(m) => {
            let k = bld.kernel(
                "recover",
                "recover.wgsl",
                kernels::RECOVER,
                real,
                acc,
                "recover",
                &[Uniform, Ro, Ro, Rw],
                &[("D", c.d), ("WG", c.wg)],
            )?;
            let bg = bld.bind(&k, "recover bind group", &[&sh.params, m, y, &dx]);
            Some((k, bg))
        }
        None => None,
    };
    let rotate = match (rotations, &sh.rot_index, &sh.rot_nodes) {
        (Some(rot), Some(ri), Some(rn)) => {
            let k = bld.kernel(
                "rotate_vectors",
                "rotate.wgsl",
                kernels::ROTATE,
                real,
                acc,
                "rotate_vectors",
                &[Uniform, Ro, Ro, Ro, Rw],
                &[("D", c.d), ("WG", c.wg), ("TRANSPOSE", 0.0)],
            )?;
            let bg = bld.bind(
                &k,
                "rotate_vectors bind group",
                &[&sh.params, ri, rn, rot, &dx],
            );
            Some((k, bg))
        }
        _ => None,
    };
    Ok(Recovery {
        real,
        dx,
        recover,
        rotate,
        staging,
    })
}

/// Bytes one CG iteration must move (each array once): operator data and indices, the
/// vectors read and written by the three kernels, and the preconditioner.
fn bytes_per_iteration(host: &Host, level: &Level, c: &Consts, pc: Preconditioner) -> u64 {
    let s = level.real.size();
    let nd = host.ndof() as u64;
    let n = host.frames.n_nodes as u64;
    let d = c.d as u64;
    let mut op = match &host.op {
        HostOp::Blocks(h) => h.values.len() as u64 * s + h.col_idx.len() as u64 * 4 + (n + 1) * 4,
        HostOp::Springs(ms) => {
            // adjacency (2 u32 per spring end), positions, spring data, masses
            (n + 1) * 4
                + 4 * 4 * ms.edges.len() as u64
                + nd * s
                + 2 * ms.edges.len() as u64 * s
                + n * s
        }
    };
    op += 2 * nd * s; // p read, q written
    if c.masked {
        op += n * 4 + nd * s; // mask, D
    }
    if c.rotated {
        if let HostOp::Springs(_) = host.op {
            op += n * 4 + host.frames.rotations.len() as u64 * s;
        }
    }
    // update_xrz: x rw, p r, r rw, q r, z w; update_p: z r, p rw.
    let vec = (2 + 1 + 2 + 1 + 1 + 1 + 2) * nd * s;
    let pre = match pc {
        Preconditioner::None => 0,
        Preconditioner::Jacobi => nd * s,
        Preconditioner::BlockJacobi => n * d * d * s,
    };
    op + vec + pre
}

#[cfg(test)]
mod tests {
    use super::next_chunk;

    #[test]
    fn chunks_follow_the_predicted_remaining_iterations() {
        // No history, or too little of it: double within [floor, cap].
        assert_eq!(next_chunk(&[], 1e-12, 8, 8, 256), 16);
        assert_eq!(next_chunk(&[(8, 0.0)], 1e-12, 8, 8, 256), 16);
        // ln r·r falls by 0.1 per iteration; 10 more iterations reach the threshold.
        let t = (-6.0f64).exp();
        let h = [(8, -0.8), (24, -2.4), (50, -5.0)];
        assert_eq!(next_chunk(&h, t, 26, 8, 256), 10);
        // Never below the floor, never above double the previous chunk.
        assert_eq!(next_chunk(&h, (-5.1f64).exp(), 26, 8, 256), 8);
        assert_eq!(next_chunk(&h, (-50.0f64).exp(), 26, 8, 256), 52);
        // No progress: plain doubling.
        assert_eq!(next_chunk(&[(8, -1.0), (24, -1.0)], t, 16, 8, 256), 32);
    }
}
