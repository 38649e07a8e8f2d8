//! Where a device run's seconds go: every second of the host's wall time attributed to one
//! [`Phase`], every compute pass and dispatch counted, every wait on the device counted.
//!
//! The host's time belongs to the innermost phase open on it (`GpuContext::phase`; the
//! bottom one is [`Phase::HostDecisions`]), so the phases partition the wall time. Time
//! the host spends waiting on the device is split among the device phases whose passes
//! ran since the last wait, by their device time from timestamp queries written around
//! every compute pass (`GpuContext::compute_pass`) where the adapter has them: each
//! phase gets its device time, scaled down when the device ran longer than the host
//! waited (it worked while the host did), and what the wait has left over is the round
//! trip itself ([`Phase::ReadBacks`]). Without timestamp queries the whole wait is
//! [`Phase::ReadBacks`]. The device times are kept as measured too
//! ([`Profile::device_seconds`]).
//!
//! The timestamps ride with the read-backs the work makes anyway: pending queries are
//! resolved into the staging buffer of the next read (`GpuContext::download_many`).

use std::time::Instant;

/// What the seconds of a device run are spent on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Building the scene, the mesh and the device's static data before the first step.
    Setup,
    /// Compiling shaders into pipelines.
    PipelineCreation,
    /// Host-to-device writes (the host's side of them).
    Uploads,
    /// Element energies, gradients and Hessians.
    ElementTerms,
    /// The assembly of H and g (and the moving boundaries' terms).
    Assembly,
    /// b̂, the preconditioner's diagonal blocks and the coarse matrices of the eliminated
    /// system.
    Elimination,
    /// Building or refreshing the preconditioner's levels and coarse inverses.
    PreconditionerSetup,
    /// The CG's iterations, verifications and Δx.
    Cg,
    /// Energies, slopes, step bounds against obstacles (CCD), trial points.
    LineSearch,
    /// The step bound before an element inverts.
    InversionBound,
    /// The barrier terms and the CCD bound against the obstacles' half-spaces, and the
    /// obstacles' distances (the CPU loop).
    Contact,
    /// The moving boundaries' penalty terms, snapping and penalty updates (the CPU loop).
    MovingBoundary,
    /// The force balance and the step's checks: finite systems, volume ratios, reactions
    /// (the CPU loop).
    Checks,
    /// The CPU loop's linear solve of the eliminated system, whichever solver (what
    /// summary.json's `linear_seconds` counts).
    LinearSolve,
    /// The Newton loop's own logic on the host, and whatever no other phase covers.
    HostDecisions,
    /// Waiting on the device beyond the device time of the work waited for.
    ReadBacks,
    /// Frames, steps.csv, checkpoints and the reads for them.
    Output,
}

impl Phase {
    pub const ALL: [Phase; 17] = [
        Phase::Setup,
        Phase::PipelineCreation,
        Phase::Uploads,
        Phase::ElementTerms,
        Phase::Assembly,
        Phase::Elimination,
        Phase::PreconditionerSetup,
        Phase::Cg,
        Phase::LineSearch,
        Phase::InversionBound,
        Phase::Contact,
        Phase::MovingBoundary,
        Phase::Checks,
        Phase::LinearSolve,
        Phase::HostDecisions,
        Phase::ReadBacks,
        Phase::Output,
    ];

