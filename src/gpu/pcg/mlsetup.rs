//! The multilevel preconditioner's levels built and refreshed on the device
//! (shaders/mlsetup.wgsl): [`Multilevel::new`] and [`Multilevel::refresh`] of the CPU CG
//! (src/solve/multilevel) carried out from the H the device PCG holds, into the buffers
//! the device V-cycle reads ([`super::multilevel`]).
//!
//! The host does the symbolic part once per hierarchy (a mesh): the clusters and patterns
//! ([`Hierarchy`]), the index lists the sums gather by (Q = A P's pattern, the P block
//! behind each entry of Pᵀ, the coarse levels' diagonal blocks), the scratch layout and
//! the parameters of every dispatch, uploaded once. What depends on the constraint set
//! (level 0's masks and rotations) is the PCG's own [`super::DeviceFrames`], bound once per
//! constraint set. Per system the device computes every value: level 0's matrix (Ĥ in the
//! node frames, formed from H's blocks where it is read), the smoothed prolongations, the
//! Galerkin matrices, the cluster pseudo-inverses and the smoothing weights ω_l from their
//! power estimates, or for kept levels ω_0 again (and the newly constrained components
//! masked); the host only records the dispatches and decides which
//! ([`crate::solve::multilevel::reuse::KeptLevels::plan`]). No byte crosses the bus per
//! system.
//!
//! The operations are the CPU's in the CPU's order, so the values agree with the host's
//! to rounding: bit for bit where the device rounds each operation as the CPU does, but
//! for the power estimates' dot products, summed in a fixed tree order (two passes:
//! partials per segment of items, one workgroup over the partials) rather than the CPU's
//! sequential one. tests/gpu_multilevel_setup.rs holds the two to stated tolerances.

use super::mllevels::{index, inverse_chunks, DeviceLevel, WORKGROUP};
use crate::gpu::blocks::{values_limit, RowRun};
use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::{GpuContext, GpuError, Launch};
use crate::solve::multilevel::reuse::Levels;
use crate::solve::multilevel::{
    Hierarchy, LevelPattern, LAMBDA_STEPS, OMEGA_LAMBDA, OMEGA_MAX, PIVOT_DROP,
};
use std::collections::HashMap;
use std::sync::Arc;

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/mlsetup.wgsl.
pub const MLSETUP: Layout = Layout {
    file: "mlsetup.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/mlsetup.wgsl")),
    bindings: &[
        ("sp", U),
        ("idx", R),
        ("sidx", R),
        ("nidx", R),
        ("vals", W),
        ("nvals", W),
        ("pattern", R),
        ("hvals", R),
        ("frame", R),
        ("rotations", R),
        ("inv", W),
        ("work", W),
        ("qv", W),
    ],
};

/// No block: a coarse item without a diagonal block (mirrors `NO_BLOCK` in the WGSL).
const NO_BLOCK: u32 = u32::MAX;
/// Scalars of the power iteration in the scratch (the WGSL's `SC_*`), before each
/// level's smoother λ̂ (from `SC_LEVELS`).
const SCALARS: usize = 8;
/// Partial-sum slots per segment (x·Ax, y·Ax, max |y|, Σ(y/s)²).
const PARTIAL_SLOTS: usize = 4;

/// One dispatch's view of a level (mirrors `SetupParams` in the WGSL): the CPU's
/// constants, the level's offsets and this dispatch's rows and inverses.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct SetupParams {
    omega_max: f64,
    omega_lambda: f64,
    pivot_drop: f64,
    finite_max: f64,
    n: u32,
    clusters: u32,
    finest: u32,
    has_next: u32,
    of_at: u32,
    pos_at: u32,
    ptr_at: u32,
    items_at: u32,
    inv_start_at: u32,
    row_at: u32,
    col_at: u32,
    p_ptr_at: u32,
    p_col_at: u32,
    pt_ptr_at: u32,
    pt_row_at: u32,
    omega_at: u32,
    a_at: u32,
    p_at: u32,
    pt_at: u32,
    q_ptr_at: u32,
    q_col_at: u32,
    pt_blk_at: u32,
    diag_at: u32,
    next_row_at: u32,
    next_col_at: u32,
    next_a_at: u32,
    row_begin: u32,
    row_end: u32,
    block_first: u32,
    h_col_at: u32,
    h_diag_at: u32,
    c_begin: u32,
    c_end: u32,
    t_begin: u32,
    t_end: u32,
    inv_base: u32,
    dinv_at: u32,
    x_at: u32,
    ax_at: u32,
    y_at: u32,
    part_at: u32,
    scal_at: u32,
    segments: u32,
    p_blocks: u32,
    level: u32,
    _pad: [u32; 3],
}
const _: () = assert!(std::mem::size_of::<SetupParams>() == 224);

