//! Conditional work: dispatches recorded ahead of a decision the device makes, which run
//! only where a flag word of a state buffer is set (shaders/gate.wgsl). A gate kernel
//! writes the work's indirect dispatch arguments, the launches the host tabled or zero
//! workgroups, so unwanted work costs one small dispatch and no wait.
//!
//! The device Newton loop records its line search's first trial after every chunk of the
//! CG this way, gated on the chunk's verification having met the tolerance.

use super::kernels::{self, Access, Layout};
use super::{GpuContext, GpuError, Launch, Phase};

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/gate.wgsl.
pub const GATE: Layout = Layout {
    file: "gate.wgsl",
    source: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/shaders/gate.wgsl")),
    bindings: &[("params", U), ("state", R), ("table", R), ("args", W)],
};

/// Uniform parameters of the gate (mirrors `GateParams` in the WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct GateParams {
    count: u32,
    flag: u32,
    pad0: u32,
    pad1: u32,
}
const _: () = assert!(std::mem::size_of::<GateParams>() == 16);

const WORKGROUP: u32 = 64;

/// One dispatch to record later: its pipeline, bind group 0 and workgroups.
#[derive(Debug, Clone)]
pub struct Dispatch {
    pub pipeline: wgpu::ComputePipeline,
    pub group: wgpu::BindGroup,
    pub launch: Launch,
}

/// The gate of one state buffer's flag, with room for `capacity` gated dispatches.
pub struct Gate {
    ctx: GpuContext,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    params: wgpu::Buffer,
    table: wgpu::Buffer,
    args: wgpu::Buffer,
    capacity: usize,
    /// The launches the table holds now.
    tabled: std::cell::RefCell<Vec<Launch>>,
}

impl Gate {
    /// A gate opened by word `flag` of `state` (u32 words), for at most `capacity`
    /// dispatches.
    pub fn new(
        ctx: &GpuContext,
        state: &wgpu::Buffer,
        flag: u32,
        capacity: usize,
    ) -> Result<Self, GpuError> {
        let dev = &ctx.device;
        GATE.check_adapter(ctx)?;
        let pipeline = {
            let _compiling = ctx.phase(Phase::PipelineCreation);
            let module = GATE.module(dev, "f32", "f32");
            let (layout, pl) = GATE.layouts(dev, "gate");
            let p = kernels::pipeline(
                dev,
                &pl,
                &module,
                "gate",
                "gate",
                &[("WG", WORKGROUP as f64)],
            );
            (layout, p)
        };
        let (layout, pipeline) = pipeline;
        let words = 3 * capacity.max(1) as u64;
        let params = ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("gate params"),
            contents: bytemuck::bytes_of(&GateParams {
                flag,
                ..GateParams::default()
            }),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let table = ctx.storage_zeroed("gate launches", 4 * words)?;
        let size = ctx.checked_size("gate arguments", 4 * words)?;
        let args = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("gate arguments"),
            size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT,
            mapped_at_creation: false,
        });
        let group = kernels::bind_group(
            dev,
            &layout,
            "gate bind group",
            &[&params, state, &table, &args],
        );
        ctx.check("building a gate")?;
        Ok(Gate {
            ctx: ctx.clone(),
            pipeline,
            group,
            params,
            table,
            args,
            capacity: capacity.max(1),
            tabled: std::cell::RefCell::new(Vec::new()),
        })
    }

    /// Records the gate and then `work` in one compute pass of `phase`, each dispatch of
    /// `work` indirect through the gate (the table is rewritten, a few words, when the
    /// launches changed since the last record).
    pub fn record(
        &self,
        enc: &mut wgpu::CommandEncoder,
        label: &str,
        phase: Phase,
        work: &[Dispatch],
    ) -> Result<(), GpuError> {
        if work.len() > self.capacity {
            return Err(GpuError::Mismatch(format!(
                "{label}: {} gated dispatches, the gate holds {}",
                work.len(),
                self.capacity
            )));
        }
        let launches: Vec<Launch> = work.iter().map(|d| d.launch).collect();
        let mut tabled = self.tabled.borrow_mut();
        if launches != *tabled {
            let words: Vec<u32> = launches.iter().flat_map(|l| [l.x, l.y, 1]).collect();
            self.ctx
                .write_buffer(&self.table, 0, bytemuck::cast_slice(&words));
            // The count is the params' first word; the flag stays.
            self.ctx.write_buffer(
                &self.params,
                0,
                bytemuck::cast_slice(&[launches.len() as u32]),
            );
            *tabled = launches;
        }
        let mut cp = self.ctx.compute_pass(enc, label, Some(phase));
        cp.set_pipeline(&self.pipeline);
        cp.set_bind_group(0, &self.group);
        cp.dispatch(Launch { x: 1, y: 1 });
        for (k, d) in work.iter().enumerate() {
            cp.set_pipeline(&d.pipeline);
            cp.set_bind_group(0, &d.group);
            cp.dispatch_indirect(&self.args, 12 * k as u64);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_and_params_match_the_wgsl() {
        crate::gpu::kernels::check::layout(
            &GATE,
            "GateParams",
            std::mem::size_of::<GateParams>(),
            &["gate"],
        );
    }
}