    /// The snake_case name (summary.json's key).
    pub fn name(self) -> &'static str {
        match self {
            Phase::Setup => "setup",
            Phase::PipelineCreation => "pipeline_creation",
            Phase::Uploads => "uploads",
            Phase::ElementTerms => "element_terms",
            Phase::Assembly => "assembly",
            Phase::Elimination => "elimination",
            Phase::PreconditionerSetup => "preconditioner_setup",
            Phase::Cg => "cg",
            Phase::LineSearch => "line_search",
            Phase::InversionBound => "inversion_bound",
            Phase::Contact => "contact",
            Phase::MovingBoundary => "moving_boundary",
            Phase::Checks => "checks",
            Phase::LinearSolve => "linear_solve",
            Phase::HostDecisions => "host_decisions",
            Phase::ReadBacks => "read_backs",
            Phase::Output => "output",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

const N: usize = Phase::ALL.len();

/// The seconds and counts of a run so far.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Profile {
    /// Wall seconds per phase (summing to the profiled wall time).
    #[serde(serialize_with = "phase_map")]
    pub phases: Vec<(Phase, f64)>,
    /// Device seconds per phase as the timestamps measured them (empty without
    /// TIMESTAMP_QUERY).
    #[serde(serialize_with = "phase_map")]
    pub device_seconds: Vec<(Phase, f64)>,
    /// Host waits on the device.
    pub host_syncs: u64,
    /// Compute passes and dispatches recorded.
    pub passes: u64,
    pub dispatches: u64,
    /// The wall seconds the phases cover.
    pub wall_seconds: f64,
    /// Bytes moved host to device and device to host while each phase was open on the
    /// host (a write counted in the phase that asked for it, not in `Uploads`).
    #[serde(serialize_with = "phase_map")]
    pub bytes: Vec<(Phase, [u64; 2])>,
}

/// Phases as a JSON object in their order, name to value.
pub fn phase_map<S: serde::Serializer, T: serde::Serialize>(
    v: &[(Phase, T)],
    s: S,
) -> Result<S::Ok, S::Error> {
    use serde::ser::SerializeMap;
    let mut m = s.serialize_map(Some(v.len()))?;
    for (p, value) in v {
        m.serialize_entry(p.name(), value)?;
    }
    m.end()
}

impl Profile {
    /// The phases with the most seconds, largest first.
    pub fn largest(&self, k: usize) -> Vec<(Phase, f64)> {
        let mut v = self.phases.clone();
        v.sort_by(|a, b| b.1.total_cmp(&a.1));
        v.truncate(k);
        v
    }

    /// Bytes (host to device, device to host) moved outside the run's set-up, pipeline
    /// creation and per-step output: what the Newton iterations moved.
    pub fn iteration_bytes(&self) -> [u64; 2] {
        self.bytes
            .iter()
            .filter(|(p, _)| !matches!(p, Phase::Setup | Phase::PipelineCreation | Phase::Output))
            .fold([0, 0], |a, (_, b)| [a[0] + b[0], a[1] + b[1]])
    }

    /// What happened between `earlier` (a profile of the same context) and this one.
    pub fn since(&self, earlier: &Profile) -> Profile {
        let sub = |a: &[(Phase, f64)], b: &[(Phase, f64)]| -> Vec<(Phase, f64)> {
            a.iter()
                .map(|&(p, s)| {
                    let before = b.iter().find(|(q, _)| *q == p).map_or(0.0, |(_, v)| *v);
                    (p, s - before)
                })
                .collect()
        };
        Profile {
            phases: sub(&self.phases, &earlier.phases),
            device_seconds: sub(&self.device_seconds, &earlier.device_seconds),
            host_syncs: self.host_syncs - earlier.host_syncs,
            passes: self.passes - earlier.passes,
            dispatches: self.dispatches - earlier.dispatches,
            wall_seconds: self.wall_seconds - earlier.wall_seconds,
            bytes: self
                .bytes
                .iter()
                .map(|&(p, [h, d])| {
                    let before = earlier
                        .bytes
                        .iter()
                        .find(|(q, _)| *q == p)
                        .map_or([0, 0], |(_, v)| *v);
                    (p, [h - before[0], d - before[1]])
                })
                .collect(),
        }
    }

