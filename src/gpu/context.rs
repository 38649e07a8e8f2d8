//! Adapter choice and device creation, separate from any work so that tests and the
//! command line share one device.

use super::profile::{Phase, Profile, Profiler, Timing, QUERIES};
use super::GpuError;
use std::any::Any;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

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
    pub shader_int64: bool,
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
    /// The minimum offset alignment of a storage binding (the pieces of a split array).
    pub min_storage_buffer_offset_alignment: u32,
    /// Size of the largest device-local memory heap (Vulkan); None where the backend does
    /// not say.
    pub device_memory: Option<u64>,
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
        shader_int64: f.contains(wgpu::Features::SHADER_INT64),
        subgroup: f.contains(wgpu::Features::SUBGROUP),
        timestamp_query: f.contains(wgpu::Features::TIMESTAMP_QUERY),
        max_storage_buffers_per_shader_stage: l.max_storage_buffers_per_shader_stage,
        max_storage_buffer_binding_size: l.max_storage_buffer_binding_size,
        max_buffer_size: l.max_buffer_size,
        max_compute_workgroup_size_x: l.max_compute_workgroup_size_x,
        max_compute_invocations_per_workgroup: l.max_compute_invocations_per_workgroup,
        max_compute_workgroups_per_dimension: l.max_compute_workgroups_per_dimension,
        min_storage_buffer_offset_alignment: l.min_storage_buffer_offset_alignment,
        device_memory: device_memory(a),
    }
}

/// The largest device-local heap of a Vulkan adapter, in bytes: the memory a solver's
/// buffers must fit in. None on other backends (wgpu does not report memory).
#[cfg(any(target_os = "linux", target_os = "windows", target_os = "android"))]
fn device_memory(a: &wgpu::Adapter) -> Option<u64> {
    // SAFETY: reads the physical device's memory properties only; the handles are the
    // adapter's own and outlive the call.
    let hal = unsafe { a.as_hal::<wgpu::hal::api::Vulkan>() }?;
    let inst = hal.shared_instance().raw_instance();
    let props = unsafe { inst.get_physical_device_memory_properties(hal.raw_physical_device()) };
    // VK_MEMORY_HEAP_DEVICE_LOCAL_BIT = 1.
    props
        .memory_heaps_as_slice()
        .iter()
        .filter(|h| h.flags.as_raw() & 1 != 0)
        .map(|h| h.size)
        .max()
}

#[cfg(not(any(target_os = "linux", target_os = "windows", target_os = "android")))]
fn device_memory(_: &wgpu::Adapter) -> Option<u64> {
    None
}

/// The backends tried: `WGPU_BACKEND`'s, else the primary ones (Vulkan, Metal, DX12).
/// GL is tried only when named: it has no f64 and too few storage buffers per kernel.
fn backends(opts: &GpuOptions) -> wgpu::Backends {
    match &opts.backend {
        Some(b) => wgpu::Backends::from_comma_list(b),
        None => wgpu::Backends::PRIMARY,
    }
}

/// The environment variables the adapter choice reads, as `NAME=value` (or `NAME unset`).
fn environment_read() -> String {
    [
        "WGPU_BACKEND",
        "WGPU_ADAPTER_NAME",
        "VK_ICD_FILENAMES",
        "VK_DRIVER_FILES",
    ]
    .iter()
    .map(|v| match std::env::var(v) {
        Ok(s) if !s.is_empty() => format!("{v}={}", crate::io::one_line(&s, 80)),
        _ => format!("{v} unset"),
    })
    .collect::<Vec<_>>()
    .join(", ")
}

/// Why no adapter was found, in one line: the backends tried and the environment read.
pub fn no_adapter_message(opts: &GpuOptions) -> String {
    let b = backends(opts);
    if b.is_empty() {
        // No backend was tried: the remedy is the variable, not a driver.
        return format!(
            "no GPU adapter found (WGPU_BACKEND='{}' names no backend; {}); set WGPU_BACKEND \
             to vulkan, metal, dx12 or gl, or unset it",
            crate::io::one_line(opts.backend.as_deref().unwrap_or(""), 40),
            environment_read()
        );
    }
    format!(
        "no GPU adapter found (backends tried: {b:?}; {}); install a Vulkan driver and its \
         loader (libvulkan1; NVIDIA's driver, or Mesa lavapipe: mesa-vulkan-drivers) or \
         point VK_ICD_FILENAMES at its ICD json",
        environment_read()
    )
}

