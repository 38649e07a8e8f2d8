//! `stickslip info`, and the adapter check the GPU commands make first.

use crate::app::cli::error::CliError;
use crate::error::InputError;

/// `stickslip info`: the GPU adapters wgpu can see (`WGPU_BACKEND` narrows them).
pub fn info() -> Result<(), CliError> {
    println!("stickslip {}", env!("CARGO_PKG_VERSION"));
    let adapters = crate::gpu::list_adapters();
    if adapters.is_empty() {
        return Err(CliError::Failed(crate::gpu::no_adapter_message(
            &crate::gpu::GpuOptions::default(),
        )));
    }
    for (k, a) in adapters.iter().enumerate() {
        println!(
            "adapter {k}: {} ({}, {}; driver {} {}); shader_f64 {}, shader_int64 {}, subgroup {} ({}..{}), timestamp_query {}, max storage binding {} MiB (larger per-block arrays are bound in pieces), max buffer {} MiB, device memory {}",
            a.name,
            a.backend,
            a.device_type,
            a.driver,
            a.driver_info,
            a.shader_f64,
            a.shader_int64,
            a.subgroup,
            a.subgroup_min_size,
            a.subgroup_max_size,
            a.timestamp_query,
            a.max_storage_buffer_binding_size >> 20,
            a.max_buffer_size >> 20,
            a.device_memory
                .map_or("not reported".to_string(), |m| format!("{} MiB", m >> 20))
        );
    }
    Ok(())
}

/// `WGPU_ADAPTER_NAME` naming no adapter is a usage error (exit 2, with the adapters
/// listed), found before any work, not a silent run on another adapter.
pub fn check_adapter_name() -> Result<(), InputError> {
    match crate::gpu::adapter_name_mismatch(&crate::gpu::GpuOptions::default()) {
        Some(problem) => Err(InputError::new("WGPU_ADAPTER_NAME", "", problem)),
        None => Ok(()),
    }
}