    /// The seconds of `phase`.
    pub fn seconds(&self, phase: Phase) -> f64 {
        self.phases
            .iter()
            .find(|(p, _)| *p == phase)
            .map_or(0.0, |(_, s)| *s)
    }
}

/// Timestamp queries per query set: two per pass; pending ones are resolved with the next
/// read-back, so this bounds the passes between two reads (more are left untimed).
pub(crate) const QUERIES: u32 = 4096;

/// The profiler's state (behind the context's mutex).
pub(crate) struct Profiler {
    start: Instant,
    /// Open phases with the instant each (re)gained the host.
    stack: Vec<(Phase, Instant)>,
    wall: [f64; N],
    device: [f64; N],
    pub(crate) syncs: u64,
    bytes: [[u64; 2]; N],
    pub(crate) passes: u64,
    pub(crate) dispatches: u64,
    /// Passes recorded since the last resolution: their phase and first query index.
    pending: Vec<(Phase, u32)>,
    /// Wait seconds not yet attributed (their passes' timestamps not read yet).
    waited: f64,
    pub(crate) timing: Option<Timing>,
}

/// The query set and the buffer its timestamps are resolved into.
pub(crate) struct Timing {
    pub set: wgpu::QuerySet,
    pub resolve: wgpu::Buffer,
    /// Seconds per timestamp tick.
    pub period: f64,
}

impl Profiler {
    pub(crate) fn new(timing: Option<Timing>) -> Self {
        let now = Instant::now();
        Profiler {
            start: now,
            stack: vec![(Phase::HostDecisions, now)],
            wall: [0.0; N],
            device: [0.0; N],
            syncs: 0,
            bytes: [[0; 2]; N],
            passes: 0,
            dispatches: 0,
            pending: Vec::new(),
            waited: 0.0,
            timing,
        }
    }

    /// Charges the time since the top phase last gained the host to it.
    fn charge_top(&mut self, now: Instant) {
        if let Some((p, since)) = self.stack.last_mut() {
            self.wall[p.index()] += now.duration_since(*since).as_secs_f64();
            *since = now;
        }
    }

    pub(crate) fn enter(&mut self, phase: Phase) {
        let now = Instant::now();
        self.charge_top(now);
        self.stack.push((phase, now));
    }

    pub(crate) fn leave(&mut self) {
        let now = Instant::now();
        self.charge_top(now);
        if self.stack.len() > 1 {
            self.stack.pop();
        }
        if let Some((_, since)) = self.stack.last_mut() {
            *since = now;
        }
    }

    /// `seconds` spent outside any phase before the profiler started (the scene's set-up),
    /// charged to `phase`.
    pub(crate) fn add(&mut self, phase: Phase, seconds: f64) {
        self.wall[phase.index()] += seconds;
    }

    /// Bytes moved while the phase open on the host is open.
    pub(crate) fn moved(&mut self, h2d: u64, d2h: u64) {
        let k = self.current().index();
        self.bytes[k][0] += h2d;
        self.bytes[k][1] += d2h;
    }

    /// The phase open on the host (what a pass recorded now belongs to unless it says).
    pub(crate) fn current(&self) -> Phase {
        self.stack.last().map_or(Phase::HostDecisions, |(p, _)| *p)
    }

    /// A pass of `phase` is being recorded: its two query indices, if the adapter times
    /// passes and queries are left.
    pub(crate) fn pass(&mut self, phase: Phase) -> Option<u32> {
        self.passes += 1;
        self.timing.as_ref()?;
        let used = self.pending_queries();
        (used + 2 <= QUERIES).then(|| {
            self.pending.push((phase, used));
            used
        })
    }

    /// Queries to resolve before the next read: 0..count.
    pub(crate) fn pending_queries(&self) -> u32 {
        self.pending.last().map_or(0, |(_, q)| q + 2)
    }

    /// A wait of `seconds` (the host's time in it is taken from the phase open on it and
    /// pooled for the passes' device times to divide).
    pub(crate) fn waited(&mut self, seconds: f64) {
        self.syncs += 1;
        self.blocked(seconds);
    }

    /// `seconds` the host spent blocked in a submit: pooled with the waits (not a sync).
    pub(crate) fn blocked(&mut self, seconds: f64) {
        let top = self.current();
        self.wall[top.index()] -= seconds;
        self.waited += seconds;
        if self.timing.is_none() {
            self.wall[Phase::ReadBacks.index()] += std::mem::take(&mut self.waited);
        }
    }

