//! E⁺ of the aggregate coarse space formed on the device (shaders/coarse_factor.wgsl):
//! after `prepare` reduces E = ZᵀĤZ (K×K) it records five kernels more, which
//! symmetrize E, form Er = WᵀEW, factor and invert it and write E⁺ = W Er⁻¹ Wᵀ where
//! `agg_solve` reads it: no read-back per Newton iteration, nothing of size K² over the
//! bus. The operations are those of the CPU CG's
//! [`crate::solve::coarse::aggregates_einv_with_basis`], entry by entry.
//!
//! W (the kept eigenvectors of each aggregate's Gram matrix G_a) depends only on the
//! constraint frames: the host forms it once per [`super::DeviceFrames`] and uploads it
//! with the aggregates. A pivot that is not positive and finite sets the PCG's
//! `state[STATE_COARSE_FAILED]`, which the host reads with the start's status and answers
//! by forming E⁺ itself (`DeviceCg::upload_aggregate_einv`).
//!
//! Layout: the factorization is one workgroup (it is a chain of K steps; its trailing
//! updates are spread over the workgroup's invocations); the triangular inverse is an
//! invocation per column (columns are independent; a column's chain is its rows); the
//! products are grids with an invocation per entry.

use super::aggregates::AggregateIndex;
use crate::gpu::kernels::{self, Access, Layout, Real};
use crate::gpu::{GpuContext, GpuError, Launch};
use crate::solve::coarse::AggregateBasis;
use std::sync::Arc;

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/coarse_factor.wgsl.
pub const COARSE_FACTOR: Layout = Layout {
    file: "coarse_factor.wgsl",
    source: include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/shaders/coarse_factor.wgsl"
    )),
    bindings: &[
        ("fp", U),
        ("coarse", W),
        ("basis", R),
        ("work", W),
        ("state", W),
    ],
};

/// Workgroup size of the grids.
const WORKGROUP: u32 = 64;

/// Workgroup size of the one-workgroup factorization: on a GPU a wide one (its trailing
/// update has up to K²/2 entries per step); on a CPU adapter, where each barrier costs a
/// coroutine switch per SIMD batch of invocations, [`FACTOR_WG_CPU`].
fn factor_workgroup(ctx: &GpuContext) -> u32 {
    if ctx.is_cpu() {
        FACTOR_WG_CPU
    } else {
        256
    }
}

/// 64: no slower than 16 or 256 on lavapipe (the machine's noise hides the rest). Not 8
/// or fewer: a workgroup of one lavapipe SIMD batch gave wrong factors at K = 168 (every
/// entry; right at K ≤ 27), where 16 and more give the specification's bits
/// (tests/gpu_coarse_factor.rs).
const FACTOR_WG_CPU: u32 = 64;

/// Offsets and sizes of one aggregate coarse space (mirrors `FactorParams` in the WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct FactorParams {
    k: u32,
    m: u32,
    count: u32,
    e_at: u32,
    einv_at: u32,
    w_at: u32,
    l_at: u32,
    x_at: u32,
    c_at: u32,
    _pad: [u32; 3],
}
const _: () = assert!(std::mem::size_of::<FactorParams>() == 48);

/// The bind group layout and pipelines of shaders/coarse_factor.wgsl for one dimension
/// and accumulator type, built once per device ([`GpuContext::cached`]).
struct Pipelines {
    layout: wgpu::BindGroupLayout,
    er: wgpu::ComputePipeline,
    chol: wgpu::ComputePipeline,
    linv: wgpu::ComputePipeline,
    cinv: wgpu::ComputePipeline,
    expand: wgpu::ComputePipeline,
}

impl Pipelines {
    fn build(dev: &wgpu::Device, dim: usize, acc: Real, factor_wg: u32) -> Self {
        // The shader has no `real` data; the prelude wants one.
        let module = COARSE_FACTOR.module(dev, acc.name(), acc.name());
        let (layout, pl) = COARSE_FACTOR.layouts(dev, "coarse factor");
        let pipe = |entry: &str, wg: u32| {
            let constants = [("D", dim as f64), ("WG", f64::from(wg))];
            let label = format!("coarse factor {entry} ({dim}D, {})", acc.name());
            kernels::pipeline(dev, &pl, &module, entry, &label, &constants)
        };
        Pipelines {
            er: pipe("agg_er", WORKGROUP),
            chol: pipe("agg_chol", factor_wg),
            linv: pipe("agg_linv", WORKGROUP),
            cinv: pipe("agg_cinv", WORKGROUP),
            expand: pipe("agg_expand", WORKGROUP),
            layout,
        }
    }
}

/// The device side of one aggregate coarse space's E⁺: W, the work matrices and the bind
/// group over them, the PCG's `coarse` buffer and its `state`; built with the frames.
pub(super) struct CoarseFactor {
    pipes: Arc<Pipelines>,
    group: wgpu::BindGroup,
    launches: [Launch; 5],
    /// Kept alive with the bind group.
    _buffers: [wgpu::Buffer; 3],
}

