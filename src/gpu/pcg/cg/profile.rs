//! What one iteration dispatches and must move at the least, and the device time of
//! each of its kernels (timestamp queries).

use super::*;
use crate::gpu::KernelTime;

impl DeviceCg {
    /// What one CG iteration launches with these frames and parameters, and the bytes it
    /// must move at the least (every array its kernels read or write, once per kernel):
    /// the floor against which a measured time per iteration is a bandwidth.
    pub fn iteration_profile(
        &self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
    ) -> Result<IterationProfile, GpuError> {
        let (pre, co) = overrides(params, frames);
        let dispatches = self
            .iteration(frames, pre, co)
            .into_iter()
            .map(|(name, (_, l, _))| DispatchRecord {
                kernel: name,
                workgroups: l.workgroups(),
                threads: l.threads(WORKGROUP),
            })
            .collect();
        let (n, d) = (self.n_nodes as u64, self.dim as u64);
        let nnz = self.host_pattern[self.n_nodes] as u64;
        let rs = self.ty.real.size();
        let vec = rs * n * d;
        let partials = self.ty.acc.size() * self.n_partials as u64;
        // matvec: H, its column indices and row pointers, the frames, pw, p, q (and the
        // difference form's row sums).
        let rowsum = if self.ty.difference {
            rs * n * d * d
        } else {
            0
        };
        let matvec = nnz * (rs * d * d + 4) + 4 * (n + 1) + 8 * n + 3 * vec + rowsum;
        // update_yr: y and r read and written, p, q and the preconditioner read, z written.
        let minv = match pre {
            Pre::Jacobi => vec,
            Pre::BlockJacobi => rs * n * d * d,
            Pre::None | Pre::Multilevel => 0,
        };
        let update_yr = 7 * vec + minv + 8 * n * u64::from(co == Co::Translations);
        // update_p: z and p read, p and pw written, the frames (and each node's aggregate).
        let update_p = 4 * vec + if co == Co::Aggregates { 12 * n } else { 8 * n };
        let agg = frames
            .agg
            .as_ref()
            .filter(|_| co == Co::Aggregates)
            .map_or(0, |a| {
                let k = a.k as u64;
                // restrict: r, the frames and the node lists; solve: E⁺ and w.
                vec + 12 * n + self.ty.acc.size() * (k * k + 2 * k)
            });
        // The V-cycle: its own kernels, two more level-0 products (pw = V P z first) and
        // ml_dot (r and z read).
        let ml = match (&self.ml, pre) {
            (Some(m), Pre::Multilevel) => {
                m.bytes_per_cycle() + 2 * (matvec + 2 * vec + 8 * n) + 2 * vec
            }
            _ => 0,
        };
        Ok(IterationProfile {
            dispatches,
            bytes: matvec + update_yr + update_p + agg + ml + 2 * partials,
        })
    }
    /// Device time of each dispatch of one CG iteration with these frames and parameters,
    /// in seconds (fastest and mean over `reps` iterations), from timestamp queries
    /// around each dispatch in its own compute pass; `None` without TIMESTAMP_QUERY.
    /// Runs from y = 0 with no stopping test; the next iterate starts afresh.
    pub fn profile_iteration(
        &mut self,
        frames: &DeviceFrames,
        params: &DeviceCgParams,
        reps: usize,
    ) -> Result<Option<Vec<KernelTime>>, GpuError> {
        if !self.ctx.has_timestamps() {
            return Ok(None);
        }
        self.own(frames)?;
        let (pre, co) = overrides(params, frames);
        if co == Co::Aggregates {
            // No start status here: the factorization's flag is read on its own.
            let flag = 4 * slots::STATE_COARSE_FAILED as u64;
            let what = "reading the coarse factorization's flag";
            let word = self.ctx.download(&self.buf.state, flag, 4, what)?;
            if crate::gpu::schedule::state_words(&word)[0] != 0 {
                self.upload_aggregate_einv(frames)?;
            }
        }
        // Tolerance 0: no stop flag is ever set, so every dispatch does its work.
        self.ctx.write_buffer(
            &self.buf.scal,
            0,
            &vec![0u8; (self.ty.acc.size() * slots::SCAL_E as u64) as usize],
        );
        self.clear_state();
        let mut enc = self.encoder("pcg profile start");
        enc.clear_buffer(&self.buf.y, 0, None);
        enc.clear_buffer(&self.buf.q, 0, None);
        self.pass(
            &mut enc,
            "pcg profile start",
            Phase::Cg,
            &self.start(frames, pre, co, Mode::Iterate),
        );
        self.ctx.submit(enc);
        let one = self.iteration(frames, pre, co);
        let n_q = 2 * one.len() as u32;
        let set = self.ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("pcg profile timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: n_q,
        });
        let resolve = self.ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pcg profile resolve"),
            size: 8 * n_q as u64,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let period_s = self.ctx.queue.get_timestamp_period() as f64 * 1e-9;
        let mut best = vec![f64::INFINITY; one.len()];
        let mut sum = vec![0.0f64; one.len()];
        for _ in 0..reps.max(1) {
            let mut enc = self.encoder("pcg profile");
            for (j, (_, (pipe, launch, group))) in one.iter().enumerate() {
                let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("pcg profile pass"),
                    timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                        query_set: &set,
                        beginning_of_pass_write_index: Some(2 * j as u32),
                        end_of_pass_write_index: Some(2 * j as u32 + 1),
                    }),
                });
                cp.set_bind_group(0, *group, &[]);
                cp.set_pipeline(pipe);
                launch.dispatch(&mut cp);
            }
            enc.resolve_query_set(&set, 0..n_q, &resolve, 0);
            self.ctx.submit(enc);
            let bytes =
                self.ctx
                    .download(&resolve, 0, 8 * n_q as u64, "reading back timestamps")?;
            let t: Vec<u64> = bytes
                .chunks_exact(8)
                .map(|c| {
                    let mut w = [0u8; 8];
                    w.copy_from_slice(c);
                    u64::from_le_bytes(w)
                })
                .collect();
            for j in 0..one.len() {
                let dt = t[2 * j + 1].saturating_sub(t[2 * j]) as f64 * period_s;
                best[j] = best[j].min(dt);
                sum[j] += dt;
            }
        }
        Ok(Some(
            one.iter()
                .zip(best.into_iter().zip(sum))
                .map(|(&(name, _), (best_s, sum_s))| KernelTime {
                    name: name.to_string(),
                    best_s,
                    mean_s: sum_s / reps.max(1) as f64,
                })
                .collect(),
        ))
    }
}