    /// The resolved timestamps (ticks of `period` seconds) of the pending passes: their
    /// device times, and the waits so far divided among their phases.
    pub(crate) fn resolved(&mut self, ticks: &[u64], period: f64) {
        let mut by_phase = [0.0f64; N];
        for &(phase, q) in &self.pending {
            let (a, b) = (ticks.get(q as usize), ticks.get(q as usize + 1));
            if let (Some(&a), Some(&b)) = (a, b) {
                by_phase[phase.index()] += b.saturating_sub(a) as f64 * period;
            }
        }
        self.pending.clear();
        let device: f64 = by_phase.iter().sum();
        let waited = std::mem::take(&mut self.waited);
        let scale = if device > waited && device > 0.0 {
            waited / device
        } else {
            1.0
        };
        for (k, s) in by_phase.iter().enumerate() {
            self.device[k] += s;
            self.wall[k] += s * scale;
        }
        self.wall[Phase::ReadBacks.index()] += (waited - device * scale).max(0.0);
    }

    pub(crate) fn snapshot(&mut self) -> Profile {
        let now = Instant::now();
        self.charge_top(now);
        // Waits whose passes are not resolved yet are round trips so far.
        let mut wall = self.wall;
        wall[Phase::ReadBacks.index()] += self.waited;
        let has_timing = self.timing.is_some();
        Profile {
            phases: Phase::ALL.iter().map(|&p| (p, wall[p.index()])).collect(),
            device_seconds: if has_timing {
                Phase::ALL
                    .iter()
                    .map(|&p| (p, self.device[p.index()]))
                    .collect()
            } else {
                Vec::new()
            },
            host_syncs: self.syncs,
            bytes: Phase::ALL
                .iter()
                .map(|&p| (p, self.bytes[p.index()]))
                .collect(),
            passes: self.passes,
            dispatches: self.dispatches,
            wall_seconds: now.duration_since(self.start).as_secs_f64() + wall[Phase::Setup.index()],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Nested phases partition the host's time; a wait is divided by the device times of
    /// the passes it waited for, the rest of it is the round trip; without timing all of
    /// it is.
    #[test]
    fn phases_partition_the_wall_time_and_waits_follow_the_device() {
        let mut p = Profiler::new(None);
        p.enter(Phase::Cg);
        std::thread::sleep(std::time::Duration::from_millis(20));
        p.enter(Phase::LineSearch);
        std::thread::sleep(std::time::Duration::from_millis(10));
        p.waited(0.004);
        p.leave();
        p.leave();
        let s = p.snapshot();
        let total: f64 = s.phases.iter().map(|(_, v)| v).sum();
        assert!((total - s.wall_seconds).abs() <= 1e-9 * s.wall_seconds.max(1.0));
        assert!(s.seconds(Phase::Cg) >= 0.02 && s.seconds(Phase::LineSearch) >= 0.005);
        assert!((s.seconds(Phase::ReadBacks) - 0.004).abs() < 1e-12);
        assert_eq!(s.host_syncs, 1);

        // Timed: 3 ms of CG and 1 ms of assembly on the device. Waited 5 ms: each phase
        // gets its device time, the round trip the remaining 1 ms. Waited 2 ms: the
        // device worked while the host did, so both are scaled to the 2 ms.
        for (wait, cg, asm, rb) in [(0.005, 0.003, 0.001, 0.001), (0.002, 0.0015, 0.0005, 0.0)] {
            let mut q = Profiler::new(None);
            q.pending = vec![(Phase::Cg, 0), (Phase::Assembly, 2)];
            q.waited = wait;
            q.resolved(&[0, 3_000_000, 3_000_000, 4_000_000], 1e-9);
            let s = q.snapshot();
            assert!((s.seconds(Phase::Cg) - cg).abs() < 1e-12, "{s:?}");
            assert!((s.seconds(Phase::Assembly) - asm).abs() < 1e-12, "{s:?}");
            assert!((s.seconds(Phase::ReadBacks) - rb).abs() < 1e-12, "{s:?}");
        }
    }
}
