//! Kernel-level access for tests and benchmarks: the operator product, per-kernel device
//! timings, the rotated blocks, the preconditioner data and raw iterations.

use super::builder::{from_planes, plane_widths, Real};
use super::host::HostOp;
use super::info::KernelTime;
use super::levels::OpData;
use super::levels::N_STATE;
use super::run::Which;
use super::GpuSolver;
use crate::gpu::GpuError;
use crate::solve::cg::Preconditioner;

impl GpuSolver {
    // ---- Kernel-level access for tests (each kernel against its CPU reference). ----

    /// q = Ĥ y with the CG's operator kernel (in the CG's precision).
    pub fn apply_operator(&mut self, y: &[f64]) -> Result<Vec<f64>, GpuError> {
        let l = &self.dev.level;
        self.ctx.write_buffer(&l.buf.p, 0, &l.real.bytes(y));
        self.ctx.write_buffer(&l.buf.state, 0, &[0u8; 4 * N_STATE]);
        let mut enc = self.encoder("apply operator");
        {
            let mut pass = enc
                .begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("apply operator pass"),
                    timestamp_writes: None,
                })
                .forget_lifetime();
            let g = self.dev.n_partials;
            self.dispatch(&mut pass, Which::MatvecP, g);
        }
        let q = self.dev.level.buf.q.clone();
        self.download(enc, &q, self.dev.level.real, y.len())
    }

    /// Device time per CG kernel in seconds (fastest and mean of `reps` iterations; the
    /// fastest is the figure least disturbed by other load on a shared CPU adapter), from timestamp
    /// queries around each dispatch in its own compute pass: `matvec` (or `spring_matvec`),
    /// `update_xrz`, with aggregates `coarse_restrict` and `coarse_solve`, `update_p`, and
    /// for mixed precision the f64 `matvec_f64` and
    /// `residual`. Runs from y = 0 without a stopping test; `None` without TIMESTAMP_QUERY.
    pub fn profile_kernels(&mut self, reps: usize) -> Result<Option<Vec<KernelTime>>, GpuError> {
        let Some(period) = self.dev.timestamps.as_ref().map(|t| t.period_ns) else {
            return Ok(None);
        };
        let reps = reps.max(1);
        if self.dev.refine.is_some() {
            let rhs = Real::F32.bytes(&self.host.rhs);
            self.ctx.write_buffer(&self.dev.level.buf.b, 0, &rhs);
        }
        self.start(false, -1.0)?;
        let dev = &self.ctx.device;
        let n_q = 14u32;
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
            self.dev.level.op.matvec.name.to_string(),
            "update_xrz".into(),
        ];
        let mut steps = vec![Which::MatvecP, Which::UpdateXrz];
        if self.dev.level.k.agg.is_some() {
            names.extend(["coarse_restrict".into(), "coarse_solve".into()]);
            steps.extend([Which::Restrict, Which::CoarseSolve]);
        }
        names.push("update_p".into());
        steps.push(Which::UpdateP);
        if self.dev.refine.as_ref().is_some_and(|r| r.op.is_some()) {
            names.push(format!("{}_f64", self.dev.level.op.matvec.name));
            names.push("residual".into());
        }
        let mut best = vec![f64::INFINITY; names.len()];
        let mut sum = vec![0.0f64; names.len()];
        let g = self.dev.n_partials;
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
            for &which in &steps {
                let mut pass = pass_for(&mut enc, &mut slot);
                self.dispatch(&mut pass, which, g);
            }
            if let Some((rf, op, bg_mv)) = self
                .dev
                .refine
                .as_ref()
                .and_then(|rf| Some((rf, rf.op.as_ref()?, rf.bg_mv.as_ref()?)))
            {
                let mut pass = pass_for(&mut enc, &mut slot);
                op.dispatch(&mut pass, bg_mv, g, &self.ctx.launch(), self.dev.wg);
                drop(pass);
                let mut pass = pass_for(&mut enc, &mut slot);
                pass.set_pipeline(&rf.k_residual.pipeline);
                pass.set_bind_group(0, &rf.bg_refine, &[]);
                self.ctx
                    .launch()
                    .reduction(g, self.dev.wg)
                    .dispatch(&mut pass);
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
        let (bufs, real, d, nb) = match (&self.dev.level.op.data, &self.host.op) {
            (OpData::Blocks { blocks, .. }, HostOp::Blocks(h)) => (
                blocks.clone(),
                self.dev.level.op.real,
                h.dim,
                h.nnz_blocks(),
            ),
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
        let d = self.dev.dim;
        let len = match self.params.preconditioner {
            Preconditioner::None | Preconditioner::Multilevel => return Ok(Vec::new()),
            Preconditioner::Jacobi => self.dev.n_nodes * d,
            Preconditioner::BlockJacobi => self.dev.n_nodes * d * d,
        };
        let Some(b) = self.dev.level.buf.minv.clone() else {
            return Ok(Vec::new());
        };
        let enc = self.encoder("download preconditioner");
        self.download(enc, &b, self.dev.level.real, len)
    }

    /// Runs `k` PCG iterations from y = 0 (no stopping test) and returns (x, r, p).
    #[allow(clippy::type_complexity)]
    pub fn iterate(&mut self, k: usize) -> Result<(Vec<f64>, Vec<f64>, Vec<f64>), GpuError> {
        if let Some(rf) = &self.dev.refine {
            // Mixed: the inner CG's right-hand side is b̂ rounded to f32.
            let rhs = Real::F32.bytes(&self.host.rhs);
            let _ = rf;
            self.ctx.write_buffer(&self.dev.level.buf.b, 0, &rhs);
        }
        self.start(false, -1.0)?;
        let _ = self.chunk(k)?;
        let nd = self.dev.n_nodes * self.dev.dim;
        let real = self.dev.level.real;
        let (x, r, p) = (
            self.dev.level.buf.x.clone(),
            self.dev.level.buf.r.clone(),
            self.dev.level.buf.p.clone(),
        );
        // The plain CG iterates on σb̂: x, r and p are σ times those of b̂.
        let sigma = self.rhs_scale;
        let unscale = |mut v: Vec<f64>| {
            v.iter_mut().for_each(|a| *a /= sigma);
            v
        };
        let xs = unscale(self.download(self.encoder("x"), &x, real, nd)?);
        let rs = unscale(self.download(self.encoder("r"), &r, real, nd)?);
        let ps = unscale(self.download(self.encoder("p"), &p, real, nd)?);
        Ok((xs, rs, ps))
    }
}