/// The pipelines of shaders/mlsetup.wgsl.
struct Pipelines {
    item_dinv: wgpu::ComputePipeline,
    p_values: wgpu::ComputePipeline,
    q_values: wgpu::ComputePipeline,
    galerkin: wgpu::ComputePipeline,
    transpose_p: wgpu::ComputePipeline,
    mask_p: wgpu::ComputePipeline,
    cluster_zero: wgpu::ComputePipeline,
    cluster_gather: wgpu::ComputePipeline,
    cluster_factor: wgpu::ComputePipeline,
    cluster_invert: wgpu::ComputePipeline,
    cluster_gram: wgpu::ComputePipeline,
    mask_inverses: wgpu::ComputePipeline,
    power_init: wgpu::ComputePipeline,
    power_matvec: wgpu::ComputePipeline,
    power_dinv: wgpu::ComputePipeline,
    power_inv: wgpu::ComputePipeline,
    power_sums: wgpu::ComputePipeline,
    power_reduce: wgpu::ComputePipeline,
    power_scaled: wgpu::ComputePipeline,
    power_step: wgpu::ComputePipeline,
    power_next: wgpu::ComputePipeline,
    omega_prolong: wgpu::ComputePipeline,
    omega_smooth: wgpu::ComputePipeline,
}

/// The layout and pipelines for one dimension, built once per device.
struct SetupKernels {
    layout: wgpu::BindGroupLayout,
    pipes: Pipelines,
}

impl SetupKernels {
    fn build(dev: &wgpu::Device, dim: usize) -> Self {
        let module = MLSETUP.module(dev, "f64", "f64");
        let (layout, pl) = MLSETUP.layouts(dev, "mlsetup");
        let pipe = |entry: &str| {
            // SUM_LANES: the trees carry two sums and a maximum in one vec4.
            let constants = [
                ("D", dim as f64),
                ("WG", WORKGROUP as f64),
                ("SUM_LANES", 3.0),
            ];
            let label = format!("mlsetup {entry} ({dim}D)");
            kernels::pipeline(dev, &pl, &module, entry, &label, &constants)
        };
        let pipes = Pipelines {
            item_dinv: pipe("item_dinv"),
            p_values: pipe("p_values"),
            q_values: pipe("q_values"),
            galerkin: pipe("galerkin"),
            transpose_p: pipe("transpose_p"),
            mask_p: pipe("mask_p"),
            cluster_zero: pipe("cluster_zero"),
            cluster_gather: pipe("cluster_gather"),
            cluster_factor: pipe("cluster_factor"),
            cluster_invert: pipe("cluster_invert"),
            cluster_gram: pipe("cluster_gram"),
            mask_inverses: pipe("mask_inverses"),
            power_init: pipe("power_init"),
            power_matvec: pipe("power_matvec"),
            power_dinv: pipe("power_dinv"),
            power_inv: pipe("power_inv"),
            power_sums: pipe("power_sums"),
            power_reduce: pipe("power_reduce"),
            power_scaled: pipe("power_scaled"),
            power_step: pipe("power_step"),
            power_next: pipe("power_next"),
            omega_prolong: pipe("omega_prolong"),
            omega_smooth: pipe("omega_smooth"),
        };
        SetupKernels { layout, pipes }
    }
}

/// The constraint set level 0 is built for: the PCG's frame words (mask, rotation index
/// per node) and rotations, and the identity of the [`super::DeviceFrames`] holding them.
pub(super) struct FramesOnDevice<'a> {
    pub id: u64,
    pub frame: &'a wgpu::Buffer,
    pub rotations: &'a wgpu::Buffer,
}

/// H as the device PCG holds it: its pattern buffer (row pointers, then the columns from
/// `col_at` and each node's diagonal block from `diag_at`), its values chunks with their
/// rows and blocks, and the constraint set.
pub(super) struct FinestMatrix<'a> {
    pub pattern: &'a wgpu::Buffer,
    pub col_at: u32,
    pub diag_at: u32,
    pub chunks: Vec<(&'a wgpu::Buffer, RowRun)>,
    pub frames: FramesOnDevice<'a>,
}

