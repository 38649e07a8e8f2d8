//! Mixed precision's f64 outer loop kept on the device (shaders/mixed.wgsl): the kernels
//! that move a residual from the f64 level into the f32 level's right-hand side and a
//! segment's solution back into the f64 iterate, so that an outer step moves two scalars
//! between host and device, not vectors.

use super::cg::DeviceCg;
use crate::gpu::kernels::{self, Layout, Real};
use crate::gpu::{GpuContext, GpuError};

use kernels::Access::{Read as R, ReadWrite as W, Uniform as U};

pub const MIXED: Layout = Layout {
    file: "mixed.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/mixed.wgsl")),
    bindings: &[
        ("params", U),
        ("r64", R),
        ("b32", W),
        ("d32", R),
        ("y64", W),
        ("factors", R),
    ],
};

/// Mirrors `MixedParams` in shaders/mixed.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct MixedParams {
    n_dofs: u32,
    pad: [u32; 3],
}

const _: () = assert!(std::mem::size_of::<MixedParams>() == 16);

const WORKGROUP: u32 = 64;

/// The two kernels bound to one pair of levels (built once per solver).
pub struct Refine {
    ctx: GpuContext,
    scale_rhs: wgpu::ComputePipeline,
    accumulate: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    factors: wgpu::Buffer,
    n_dofs: u64,
    _params: wgpu::Buffer,
}

impl Refine {
    /// Binds the f64 level's r and y to the f32 level's b and y.
    pub fn new(
        ctx: &GpuContext,
        f64_level: &DeviceCg,
        f32_level: &DeviceCg,
    ) -> Result<Self, GpuError> {
        if f64_level.scalars().real != Real::F64 || f32_level.scalars().real != Real::F32 {
            return Err(GpuError::Mismatch(
                "mixed precision's refinement binds an f64 level to an f32 one".into(),
            ));
        }
        let n_dofs = f64_level.n_dofs();
        if f32_level.n_dofs() != n_dofs {
            return Err(GpuError::Mismatch(
                "mixed precision's levels differ in size".into(),
            ));
        }
        let dev = &ctx.device;
        MIXED.check_adapter(ctx)?;
        let _compiling = ctx.phase(crate::gpu::Phase::PipelineCreation);
        let module = MIXED.module(dev, "f64", "f64");
        let (layout, pl) = MIXED.layouts(dev, "mixed");
        let pipe = |entry: &str| {
            kernels::pipeline(
                dev,
                &pl,
                &module,
                entry,
                &format!("mixed {entry}"),
                &[("WG", f64::from(WORKGROUP))],
            )
        };
        let n = u32::try_from(n_dofs).map_err(|_| {
            GpuError::Unsupported("mixed precision's refinement indexes unknowns in u32".into())
        })?;
        let params = ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mixed params"),
            contents: bytemuck::bytes_of(&MixedParams {
                n_dofs: n,
                pad: [0; 3],
            }),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let factors = ctx.storage_with("mixed factors", &Real::F64.bytes(&[0.0, 0.0]))?;
        let bufs = [
            &params,
            f64_level.residual_buffer(),
            f32_level.rhs_buffer(),
            f32_level.y_buffer(),
            f64_level.y_buffer(),
            &factors,
        ];
        let group = kernels::bind_group(dev, &layout, "mixed bind group", &bufs);
        let s = Refine {
            ctx: ctx.clone(),
            scale_rhs: pipe("scale_rhs"),
            accumulate: pipe("accumulate"),
            group,
            factors,
            n_dofs,
            _params: params,
        };
        ctx.check("building mixed precision's refinement kernels")?;
        Ok(s)
    }

    fn run(&self, pipeline: &wgpu::ComputePipeline, label: &str) -> Result<(), GpuError> {
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        {
            let mut pass = self.ctx.compute_pass(&mut enc, label, None);
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &self.group);
            pass.dispatch(self.ctx.launch().grid(self.n_dofs, WORKGROUP));
        }
        self.ctx.submit(enc);
        self.ctx.check(label)
    }

    /// The f32 level's b̂ = r/‖r‖ from the f64 level's residual r (norm `rn`), and the
    /// factor 2^s·‖r‖ of the next [`Refine::accumulate`].
    pub fn scale_rhs(&self, rn: f64, inner_scale: f64) -> Result<(), GpuError> {
        let inv = if rn > 0.0 && (1.0 / rn).is_finite() {
            1.0 / rn
        } else {
            1.0
        };
        self.ctx
            .write_buffer(&self.factors, 0, &Real::F64.bytes(&[inv, inner_scale * rn]));
        self.run(&self.scale_rhs, "mixed scale_rhs")
    }

    /// y += 2^s·‖r‖·d in the f64 level, d the f32 level's segment solution.
    pub fn accumulate(&self) -> Result<(), GpuError> {
        self.run(&self.accumulate, "mixed accumulate")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_and_params_match_the_wgsl() {
        let size = std::mem::size_of::<MixedParams>();
        kernels::check::layout(&MIXED, "MixedParams", size, &["scale_rhs", "accumulate"]);
    }
}
