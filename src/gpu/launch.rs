//! Dispatch sizes, from the adapter's limits: the one place every kernel launch of
//! `gpu` and `sim::device` gets its workgroup counts.
//!
//! A dispatch is `(x, y, 1)` workgroups with x and y each at most the adapter's
//! `max_compute_workgroups_per_dimension` (65,535 on NVIDIA and lavapipe). Kernels read
//! their position through the helpers of shaders/common.wgsl, which hold for any such
//! dispatch:
//!
//! - an invocation's linear index `grid_index(gid, nwg) = gid.x + gid.y·(nwg.x·WG)` and the
//!   grid-stride step `grid_stride(nwg) = nwg.x·nwg.y·WG`: per-item kernels loop
//!   `for (i = grid_index; i < n; i += grid_stride)`, so any dispatch covers any n;
//! - a workgroup's linear index `group_index(wid, nwg) = wid.x + wid.y·nwg.x` and the count
//!   `group_count(nwg) = nwg.x·nwg.y`: reductions leave one partial per workgroup, so
//!   their dispatch has exactly the workgroups asked for ([`LaunchLimits::exact`]) and the
//!   sums are the same bits however the workgroups are laid out.
//!
//! [`LaunchLimits::grid`] gives one invocation per item up to the limits (a second
//! dimension above `per_dim` workgroups, the grid-stride loop above `per_dim²`). The
//! hidden per-dimension limit (`GpuContext::with_dispatch_limit`, the environment variable
//! [`DISPATCH_LIMIT_ENV`]) lowers `per_dim` so that small systems take these paths.

/// Environment variable read by `GpuContext::new`: a per-dimension workgroup limit below
/// the adapter's (tests and rehearsals; at least [`MIN_DISPATCH_LIMIT`]).
pub const DISPATCH_LIMIT_ENV: &str = "STICKSLIP_MAX_WORKGROUPS_PER_DIM";

/// The smallest forced per-dimension limit: a reduction of up to `MIN²` workgroups whose
/// count is a power of two still splits exactly.
pub const MIN_DISPATCH_LIMIT: u32 = 2;

/// One dispatch: `(x, y, 1)` workgroups.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Launch {
    pub x: u32,
    pub y: u32,
}

impl Launch {
    /// Workgroups of the dispatch (`x·y`).
    pub fn workgroups(&self) -> u64 {
        self.x as u64 * self.y as u64
    }

    /// Invocations of the dispatch: `x·y·wg`, the grid-stride step of its kernels.
    pub fn threads(&self, wg: u32) -> u64 {
        self.workgroups() * wg as u64
    }

    /// Records the dispatch.
    pub fn dispatch(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.dispatch_workgroups(self.x, self.y, 1);
    }
}

/// The per-dimension workgroup limit kernels are launched under.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LaunchLimits {
    pub per_dim: u32,
}

impl LaunchLimits {
    /// The adapter's per-dimension limit, lowered to `forced` where that is given (and
    /// at least [`MIN_DISPATCH_LIMIT`]).
    pub fn new(adapter_per_dim: u32, forced: Option<u32>) -> Self {
        let per_dim = match forced {
            Some(f) => f.max(MIN_DISPATCH_LIMIT).min(adapter_per_dim.max(1)),
            None => adapter_per_dim.max(1),
        };
        LaunchLimits { per_dim }
    }

    /// Up to `groups` workgroups (at least one) for a grid-stride kernel: one dimension
    /// while that fits, else `per_dim` by as many rows as needed (at most `per_dim`), and
    /// never more invocations than a u32 index can count at workgroup size `wg`.
    pub fn groups(&self, groups: u64, wg: u32) -> Launch {
        let l = self.per_dim as u64;
        // x·y·wg must stay below 2^32 (the kernels' u32 index and step).
        let max_groups = (u32::MAX as u64 / wg.max(1) as u64).min(l * l);
        let g = groups.clamp(1, max_groups);
        if g <= l {
            return Launch { x: g as u32, y: 1 };
        }
        let y = g.div_ceil(l).min(l);
        // Only as wide as needed with that many rows.
        let x = g.div_ceil(y).min(l).min(max_groups / y);
        Launch {
            x: x as u32,
            y: y as u32,
        }
    }

    /// One invocation per item (`items` of them, at least one workgroup) up to the limits;
    /// the kernel loops grid-stride beyond them.
    pub fn grid(&self, items: u64, wg: u32) -> Launch {
        self.groups(items.div_ceil(wg.max(1) as u64), wg)
    }

