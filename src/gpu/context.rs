//! Adapter choice and device creation, separate from any work so that tests and the
//! command line share one device.

use super::GpuError;
use std::sync::{Arc, Mutex};

/// How to pick the adapter. `Default` reads `WGPU_ADAPTER_NAME` (a case-insensitive
/// substring of the adapter name) and `WGPU_BACKEND` (e.g. `vulkan`, `gl`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GpuOptions {
    pub adapter_name: Option<String>,
    pub backend: Option<String>,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            adapter_name: std::env::var("WGPU_ADAPTER_NAME")
                .ok()
                .filter(|s| !s.is_empty()),
            backend: std::env::var("WGPU_BACKEND").ok().filter(|s| !s.is_empty()),
        }
    }
}

/// One adapter as `stickslip info` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AdapterReport {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub driver_info: String,
    pub shader_f64: bool,
    pub subgroup: bool,
    pub timestamp_query: bool,
    pub subgroup_min_size: u32,
    pub subgroup_max_size: u32,
    pub max_storage_buffers_per_shader_stage: u32,
    pub max_storage_buffer_binding_size: u64,
    pub max_buffer_size: u64,
    pub max_compute_workgroup_size_x: u32,
    pub max_compute_invocations_per_workgroup: u32,
    pub max_compute_workgroups_per_dimension: u32,
}

fn report(a: &wgpu::Adapter) -> AdapterReport {
    let info = a.get_info();
    let f = a.features();
    let l = a.limits();
    AdapterReport {
        subgroup_min_size: info.subgroup_min_size,
        subgroup_max_size: info.subgroup_max_size,
        name: info.name,
        backend: format!("{:?}", info.backend),
        device_type: format!("{:?}", info.device_type),
        driver: info.driver,
        driver_info: info.driver_info,
        shader_f64: f.contains(wgpu::Features::SHADER_F64),
        subgroup: f.contains(wgpu::Features::SUBGROUP),
        timestamp_query: f.contains(wgpu::Features::TIMESTAMP_QUERY),
        max_storage_buffers_per_shader_stage: l.max_storage_buffers_per_shader_stage,
        max_storage_buffer_binding_size: l.max_storage_buffer_binding_size,
        max_buffer_size: l.max_buffer_size,
        max_compute_workgroup_size_x: l.max_compute_workgroup_size_x,
        max_compute_invocations_per_workgroup: l.max_compute_invocations_per_workgroup,
        max_compute_workgroups_per_dimension: l.max_compute_workgroups_per_dimension,
    }
}

fn backends(opts: &GpuOptions) -> wgpu::Backends {
    match &opts.backend {
        Some(b) => wgpu::Backends::from_comma_list(b),
        None => wgpu::Backends::all(),
    }
}

fn instance(b: wgpu::Backends) -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = b;
    wgpu::Instance::new(desc)
}

/// Every adapter wgpu can see (all backends unless `WGPU_BACKEND` narrows them).
pub fn list_adapters() -> Vec<AdapterReport> {
    let opts = GpuOptions::default();
    let inst = instance(backends(&opts));
    pollster::block_on(inst.enumerate_adapters(backends(&opts)))
        .iter()
        .map(report)
        .collect()
}

fn rank(a: &wgpu::Adapter) -> (u32, u32) {
    let info = a.get_info();
    let t = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    };
    // Vulkan first among equals: the backend this crate is tested on.
    let b = match info.backend {
        wgpu::Backend::Vulkan => 0,
        wgpu::Backend::Metal | wgpu::Backend::Dx12 => 1,
        _ => 2,
    };
    (t, b)
}

/// A device and queue with the adapter's own limits and the optional features the solver
/// uses (SHADER_F64, SUBGROUP, TIMESTAMP_QUERY) where the adapter has them.
#[derive(Clone)]
pub struct GpuContext {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) info: wgpu::AdapterInfo,
    pub(crate) features: wgpu::Features,
    pub(crate) limits: wgpu::Limits,
    report: AdapterReport,
    /// Errors wgpu reports outside an error scope; checked after each batch of work so
    /// that a device error becomes a GpuError instead of a panic.
    errors: Arc<Mutex<Vec<String>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.info.name)
            .finish()
    }
}

impl GpuContext {
    pub fn new(opts: &GpuOptions) -> Result<Self, GpuError> {
        // Primary backends (Vulkan, Metal, DX12) first; GL only when they offer nothing.
        let mut b = backends(opts);
        if opts.backend.is_none() {
            b = wgpu::Backends::PRIMARY;
        }
        let mut inst = instance(b);
        let mut adapters = pollster::block_on(inst.enumerate_adapters(b));
        if adapters.is_empty() && opts.backend.is_none() {
            b = wgpu::Backends::all();
            inst = instance(b);
            adapters = pollster::block_on(inst.enumerate_adapters(b));
        }
        if let Some(name) = &opts.adapter_name {
            let needle = name.to_lowercase();
            adapters.retain(|a| a.get_info().name.to_lowercase().contains(&needle));
        }
        adapters.sort_by_key(rank);
        let adapter = match adapters.into_iter().next() {
            Some(a) => a,
            None => {
                // Last resort: whatever software adapter wgpu offers.
                pollster::block_on(inst.request_adapter(&wgpu::RequestAdapterOptions {
                    power_preference: wgpu::PowerPreference::HighPerformance,
                    force_fallback_adapter: true,
                    compatible_surface: None,
                    apply_limit_buckets: false,
                }))
                .map_err(|e| {
                    GpuError::NoAdapter(format!(
                        "no GPU adapter found (backends {b:?}{}): {e}; install a Vulkan driver \
                         (e.g. Mesa lavapipe: mesa-vulkan-drivers) or set WGPU_BACKEND",
                        opts.adapter_name
                            .as_ref()
                            .map(|n| format!(", name containing '{n}'"))
                            .unwrap_or_default()
                    ))
                })?
            }
        };
        let wanted =
            wgpu::Features::SHADER_F64 | wgpu::Features::SUBGROUP | wgpu::Features::TIMESTAMP_QUERY;
        let features = adapter.features() & wanted;
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("stickslip device"),
            required_features: features,
            required_limits: limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));
        Ok(GpuContext {
            report: report(&adapter),
            info: adapter.get_info(),
            device,
            queue,
            features,
            limits,
            errors,
        })
    }

    pub fn adapter_name(&self) -> &str {
        &self.info.name
    }

    pub fn report(&self) -> &AdapterReport {
        &self.report
    }

    pub fn has_f64(&self) -> bool {
        self.features.contains(wgpu::Features::SHADER_F64)
    }

    pub fn has_timestamps(&self) -> bool {
        self.features.contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// Fails with the first device error recorded since the last check.
    pub(crate) fn check(&self, what: &str) -> Result<(), GpuError> {
        let mut v = self
            .errors
            .lock()
            .map_err(|_| GpuError::Device("error log poisoned".into()))?;
        if v.is_empty() {
            Ok(())
        } else {
            let msg = v.join("; ");
            v.clear();
            Err(GpuError::Device(format!("{what}: {msg}")))
        }
    }
}