fn instance(b: wgpu::Backends) -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = b;
    wgpu::Instance::new(desc)
}

/// Every adapter wgpu can see on the backends tried (`WGPU_BACKEND`, else the primary
/// ones).
pub fn list_adapters() -> Vec<AdapterReport> {
    let opts = GpuOptions::default();
    let inst = instance(backends(&opts));
    pollster::block_on(inst.enumerate_adapters(backends(&opts)))
        .iter()
        .map(report)
        .collect()
}

/// When `WGPU_ADAPTER_NAME` (in `opts`) names no adapter wgpu can see: the one-line
/// problem, listing the adapters there are. None when it is unset or matches one.
pub fn adapter_name_mismatch(opts: &GpuOptions) -> Option<String> {
    let name = opts.adapter_name.as_ref()?;
    let inst = instance(backends(opts));
    let infos: Vec<wgpu::AdapterInfo> = pollster::block_on(inst.enumerate_adapters(backends(opts)))
        .iter()
        .map(|a| a.get_info())
        .collect();
    let needle = name.to_lowercase();
    if infos
        .iter()
        .any(|i| i.name.to_lowercase().contains(&needle))
    {
        return None;
    }
    let names: Vec<String> = infos
        .iter()
        .map(|i| format!("{} ({:?})", i.name, i.backend))
        .collect();
    Some(format!(
        "'{}' names no GPU adapter; the adapters are: {}",
        crate::io::one_line(name, 80),
        if names.is_empty() {
            "none (install a Vulkan driver, e.g. mesa-vulkan-drivers)".to_string()
        } else {
            names.join(", ")
        }
    ))
}

/// The per-dimension workgroup limit of `STICKSLIP_MAX_WORKGROUPS_PER_DIM` (hidden: tests
/// and rehearsals), None when unset.
fn forced_dispatch_limit() -> Result<Option<u32>, GpuError> {
    let var = super::launch::DISPATCH_LIMIT_ENV;
    match std::env::var(var) {
        Ok(v) if !v.trim().is_empty() => v
            .trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| n >= super::launch::MIN_DISPATCH_LIMIT)
            .map(Some)
            .ok_or_else(|| GpuError::BadSetting {
                var,
                value: crate::io::one_line(&v, 40),
                min: super::launch::MIN_DISPATCH_LIMIT,
            }),
        _ => Ok(None),
    }
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

pub use super::error::DOES_NOT_FIT;

/// The size of every device buffer of `bytes`: at least 16 (bindings must not be empty),
/// whole 16-byte units ([`GpuContext::checked_size`], and the memory plans before it).
pub(crate) fn padded_size(bytes: u64) -> u64 {
    bytes.max(16).div_ceil(16) * 16
}

/// The usage of every storage buffer: bound, written and read back.
pub(crate) const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

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
    /// Bytes moved between host and device through this context (shared by its clones).
    traffic: Arc<Traffic>,
    /// A per-dimension workgroup limit below the adapter's (`with_dispatch_limit`).
    dispatch_limit: Option<u32>,
    /// Workgroups of every segmented reduction (`with_reduction_workgroups`).
    reduction_workgroups: Option<u64>,
    /// Device objects built once per key and shared by the context's clones
    /// ([`GpuContext::cached`]).
    built: Arc<Mutex<HashMap<String, Arc<dyn Any + Send + Sync>>>>,
    /// Where the run's seconds go (shared by the context's clones).
    profiler: Arc<Mutex<Profiler>>,
}

/// Leaves the phase [`GpuContext::phase`] opened when dropped.
pub struct PhaseGuard {
    profiler: Arc<Mutex<Profiler>>,
}