/// The setup's index words of one level (`sidx`): Q's row pointers and columns, the P
/// block behind each entry of Pᵀ, each item's diagonal block below the finest level.
struct LevelIndex {
    words: Vec<u32>,
    q_ptr_at: u32,
    q_col_at: u32,
    pt_blk_at: u32,
    diag_at: u32,
    q_blocks: usize,
    p_blocks: usize,
}

impl LevelIndex {
    fn new(v: &LevelPattern<'_>, finest: bool) -> Result<Self, GpuError> {
        let mut words = Vec::new();
        let mut put = |xs: &mut dyn Iterator<Item = usize>| -> Result<u32, GpuError> {
            let at = index(words.len())?;
            for x in xs {
                words.push(index(x)?);
            }
            Ok(at)
        };
        let (mut q_ptr_at, mut q_col_at, mut pt_blk_at, mut diag_at) = (0, 0, 0, 0);
        let (mut q_blocks, mut p_blocks) = (0, 0);
        if let Some(sv) = &v.to_next {
            q_ptr_at = put(&mut sv.q_ptr.iter().copied())?;
            q_col_at = put(&mut sv.q_col.iter().map(|&c| c as usize))?;
            pt_blk_at = put(&mut sv.pt.iter().map(|&(_, k)| k as usize))?;
            if !finest {
                // The CPU's Level::diag_index: the stored block (i, i), if any.
                let diag = (0..v.n).map(|i| {
                    let row = &v.col_idx[v.row_ptr[i]..v.row_ptr[i + 1]];
                    row.binary_search(&i)
                        .map_or(NO_BLOCK as usize, |k| v.row_ptr[i] + k)
                });
                diag_at = put(&mut diag.into_iter())?;
            }
            q_blocks = sv.q_col.len();
            p_blocks = sv.p_col.len();
        }
        Ok(LevelIndex {
            words,
            q_ptr_at,
            q_col_at,
            pt_blk_at,
            diag_at,
            q_blocks,
            p_blocks,
        })
    }
}

/// Where the scratch's arrays start (f64 entries), shared by every level (the levels are
/// built one after another), its length and Q's (its own buffer, the largest array).
#[derive(Debug, Clone, Copy)]
struct WorkLayout {
    dinv_at: usize,
    x_at: usize,
    ax_at: usize,
    y_at: usize,
    part_at: usize,
    scal_at: usize,
    len: usize,
    q_len: usize,
}

