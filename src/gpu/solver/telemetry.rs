//! What the solver records for its reports: the buffers it allocated and kernels it
//! compiled, dispatches per kernel, the bytes one iteration moves, stage timings, and per
//! solve the read-backs, device time and iterations recorded.

use super::info::{BufferRecord, KernelRecord, Resources};
use std::collections::BTreeMap;

pub(super) struct Telemetry {
    pub(super) buffers: Vec<BufferRecord>,
    pub(super) kernels: Vec<KernelRecord>,
    /// Dispatches per kernel name since the solver was built.
    pub(super) dispatches: BTreeMap<String, u64>,
    pub(super) bytes_per_iteration: u64,
    /// Of the last build or update.
    pub(super) upload_seconds: f64,
    pub(super) setup_seconds: f64,
    /// Status and result read-backs of this solve.
    pub(super) readbacks: usize,
    /// Device time of this solve's chunks (timestamp queries).
    pub(super) gpu_seconds: f64,
    /// Iterations recorded in chunks since the solve began.
    pub(super) recorded: usize,
}

impl Telemetry {
    pub(super) fn new(
        buffers: Vec<BufferRecord>,
        kernels: Vec<KernelRecord>,
        bytes_per_iteration: u64,
    ) -> Self {
        Telemetry {
            buffers,
            kernels,
            dispatches: BTreeMap::new(),
            bytes_per_iteration,
            upload_seconds: 0.0,
            setup_seconds: 0.0,
            readbacks: 0,
            gpu_seconds: 0.0,
            recorded: 0,
        }
    }

    /// Clears the per-solve counters.
    pub(super) fn start_solve(&mut self) {
        self.readbacks = 0;
        self.gpu_seconds = 0.0;
        self.recorded = 0;
    }

    pub(super) fn record(&mut self, name: &str) {
        *self.dispatches.entry(name.to_string()).or_default() += 1;
    }

    /// Adds what a later build step (the f64 fallback level) allocated and compiled; its
    /// buffers are labelled with `prefix`.
    pub(super) fn extend(
        &mut self,
        prefix: &str,
        buffers: Vec<BufferRecord>,
        kernels: Vec<KernelRecord>,
    ) {
        self.buffers
            .extend(buffers.into_iter().map(|b| BufferRecord {
                label: format!("{prefix}{}", b.label),
                bytes: b.bytes,
            }));
        self.kernels.extend(kernels);
    }

    pub(super) fn resources(&self) -> Resources {
        Resources {
            buffers: self.buffers.clone(),
            kernels: self.kernels.clone(),
            dispatches: self.dispatches.clone(),
        }
    }
}
