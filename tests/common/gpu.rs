//! One GPU context per test binary, with the tests serialized on it (lavapipe is slow and
//! one device is all a binary needs). Without an adapter the first caller prints a loud
//! SKIP and every GPU test returns early, unless STICKSLIP_REQUIRE_GPU=1 (CI), where a
//! missing adapter fails the test instead.

use std::sync::{LazyLock, Mutex, MutexGuard};
use stickslip::core::elimination::Eliminated;
use stickslip::gpu::{
    GpuContext, GpuError, GpuOptions, GpuParams, GpuSolver, PcgSolver, Precision, SolveOutcome,
};

static CTX: LazyLock<Option<GpuContext>> = LazyLock::new(|| {
    match GpuContext::new(&GpuOptions::default()) {
        Ok(c) => {
            eprintln!("GPU tests on adapter '{}'", c.adapter_name());
            Some(c)
        }
        Err(e) => {
            if std::env::var("STICKSLIP_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                panic!("STICKSLIP_REQUIRE_GPU=1 but no GPU adapter: {e}");
            }
            super::skip(&format!(
                "!!!!!!!! SKIP: no GPU adapter ({e}); the GPU tests of this binary did not run !!!!!!!!"
            ));
            None
        }
    }
});
static LOCK: Mutex<()> = Mutex::new(());

/// The shared context and the lock that serializes GPU tests; None without an adapter.
pub fn gpu() -> Option<(&'static GpuContext, MutexGuard<'static, ()>)> {
    let g = LOCK.lock().unwrap_or_else(|p| p.into_inner());
    CTX.as_ref().map(|c| (c, g))
}

/// What `solve --solver gpu` builds for a precision: the device PCG in f64 and f32, the
/// precision kernels in mixed precision.
pub enum Facade {
    Pcg(Box<PcgSolver>),
    Kernels(Box<GpuSolver>),
}

impl Facade {
    pub fn new(ctx: &GpuContext, e: &Eliminated, p: &GpuParams) -> Result<Self, GpuError> {
        Ok(match p.precision {
            Precision::Mixed => Facade::Kernels(Box::new(GpuSolver::new(ctx, e, p)?)),
            _ => Facade::Pcg(Box::new(PcgSolver::new(ctx, e, p)?)),
        })
    }

    pub fn solve(&mut self) -> Result<SolveOutcome, GpuError> {
        match self {
            Facade::Pcg(s) => s.solve(),
            Facade::Kernels(s) => s.solve(),
        }
    }

    /// Dispatches per CG iteration at most: the PCG's five, two more with the aggregates
    /// (the default coarse space); the precision kernels' three, one more per extra row
    /// chunk of the operator.
    pub fn dispatch_bound(&self) -> usize {
        match self {
            Facade::Pcg(_) => 7,
            Facade::Kernels(_) => 4,
        }
    }
}
