//! Per-system device work of `GpuSolver::new` and `update`: writing Ĥ's values, b̂ and
//! D into the device levels, and the setup kernels (block rotation, preconditioner
//! build).

use super::builder::{to_planes, Real};
use super::host::{row_sums, spring_data, spring_diag_blocks, HostOp};
use super::levels::{Level, OpData, Operator};
use super::GpuSolver;
use crate::gpu::GpuError;
use crate::solve::coarse::{aggregates_einv_from_blocks, translations_einv_from_blocks, Coarse};

impl GpuSolver {
    /// Writes Ĥ's values into `op`, multiplied by `scale` (a power of two: exact) except
    /// for the geometry (positions, rest lengths, rotations).
    pub(super) fn write_operator(&self, op: &Operator, scale: f64) {
        let q = &self.ctx;
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
                if let Some(rs) = &op.rowsum {
                    q.write_buffer(rs, 0, &op.real.bytes(&sc(&row_sums(h, &host.frames))));
                }
            }
            (
                OpData::Springs {
                    pos,
                    springs,
                    mass,
                    diag_blocks,
                    ..
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

    /// E⁺ of the coarse correction for the current values (zeros when every translation
    /// is constrained: the correction then adds nothing).
    pub(super) fn compute_coarse(&mut self) {
        if !self.dev.consts.coarse && self.dev.consts.agg == 0 {
            return;
        }
        let d = self.host.frames.dim;
        let k = d * self.coarse.aggregation.as_ref().map_or(1, |a| a.count);
        let einv = match (&self.host.op, &self.coarse.aggregation) {
            (HostOp::Blocks(h), Some(a)) => aggregates_einv_from_blocks(h, &self.host.frames, a),
            // One pass over the blocks (no basis, no products).
            (HostOp::Blocks(h), None) => translations_einv_from_blocks(h, &self.host.frames),
            (HostOp::Springs(_), _) => {
                let frames = self.host.frames.clone();
                let host = &mut self.host;
                Coarse::translations(&frames, None, |v, o| host.apply(v, o)).map(|c| c.einv)
            }
        };
        self.coarse.einv = Some(einv.unwrap_or_else(|| vec![0.0; k * k]));
    }

    /// Writes E⁺ into a level whose operator is `scale`·Ĥ (its E⁺ is E⁺/scale).
    pub(super) fn write_coarse(&self, level: &Level, scale: f64) {
        if let (Some(buf), Some(e)) = (&level.buf.einv, &self.coarse.einv) {
            let v: Vec<f64> = e.iter().map(|x| x / scale).collect();
            self.ctx.write_buffer(buf, 0, &level.acc.bytes(&v));
        }
    }

    pub(super) fn upload_values(&mut self) -> Result<(), GpuError> {
        self.compute_coarse();
        self.write_operator(&self.dev.level.op, self.mixed.inner_scale);
        self.write_coarse(&self.dev.level, self.mixed.inner_scale);
        if let Some(fl) = &self.dev.fallback_level {
            self.write_operator(&fl.op, 1.0);
            self.write_coarse(fl, 1.0);
        }
        match &self.dev.refine {
            Some(rf) => {
                if let Some(op) = &rf.op {
                    self.write_operator(op, 1.0);
                }
                self.ctx
                    .write_buffer(&rf.b64, 0, &Real::F64.bytes(&self.host.rhs));
                self.rhs_scale = 1.0;
            }
            None => {
                // σb̂ keeps rᵀr and pᵀĤp inside the range for any ‖b̂‖ (exact: σ = 2^k).
                self.rhs_scale =
                    crate::solve::cg::rhs_scale(crate::core::linalg::norm2(&self.host.rhs));
                let sigma = self.rhs_scale;
                let b: Vec<f64> = self.host.rhs.iter().map(|v| v * sigma).collect();
                let l = &self.dev.level;
                self.ctx.write_buffer(&l.buf.b, 0, &l.real.bytes(&b));
            }
        }
        self.ctx.check("uploading the system")
    }

    /// Rotation of the H blocks (slip nodes only) and the preconditioner build.
    pub(super) fn device_setup(&mut self) -> Result<(), GpuError> {
        self.setup_levels(true, true)
    }

    /// Rotation and preconditioner build of the main levels (`main`: the CG level and the
    /// refinement operator) and/or of the f64 fallback level where it exists.
    pub(super) fn setup_levels(&mut self, main: bool, fallback: bool) -> Result<(), GpuError> {
        let mut enc = self.encoder("setup");
        let mut names = Vec::new();
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("setup pass"),
                timestamp_writes: None,
            });
            let wg = self.dev.wg;
            let launch = self.ctx.launch();
            let main_ops = std::iter::once(&self.dev.level.op)
                .chain(self.dev.refine.as_ref().and_then(|r| r.op.as_ref()))
                .filter(|_| main);
            let fb = self.dev.fallback_level.as_ref().filter(|_| fallback);
            let ops = main_ops.chain(fb.map(|l| &l.op));
            for op in ops {
                if let OpData::Blocks {
                    rotate: Some(rot), ..
                } = &op.data
                {
                    rot.dispatch(&mut pass, wg, &launch);
                    names.push(rot.kernel.name);
                }
            }
            let pre = std::iter::once(&self.dev.level)
                .filter(|_| main)
                .chain(fb)
                .filter_map(|l| l.k.precond.as_ref());
            for pre in pre {
                pre.dispatch(&mut pass, wg, &launch);
                names.push(pre.kernel.name);
            }
        }
        self.ctx.queue.submit([enc.finish()]);
        for n in names {
            self.record(n);
        }
        self.wait()?;
        self.ctx.check("device setup")
    }
}