impl WorkLayout {
    /// For the largest level of `patterns` and its Q in `indices`.
    fn new(patterns: &[LevelPattern<'_>], indices: &[LevelIndex], d: usize) -> Self {
        let n = patterns.iter().map(|p| p.n).max().unwrap_or(0);
        let q = indices.iter().map(|x| x.q_blocks).max().unwrap_or(0);
        let segments = n.div_ceil(WORKGROUP as usize).max(1);
        let dinv_at = 0;
        let x_at = dinv_at + n * d * d;
        let ax_at = x_at + n * d;
        let y_at = ax_at + n * d;
        let part_at = y_at + n * d;
        let scal_at = part_at + PARTIAL_SLOTS * segments;
        WorkLayout {
            dinv_at,
            x_at,
            ax_at,
            y_at,
            part_at,
            scal_at,
            len: scal_at + SCALARS + patterns.len(),
            q_len: q * d * d,
        }
    }
}

/// The device bytes the setup takes beside the levels ([`super::multilevel_bytes`]) for
/// `hierarchy` in `dim`, with H in `h_chunks` buffers and the inverses split under
/// `forced` (or the adapter's binding limit): its index words, its scratch and Q, the
/// parameters of its dispatches and two placeholders, each buffer checked against the
/// adapter's limits (the error names the first that does not fit). What a caller adds to
/// its memory check before building anything.
pub fn multilevel_setup_bytes(
    ctx: &GpuContext,
    hierarchy: &Hierarchy,
    dim: usize,
    h_chunks: usize,
    forced: Option<u64>,
) -> Result<u64, GpuError> {
    let patterns = hierarchy.patterns();
    let indices = patterns
        .iter()
        .enumerate()
        .map(|(l, v)| LevelIndex::new(v, l == 0))
        .collect::<Result<Vec<_>, _>>()?;
    let work = WorkLayout::new(&patterns, &indices, dim);
    let limit = values_limit(ctx, forced);
    let sizes = hierarchy.level_sizes(dim);
    let mut total = 2 * ctx.checked_size("mlsetup placeholder", 16)?;
    total += ctx.checked_size("mlsetup scratch", 8 * work.len as u64)?;
    total += ctx.checked_size("mlsetup Q = A P", 8 * work.q_len as u64)?;
    let param = std::mem::size_of::<SetupParams>() as u64;
    for (l, (x, s)) in indices.iter().zip(&sizes).enumerate() {
        total += ctx.checked_size(
            &format!("mlsetup level {l} indices"),
            4 * x.words.len() as u64,
        )?;
        let runs = if l == 0 { h_chunks.max(1) } else { 1 };
        let k = inverse_chunks(&s.inverses, limit, l)?.len();
        total += (runs * k) as u64 * param;
    }
    Ok(total)
}

/// One level's setup: its index words, the parameters of its dispatches per run of rows
/// (level 0: per chunk of H) and per buffer of inverses, and below the finest level their
/// bind groups (level 0's depend on the constraint set: [`DeviceSetup::finest_groups`]).
struct SetupLevel {
    n: usize,
    clusters: usize,
    p_blocks: usize,
    has_next: bool,
    sidx: wgpu::Buffer,
    /// Rows of each run; clusters, unknowns and values of each buffer of inverses.
    rows: Vec<usize>,
    inverse_clusters: Vec<usize>,
    inverse_unknowns: Vec<usize>,
    inverse_values: Vec<usize>,
    params: Vec<Vec<wgpu::Buffer>>,
    groups: Vec<Vec<wgpu::BindGroup>>,
}

/// The setup's kernels and buffers for one hierarchy on one device PCG.
pub(super) struct DeviceSetup {
    ctx: GpuContext,
    dim: usize,
    kernels: Arc<SetupKernels>,
    levels: Vec<SetupLevel>,
    work: wgpu::Buffer,
    q: wgpu::Buffer,
    /// Where the smoothers' λ̂ are in the scratch (f64 entries).
    lambdas_at: usize,
    segments: Vec<usize>,
    /// Bound where a level has no such array (read-only and read-write bindings).
    none_r: wgpu::Buffer,
    none_w: wgpu::Buffer,
    /// Level 0's bind groups per constraint set (by the frames' identity), per chunk of H
    /// and buffer of inverses.
    finest_groups: HashMap<u64, Vec<Vec<wgpu::BindGroup>>>,
}

/// What the power iteration's M⁻¹ is: D⁻¹ of the item blocks (the prolongation's ω) or
/// the cluster pseudo-inverses (the smoother's).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Estimate {
    Prolongation,
    Smoother,
}

/// Recorded dispatches: a name (the pass's debug marker), the pipeline, the launch and the
/// bind group.
type Dispatches<'a> = Vec<(
    &'static str,
    &'a wgpu::ComputePipeline,
    Launch,
    &'a wgpu::BindGroup,
)>;

const ONE: Launch = Launch { x: 1, y: 1 };

impl DeviceSetup {
    /// The setup of `hierarchy` (whose levels' buffers are `levels`) for H as `matrix`
    /// holds it: pipelines from the device's cache, index words uploaded once, the
    /// scratch and every dispatch's parameters.
    pub(super) fn new(
        ctx: &GpuContext,
        dim: usize,
        hierarchy: &Hierarchy,
        levels: &[DeviceLevel],
        matrix: &FinestMatrix<'_>,
    ) -> Result<Self, GpuError> {
        MLSETUP.check_adapter(ctx)?;
        let dev = &ctx.device;
        let kernels = ctx.cached(&format!("mlsetup pipelines: {dim}D"), || {
            SetupKernels::build(dev, dim)
        })?;
        let patterns = hierarchy.patterns();
        if patterns.len() != levels.len() {
            return Err(GpuError::Mismatch(
                "the multilevel setup's hierarchy is not its levels'".into(),
            ));
        }
        let indices = patterns
            .iter()
            .enumerate()
            .map(|(l, v)| LevelIndex::new(v, l == 0))
            .collect::<Result<Vec<_>, _>>()?;
        let work = WorkLayout::new(&patterns, &indices, dim);
        let none_r = ctx.storage_zeroed("mlsetup no array (read)", 16)?;
        let none_w = ctx.storage_zeroed("mlsetup no array (written)", 16)?;
        let work_buf = ctx.storage_zeroed("mlsetup scratch", 8 * work.len as u64)?;
        let q = ctx.storage_zeroed("mlsetup Q = A P", 8 * work.q_len as u64)?;
        let mut out = Vec::with_capacity(levels.len());
        for (l, x) in indices.iter().enumerate() {
            let level = Self::level(ctx, l, levels, x, &work, matrix)?;
            out.push(level);
        }
        let mut setup = DeviceSetup {
            ctx: ctx.clone(),
            dim,
            kernels,
            segments: patterns
                .iter()
                .map(|p| p.n.div_ceil(WORKGROUP as usize).max(1))
                .collect(),
            levels: out,
            work: work_buf,
            q,
            lambdas_at: work.scal_at + SCALARS,
            none_r,
            none_w,
            finest_groups: HashMap::new(),
        };
        for l in 1..levels.len() {
            let groups = setup.bind_groups(l, levels, None);
            setup.levels[l].groups = groups;
        }
        ctx.check("building the multilevel setup")?;
        Ok(setup)
    }

