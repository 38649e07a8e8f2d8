//! The device memory a solver will allocate, computed before anything is allocated so
//! that a system that does not fit is refused with one line (bytes needed against bytes
//! the device has) instead of failing part-way. Mirrors every allocation of
//! `Device::build` (a test holds the two equal).

use super::builder::{plan_chunks, plane_widths, Builder, Real};
use super::host::{Host, HostOp};
use super::levels::{block_elem, row_elem, Consts, LANCZOS_HIST, N_SCAL, N_STATE};
use crate::gpu::kernels::slots;
use crate::gpu::{GpuContext, GpuError, GpuParams, Precision, MAX_WORKGROUPS};
use crate::solve::cg::Preconditioner;
use crate::solve::coarse::Aggregation;

/// Marks the refusal of a system too large for the device (the command line exits 2 on
/// it: the input, not the device, is what must change).
pub use crate::gpu::context::DOES_NOT_FIT;

/// Why the f32 and mixed-precision GPU solver refuses the multilevel preconditioner.
pub const MULTILEVEL_ON_CPU: &str =
    "the multilevel preconditioner runs in f64 only (the CPU CG and the f64 device PCG); f32 and mixed take none, jacobi or block-jacobi";

// Every buffer the builder makes has the size the one allocator gives it.
use crate::gpu::context::padded_size;

/// The device memory in force for these parameters (see `GpuContext::memory_in_force`).
pub(super) fn memory_limit(ctx: &GpuContext, params: &GpuParams) -> Option<u64> {
    ctx.memory_in_force(params.memory_limit)
}

/// Bytes of one operator in `real` (`levels::build_operator`).
fn operator(
    ctx: &GpuContext,
    params: &GpuParams,
    host: &Host,
    real: Real,
    acc: Real,
    c: &Consts,
) -> Result<u64, GpuError> {
    let f = &host.frames;
    let s = real.size();
    let nd = host.ndof() as u64;
    let n = f.n_nodes as u64;
    let mut t = 0;
    if c.masked {
        t += padded_size(nd * s);
    }
    if c.rotated {
        t += padded_size(f.rotations.len() as u64 * s);
    }
    let limit = binding_limit(ctx, params);
    let diff = c.diff && real == Real::F32 && matches!(host.op, HostOp::Blocks(_));
    let planes = |blocks: u64| -> u64 {
        plane_widths(f.dim)
            .iter()
            .map(|&w| padded_size((blocks * w as u64 * s).max(4 * s)))
            .sum()
    };
    let chunks = |rp: &[u32], re: u64| {
        let shape = Builder::chunk_shape(ctx, block_elem(real), re);
        plan_chunks(rp, &shape, limit).map_or(1, |v| v.len() as u64)
    };
    // A split array is bound in pieces but must still be one buffer.
    let max = ctx.limits.max_buffer_size;
    let widest = match &host.op {
        HostOp::Blocks(h) => h.nnz_blocks() as u64 * block_elem(real),
        HostOp::Springs(_) => n * block_elem(real),
    };
    if padded_size(widest) > max {
        return Err(GpuError::BufferTooLarge {
            label: format!("blocks_{}", real.name()),
            bytes: padded_size(widest),
            limit: max,
            what: "buffer",
            adapter: ctx.info.name.clone(),
        });
    }
    match &host.op {
        HostOp::Blocks(h) => {
            if diff {
                t += padded_size(nd * f.dim as u64 * s);
            }
            t += planes(h.nnz_blocks() as u64);
            let rp: Vec<u32> = h.row_ptr.iter().map(|&v| v as u32).collect();
            let k = chunks(&rp, row_elem(host, real, diff));
            t += 16 * k;
            t += if k > 1 {
                padded_size(u64::from(c.n_partials) * c.wg as u64 * acc.size())
            } else {
                16
            };
        }
        HostOp::Springs(ms) => {
            t += padded_size(nd * s)
                + padded_size(2 * ms.edges.len() as u64 * s)
                + padded_size(n * s);
            t += planes(n);
            let identity: Vec<u32> = (0..=n as u32).collect();
            t += 16 * chunks(&identity, 0);
        }
    }
    Ok(t)
}