impl Drop for PhaseGuard {
    fn drop(&mut self) {
        if let Ok(mut p) = self.profiler.lock() {
            p.leave();
        }
    }
}

/// A compute pass begun by [`GpuContext::compute_pass`]: its dispatches are counted.
pub(crate) struct Pass<'e> {
    cp: wgpu::ComputePass<'e>,
    profiler: Arc<Mutex<Profiler>>,
    dispatches: u64,
}

impl Pass<'_> {
    pub fn set_pipeline(&mut self, pipeline: &wgpu::ComputePipeline) {
        self.cp.set_pipeline(pipeline);
    }

    pub fn set_bind_group(&mut self, index: u32, group: &wgpu::BindGroup) {
        self.cp.set_bind_group(index, group, &[]);
    }

    pub fn insert_debug_marker(&mut self, label: &str) {
        self.cp.insert_debug_marker(label);
    }

    pub fn dispatch(&mut self, launch: super::Launch) {
        self.dispatches += 1;
        launch.dispatch(&mut self.cp);
    }

    /// A dispatch whose workgroup counts a kernel wrote into `args` at `offset` (three
    /// u32): what gated work uses.
    pub fn dispatch_indirect(&mut self, args: &wgpu::Buffer, offset: u64) {
        self.dispatches += 1;
        self.cp.dispatch_workgroups_indirect(args, offset);
    }
}

impl Drop for Pass<'_> {
    fn drop(&mut self) {
        if let Ok(mut p) = self.profiler.lock() {
            p.dispatches += self.dispatches;
        }
    }
}

#[derive(Default)]
struct Traffic {
    h2d: AtomicU64,
    d2h: AtomicU64,
    /// Waits of the host on the device (read-backs and explicit waits).
    syncs: AtomicU64,
    /// Bytes of every buffer allocated through the context's helpers.
    allocated: AtomicU64,
}

