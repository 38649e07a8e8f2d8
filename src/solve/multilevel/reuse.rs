//! The levels kept between the systems of a Newton solve ([`MultilevelSetup::Reuse`]).
//!
//! Ĥ changes little from one Newton iteration to the next, and the setup of the levels
//! costs about as much as the 10–20 V-cycles of a solve (BENCHMARKS.md, "The multilevel
//! preconditioner"). So the levels of one system serve the next ones of the same pattern
//! and constraint set ([`Multilevel::refresh`]: the finest matrix and its smoothing weight
//! are the new system's) until a solve on them takes more than [`REBUILD_GROWTH`] times
//! the iterations per decade of residual reduction of the first solve after the build (or
//! after their first remasking), or fails, or a new Newton solve begins
//! ([`KeptLevels::new_newton_solve`]: a simulation step's first system builds its own
//! levels, so that a run resumed at a step boundary decides and builds as the run that
//! went through it). Every decision comes from
//! iteration counts, tolerances and constraint sets, so the CPU CG and the device PCG,
//! which take the same iterations, keep and rebuild on the same systems.
//!
//! The decision ([`KeptLevels::plan`]) is apart from the building: the CPU CG's solver and
//! `solve --solver gpu` build on the host ([`KeptLevels::for_system`]), the device Newton
//! loop asks only for the decision and carries it out on the device
//! (src/gpu/pcg/mlsetup.rs).

use super::{frames_fit, FramesFit, Hierarchy, Multilevel};
use crate::core::constraints::Frames;
use crate::core::elimination::Eliminated;
use crate::core::sparse::BlockCsr;
use crate::solve::options::MultilevelSetup;
use std::sync::Arc;

/// A solve on kept levels taking more than this many times the iterations per decade of
/// the first solve on them (since their build or their first remasking) has the next
/// system rebuild them.
pub const REBUILD_GROWTH: f64 = 1.5;

/// What [`KeptLevels::plan`] decided (and [`KeptLevels::for_system`] did).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Levels {
    /// Built for this system.
    Built,
    /// Kept from an earlier system of the same constraint set, refreshed for this one
    /// (only the finest level's matrix and smoothing weight changed).
    Kept,
    /// Kept from an earlier system whose constraint set left free some components this
    /// one constrains: refreshed, and those components masked in the finest level's
    /// inverses and the prolongation from it.
    Remasked,
}

/// The multilevel preconditioner's hierarchy (once per pattern) and, with
/// [`MultilevelSetup::Reuse`], its levels, across the systems one solver meets.
#[derive(Debug, Clone)]
pub struct KeptLevels {
    setup: MultilevelSetup,
    hierarchy: Option<Arc<Hierarchy>>,
    /// The levels built on the host ([`KeptLevels::for_system`]), when kept.
    levels: Option<Arc<Multilevel>>,
    /// The hierarchy and the constraint set the current levels were built on (or
    /// remasked to), when they may be kept.
    serving: Option<(Arc<Hierarchy>, Frames)>,
    /// Iterations per decade of the first solve on the current levels (or after their
    /// first remasking).
    fresh_rate: Option<f64>,
    /// No remasking since the build yet.
    first_remask: bool,
    /// The next system rebuilds the levels.
    rebuild: bool,
    last: Levels,
    builds: usize,
    kept: usize,
}

impl KeptLevels {
    pub fn new(setup: MultilevelSetup) -> Self {
        KeptLevels {
            setup,
            hierarchy: None,
            levels: None,
            serving: None,
            fresh_rate: None,
            first_remask: false,
            rebuild: false,
            last: Levels::Built,
            builds: 0,
            kept: 0,
        }
    }

    /// Starts from a hierarchy built beforehand (a device checks its memory on it).
    pub fn with_hierarchy(setup: MultilevelSetup, hierarchy: Arc<Hierarchy>) -> Self {
        KeptLevels {
            hierarchy: Some(hierarchy),
            ..Self::new(setup)
        }
    }

    /// The hierarchy of `h`'s pattern: the kept one when it fits, else a new one.
    pub fn hierarchy_for(&mut self, h: &BlockCsr) -> Arc<Hierarchy> {
        Hierarchy::kept_for(&mut self.hierarchy, h)
    }

