//! One GPU context per test binary, with the tests serialized on it (lavapipe is slow and
//! one device is all a binary needs). Without an adapter the first caller prints a loud
//! SKIP and every GPU test returns early, unless STICKSLIP_REQUIRE_GPU=1 (CI), where a
//! missing adapter fails the test instead.

use std::sync::{LazyLock, Mutex, MutexGuard};
use stickslip::gpu::{GpuContext, GpuOptions};

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