/// Bytes moved between host and device since the context was created: every buffer
/// write and initialized buffer (host to device) and every read-back (device to host).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct TrafficCount {
    pub host_to_device_bytes: u64,
    pub device_to_host_bytes: u64,
    /// Every wait of the host on the device: each read-back and each explicit wait.
    pub host_syncs: u64,
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
        // Primary backends (Vulkan, Metal, DX12) unless WGPU_BACKEND names others; never a
        // silent other backend.
        let b = backends(opts);
        if b.is_empty() {
            return Err(GpuError::NoAdapter(no_adapter_message(opts)));
        }
        let named = |mut v: Vec<wgpu::Adapter>| {
            if let Some(name) = &opts.adapter_name {
                let needle = name.to_lowercase();
                v.retain(|a| a.get_info().name.to_lowercase().contains(&needle));
            }
            v
        };
        let inst = instance(b);
        let mut adapters = named(pollster::block_on(inst.enumerate_adapters(b)));
        // A name that matches nothing is an error, never a silent other adapter.
        if let (Some(name), true) = (&opts.adapter_name, adapters.is_empty()) {
            let why = adapter_name_mismatch(opts)
                .unwrap_or_else(|| format!("'{name}' names no GPU adapter"));
            return Err(GpuError::NoAdapter(format!("WGPU_ADAPTER_NAME: {why}")));
        }
        adapters.sort_by_key(rank);
        let adapter = adapters
            .into_iter()
            .next()
            .ok_or_else(|| GpuError::NoAdapter(no_adapter_message(opts)))?;
        let wanted = wgpu::Features::SHADER_F64
            | wgpu::Features::SHADER_INT64
            | wgpu::Features::SUBGROUP
            | wgpu::Features::TIMESTAMP_QUERY;
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
        .map_err(|e| GpuError::RequestDevice(e.to_string()))?;
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));
        let timing = features
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| Timing {
                set: device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("stickslip pass timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count: QUERIES,
                }),
                resolve: device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("stickslip pass timestamps resolved"),
                    size: 8 * QUERIES as u64,
                    usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                    mapped_at_creation: false,
                }),
                period: queue.get_timestamp_period() as f64 * 1e-9,
            });
        Ok(GpuContext {
            profiler: Arc::new(Mutex::new(Profiler::new(timing))),
            report: report(&adapter),
            info: adapter.get_info(),
            device,
            queue,
            features,
            limits,
            errors,
            traffic: Arc::default(),
            dispatch_limit: forced_dispatch_limit()?,
            reduction_workgroups: None,
            built: Arc::default(),
        })
    }

    /// The limits every dispatch of this context is sized by (`gpu::launch`).
    pub fn launch(&self) -> super::LaunchLimits {
        super::LaunchLimits::new(
            self.limits.max_compute_workgroups_per_dimension,
            self.dispatch_limit,
        )
    }

    /// `bytes` padded to a 16-byte multiple (at least 16: bindings must not be empty), or
    /// the error naming `label` where that exceeds the adapter's buffer size or its
    /// storage binding limit (every buffer is bound whole; H's values come in chunks that
    /// each meet it: [`crate::gpu::blocks::values_chunks`]).
    pub(crate) fn checked_size(&self, label: &str, bytes: u64) -> Result<u64, GpuError> {
        let bytes = padded_size(bytes);
        let l = &self.limits;
        let too_large = |limit: u64, what: &'static str| GpuError::BufferTooLarge {
            label: label.to_string(),
            bytes,
            limit,
            what,
            adapter: self.adapter_name().to_string(),
        };
        if bytes > l.max_buffer_size {
            return Err(too_large(l.max_buffer_size, "buffer"));
        }
        if bytes > l.max_storage_buffer_binding_size {
            return Err(too_large(
                l.max_storage_buffer_binding_size,
                "storage binding",
            ));
        }
        Ok(bytes)
    }

    /// A zeroed storage buffer (storage, copy source and destination) of at least
    /// `bytes`, labelled, its size checked first ([`GpuContext::checked_size`]): with
    /// [`GpuContext::storage_with`], the one allocation path of every device buffer that
    /// can grow with the problem.
    pub(crate) fn storage_zeroed(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        let size = self.checked_size(label, bytes)?;
        self.traffic.allocated.fetch_add(size, Ordering::Relaxed);
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: STORAGE,
            mapped_at_creation: false,
        }))
    }

    /// A storage buffer holding `data` (zero-padded to the checked size), labelled,
    /// counted as host-to-device traffic.
    pub(crate) fn storage_with(&self, label: &str, data: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        let size = self.checked_size(label, data.len() as u64)?;
        let mut padded;
        let contents = if size as usize == data.len() {
            data
        } else {
            padded = data.to_vec();
            padded.resize(size as usize, 0);
            &padded[..]
        };
        Ok(self.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage: STORAGE,
        }))
    }

    /// The policy of segmented reductions on this adapter (`gpu::launch`).
    pub fn segments(&self) -> super::SegmentPolicy {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let mut p = super::SegmentPolicy::for_device(self.info.device_type, threads);
        if let Some(w) = self.reduction_workgroups {
            p.workgroups = super::SegmentWorkgroups::Exactly(w);
        }
        p
    }

    /// What `build` makes, built the first time `key` is asked for on this device and
    /// shared afterwards (compiled pipelines: compiling the device PCG's again for every
    /// solver cost about 0.5 s on lavapipe). `key` must name everything the object depends
    /// on; a build that leaves a device error behind is an error and is not kept.
    pub(crate) fn cached<T: Any + Send + Sync>(
        &self,
        key: &str,
        build: impl FnOnce() -> T,
    ) -> Result<Arc<T>, GpuError> {
        let mut built = self.built.lock().map_err(|_| GpuError::Poisoned {
            lock: "the cache of built kernels",
        })?;
        if let Some(t) = built.get(key).and_then(|b| b.clone().downcast::<T>().ok()) {
            return Ok(t);
        }
        let t = {
            let _compiling = self.phase(Phase::PipelineCreation);
            Arc::new(build())
        };
        self.check(key)?;
        built.insert(key.to_string(), t.clone());
        Ok(t)
    }

    /// The same device with exactly `workgroups` workgroups in every segmented reduction
    /// (None: the adapter's policy), idle ones included: the sums must not change (tests).
    #[doc(hidden)]
    pub fn with_reduction_workgroups(&self, workgroups: Option<u64>) -> GpuContext {
        let mut c = self.clone();
        c.reduction_workgroups = workgroups;
        c
    }

    /// The same device with at most `limit` workgroups per dispatch dimension (None: the
    /// adapter's limit), so that small systems take the two-dimensional and grid-stride
    /// launches of large ones (tests).
    #[doc(hidden)]
    pub fn with_dispatch_limit(&self, limit: Option<u32>) -> GpuContext {
        let mut c = self.clone();
        c.dispatch_limit = limit;
        c
    }

    /// Bytes moved between host and device so far, by this context and its clones.
    pub fn traffic(&self) -> TrafficCount {
        TrafficCount {
            host_to_device_bytes: self.traffic.h2d.load(Ordering::Relaxed),
            device_to_host_bytes: self.traffic.d2h.load(Ordering::Relaxed),
            host_syncs: self.traffic.syncs.load(Ordering::Relaxed),
        }
    }

    /// Bytes of every buffer allocated through this context (and its clones) so far,
    /// staging buffers of read-backs aside: a running total, not lowered when a buffer is
    /// dropped. What tests hold a memory plan to.
    pub fn allocated_bytes(&self) -> u64 {
        self.traffic.allocated.load(Ordering::Relaxed)
    }

    /// `queue.write_buffer`, counted as host-to-device traffic.
    pub(crate) fn write_buffer(&self, buf: &wgpu::Buffer, offset: u64, data: &[u8]) {
        self.with_profiler(|p| p.moved(data.len() as u64, 0));
        let _uploading = self.phase(Phase::Uploads);
        self.traffic
            .h2d
            .fetch_add(data.len() as u64, Ordering::Relaxed);
        self.queue.write_buffer(buf, offset, data);
    }

    /// Opens `phase` on the host until the guard is dropped: the host's time meanwhile is
    /// charged to it (see [`crate::gpu::profile`]).
    pub fn phase(&self, phase: Phase) -> PhaseGuard {
        self.with_profiler(|p| p.enter(phase));
        PhaseGuard {
            profiler: self.profiler.clone(),
        }
    }

    /// Charges `seconds` spent before this context existed to `phase` (a run's set-up).
    pub fn add_phase_seconds(&self, phase: Phase, seconds: f64) {
        self.with_profiler(|p| p.add(phase, seconds));
    }

    /// The run's profile so far.
    pub fn profile(&self) -> Profile {
        self.with_profiler(|p| p.snapshot()).unwrap_or_default()
    }

    fn with_profiler<T>(&self, f: impl FnOnce(&mut Profiler) -> T) -> Option<T> {
        // A poisoned profiler only loses the profile, never the run.
        self.profiler.lock().ok().map(|mut p| f(&mut p))
    }

    /// A compute pass on `enc` labelled `label`, its work counted under `phase` (None:
    /// the phase open on the host) and timed where the adapter has timestamp queries.
    /// Every compute pass of the crate is begun here.
    pub(crate) fn compute_pass<'e>(
        &self,
        enc: &'e mut wgpu::CommandEncoder,
        label: &str,
        phase: Option<Phase>,
    ) -> Pass<'e> {
        let (query, set) = self
            .with_profiler(|p| {
                let phase = phase.unwrap_or_else(|| p.current());
                let q = p.pass(phase);
                (q, p.timing.as_ref().map(|t| t.set.clone()))
            })
            .unwrap_or((None, None));
        let timestamp_writes = match (query, &set) {
            (Some(q), Some(set)) => Some(wgpu::ComputePassTimestampWrites {
                query_set: set,
                beginning_of_pass_write_index: Some(q),
                end_of_pass_write_index: Some(q + 1),
            }),
            _ => None,
        };
        let cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes,
        });
        Pass {
            cp,
            profiler: self.profiler.clone(),
            dispatches: 0,
        }
    }

    /// `device.create_buffer_init`, counted as host-to-device traffic.
    pub(crate) fn buffer_init(&self, desc: &wgpu::util::BufferInitDescriptor) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        let bytes = desc.contents.len() as u64;
        self.with_profiler(|p| p.moved(bytes, 0));
        self.traffic.h2d.fetch_add(bytes, Ordering::Relaxed);
        self.traffic.allocated.fetch_add(bytes, Ordering::Relaxed);
        self.device.create_buffer_init(desc)
    }

    /// Counts `bytes` read back to the host.
    pub(crate) fn note_download(&self, bytes: u64) {
        self.with_profiler(|p| p.moved(0, bytes));
        self.traffic.d2h.fetch_add(bytes, Ordering::Relaxed);
    }

    /// Copies `bytes` of `buf` from `offset` to the host (through a staging buffer), waits
    /// and counts the read-back. `offset` and `bytes` are rounded to whole 4-byte words
    /// for the copy; exactly `bytes` come back.
    #[cfg_attr(not(feature = "sim"), allow(dead_code))]
    pub(crate) fn download(
        &self,
        buf: &wgpu::Buffer,
        offset: u64,
        bytes: u64,
        what: &str,
    ) -> Result<Vec<u8>, GpuError> {
        let range = ReadRange {
            buffer: buf,
            offset,
            bytes,
        };
        let mut v = self.download_many(&[range], what)?;
        Ok(v.pop().unwrap_or_default())
    }

    /// Several ranges copied into one staging buffer after the work submitted so far and
    /// read back with one wait, in order: a status read and what rides along with it.
    /// Each range as [`GpuContext::download`] takes it.
    pub(crate) fn download_many(
        &self,
        ranges: &[ReadRange],
        what: &str,
    ) -> Result<Vec<Vec<u8>>, GpuError> {
        let sizes: Vec<u64> = ranges.iter().map(|r| r.bytes.div_ceil(4) * 4).collect();
        let data: u64 = sizes.iter().sum();
        if data == 0 {
            return Ok(ranges.iter().map(|_| Vec::new()).collect());
        }
        let timed = self
            .with_profiler(|p| p.pending_queries())
            .filter(|&q| q > 0);
        let total = data + 8 * timed.unwrap_or(0) as u64;
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: total,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(what) });
        let mut at = 0;
        for (
            &ReadRange {
                buffer: buf,
                offset,
                ..
            },
            &size,
        ) in ranges.iter().zip(&sizes)
        {
            if size > 0 {
                enc.copy_buffer_to_buffer(buf, offset, &staging, at, size);
            }
            at += size;
        }
        // The timestamps of the passes since the last read ride along.
        if let Some(q) = timed {
            if let Some(t) = self
                .with_profiler(|p| {
                    p.timing
                        .as_ref()
                        .map(|t| (t.set.clone(), t.resolve.clone()))
                })
                .flatten()
            {
                enc.resolve_query_set(&t.0, 0..q, &t.1, 0);
                enc.copy_buffer_to_buffer(&t.1, 0, &staging, at, 8 * q as u64);
            }
        }
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.wait(what)?;
        rx.recv()
            .map_err(|_| read_back("mapping a read-back buffer", "the mapping was dropped"))?
            .map_err(|e| read_back("mapping a read-back buffer", e))?;
        let v = staging
            .get_mapped_range(..)
            .map_err(|e| read_back("reading a mapped buffer", e))?
            .to_vec();
        staging.unmap();
        self.note_download(total);
        self.check(what)?;
        if timed.is_some() {
            let ticks: Vec<u64> = v[data as usize..]
                .chunks_exact(8)
                .map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
                .collect();
            self.with_profiler(|p| {
                let period = p.timing.as_ref().map_or(0.0, |t| t.period);
                p.resolved(&ticks, period)
            });
        }
        let mut out = Vec::with_capacity(ranges.len());
        let mut at = 0usize;
        for (r, &size) in ranges.iter().zip(&sizes) {
            out.push(v[at..at + r.bytes as usize].to_vec());
            at += size as usize;
        }
        Ok(out)
    }

    /// Submits `enc`'s commands. A driver that blocks in the submit (one that runs the
    /// work on the host, as lavapipe does) spends that time on the device's work: the
    /// profile counts it as waiting, not as the phase open on the host.
    pub(crate) fn submit(&self, enc: wgpu::CommandEncoder) {
        let t = Instant::now();
        self.queue.submit([enc.finish()]);
        self.with_profiler(|p| p.blocked(t.elapsed().as_secs_f64()));
    }

    /// Waits until the device has finished the work submitted so far (counted as a host
    /// sync).
    pub(crate) fn wait(&self, what: &str) -> Result<(), GpuError> {
        self.traffic.syncs.fetch_add(1, Ordering::Relaxed);
        let t = Instant::now();
        let r = self
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Lost {
                what: what.to_string(),
                cause: e.to_string(),
            });
        self.with_profiler(|p| p.waited(t.elapsed().as_secs_f64()));
        r.map(|_| ())
    }

    pub fn adapter_name(&self) -> &str {
        &self.info.name
    }

    pub fn report(&self) -> &AdapterReport {
        &self.report
    }

    /// The device's memory in bytes where the backend reports it (Vulkan).
    pub fn device_memory(&self) -> Option<u64> {
        self.report.device_memory
    }

    pub fn has_f64(&self) -> bool {
        self.features.contains(wgpu::Features::SHADER_F64)
    }

    /// Whether the adapter is a CPU (lavapipe, WARP, SwiftShader).
    pub fn is_cpu(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The workgroups of a fixed-tree reduction (the device Newton loop's energy and
    /// gᵀΔx sums): 256 on a GPU, 8 per hardware thread (at least 16) on a CPU adapter,
    /// whose barriers cost a coroutine switch per workgroup.
    pub fn reduction_groups(&self) -> usize {
        if self.is_cpu() {
            8 * std::thread::available_parallelism()
                .map_or(4, |t| t.get())
                .max(2)
        } else {
            256
        }
    }

    /// The device memory in force: the device's (where the backend reports it), or
    /// `forced` where that is lower (`GpuParams::memory_limit`, tests).
    pub(crate) fn memory_in_force(&self, forced: Option<u64>) -> Option<u64> {
        match (self.device_memory(), forced) {
            (Some(d), Some(l)) => Some(d.min(l)),
            (d, l) => d.or(l),
        }
    }

    /// Refuses a system whose buffers exceed the device's memory: one line with the bytes
    /// needed and the bytes the device has. `memory` None: the device's size is unknown.
    pub(crate) fn check_fits(&self, needed: u64, memory: Option<u64>) -> Result<(), GpuError> {
        match memory {
            Some(m) if needed > m => Err(GpuError::DoesNotFit {
                need: needed,
                limit: m,
                adapter: self.info.name.clone(),
            }),
            _ => Ok(()),
        }
    }

    pub fn has_timestamps(&self) -> bool {
        self.features.contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// Fails with the first device error recorded since the last check.
    pub(crate) fn check(&self, what: &str) -> Result<(), GpuError> {
        let mut v = self.errors.lock().map_err(|_| GpuError::Poisoned {
            lock: "the device's error log",
        })?;
        if v.is_empty() {
            Ok(())
        } else {
            let msg = v.join("; ");
            v.clear();
            Err(GpuError::Validation {
                what: what.to_string(),
                message: msg,
            })
        }
    }
}

/// One range of a device buffer to read back (`GpuContext::download_many`).
#[derive(Debug, Clone, Copy)]
pub struct ReadRange<'a> {
    pub buffer: &'a wgpu::Buffer,
    /// Its first byte.
    pub offset: u64,
    /// Its length in bytes.
    pub bytes: u64,
}

/// A read-back that failed while `what` (mapping or reading a staging buffer).
fn read_back(what: &'static str, cause: impl std::fmt::Display) -> GpuError {
    GpuError::ReadBack {
        what,
        cause: cause.to_string(),
    }
}

/// Copy bandwidth of the adapter in GB/s, counting read + write bytes: a timestamped
/// `copy_buffer_to_buffer` between two 128 MiB buffers (smaller where the adapter's buffer
/// limit is lower), best of several repetitions after a warm-up copy. Without
/// TIMESTAMP_QUERY the host wall time of submit + wait is used instead.
pub fn measure_copy_bandwidth(ctx: &GpuContext) -> Result<f64, GpuError> {
    const REPS: usize = 5;
    let bytes = (128u64 << 20).min(ctx.limits.max_buffer_size / 4 * 4);
    let dev = &ctx.device;
    let mk = |label: &str, usage: wgpu::BufferUsages| {
        dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes,
            usage,
            mapped_at_creation: false,
        })
    };
    let src = mk(
        "copy bandwidth src",
        wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
    );
    let dst = mk("copy bandwidth dst", wgpu::BufferUsages::COPY_DST);
    // Touch the source so that the copy reads committed memory.
    let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("copy bandwidth init"),
    });
    enc.clear_buffer(&src, 0, None);
    ctx.queue.submit([enc.finish()]);
    let wait = || {
        dev.poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Lost {
                what: "measuring the copy bandwidth".into(),
                cause: e.to_string(),
            })
    };
    wait()?;
    let ts = ctx.has_timestamps();
    let set = ts.then(|| {
        dev.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("copy bandwidth timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: 2,
        })
    });
    let resolve = mk_small(
        dev,
        "copy bandwidth resolve",
        wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
    );
    let staging = mk_small(
        dev,
        "copy bandwidth staging",
        wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
    );
    let period = ctx.queue.get_timestamp_period() as f64;
    let mut best = f64::INFINITY;
    for rep in 0..=REPS {
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("copy bandwidth"),
        });
        // Empty compute passes bracket the copy: their timestamps need only TIMESTAMP_QUERY
        // (encoder-level timestamps would need TIMESTAMP_QUERY_INSIDE_ENCODERS).
        let mark = |enc: &mut wgpu::CommandEncoder, i: u32| {
            if let Some(s) = &set {
                enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("copy bandwidth mark"),
                    timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                        query_set: s,
                        beginning_of_pass_write_index: Some(i),
                        end_of_pass_write_index: None,
                    }),
                });
            }
        };
        mark(&mut enc, 0);
        enc.copy_buffer_to_buffer(&src, 0, &dst, 0, bytes);
        mark(&mut enc, 1);
        if let Some(s) = &set {
            enc.resolve_query_set(s, 0..2, &resolve, 0);
            enc.copy_buffer_to_buffer(&resolve, 0, &staging, 0, 16);
        }
        let t = std::time::Instant::now();
        ctx.queue.submit([enc.finish()]);
        wait()?;
        let wall = t.elapsed().as_secs_f64();
        let secs = if ts {
            let (tx, rx) = std::sync::mpsc::channel();
            staging.map_async(wgpu::MapMode::Read, 0..16, move |r| {
                let _ = tx.send(r);
            });
            wait()?;
            rx.recv()
                .map_err(|_| read_back("mapping timestamps", "the mapping was dropped"))?
                .map_err(|e| read_back("mapping timestamps", e))?;
            let v: Vec<u8> = staging
                .get_mapped_range(0..16)
                .map_err(|e| read_back("reading timestamps", e))?
                .to_vec();
            staging.unmap();
            let t0 = u64::from_le_bytes(v[0..8].try_into().expect("8 bytes"));
            let t1 = u64::from_le_bytes(v[8..16].try_into().expect("8 bytes"));
            let s = t1.saturating_sub(t0) as f64 * period * 1e-9;
            if s > 0.0 {
                s
            } else {
                wall
            }
        } else {
            wall
        };
        if rep > 0 {
            best = best.min(secs);
        }
    }
    ctx.check("measuring copy bandwidth")?;
    Ok(2.0 * bytes as f64 / best / 1e9)
}

fn mk_small(dev: &wgpu::Device, label: &str, usage: wgpu::BufferUsages) -> wgpu::Buffer {
    dev.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: 16,
        usage,
        mapped_at_creation: false,
    })
}