    /// Level `l`'s index words and dispatch parameters.
    fn level(
        ctx: &GpuContext,
        l: usize,
        levels: &[DeviceLevel],
        x: &LevelIndex,
        work: &WorkLayout,
        matrix: &FinestMatrix<'_>,
    ) -> Result<SetupLevel, GpuError> {
        let u = index;
        let lev = &levels[l];
        let vp = &lev.params;
        let words: &[u32] = if x.words.is_empty() {
            &[0; 4]
        } else {
            &x.words
        };
        let sidx = ctx.storage_with(
            &format!("mlsetup level {l} indices"),
            bytemuck::cast_slice(words),
        )?;
        let next = levels.get(l + 1).map(|n| n.params);
        let segments = lev.n.div_ceil(WORKGROUP as usize).max(1);
        let base = SetupParams {
            omega_max: OMEGA_MAX,
            omega_lambda: OMEGA_LAMBDA,
            pivot_drop: PIVOT_DROP,
            finite_max: f64::MAX,
            n: vp.n,
            clusters: vp.clusters,
            finest: u32::from(l == 0),
            has_next: vp.has_next,
            of_at: vp.of_at,
            pos_at: vp.pos_at,
            ptr_at: vp.ptr_at,
            items_at: vp.items_at,
            inv_start_at: vp.inv_start_at,
            row_at: vp.row_at,
            col_at: vp.col_at,
            p_ptr_at: vp.p_ptr_at,
            p_col_at: vp.p_col_at,
            pt_ptr_at: vp.pt_ptr_at,
            pt_row_at: vp.pt_row_at,
            omega_at: vp.omega_at,
            a_at: vp.a_at,
            p_at: vp.p_at,
            pt_at: vp.pt_at,
            q_ptr_at: x.q_ptr_at,
            q_col_at: x.q_col_at,
            pt_blk_at: x.pt_blk_at,
            diag_at: x.diag_at,
            next_row_at: next.map_or(0, |n| n.row_at),
            next_col_at: next.map_or(0, |n| n.col_at),
            next_a_at: next.map_or(0, |n| n.a_at),
            h_col_at: matrix.col_at,
            h_diag_at: matrix.diag_at,
            dinv_at: u(work.dinv_at)?,
            x_at: u(work.x_at)?,
            ax_at: u(work.ax_at)?,
            y_at: u(work.y_at)?,
            part_at: u(work.part_at)?,
            scal_at: u(work.scal_at)?,
            segments: u(segments)?,
            p_blocks: u(x.p_blocks)?,
            level: u(l)?,
            ..Default::default()
        };
        // Level 0 per chunk of H (its rows and first block), deeper levels one run.
        let runs: Vec<(std::ops::Range<usize>, usize)> = if l == 0 {
            matrix
                .chunks
                .iter()
                .map(|(_, (rows, blocks))| (rows.clone(), blocks.start))
                .collect()
        } else {
            vec![(0..lev.n, 0)]
        };
        let mut params = Vec::with_capacity(runs.len());
        for (h, (rows, first)) in runs.iter().enumerate() {
            let mut row = Vec::with_capacity(lev.inverses.len());
            for (k, ch) in lev.inverses.iter().enumerate() {
                let p = SetupParams {
                    row_begin: u(rows.start)?,
                    row_end: u(rows.end)?,
                    block_first: u(*first)?,
                    c_begin: u(ch.clusters.start)?,
                    c_end: u(ch.clusters.end)?,
                    t_begin: u(ch.unknowns.start)?,
                    t_end: u(ch.unknowns.end)?,
                    inv_base: u(ch.base)?,
                    ..base
                };
                row.push(ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(&format!("mlsetup level {l} params {h}/{k}")),
                    contents: bytemuck::bytes_of(&p),
                    usage: wgpu::BufferUsages::UNIFORM,
                }));
            }
            params.push(row);
        }
        Ok(SetupLevel {
            n: lev.n,
            clusters: lev.clusters,
            p_blocks: x.p_blocks,
            has_next: vp.has_next != 0,
            sidx,
            rows: runs.iter().map(|(r, _)| r.len()).collect(),
            inverse_clusters: lev.inverses.iter().map(|c| c.clusters.len()).collect(),
            inverse_unknowns: lev.inverses.iter().map(|c| c.unknowns.len()).collect(),
            inverse_values: lev.inverses.iter().map(|c| c.len).collect(),
            params,
            groups: Vec::new(),
        })
    }

    /// Level `l`'s bind groups per run of rows and buffer of inverses; level 0's with
    /// `matrix` (H and the constraint set), deeper ones with placeholders there.
    fn bind_groups(
        &self,
        l: usize,
        levels: &[DeviceLevel],
        matrix: Option<&FinestMatrix<'_>>,
    ) -> Vec<Vec<wgpu::BindGroup>> {
        let lev = &levels[l];
        let me = &self.levels[l];
        let (nidx, nvals) = match levels.get(l + 1) {
            Some(n) => (&n.idx, &n.vals),
            None => (&self.none_r, &self.none_w),
        };
        let r = &self.none_r;
        me.params
            .iter()
            .enumerate()
            .map(|(h, row)| {
                let (pattern, hvals, frame, rotations) = match matrix {
                    Some(m) => (m.pattern, m.chunks[h].0, m.frames.frame, m.frames.rotations),
                    None => (r, r, r, r),
                };
                row.iter()
                    .zip(&lev.inverses)
                    .enumerate()
                    .map(|(k, (params, ch))| {
                        let bufs = [
                            params, &lev.idx, &me.sidx, nidx, &lev.vals, nvals, pattern, hvals,
                            frame, rotations, &ch.buffer, &self.work, &self.q,
                        ];
                        kernels::bind_group(
                            &self.ctx.device,
                            &self.kernels.layout,
                            &format!("mlsetup level {l} run {h} inverses {k}"),
                            &bufs,
                        )
                    })
                    .collect()
            })
            .collect()
    }

    /// Builds or refreshes the levels as `how` says, for H and the constraint set of
    /// `matrix`: every dispatch recorded into one pass, one submit, no read-back.
    pub(super) fn run(
        &mut self,
        levels: &[DeviceLevel],
        how: Levels,
        matrix: &FinestMatrix<'_>,
    ) -> Result<(), GpuError> {
        if matrix.chunks.len() != self.levels[0].params.len() {
            return Err(GpuError::Mismatch(
                "the multilevel setup was made for another split of H".into(),
            ));
        }
        let id = matrix.frames.id;
        if !self.finest_groups.contains_key(&id) {
            let groups = self.bind_groups(0, levels, Some(matrix));
            self.finest_groups.insert(id, groups);
        }
        let g0 = &self.finest_groups[&id];
        let nl = self.levels.len();
        let mut rec: Dispatches<'_> = Vec::new();
        match how {
            Levels::Built => {
                for l in 0..nl - 1 {
                    self.prolongation(l, g0, &mut rec);
                }
                for l in 0..nl {
                    self.factors(l, g0, &mut rec);
                }
                self.mask(g0, false, &mut rec);
                for l in 0..nl - 1 {
                    self.power(l, Estimate::Smoother, g0, &mut rec);
                }
            }
            Levels::Kept | Levels::Remasked => {
                if how == Levels::Remasked {
                    self.mask(g0, true, &mut rec);
                }
                // A single level is solved (ω = 1): no estimate, as on the host.
                if nl > 1 {
                    self.power(0, Estimate::Smoother, g0, &mut rec);
                }
            }
        }
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("mlsetup"),
            });
        {
            let mut cp = self.ctx.compute_pass(&mut enc, "mlsetup", None);
            for (name, pipe, launch, group) in &rec {
                cp.insert_debug_marker(name);
                cp.set_bind_group(0, group);
                cp.set_pipeline(pipe);
                cp.dispatch(*launch);
            }
        }
        self.ctx.submit(enc);
        self.ctx
            .check("building the multilevel levels on the device")
    }

    /// The smoothers' λ̂ of the last build or refresh, per level below the coarsest (read
    /// back: tests and diagnostics).
    pub(super) fn lambdas(&self) -> Result<Vec<f64>, GpuError> {
        let n = self.levels.len().saturating_sub(1);
        let bytes = self.ctx.download(
            &self.work,
            8 * self.lambdas_at as u64,
            8 * n as u64,
            "reading back the multilevel power estimates",
        )?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }

    /// Level `l`'s bind groups: level 0's of the current constraint set, or its own.
    fn groups<'a>(
        &'a self,
        l: usize,
        g0: &'a [Vec<wgpu::BindGroup>],
    ) -> &'a [Vec<wgpu::BindGroup>] {
        if l == 0 {
            g0
        } else {
            &self.levels[l].groups
        }
    }

    /// A grid-stride kernel over `items`.
    fn launch(&self, items: usize) -> Launch {
        let limits = self.ctx.launch();
        let groups = (items as u64).div_ceil(WORKGROUP as u64);
        self.ctx.segments().launch(&limits, groups, WORKGROUP)
    }

    /// A segmented kernel over level `l`'s segments (they loop over segments).
    fn segmented(&self, l: usize) -> Launch {
        let limits = self.ctx.launch();
        self.ctx
            .segments()
            .launch(&limits, self.segments[l] as u64, WORKGROUP)
    }

    /// Level `l`'s smoothed prolongation, the next level's matrix and Pᵀ.
    fn prolongation<'a>(
        &'a self,
        l: usize,
        g0: &'a [Vec<wgpu::BindGroup>],
        rec: &mut Dispatches<'a>,
    ) {
        let p = &self.kernels.pipes;
        let me = &self.levels[l];
        let g = self.groups(l, g0);
        for (h, &rows) in me.rows.iter().enumerate() {
            rec.push(("item_dinv", &p.item_dinv, self.launch(rows), &g[h][0]));
        }
        self.power(l, Estimate::Prolongation, g0, rec);
        for (h, &rows) in me.rows.iter().enumerate() {
            rec.push(("p_values", &p.p_values, self.launch(rows), &g[h][0]));
        }
        for (h, &rows) in me.rows.iter().enumerate() {
            rec.push(("q_values", &p.q_values, self.launch(rows), &g[h][0]));
        }
        rec.push(("galerkin", &p.galerkin, self.launch(me.clusters), &g[0][0]));
        rec.push((
            "transpose_p",
            &p.transpose_p,
            self.launch(me.p_blocks),
            &g[0][0],
        ));
    }

    /// Level `l`'s cluster pseudo-inverses, gathered and factored in place.
    fn factors<'a>(&'a self, l: usize, g0: &'a [Vec<wgpu::BindGroup>], rec: &mut Dispatches<'a>) {
        let p = &self.kernels.pipes;
        let me = &self.levels[l];
        let g = self.groups(l, g0);
        for (k, &v) in me.inverse_values.iter().enumerate() {
            rec.push(("cluster_zero", &p.cluster_zero, self.launch(v), &g[0][k]));
        }
        for row in g {
            for (k, &c) in me.inverse_clusters.iter().enumerate() {
                rec.push(("cluster_gather", &p.cluster_gather, self.launch(c), &row[k]));
            }
        }
        // Three dispatches per buffer (shaders/mlsetup.wgsl, cluster_factor).
        for (name, pipe) in [
            ("cluster_factor", &p.cluster_factor),
            ("cluster_invert", &p.cluster_invert),
            ("cluster_gram", &p.cluster_gram),
        ] {
            for (k, &c) in me.inverse_clusters.iter().enumerate() {
                rec.push((name, pipe, self.launch(c), &g[0][k]));
            }
        }
    }

    /// Level 0's constrained components masked out of its inverses and, after the
    /// constraint set grew (`remask`), out of P's rows (then Pᵀ again).
    fn mask<'a>(&'a self, g0: &'a [Vec<wgpu::BindGroup>], remask: bool, rec: &mut Dispatches<'a>) {
        let p = &self.kernels.pipes;
        let me = &self.levels[0];
        for (k, &c) in me.inverse_clusters.iter().enumerate() {
            rec.push(("mask_inverses", &p.mask_inverses, self.launch(c), &g0[0][k]));
        }
        if remask && me.has_next {
            rec.push(("mask_p", &p.mask_p, self.launch(me.n), &g0[0][0]));
            rec.push((
                "transpose_p",
                &p.transpose_p,
                self.launch(me.p_blocks),
                &g0[0][0],
            ));
        }
    }

    /// The power estimate of level `l` (LAMBDA_STEPS steps, as the CPU's) and the ω it
    /// gives: the prolongation's (in the scratch) or the smoother's (where the V-cycle
    /// reads it).
    fn power<'a>(
        &'a self,
        l: usize,
        what: Estimate,
        g0: &'a [Vec<wgpu::BindGroup>],
        rec: &mut Dispatches<'a>,
    ) {
        let p = &self.kernels.pipes;
        let me = &self.levels[l];
        let g = self.groups(l, g0);
        let g00 = &g[0][0];
        let nd = me.n * self.dim;
        rec.push(("power_init", &p.power_init, self.launch(nd), g00));
        for _ in 0..LAMBDA_STEPS {
            for (h, &rows) in me.rows.iter().enumerate() {
                rec.push(("power_matvec", &p.power_matvec, self.launch(rows), &g[h][0]));
            }
            match what {
                Estimate::Prolongation => {
                    rec.push(("power_dinv", &p.power_dinv, self.launch(me.n), g00));
                }
                Estimate::Smoother => {
                    for (k, &t) in me.inverse_unknowns.iter().enumerate() {
                        rec.push(("power_inv", &p.power_inv, self.launch(t), &g[0][k]));
                    }
                }
            }
            rec.push(("power_sums", &p.power_sums, self.segmented(l), g00));
            rec.push(("power_reduce", &p.power_reduce, ONE, g00));
            rec.push(("power_scaled", &p.power_scaled, self.segmented(l), g00));
            rec.push(("power_step", &p.power_step, ONE, g00));
            rec.push(("power_next", &p.power_next, self.launch(nd), g00));
        }
        match what {
            Estimate::Prolongation => rec.push(("omega_prolong", &p.omega_prolong, ONE, g00)),
            Estimate::Smoother => rec.push(("omega_smooth", &p.omega_smooth, ONE, g00)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bind group 0 is [`MLSETUP`]'s bindings in order, the params struct has Rust's size
    /// and its members are Rust's, in Rust's order.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let entries = [
            "item_dinv",
            "p_values",
            "q_values",
            "galerkin",
            "transpose_p",
            "mask_p",
            "cluster_zero",
            "cluster_gather",
            "cluster_factor",
            "cluster_invert",
            "cluster_gram",
            "mask_inverses",
            "power_init",
            "power_matvec",
            "power_dinv",
            "power_inv",
            "power_sums",
            "power_reduce",
            "power_scaled",
            "power_step",
            "power_next",
            "omega_prolong",
            "omega_smooth",
        ];
        let size = std::mem::size_of::<SetupParams>();
        let m = kernels::check::layout(&MLSETUP, "SetupParams", size, &entries);
        assert_eq!(
            kernels::check::struct_members(&m, "SetupParams"),
            [
                "omega_max",
                "omega_lambda",
                "pivot_drop",
                "finite_max",
                "n",
                "clusters",
                "finest",
                "has_next",
                "of_at",
                "pos_at",
                "ptr_at",
                "items_at",
                "inv_start_at",
                "row_at",
                "col_at",
                "p_ptr_at",
                "p_col_at",
                "pt_ptr_at",
                "pt_row_at",
                "omega_at",
                "a_at",
                "p_at",
                "pt_at",
                "q_ptr_at",
                "q_col_at",
                "pt_blk_at",
                "diag_at",
                "next_row_at",
                "next_col_at",
                "next_a_at",
                "row_begin",
                "row_end",
                "block_first",
                "h_col_at",
                "h_diag_at",
                "c_begin",
                "c_end",
                "t_begin",
                "t_end",
                "inv_base",
                "dinv_at",
                "x_at",
                "ax_at",
                "y_at",
                "part_at",
                "scal_at",
                "segments",
                "p_blocks",
                "level",
                "_pad1",
                "_pad2",
                "_pad3",
            ]
        );
        // The shader's sentinel and scalar slots are the host's.
        let constant = |name: &str| match m
            .constants
            .iter()
            .find(|(_, c)| c.name.as_deref() == Some(name))
            .map(|(_, c)| &m.global_expressions[c.init])
        {
            Some(naga::Expression::Literal(naga::Literal::U32(v))) => *v,
            other => panic!("{name}: {other:?}"),
        };
        assert_eq!(constant("NO_BLOCK"), NO_BLOCK);
        assert_eq!(constant("SC_LEVELS") as usize, SCALARS);
        for name in [
            "SC_LAM",
            "SC_STOP",
            "SC_XAX",
            "SC_YAX",
            "SC_MAX",
            "SC_NRM",
            "SC_OMEGA_P",
        ] {
            assert!((constant(name) as usize) < SCALARS, "{name}");
        }
    }
}
