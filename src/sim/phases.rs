//! Where the CPU Newton loop's seconds go: the device loop's phase table
//! ([`crate::gpu::profile`]) kept on the host alone. Every second of the run belongs to
//! the innermost [`Phase`] open (the bottom one is [`Phase::HostDecisions`]), so the
//! phases partition the wall time; summary.json's `phases` reports them
//! ([`crate::sim::driver::PhaseSummary`]).

use crate::gpu::profile::Profiler;
use crate::gpu::{Phase, PhaseGuard, Profile};
use std::sync::{Arc, Mutex};

/// The CPU loop's profile; clones share it (the backend, its assembly buffers).
#[derive(Clone)]
pub struct HostPhases(Arc<Mutex<Profiler>>);

impl Default for HostPhases {
    fn default() -> Self {
        HostPhases(Arc::new(Mutex::new(Profiler::new(None))))
    }
}

impl std::fmt::Debug for HostPhases {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("HostPhases")
    }
}

impl HostPhases {
    /// Opens `phase` until the span drops: the time meanwhile is charged to it.
    pub fn open(&self, phase: Phase) -> PhaseSpan {
        self.with(|p| p.enter(phase));
        PhaseSpan(Span::Host(self.0.clone()))
    }

    /// Charges `seconds` spent before the profile started to `phase` (a run's set-up).
    pub fn add(&self, phase: Phase, seconds: f64) {
        self.with(|p| p.add(phase, seconds));
    }

    /// The profile so far; its wall time is what its phases cover: the run so far, the
    /// seconds charged from before the profile started included.
    pub fn profile(&self) -> Profile {
        let mut p = self.with(|p| p.snapshot()).unwrap_or_default();
        p.wall_seconds = p.phases.iter().map(|(_, s)| s).sum();
        p
    }

    fn with<T>(&self, f: impl FnOnce(&mut Profiler) -> T) -> Option<T> {
        // A poisoned profiler only loses the profile, never the run.
        self.0.lock().ok().map(|mut p| f(&mut p))
    }
}

/// A phase open on a run's profile (the device loop's or the CPU loop's), closed when it
/// drops.
pub struct PhaseSpan(Span);

enum Span {
    // Held for its own drop, which closes the device's phase.
    Device(#[allow(dead_code)] PhaseGuard),
    Host(Arc<Mutex<Profiler>>),
}

impl From<PhaseGuard> for PhaseSpan {
    fn from(g: PhaseGuard) -> Self {
        PhaseSpan(Span::Device(g))
    }
}

impl Drop for PhaseSpan {
    fn drop(&mut self) {
        if let Span::Host(p) = &self.0 {
            if let Ok(mut p) = p.lock() {
                p.leave();
            }
        }
    }
}

/// Opens `phase` on `phases` when there is a profile (None: nothing is timed).
pub fn open(phases: Option<&HostPhases>, phase: Phase) -> Option<PhaseSpan> {
    phases.map(|p| p.open(phase))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Nested spans partition the time: the inner phase gets its own time only, the
    /// outer one the rest, and the profile's phases sum to its wall time.
    #[test]
    fn nested_spans_partition_the_wall_time() {
        let p = HostPhases::default();
        {
            let _outer = p.open(Phase::LineSearch);
            std::thread::sleep(std::time::Duration::from_millis(20));
            let _inner = p.open(Phase::Contact);
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        let s = p.profile();
        let total: f64 = s.phases.iter().map(|(_, v)| v).sum();
        assert!((total - s.wall_seconds).abs() <= 1e-9 * s.wall_seconds.max(1.0));
        assert!(s.seconds(Phase::LineSearch) >= 0.02, "{s:?}");
        assert!(s.seconds(Phase::Contact) >= 0.01, "{s:?}");
    }
}
