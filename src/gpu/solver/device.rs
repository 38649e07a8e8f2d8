//! The solver's device side, built once per solver: the type-independent data of the
//! system (`Shared`), the CG level, mixed precision's f64 outer loop (and, on first use,
//! its f64 fallback level), the solution's read-back buffer and the chunk timestamps,
//! with the kernel specialization they share; and the checks of the parameters against
//! the adapter.

use super::builder::{u32s, AggBuffers, Builder, Params, Real, Shared};
use super::host::{spring_adjacency, Host, HostOp};
use super::info::{BufferRecord, KernelRecord};
use super::levels::{
    blocks_fit, build_level, build_operator, build_refine, Consts, Level, Refine, Timestamps,
};
use super::plan::{self, binding_limit, memory_limit};
use crate::gpu::kernels::{MASK_SHIFT, WG_MAX};
use crate::gpu::{DifferenceForm, GpuContext, GpuError, GpuParams, Precision, MAX_WORKGROUPS};
use crate::solve::cg::Preconditioner;
use crate::solve::coarse::{Aggregation, CoarseSpace};

/// A packed column index holds the column node's mask above bit MASK_SHIFT.
const MAX_NODES: usize = 1 << MASK_SHIFT;

/// Buffers and compiled kernels (with their bind groups) on the device.
pub(super) struct Device {
    pub(super) dim: usize,
    pub(super) n_nodes: usize,
    /// Workgroup size.
    pub(super) wg: u32,
    /// Workgroups of the grid-stride CG kernels, and so partial sums per reduction.
    pub(super) n_partials: u32,
    pub(super) consts: Consts,
    /// Held for the solver's lifetime: bind groups reference these buffers.
    pub(super) shared: Shared,
    /// The CG in the solve's precision (f32 for mixed).
    pub(super) level: Level,
    /// Mixed: the f64 outer loop.
    pub(super) refine: Option<Refine>,
    /// Mixed: the f64 CG level of the fallback, built on first use.
    pub(super) fallback_level: Option<Level>,
    /// Read-back buffer of the solution y (the f64 iterate of mixed precision, else x).
    pub(super) solution_staging: wgpu::Buffer,
    pub(super) timestamps: Option<Timestamps>,
}

/// What building the device leaves besides it: the coarse aggregation and the records of
/// what was allocated and compiled.
pub(super) struct Built {
    pub(super) device: Device,
    pub(super) aggregation: Option<Aggregation>,
    pub(super) buffers: Vec<BufferRecord>,
    pub(super) kernels: Vec<KernelRecord>,
}

impl Device {
    /// Checks `params` against the adapter and the system, then allocates and compiles
    /// everything a solve needs (the values are written later by `upload_values`).
    pub(super) fn build(
        ctx: &GpuContext,
        host: &Host,
        params: &GpuParams,
    ) -> Result<Built, GpuError> {
        check_params(ctx, params)?;
        for layout in crate::gpu::kernels::LAYOUTS {
            layout.check_adapter(ctx)?;
        }
        let (n, wg, n_partials) = geometry(ctx, host, params)?;
        let acc = if ctx.has_f64() { Real::F64 } else { Real::F32 };
        let mut bld = Builder::new(ctx, binding_limit(ctx, params));
        // Aggregates need H's blocks (E from one pass over them): matrix-free springs keep
        // the rigid translations. No aggregate (every node fixed): no correction.
        let aggregation = match (&host.op, params.coarse) {
            (HostOp::Blocks(h), CoarseSpace::Aggregates) => {
                Some(Aggregation::build(h, &host.frames)).filter(|a| a.count > 0)
            }
            _ => None,
        };
        let inner_real = match params.precision {
            Precision::F64 => Real::F64,
            _ => Real::F32,
        };
        let consts = specialization(
            host,
            params,
            (wg, n_partials),
            aggregation.as_ref(),
            inner_real,
            acc,
        );
        // The outer residual of mixed precision on the device needs the f64 blocks there.
        let op64 = params.precision == Precision::Mixed
            && blocks_fit(ctx, host, Real::F64)
            && std::env::var_os("STICKSLIP_MIXED_HOST_RESIDUAL").is_none();
        let needed = plan::device_bytes(
            ctx,
            host,
            params,
            aggregation.as_ref(),
            &consts,
            inner_real,
            acc,
            op64,
        )?;
        ctx.check_fits(needed, memory_limit(ctx, params))?;
        let shared = shared_buffers(&mut bld, host, n_partials, aggregation.as_ref())?;
        let op = build_operator(&mut bld, &shared, host, inner_real, acc, &consts)?;
        let level = build_level(
            &mut bld,
            &shared,
            op,
            host,
            acc,
            &consts,
            params.preconditioner,
        )?;
        let refine = if params.precision == Precision::Mixed {
            let op64 = if op64 {
                Some(build_operator(
                    &mut bld,
                    &shared,
                    host,
                    Real::F64,
                    acc,
                    &consts,
                )?)
            } else {
                None
            };
            Some(build_refine(
                &mut bld, &shared, op64, &level, host, &consts,
            )?)
        } else {
            None
        };
        let y_real = if refine.is_some() {
            Real::F64
        } else {
            inner_real
        };
        let solution_staging =
            bld.staging("solution_staging", host.ndof() as u64 * y_real.size())?;
        let timestamps = chunk_timestamps(ctx, &mut bld)?;
        ctx.check("allocating GPU buffers")?;
        let device = Device {
            dim: host.frames.dim,
            n_nodes: n,
            wg,
            n_partials,
            consts,
            shared,
            level,
            refine,
            fallback_level: None,
            solution_staging,
            timestamps,
        };
        Ok(Built {
            device,
            aggregation,
            buffers: bld.buffers,
            kernels: bld.kernels,
        })
    }
}