    /// Exactly `groups` workgroups (a reduction's partial sums): one dimension when it
    /// fits, else x·y = groups with both within the limit; None when no such split exists
    /// (only under a forced limit: reductions use at most a few hundred workgroups).
    pub fn exact(&self, groups: u32) -> Option<Launch> {
        let g = groups.max(1);
        let l = self.per_dim;
        if g <= l {
            return Some(Launch { x: g, y: 1 });
        }
        (1..=l)
            .rev()
            .find(|x| g % x == 0 && g / x <= l)
            .map(|x| Launch { x, y: g / x })
    }

    /// [`Self::exact`], or the error naming the reduction that does not split.
    pub fn require_exact(&self, groups: u32, what: &str) -> Result<Launch, super::GpuError> {
        self.exact(groups).ok_or_else(|| {
            super::GpuError::Unsupported(format!(
                "{what}: {groups} workgroups do not split into two dimensions of at most {}",
                self.per_dim
            ))
        })
    }

    /// [`Self::exact`] where it exists (always, for counts checked by
    /// [`Self::require_exact`] when the kernels were built), else [`Self::groups`].
    pub fn reduction(&self, groups: u32, wg: u32) -> Launch {
        self.exact(groups)
            .unwrap_or_else(|| self.groups(groups as u64, wg))
    }
}

/// How many workgroups a segmented reduction launches (see [`SegmentPolicy`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SegmentWorkgroups {
    /// One per segment (up to the launch limits): a GPU.
    PerSegment,
    /// At most this many, each looping over segments: a CPU adapter, whose workgroups
    /// run a few at a time on its threads.
    AtMost(u64),
    /// Exactly this many, idle ones included (tests of the reductions' independence
    /// from the workgroup count).
    Exactly(u64),
}

/// The device policy of segmented reductions (shaders/pcg_*.wgsl): the items are cut
/// into segments of `WG · items` consecutive items; invocation `lid` of the workgroup
/// that takes segment s sums items s·WG·items + lid + m·WG (m = 0, 1, …) in that order,
/// then one tree per segment writes segment s's partial, and a one-workgroup kernel
/// sums the partials in a fixed order. The partials and their order depend on the
/// segment length only, never on how many workgroups run, so every workgroup count
/// gives the same bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SegmentPolicy {
    /// Items per invocation within a segment: 1 on a GPU (one invocation per item, as
    /// many in flight as the system has), more on a CPU adapter (fewer trees).
    pub items: u32,
    pub workgroups: SegmentWorkgroups,
}

impl SegmentPolicy {
    /// The policy for an adapter of this type on a host with `cpu_threads` threads: a GPU
    /// launches a workgroup per segment of 64 items; a CPU adapter segments of 8·64 items
    /// and at most 8 workgroups per thread (at least 16).
    pub fn for_device(device_type: wgpu::DeviceType, cpu_threads: usize) -> Self {
        match device_type {
            wgpu::DeviceType::Cpu => SegmentPolicy {
                items: 8,
                workgroups: SegmentWorkgroups::AtMost((8 * cpu_threads as u64).max(16)),
            },
            _ => SegmentPolicy {
                items: 1,
                workgroups: SegmentWorkgroups::PerSegment,
            },
        }
    }

    /// Segments of `items` items at workgroup size `wg` (at least one).
    pub fn segments(&self, items: u64, wg: u32) -> u64 {
        items.div_ceil(wg as u64 * self.items.max(1) as u64).max(1)
    }

    /// The launch of a segmented kernel over `segments` segments whose every workgroup
    /// also sums all the partials of an earlier reduction (the device PCG's fused scalar
    /// kernels, `update_yr` and `update_p`): at most `cap` workgroups, each looping over
    /// segments, so that redundant work grows with the partials, not with their square.
    /// The partials themselves are per segment, so the bits do not change.
    pub fn launch_capped(&self, limits: &LaunchLimits, segments: u64, cap: u64, wg: u32) -> Launch {
        match self.workgroups {
            SegmentWorkgroups::Exactly(_) => self.launch(limits, segments, wg),
            _ => self.launch(limits, segments.min(cap.max(1)), wg),
        }
    }