    /// Decides the levels of the next system, on the hierarchy `hierarchy` with the
    /// constraint set `frames`, and counts it: [`Levels::Kept`] or [`Levels::Remasked`]
    /// when the setup keeps levels, no rebuild is due and the current levels were built
    /// on `hierarchy` for a constraint set that `frames` leaves alone or masks further
    /// ([`frames_fit`]); [`Levels::Built`] otherwise. The caller builds or refreshes the
    /// levels accordingly (the device Newton loop on the device).
    pub fn plan(&mut self, hierarchy: &Arc<Hierarchy>, frames: &Frames) -> Levels {
        self.decide(hierarchy, frames, true)
    }

    /// [`KeptLevels::plan`], keeping levels only where `can_keep` (the caller holds them).
    fn decide(&mut self, hierarchy: &Arc<Hierarchy>, frames: &Frames, can_keep: bool) -> Levels {
        if can_keep && self.setup == MultilevelSetup::Reuse && !self.rebuild {
            let how = self.serving.as_ref().and_then(|(h, served)| {
                if !Arc::ptr_eq(h, hierarchy) {
                    return None;
                }
                match frames_fit(served, frames) {
                    FramesFit::Same => Some(Levels::Kept),
                    FramesFit::Masked => Some(Levels::Remasked),
                    FramesFit::No => None,
                }
            });
            if let Some(how) = how {
                if how == Levels::Remasked {
                    self.serving = Some((hierarchy.clone(), frames.clone()));
                    if std::mem::take(&mut self.first_remask) {
                        // The constraint set the levels mostly serve starts here: its
                        // first solve sets the rate. (A step's first system, with its
                        // moving nodes free, converges faster than the rest of the
                        // step's; held to its rate, the first remasked system rebuilt the
                        // levels in every step, and the levels built then did no
                        // better.) Later remaskings keep the rate, or a run of them would
                        // let it drift up with levels that get worse.
                        self.fresh_rate = None;
                    }
                }
                self.last = how;
                self.kept += 1;
                return how;
            }
        }
        self.serving =
            (self.setup == MultilevelSetup::Reuse).then(|| (hierarchy.clone(), frames.clone()));
        self.rebuild = false;
        self.fresh_rate = None;
        self.first_remask = true;
        self.last = Levels::Built;
        self.builds += 1;
        Levels::Built
    }

    /// The levels for the system `e`, built on the host: kept and refreshed when
    /// [`KeptLevels::plan`] keeps them, else built.
    pub fn for_system(&mut self, e: &Eliminated) -> (Arc<Multilevel>, Levels) {
        self.levels_for(e, Multilevel::refresh)
    }

    /// [`KeptLevels::for_system`] for the CPU V-cycle alone: kept levels are refreshed
    /// by [`Multilevel::refresh_cycle`], so their [`Multilevel::levels`] are not asked
    /// until a [`KeptLevels::for_system`] refreshes them again.
    pub fn for_cpu_system(&mut self, e: &Eliminated) -> (Arc<Multilevel>, Levels) {
        self.levels_for(e, Multilevel::refresh_cycle)
    }

    fn levels_for(
        &mut self,
        e: &Eliminated,
        refresh: fn(&mut Multilevel, &Eliminated),
    ) -> (Arc<Multilevel>, Levels) {
        let hierarchy = self.hierarchy_for(e.h);
        let how = self.decide(&hierarchy, e.frames, self.levels.is_some());
        if let Some(ml) = self.levels.as_mut().filter(|_| how != Levels::Built) {
            refresh(Arc::make_mut(ml), e);
            return (ml.clone(), how);
        }
        // The old levels go first: their memory serves the new ones (at 44,541 nodes,
        // faulting in fresh pages made a build take 0.46 s instead of 0.16 s).
        self.levels = None;
        let ml = Arc::new(Multilevel::new(e, hierarchy));
        self.levels = (self.setup == MultilevelSetup::Reuse).then(|| ml.clone());
        (ml, Levels::Built)
    }

    /// A new Newton solve begins: its first system builds its levels
    /// ([`MultilevelSetup::Reuse`]; nothing changes with [`MultilevelSetup::Every`]). The
    /// levels then depend only on the systems of this solve, never on earlier ones.
    pub fn new_newton_solve(&mut self) {
        if self.setup == MultilevelSetup::Reuse {
            self.rebuild = true;
        }
    }