/// The node count, workgroup size and workgroups of the CG kernels, checked against the
/// packed column indices and the dispatch limits.
fn geometry(
    ctx: &GpuContext,
    host: &Host,
    params: &GpuParams,
) -> Result<(usize, u32, u32), GpuError> {
    let n = host.frames.n_nodes;
    if n == 0 || n >= MAX_NODES {
        return Err(GpuError::Unsupported(format!(
            "{n} nodes (the GPU solver takes 1 to {} nodes)",
            MAX_NODES - 1
        )));
    }
    let wg = params.workgroup_size;
    // The grid-stride CG kernels cover any n; their reductions need exactly n_partials
    // workgroups (`gpu::launch`).
    let n_partials = (n.div_ceil(wg as usize)).clamp(1, ctx.workgroups(params.workgroups)) as u32;
    ctx.launch()
        .require_exact(n_partials, "the CG reductions")?;
    Ok((n, wg, n_partials))
}

/// The uniform parameters, the pattern (block rows or spring adjacency, columns packed
/// with their masks), the mask, the rotation indices and the aggregates.
fn shared_buffers(
    bld: &mut Builder,
    host: &Host,
    n_partials: u32,
    aggregation: Option<&Aggregation>,
) -> Result<Shared, GpuError> {
    let f = &host.frames;
    let n = f.n_nodes;
    let masked = f.has_constraints();
    let rotated = f.has_rotation();
    let n_blocks = match &host.op {
        HostOp::Blocks(h) => h.nnz_blocks(),
        HostOp::Springs(ms) => ms.edges.len(),
    };
    let prm = Params {
        n_nodes: n as u32,
        n_rot: f.rot_nodes.len() as u32,
        n_partials,
        n_blocks: n_blocks as u32,
    };
    let params = bld.init(
        "params",
        bytemuck::bytes_of(&prm),
        wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    )?;
    let mask_packed = |j: usize| -> u32 {
        if masked {
            (j as u32) | (u32::from(f.mask[j]) << MASK_SHIFT)
        } else {
            j as u32
        }
    };
    let (row_ptr, col, diag_row_ptr, diag_col) = match &host.op {
        HostOp::Blocks(h) => (
            bld.storage("row_ptr", &u32s(h.row_ptr.iter().map(|&v| v as u32)))?,
            bld.split_storage("col_idx", &u32s(h.col_idx.iter().map(|&j| mask_packed(j))))?,
            None,
            None,
        ),
        HostOp::Springs(ms) => {
            let (ptr, adj) = spring_adjacency(ms);
            (
                bld.storage("spring_adj_ptr", &u32s(ptr))?,
                bld.storage("spring_adj", &u32s(adj))?,
                Some(bld.storage("diag_row_ptr", &u32s(0..=n as u32))?),
                Some(bld.split_storage("diag_col", &u32s((0..n).map(mask_packed)))?),
            )
        }
    };
    let agg = match aggregation {
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
    let mask = if masked {
        Some(bld.storage("mask", &u32s(f.mask.iter().map(|&m| u32::from(m))))?)
    } else {
        None
    };
    let (rot_index, rot_nodes) = if rotated {
        (
            Some(bld.storage("rot_index", &u32s(f.rot_index.iter().copied()))?),
            Some(bld.storage("rot_nodes", &u32s(f.rot_nodes.iter().copied()))?),
        )
    } else {
        (None, None)
    };
    Ok(Shared {
        dim: f.dim,
        agg,
        params,
        row_ptr,
        col,
        mask,
        rot_index,
        rot_nodes,
        diag_row_ptr,
        diag_col,
        placeholder: bld.storage("placeholder", &[0u8; 16])?,
    })
}

/// The specialization constants of every kernel of this solver.
fn specialization(
    host: &Host,
    params: &GpuParams,
    (wg, n_partials): (u32, u32),
    aggregation: Option<&Aggregation>,
    inner_real: Real,
    acc: Real,
) -> Consts {
    let f = &host.frames;
    Consts {
        d: f.dim as f64,
        wg: f64::from(wg),
        n_partials,
        masked: f.has_constraints(),
        rotated: f.has_rotation(),
        precond: match params.preconditioner {
            Preconditioner::None | Preconditioner::Multilevel => 0.0,
            Preconditioner::Jacobi => 1.0,
            Preconditioner::BlockJacobi => 2.0,
        },
        coarse: params.coarse == CoarseSpace::Translations
            || (params.coarse == CoarseSpace::Aggregates && aggregation.is_none()),
        agg: aggregation.map_or(0, |a| a.count as u32),
        diff: inner_real == Real::F32 && wants_difference_form(host, params.f32_difference, acc),
    }
}

/// The query set and resolve buffer of the chunk timestamps, where the adapter has them.
fn chunk_timestamps(ctx: &GpuContext, bld: &mut Builder) -> Result<Option<Timestamps>, GpuError> {
    if !ctx.has_timestamps() {
        return Ok(None);
    }
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
    Ok(Some(Timestamps {
        set,
        resolve,
        period_ns: ctx.queue.get_timestamp_period() as f64,
    }))
}

/// Whether the f32 operator of `host` should use the difference form.
fn wants_difference_form(host: &Host, choice: DifferenceForm, acc: Real) -> bool {
    let HostOp::Blocks(h) = &host.op else {
        return false;
    };
    choice.wanted(acc == Real::F64, h, &host.frames, || host.diag_max())
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
        || !(32..=WG_MAX).contains(&wg)
        || wg > ctx.limits.max_compute_workgroup_size_x
    {
        return Err(GpuError::Unsupported(format!(
            "workgroup size {wg} (expected a power of two in 32..={WG_MAX} within the adapter's limit {})",
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