impl CoarseFactor {
    /// W from the aggregates' Gram matrices, uploaded with its index, and the work space
    /// (3 m² values, m ≤ K) for the E and E⁺ of `coarse` (laid out as `index` says).
    pub(super) fn new(
        ctx: &GpuContext,
        dim: usize,
        acc: Real,
        index: &AggregateIndex,
        coarse: &wgpu::Buffer,
        state: &wgpu::Buffer,
    ) -> Result<Self, GpuError> {
        let basis = AggregateBasis::new(dim, index.count, &index.gram).ok_or_else(|| {
            GpuError::Mismatch("the aggregates' Gram matrices are not finite".into())
        })?;
        let m = basis.columns();
        let too_big =
            || GpuError::Unsupported("the aggregates' coarse matrix exceeds u32 indices".into());
        let u = |v: usize| u32::try_from(v).map_err(|_| too_big());
        let mut words: Vec<u32> = Vec::with_capacity(index.count + 1 + m);
        for &v in basis.ptr.iter().chain(&basis.of) {
            words.push(u(v)?);
        }
        let mm = m.checked_mul(m).ok_or_else(too_big)?;
        let w_len = m * dim;
        let p = FactorParams {
            k: u(index.k)?,
            m: u(m)?,
            count: u(index.count)?,
            e_at: u(index.e_at)?,
            einv_at: u(index.einv_at)?,
            w_at: 0,
            l_at: u(w_len)?,
            x_at: u(w_len + mm)?,
            c_at: u(w_len + 2 * mm)?,
            _pad: [0; 3],
        };
        let params = ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("coarse factor params"),
            contents: bytemuck::bytes_of(&p),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let idx = ctx.storage_with("coarse factor basis index", bytemuck::cast_slice(&words))?;
        // Zeroed on the device; only W crosses the bus.
        let work =
            ctx.storage_zeroed("coarse factor work", acc.size() * (w_len + 3 * mm) as u64)?;
        ctx.write_buffer(&work, 0, &acc.bytes(&basis.values));
        let factor_wg = factor_workgroup(ctx);
        let key = format!(
            "coarse factor pipelines: {dim}D, {}, factor workgroup {factor_wg}",
            acc.name()
        );
        let pipes = ctx.cached(&key, || Pipelines::build(&ctx.device, dim, acc, factor_wg))?;
        let group = kernels::bind_group(
            &ctx.device,
            &pipes.layout,
            "coarse factor bind group",
            &[&params, coarse, &idx, &work, state],
        );
        let limits = ctx.launch();
        let entries = |n: usize| limits.grid(n.max(1) as u64, WORKGROUP);
        ctx.check("building the aggregates' coarse factorization")?;
        Ok(CoarseFactor {
            pipes,
            group,
            launches: [
                entries(mm),
                Launch { x: 1, y: 1 },
                entries(m),
                entries(mm),
                entries(index.k * index.k),
            ],
            _buffers: [params, idx, work],
        })
    }

    /// The five dispatches, in order (pipeline, workgroups, bind group).
    pub(super) fn kernels(&self) -> [(&wgpu::ComputePipeline, Launch, &wgpu::BindGroup); 5] {
        let p = &self.pipes;
        let l = &self.launches;
        let g = &self.group;
        [
            (&p.er, l[0], g),
            (&p.chol, l[1], g),
            (&p.linv, l[2], g),
            (&p.cinv, l[3], g),
            (&p.expand, l[4], g),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shader is well typed with f64 and (a device without SHADER_F64) f32 sums.
    #[test]
    fn every_precision_parses() {
        for acc in ["f64", "f32"] {
            let m = kernels::check::module(&COARSE_FACTOR, acc, acc);
            naga::valid::Validator::new(
                naga::valid::ValidationFlags::all(),
                naga::valid::Capabilities::all(),
            )
            .validate(&m)
            .unwrap_or_else(|e| panic!("coarse_factor.wgsl ({acc}): {e:?}"));
        }
    }

    /// Bind group 0 is [`COARSE_FACTOR`]'s, `FactorParams` has Rust's size and members,
    /// and every entry point exists.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let m = kernels::check::layout(
            &COARSE_FACTOR,
            "FactorParams",
            std::mem::size_of::<FactorParams>(),
            &["agg_er", "agg_chol", "agg_linv", "agg_cinv", "agg_expand"],
        );
        assert_eq!(
            kernels::check::struct_members(&m, "FactorParams"),
            [
                "k", "m", "count", "e_at", "einv_at", "w_at", "l_at", "x_at", "c_at", "_pad0",
                "_pad1", "_pad2"
            ]
        );
    }
}
