//! GPU solver (wgpu). Filled in by the GPU work.