    /// Records a solve on the current levels: `iterations` to the relative residual
    /// `tol`. The first solve after a build sets the rate the later ones are held to (a
    /// solve again on the same system counts as a later one, whether or not it asked
    /// [`KeptLevels::for_system`] first).
    pub fn solved(&mut self, iterations: usize, tol: f64) {
        if self.setup != MultilevelSetup::Reuse || iterations == 0 {
            return;
        }
        let decades = (1.0 / tol).log10().max(0.5);
        let rate = iterations as f64 / decades;
        match self.fresh_rate {
            Some(fresh) => {
                if rate > REBUILD_GROWTH * fresh {
                    self.rebuild = true;
                }
            }
            None => self.fresh_rate = Some(rate),
        }
    }

    /// A solve on the levels of the last [`KeptLevels::for_system`] failed: the next
    /// system rebuilds them. True when they were kept levels, so that a solve on fresh
    /// ones may succeed where it failed.
    pub fn failed(&mut self) -> bool {
        self.rebuild = true;
        self.last != Levels::Built
    }

    /// Whether the next [`KeptLevels::for_system`] rebuilds kept levels that the last
    /// solves found slow or failed on ([`MultilevelSetup::Reuse`] only): a caller that
    /// solves a system again without asking (`again`) asks then, to decide as one that
    /// always asks.
    pub fn rebuild_due(&self) -> bool {
        self.setup == MultilevelSetup::Reuse && self.rebuild
    }

    /// Counts a system solved again on the current levels as they are (a re-solve of the
    /// last system that did not ask [`KeptLevels::for_system`]) as a caller that asks
    /// would have it counted: built with [`MultilevelSetup::Every`] (the same levels
    /// again), kept otherwise.
    pub fn again(&mut self) {
        match self.setup {
            MultilevelSetup::Every => self.builds += 1,
            MultilevelSetup::Reuse => self.kept += 1,
        }
    }