    /// The launch of a segmented kernel over `segments` segments.
    pub fn launch(&self, limits: &LaunchLimits, segments: u64, wg: u32) -> Launch {
        let groups = match self.workgroups {
            SegmentWorkgroups::PerSegment => segments,
            SegmentWorkgroups::AtMost(c) => segments.min(c),
            SegmentWorkgroups::Exactly(w) => w,
        };
        limits.groups(groups, wg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A discrete GPU with NVIDIA's limits launches one invocation per block row of a
    /// 1M-row matvec; a CPU adapter keeps a few workgroups.
    #[test]
    fn a_gpu_launches_an_invocation_per_row() {
        let rows = 1_000_000u64;
        let gpu = SegmentPolicy::for_device(wgpu::DeviceType::DiscreteGpu, 16);
        let segs = gpu.segments(rows, 64);
        let l = gpu.launch(&NVIDIA, segs, 64);
        assert!(l.threads(64) >= rows, "{l:?}");
        let cpu = SegmentPolicy::for_device(wgpu::DeviceType::Cpu, 2);
        let l = cpu.launch(&NVIDIA, cpu.segments(rows, 64), 64);
        assert_eq!(l.workgroups(), 16);
        let exact = SegmentPolicy {
            items: 1,
            workgroups: SegmentWorkgroups::Exactly(4096),
        };
        assert_eq!(exact.launch(&NVIDIA, 3, 64).workgroups(), 4096);
    }

    const NVIDIA: LaunchLimits = LaunchLimits { per_dim: 65_535 };

    fn covers(l: &LaunchLimits, items: u64, wg: u32) -> Launch {
        let d = l.grid(items, wg);
        assert!(d.x >= 1 && d.y >= 1, "{items}: {d:?}");
        assert!(d.x <= l.per_dim && d.y <= l.per_dim, "{items}: {d:?}");
        assert!(d.threads(wg) <= u32::MAX as u64, "{items}: {d:?}");
        d
    }

    #[test]
    fn one_invocation_per_item_while_one_dimension_holds() {
        let d = covers(&NVIDIA, 1_000_000, 64);
        assert_eq!(d, Launch { x: 15_625, y: 1 });
        assert!(d.threads(64) >= 1_000_000);
        assert_eq!(covers(&NVIDIA, 0, 64), Launch { x: 1, y: 1 });
        assert_eq!(covers(&NVIDIA, 65_535 * 64, 64), Launch { x: 65_535, y: 1 });
    }

    #[test]
    fn a_second_dimension_above_the_limit() {
        // The 2.2M-node 2D mixed solve: 4.4M DOFs, 68,750 workgroups of 64.
        let d = covers(&NVIDIA, 4_400_000, 64);
        assert_eq!(d.y, 2);
        assert!(d.threads(64) >= 4_400_000);
        let small = LaunchLimits::new(65_535, Some(4));
        assert_eq!(small.per_dim, 4);
        // 47 workgroups wanted, 16 allowed: grid-stride.
        assert_eq!(covers(&small, 3000, 64), Launch { x: 4, y: 4 });
        // 6 wanted: 3 by 2, not 4 by 2.
        assert_eq!(covers(&small, 6 * 64, 64), Launch { x: 3, y: 2 });
    }

    /// Every kernel of a 10-million-node 3D system: per-node, per-DOF, per-block and
    /// per-element launches fit the NVIDIA limits and give each item its own invocation;
    /// every reduction splits exactly.
    #[test]
    fn a_ten_million_node_3d_system_fits_every_kernel() {
        let n: u64 = 10_000_000;
        let items = [
            ("nodes: precond build, newton precond, recover, gather", n),
            (
                "DOFs: scale_rhs, accumulate, begin_step, trial, end_step",
                3 * n,
            ),
            (
                "blocks: assembly blocks_init, blocks_add_*, matvec_blocks",
                27 * n,
            ),
            ("elements: neohookean_elements, grad_add_elements", 6 * n),
        ];
        for wg in [32u32, 64, 128, 256] {
            for (what, count) in items {
                let d = covers(&NVIDIA, count, wg);
                let per_item = d.threads(wg) >= count;
                // Per-block at wg 32: 8.4M workgroups > 65,535² is false, so every
                // count here is covered one invocation per item.
                assert!(per_item, "{what} at wg {wg}: {d:?}");
            }
        }
        // The Newton loop's fixed-tree reductions: at most 256 workgroups.
        for g in 1..=256 {
            assert_eq!(NVIDIA.exact(g), Some(Launch { x: g, y: 1 }));
        }
    }

    #[test]
    fn reductions_split_exactly_or_not_at_all() {
        let l = LaunchLimits::new(65_535, Some(8));
        assert_eq!(l.exact(16), Some(Launch { x: 8, y: 2 }));
        assert_eq!(l.exact(64), Some(Launch { x: 8, y: 8 }));
        assert_eq!(l.exact(5), Some(Launch { x: 5, y: 1 }));
        assert_eq!(l.exact(13), None);
        assert_eq!(l.exact(65), None);
        assert!(l.require_exact(13, "cg").is_err());
        for g in 1..=64u32 {
            if let Some(d) = l.exact(g) {
                assert_eq!(d.workgroups(), g as u64);
            }
        }
    }

    #[test]
    fn the_invocation_count_stays_within_u32() {
        let d = covers(&NVIDIA, u32::MAX as u64, 256);
        assert!(d.threads(256) <= u32::MAX as u64);
        let forced = LaunchLimits::new(65_535, Some(0));
        assert_eq!(forced.per_dim, MIN_DISPATCH_LIMIT);
        assert_eq!(LaunchLimits::new(1000, Some(5000)).per_dim, 1000);
    }
}