/// Bytes of one CG level (`levels::cg_buffers`).
fn level(host: &Host, real: Real, acc: Real, c: &Consts, pc: Preconditioner) -> u64 {
    let s = real.size();
    let nd = host.ndof() as u64;
    let n = host.frames.n_nodes as u64;
    let d = host.frames.dim as u64;
    let mut t = 6 * padded_size(nd * s);
    t += match pc {
        Preconditioner::None | Preconditioner::Multilevel => 0,
        Preconditioner::Jacobi => padded_size(n * d * s),
        Preconditioner::BlockJacobi => padded_size(n * d * d * s),
    };
    let part_slots = u64::from(slots::PART_ZR) + if c.coarse { d } else { 0 };
    t += padded_size(part_slots * u64::from(MAX_WORKGROUPS) * acc.size());
    let kc = d * u64::from(c.agg.max(1));
    if c.coarse || c.agg > 0 {
        t += padded_size(kc * kc * acc.size());
    }
    if c.agg > 0 {
        t += padded_size(2 * kc * acc.size());
    }
    let scal = (N_SCAL + 2 * LANCZOS_HIST) as u64 * acc.size();
    t += padded_size(scal)
        + padded_size(4 * N_STATE as u64)
        + padded_size(scal + 4 * N_STATE as u64 + 16);
    t
}

/// Bytes of a CG level with its own operator in `real` (mixed precision's f64 fallback).
pub(super) fn level_bytes(
    ctx: &GpuContext,
    host: &Host,
    params: &GpuParams,
    c: &Consts,
    real: Real,
    acc: Real,
) -> Result<u64, GpuError> {
    Ok(operator(ctx, params, host, real, acc, c)?
        + level(host, real, acc, c, params.preconditioner))
}

/// Every byte `Device::build` allocates for this system: the shared data, the CG level,
/// mixed precision's f64 outer loop (with its operator when `op64`), the read-back and
/// timestamp buffers. The f64 fallback level of mixed precision, built on first use, is
/// not counted (it falls back to the CPU when it does not fit).
#[allow(clippy::too_many_arguments)]
pub(super) fn device_bytes(
    ctx: &GpuContext,
    host: &Host,
    params: &GpuParams,
    aggregation: Option<&Aggregation>,
    c: &Consts,
    inner: Real,
    acc: Real,
    op64: bool,
) -> Result<u64, GpuError> {
    let f = &host.frames;
    let n = f.n_nodes as u64;
    let nd = host.ndof() as u64;
    // Shared: params, pattern, aggregates, mask, rotation indices, placeholder.
    let mut t = padded_size(16) + padded_size(16);
    t += match &host.op {
        HostOp::Blocks(h) => padded_size((n + 1) * 4) + padded_size(h.nnz_blocks() as u64 * 4),
        HostOp::Springs(ms) => {
            let e = ms.edges.len() as u64;
            padded_size((n + 1) * 4)
                + padded_size(4 * e * 4)
                + padded_size((n + 1) * 4)
                + padded_size(n * 4)
        }
    };
    if let Some(a) = aggregation {
        let members = a
            .of_node
            .iter()
            .filter(|&&g| g != crate::solve::coarse::NO_AGGREGATE)
            .count() as u64;
        t += padded_size(n * 4) + padded_size((a.count as u64 + 1) * 4) + padded_size(members * 4);
    }
    if c.masked {
        t += padded_size(n * 4);
    }
    if c.rotated {
        t += padded_size(n * 4) + padded_size(f.rot_nodes.len() as u64 * 4);
    }
    t += operator(ctx, params, host, inner, acc, c)?;
    t += level(host, inner, acc, c, params.preconditioner);
    let mixed = params.precision == Precision::Mixed;
    if mixed {
        if op64 {
            t += operator(ctx, params, host, Real::F64, acc, c)?;
        }
        let w = u64::from(MAX_WORKGROUPS) * 8;
        t += 3 * padded_size(nd * 8)
            + padded_size(w)
            + padded_size(4 * N_STATE as u64)
            + padded_size(w)
            + padded_size(16);
    }
    let y = if mixed { 8 } else { inner.size() };
    t += padded_size(nd * y);
    if ctx.has_timestamps() {
        t += padded_size(16);
    }
    Ok(t)
}

/// The storage binding limit in force: the adapter's, or `GpuParams::binding_limit` where
/// that is lower.
pub(super) fn binding_limit(ctx: &GpuContext, params: &GpuParams) -> u64 {
    let adapter = ctx.limits.max_storage_buffer_binding_size;
    params.binding_limit.map_or(adapter, |l| l.min(adapter))
}