    /// Systems whose levels were built, and systems that kept them.
    pub fn counts(&self) -> (usize, usize) {
        (self.builds, self.kept)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cases::generate::{random_system, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    /// Kept levels serve a scaled system (Ĥ grown 8×, as a penalty doubling three times
    /// grows its nodes' blocks): the refreshed V-cycle stays symmetric positive definite,
    /// CG on it converges, and a slow solve or a failure has the next system rebuild.
    #[test]
    fn kept_levels_refresh_and_rebuild_when_solves_slow_down() {
        let s = random_system(&SystemSpec::with_nodes(3, 700, 11));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
        let mut kept = KeptLevels::new(MultilevelSetup::Reuse);
        let (first, how) = kept.for_system(&e);
        assert_eq!(how, Levels::Built);
        kept.solved(20, 1e-4);
        let mut h2 = s.h.clone();
        h2.values.iter_mut().for_each(|v| *v *= 8.0);
        let e2 = Eliminated::new(&h2, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
        let (second, how) = kept.for_system(&e2);
        assert_eq!(how, Levels::Kept);
        // The same inverses (kept), a new finest matrix and smoothing weight.
        assert_eq!(first.levels()[0].inv, second.levels()[0].inv);
        assert_eq!(
            second.levels()[0].values[0],
            8.0 * first.levels()[0].values[0]
        );
        let n = e2.ndof();
        let x: Vec<f64> = (0..n).map(|k| ((k * 7919) % 23) as f64 - 11.0).collect();
        let y: Vec<f64> = (0..n).map(|k| ((k * 104729) % 17) as f64 - 8.0).collect();
        let (mut mx, mut my) = (vec![0.0; n], vec![0.0; n]);
        second.apply(&x, &mut mx);
        second.apply(&y, &mut my);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(u, v)| u * v).sum::<f64>();
        let mag: f64 = y.iter().zip(&mx).map(|(u, v)| (u * v).abs()).sum();
        // The same products in two orders: a few ulps of the magnitudes summed.
        assert!((dot(&y, &mx) - dot(&x, &my)).abs() <= 1e-12 * mag);
        assert!(dot(&x, &mx) > 0.0 && dot(&y, &my) > 0.0);
        // 1.4× the fresh rate keeps the levels, 1.6× rebuilds them.
        kept.solved(28, 1e-4);
        assert_eq!(kept.for_system(&e2).1, Levels::Kept);
        assert!(!kept.rebuild_due());
        kept.solved(32, 1e-4);
        assert!(kept.rebuild_due());
        assert_eq!(kept.for_system(&e2).1, Levels::Built);
        assert!(!kept.rebuild_due());
        kept.solved(20, 1e-4);
        // A failure on kept levels asks for a retry on fresh ones.
        assert_eq!(kept.for_system(&e).1, Levels::Kept);
        assert!(kept.failed());
        assert_eq!(kept.for_system(&e).1, Levels::Built);
        assert!(!kept.failed());
        assert_eq!(kept.counts(), (3, 3));
        // More constrained components mask the kept levels: the V-cycle stays SPD and
        // leaves them zero; fewer rebuild them.
        let node = (0..s.frames.n_nodes)
            .find(|&i| s.frames.mask[i] == 0 && s.frames.rotation(i).is_none())
            .expect("a free node");
        assert_eq!(kept.for_system(&e).1, Levels::Built);
        let mut more = s.frames.clone();
        more.mask[node] = 0b111;
        let e3 = Eliminated::new(&s.h, &s.g, &more, ConstrainedDiagonal::Hessian);
        let (masked, how) = kept.for_system(&e3);
        assert_eq!(how, Levels::Remasked);
        let mut r: Vec<f64> = x.clone();
        for (k, v) in r.iter_mut().enumerate() {
            if more.mask[k / 3] & (1 << (k % 3)) != 0 {
                *v = 0.0;
            }
        }
        let (mut mr, mut my) = (vec![0.0; n], vec![0.0; n]);
        masked.apply(&r, &mut mr);
        masked.apply(&y, &mut my);
        assert_eq!(&mr[node * 3..node * 3 + 3], &[0.0; 3]);
        assert!(dot(&r, &mr) > 0.0);
        let mag: f64 = y.iter().zip(&mr).map(|(u, v)| (u * v).abs()).sum();
        assert!((dot(&y, &mr) - dot(&r, &my)).abs() <= 1e-12 * mag);
        assert_eq!(kept.for_system(&e).1, Levels::Built);
        let mut every = KeptLevels::new(MultilevelSetup::Every);
        every.for_system(&e);
        every.solved(20, 1e-4);
        assert_eq!(every.for_system(&e).1, Levels::Built);
    }

    /// The first remasking after a build starts the rate over: the first solve on the new
    /// constraint set sets the rate the next ones are held to, whatever the build's first
    /// solve took; a second remasking keeps it.
    #[test]
    fn the_first_remasking_sets_the_rate_anew() {
        let s = random_system(&SystemSpec::with_nodes(3, 700, 12));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
        let mut kept = KeptLevels::new(MultilevelSetup::Reuse);
        assert_eq!(kept.for_system(&e).1, Levels::Built);
        kept.solved(10, 1e-4);
        let mut free = (0..s.frames.n_nodes)
            .filter(|&i| s.frames.mask[i] == 0 && s.frames.rotation(i).is_none());
        let mut more = s.frames.clone();
        more.mask[free.next().expect("a free node")] = 0b111;
        let e3 = Eliminated::new(&s.h, &s.g, &more, ConstrainedDiagonal::Hessian);
        assert_eq!(kept.for_system(&e3).1, Levels::Remasked);
        // Twice the build's rate, but the first on this constraint set.
        kept.solved(20, 1e-4);
        assert!(!kept.rebuild_due());
        assert_eq!(kept.for_system(&e3).1, Levels::Kept);
        kept.solved(28, 1e-4);
        assert!(
            !kept.rebuild_due(),
            "1.4× the remasked rate keeps the levels"
        );
        more.mask[free.next().expect("a second free node")] = 0b111;
        let e4 = Eliminated::new(&s.h, &s.g, &more, ConstrainedDiagonal::Hessian);
        assert_eq!(kept.for_system(&e4).1, Levels::Remasked);
        kept.solved(32, 1e-4);
        assert!(
            kept.rebuild_due(),
            "1.6× the first remasked rate rebuilds them"
        );
        assert_eq!(kept.for_system(&e4).1, Levels::Built);
    }

    /// A refresh for the CPU V-cycle alone rounds the same f32 finest matrix, and
    /// estimates the same smoothing weight, as a refresh through the f64 level; only the
    /// f64 view is left behind, and asking for it is refused.
    #[test]
    fn a_cycle_refresh_gives_the_cycle_a_full_refresh_gives() {
        for (dim, nodes, seed) in [(3, 900, 7u64), (2, 1200, 8)] {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            let f = &s.frames;
            assert!(f.has_rotation(), "{dim}D: rotated nodes to refresh");
            let e = Eliminated::new(&s.h, &s.g, f, ConstrainedDiagonal::Hessian);
            let built = Multilevel::new(&e, Arc::new(Hierarchy::new(&s.h)));
            let mut h2 = s.h.clone();
            h2.values.iter_mut().for_each(|v| *v *= 3.0);
            let mut more = f.clone();
            let free = (0..f.n_nodes)
                .find(|&i| f.mask[i] == 0 && f.rotation(i).is_none())
                .expect("a free node");
            more.mask[free] = 1;
            let e2 = Eliminated::new(&h2, &s.g, &more, ConstrainedDiagonal::Hessian);
            let (mut full, mut cycle) = (built.clone(), built);
            full.refresh(&e2);
            cycle.refresh_cycle(&e2);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits(&full.cycle[0].values),
                bits(&cycle.cycle[0].values),
                "{dim}D"
            );
            assert_eq!(
                full.cycle[0].omega.to_bits(),
                cycle.cycle[0].omega.to_bits()
            );
            assert_eq!(
                bits(&full.cycle[0].p),
                bits(&cycle.cycle[0].p),
                "{dim}D: masked P"
            );
            let n = e2.ndof();
            let r: Vec<f64> = (0..n).map(|k| ((k * 7919) % 23) as f64 - 11.0).collect();
            let (mut z1, mut z2) = (vec![0.0; n], vec![0.0; n]);
            full.apply(&r, &mut z1);
            cycle.apply(&r, &mut z2);
            assert!(z1.iter().zip(&z2).all(|(a, b)| a.to_bits() == b.to_bits()));
            let asked =
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| cycle.levels().len()));
            assert!(asked.is_err(), "{dim}D: the f64 view after a cycle refresh");
            cycle.refresh(&e2);
            assert_eq!(cycle.levels().len(), full.levels().len());
        }
    }

    /// The decision alone ([`KeptLevels::plan`], what the device loop asks) is the host
    /// builder's ([`KeptLevels::for_system`]) system by system: through keeps, a slow
    /// solve, a grown constraint set, a failure and a constraint set the levels do not
    /// serve, with the same counts.
    #[test]
    fn the_plan_decides_as_the_host_builder() {
        let s = random_system(&SystemSpec::with_nodes(3, 400, 12));
        let hier = Arc::new(Hierarchy::new(&s.h));
        let node = (0..s.frames.n_nodes)
            .find(|&i| s.frames.mask[i] == 0 && s.frames.rotation(i).is_none())
            .expect("a free node");
        let mut more = s.frames.clone();
        more.mask[node] = 0b111;
        let mut host = KeptLevels::with_hierarchy(MultilevelSetup::Reuse, hier.clone());
        let mut dev = KeptLevels::with_hierarchy(MultilevelSetup::Reuse, hier.clone());
        // (constraint set, iterations of the solve or None for a failure, the decision).
        let f = &s.frames;
        let sequence = [
            (f, Some(20), Levels::Built),
            (f, Some(28), Levels::Kept),
            (f, Some(32), Levels::Kept),
            (f, Some(20), Levels::Built),
            (&more, None, Levels::Remasked),
            (&more, Some(20), Levels::Built),
            (f, Some(20), Levels::Built),
            (f, Some(20), Levels::Kept),
        ];
        for (k, (frames, solve, want)) in sequence.into_iter().enumerate() {
            let e = Eliminated::new(&s.h, &s.g, frames, ConstrainedDiagonal::Identity);
            let built = host.for_system(&e).1;
            let planned = dev.plan(&hier, frames);
            assert_eq!((built, planned), (want, want), "system {k}");
            match solve {
                Some(iterations) => {
                    host.solved(iterations, 1e-4);
                    dev.solved(iterations, 1e-4);
                }
                None => assert_eq!(host.failed(), dev.failed()),
            }
            assert_eq!(host.rebuild_due(), dev.rebuild_due(), "system {k}");
        }
        assert_eq!(host.counts(), dev.counts());
        assert_eq!(host.counts(), (4, 4));
    }
}
