//! Device allocation and kernel compilation: the scalar type of a kernel instance
//! (`Real`), the uniform `Params`, the `Builder` (buffers and pipelines with bookkeeping
//! and limit checks; bind-group layouts and bind groups from the one `kernels::Layout`
//! of each shader), the type-independent device data (`Shared`) and the block-plane
//! layout helpers.

use super::info::{BufferRecord, KernelRecord};
use crate::gpu::context::Binding;
use crate::gpu::kernels::{self, Layout};
use crate::gpu::{GpuContext, GpuError};
use std::collections::BTreeMap;

pub(super) use crate::gpu::kernels::Real;

/// Uniform parameters shared by every kernel (mirrors `struct Params` in
/// shaders/common.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct Params {
    pub(super) n_nodes: u32,
    pub(super) n_rot: u32,
    pub(super) n_partials: u32,
    pub(super) n_blocks: u32,
}
const _: () = assert!(std::mem::size_of::<Params>() == 16);

/// The row range of one dispatch over per-block arrays (mirrors `struct Chunk` in
/// shaders/common.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct ChunkParams {
    pub(super) row0: u32,
    pub(super) row1: u32,
    pub(super) kbase: u32,
    pub(super) flags: u32,
}
const _: () = assert!(std::mem::size_of::<ChunkParams>() == 16);
const CHUNK_FIRST: u32 = 1;
const CHUNK_LAST: u32 = 2;

/// Rows `row0..row1` whose blocks `kbase..kend` are bound as one piece of each per-block
/// array (`kbase` aligned down so that every piece's offset meets the adapter's offset
/// alignment), with the chunk's uniform.
pub(super) struct Chunk {
    pub(super) row0: u32,
    pub(super) row1: u32,
    pub(super) kbase: u64,
    pub(super) kend: u64,
    pub(super) uniform: wgpu::Buffer,
}

/// What the row chunks of a pattern must respect: per-block arrays of at most `elem`
/// bytes a block, bound from a block that is a multiple of `base_multiple`; and per-row
/// arrays (the difference form's row sums) of `row_elem` bytes a row (0: none), bound
/// from the chunk's first row, a multiple of `row_multiple`. The multiples make every
/// piece's offset a multiple of the adapter's storage offset alignment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct ChunkShape {
    pub(super) elem: u64,
    pub(super) base_multiple: u64,
    pub(super) row_elem: u64,
    pub(super) row_multiple: u64,
}

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

impl ChunkShape {
    pub(super) fn new(align: u64, elem: u64, row_elem: u64) -> Self {
        let align = align.max(1);
        // Offsets k·e with e a multiple of 4: k a multiple of align/4 suffices.
        let multiple = |e: u64| if e == 0 { 1 } else { align / gcd(align, e) };
        ChunkShape {
            elem,
            base_multiple: multiple(4),
            row_elem,
            row_multiple: multiple(row_elem),
        }
    }
}

/// Row chunks of a block pattern (`row_ptr`, n + 1 entries) whose pieces each take at most
/// `limit` bytes (see [`ChunkShape`]): (first row, end row, first bound block, end
/// block). One chunk when every array fits whole. Err: the blocks of the rows up to the
/// next allowed boundary do not fit (their number).
pub(super) fn plan_chunks(
    row_ptr: &[u32],
    shape: &ChunkShape,
    limit: u64,
) -> Result<Vec<(u32, u32, u64, u64)>, u64> {
    let n = row_ptr.len().saturating_sub(1);
    let total = u64::from(row_ptr[n]);
    if total * shape.elem <= limit && n as u64 * shape.row_elem <= limit {
        return Ok(vec![(0, n as u32, 0, total)]);
    }
    let cap = limit / shape.elem.max(1);
    let row_cap = limit.checked_div(shape.row_elem).unwrap_or(u64::MAX);
    let step = shape.row_multiple as usize;
    let mut out = Vec::new();
    let mut r0 = 0usize;
    while r0 < n {
        let kbase = u64::from(row_ptr[r0]) / shape.base_multiple * shape.base_multiple;
        let fits = |r: usize| u64::from(row_ptr[r]) - kbase <= cap && (r - r0) as u64 <= row_cap;
        // Chunk ends on multiples of the row step (or at n).
        let next = |r: usize| ((r / step + 1) * step).min(n);
        let mut r1 = r0;
        while r1 < n && fits(next(r1)) {
            r1 = next(r1);
        }
        if r1 == r0 {
            let r = next(r0);
            return Err(u64::from(row_ptr[r] - row_ptr[r0]));
        }
        out.push((r0 as u32, r1 as u32, kbase, u64::from(row_ptr[r1])));
        r0 = r1;
    }
    Ok(out)
}

/// How a per-block array is bound in one chunk: the whole buffer when there is one chunk
/// (or the array is an unused plane), else its blocks `kbase..kend` (`elem` bytes each).
pub(super) fn piece<'b>(
    buf: &'b wgpu::Buffer,
    c: &Chunk,
    elem: u64,
    whole: bool,
) -> wgpu::BufferBinding<'b> {
    if whole || c.kend == c.kbase {
        return buf.as_entire_buffer_binding();
    }
    let offset = c.kbase * elem;
    let size = ((c.kend - c.kbase) * elem).min(buf.size() - offset);
    wgpu::BufferBinding {
        buffer: buf,
        offset,
        size: std::num::NonZeroU64::new(size),
    }
}

/// One compiled entry point with the bind-group layout of its shader.
pub(super) struct Kernel {
    pub(super) name: &'static str,
    pub(super) pipeline: wgpu::ComputePipeline,
    desc: &'static Layout,
    layout: wgpu::BindGroupLayout,
}

/// A one-invocation-per-row kernel over per-block arrays: one bind group per row chunk,
/// with the chunk's row count.
pub(super) struct Chunked {
    pub(super) kernel: Kernel,
    pub(super) groups: Vec<(wgpu::BindGroup, u32)>,
}

/// Allocation and compilation with bookkeeping and limit checks.
pub(super) struct Builder<'a> {
    ctx: &'a GpuContext,
    /// The storage binding limit in force: the adapter's, or less (`GpuParams::binding_limit`).
    pub(super) binding_limit: u64,
    pub(super) buffers: Vec<BufferRecord>,
    pub(super) kernels: Vec<KernelRecord>,
    modules: BTreeMap<(String, &'static str, &'static str), wgpu::ShaderModule>,
}

pub(super) use crate::gpu::context::STORAGE;

impl<'a> Builder<'a> {
    pub(super) fn new(ctx: &'a GpuContext, binding_limit: u64) -> Self {
        Builder {
            ctx,
            binding_limit,
            buffers: Vec::new(),
            kernels: Vec::new(),
            modules: BTreeMap::new(),
        }
    }

    /// The limits a buffer of this usage meets: a storage array bound whole meets the
    /// binding limit in force, a split one (bound in row-chunk pieces) and any other
    /// buffer the buffer size alone.
    fn binding(&self, usage: wgpu::BufferUsages, split: bool) -> Binding {
        if usage.contains(wgpu::BufferUsages::STORAGE) && !split {
            Binding::Whole(self.binding_limit)
        } else {
            Binding::Pieces
        }
    }

    pub(super) fn buffer(
        &mut self,
        label: &str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<wgpu::Buffer, GpuError> {
        self.buffer_as(label, bytes, usage, false)
    }

    /// A per-block storage array bound in row-chunk pieces: only the buffer limit applies.
    pub(super) fn split_buffer(
        &mut self,
        label: &str,
        bytes: u64,
    ) -> Result<wgpu::Buffer, GpuError> {
        self.buffer_as(label, bytes, STORAGE, true)
    }

    fn buffer_as(
        &mut self,
        label: &str,
        bytes: u64,
        usage: wgpu::BufferUsages,
        split: bool,
    ) -> Result<wgpu::Buffer, GpuError> {
        let b = self
            .ctx
            .zeroed_buffer(label, bytes, usage, self.binding(usage, split))?;
        self.buffers.push(BufferRecord {
            label: label.to_string(),
            bytes: b.size(),
        });
        Ok(b)
    }

    pub(super) fn init(
        &mut self,
        label: &str,
        data: &[u8],
        usage: wgpu::BufferUsages,
    ) -> Result<wgpu::Buffer, GpuError> {
        self.init_as(label, data, usage, false)
    }

    /// A per-block storage array with contents, bound in row-chunk pieces.
    pub(super) fn split_storage(
        &mut self,
        label: &str,
        data: &[u8],
    ) -> Result<wgpu::Buffer, GpuError> {
        self.init_as(label, data, STORAGE, true)
    }

    fn init_as(
        &mut self,
        label: &str,
        data: &[u8],
        usage: wgpu::BufferUsages,
        split: bool,
    ) -> Result<wgpu::Buffer, GpuError> {
        let b = self
            .ctx
            .init_buffer(label, data, usage, self.binding(usage, split))?;
        self.buffers.push(BufferRecord {
            label: label.to_string(),
            bytes: b.size(),
        });
        Ok(b)
    }

    pub(super) fn storage(&mut self, label: &str, data: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        self.init(label, data, STORAGE)
    }

    pub(super) fn staging(&mut self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        self.buffer(
            label,
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )
    }

    /// The shape of the chunks of per-block arrays of `elem` bytes a block and per-row
    /// arrays of `row_elem` bytes a row on this adapter.
    pub(super) fn chunk_shape(ctx: &GpuContext, elem: u64, row_elem: u64) -> ChunkShape {
        let align = u64::from(ctx.limits.min_storage_buffer_offset_alignment);
        ChunkShape::new(align, elem, row_elem)
    }

    /// The row chunks of a block pattern (see [`plan_chunks`]), each with its uniform
    /// `{label}_chunk{c}`.
    pub(super) fn chunks(
        &mut self,
        label: &str,
        row_ptr: &[u32],
        elem: u64,
        row_elem: u64,
    ) -> Result<Vec<Chunk>, GpuError> {
        let shape = Self::chunk_shape(self.ctx, elem, row_elem);
        let plan = plan_chunks(row_ptr, &shape, self.binding_limit).map_err(|blocks| {
            GpuError::Unsupported(format!(
                "{blocks} blocks of consecutive rows need {} bytes in '{label}', more \
                     than one storage binding of adapter '{}' holds ({} bytes)",
                blocks * elem,
                self.ctx.info.name,
                self.binding_limit
            ))
        })?;
        let last = plan.len() - 1;
        plan.into_iter()
            .enumerate()
            .map(|(c, (row0, row1, kbase, kend))| {
                let flags =
                    if c == 0 { CHUNK_FIRST } else { 0 } | if c == last { CHUNK_LAST } else { 0 };
                let prm = ChunkParams {
                    row0,
                    row1,
                    kbase: kbase as u32,
                    flags,
                };
                let uniform = self.init(
                    &format!("{label}_chunk{c}"),
                    bytemuck::bytes_of(&prm),
                    wgpu::BufferUsages::UNIFORM,
                )?;
                Ok(Chunk {
                    row0,
                    row1,
                    kbase,
                    kend,
                    uniform,
                })
            })
            .collect()
    }

    /// Compiles `entry` of the shader `desc` for the scalar types (real, acc) with the
    /// given override constants; the bind-group layout follows `desc`.
    pub(super) fn kernel(
        &mut self,
        name: &'static str,
        desc: &'static Layout,
        real: Real,
        acc: Real,
        entry: &'static str,
        constants: &[(&str, f64)],
    ) -> Result<Kernel, GpuError> {
        let dev = &self.ctx.device;
        let (file, src) = (desc.file, desc.source);
        let key = (file.to_string(), real.name(), acc.name());
        let packed = real == Real::F32 && self.ctx.has_int64();
        if !self.modules.contains_key(&key) {
            let code = format!(
                "{}{}",
                kernels::prelude(real.name(), acc.name(), packed),
                src
            );
            let m = dev.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(&format!("{file} ({}/{})", real.name(), acc.name())),
                source: wgpu::ShaderSource::Wgsl(code.into()),
            });
            self.modules.insert(key.clone(), m);
        }
        let module = &self.modules[&key];
        let (layout, pl) = desc.layouts(dev, name);
        let label = format!("{name} ({})", real.name());
        let pipeline = kernels::pipeline(dev, &pl, module, entry, &label, constants);
        self.ctx.check(&format!("building kernel {name}"))?;
        self.kernels.push(KernelRecord {
            name: name.to_string(),
            entry: entry.to_string(),
            real: real.name().to_string(),
            acc: acc.name().to_string(),
            packed,
            constants: constants.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        });
        Ok(Kernel {
            name,
            pipeline,
            desc,
            layout,
        })
    }

    /// The bind group of `k` with each binding of its layout given by name, in any
    /// order; a name the layout lacks, a repeated one or a missing one is an error.
    pub(super) fn bind(
        &self,
        k: &Kernel,
        label: &str,
        bufs: &[(&str, &wgpu::Buffer)],
    ) -> Result<wgpu::BindGroup, GpuError> {
        let whole: Vec<(&str, wgpu::BufferBinding)> = bufs
            .iter()
            .map(|&(n, b)| (n, b.as_entire_buffer_binding()))
            .collect();
        self.bind_ranges(k, label, &whole)
    }

    /// [`Builder::bind`] with each binding a range of its buffer.
    pub(super) fn bind_ranges(
        &self,
        k: &Kernel,
        label: &str,
        bufs: &[(&str, wgpu::BufferBinding)],
    ) -> Result<wgpu::BindGroup, GpuError> {
        let desc = k.desc;
        let mut slots: Vec<Option<wgpu::BufferBinding>> = vec![None; desc.bindings.len()];
        for (name, buf) in bufs.iter().cloned() {
            let i = desc
                .bindings
                .iter()
                .position(|(n, _)| *n == name)
                .ok_or_else(|| {
                    GpuError::Device(format!("{label}: {} has no binding '{name}'", desc.file))
                })?;
            if slots[i].replace(buf).is_some() {
                return Err(GpuError::Device(format!(
                    "{label}: binding '{name}' given twice"
                )));
            }
        }
        let entries = slots
            .iter()
            .zip(desc.bindings)
            .enumerate()
            .map(|(i, (b, (name, _)))| {
                let b = b.clone().ok_or_else(|| {
                    GpuError::Device(format!(
                        "{label}: binding '{name}' of {} is missing",
                        desc.file
                    ))
                })?;
                Ok(wgpu::BindGroupEntry {
                    binding: i as u32,
                    resource: wgpu::BindingResource::Buffer(b),
                })
            })
            .collect::<Result<Vec<_>, GpuError>>()?;
        Ok(self
            .ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout: &k.layout,
                entries: &entries,
            }))
    }
}

/// The aggregates of the coarse correction (coarse.wgsl): each node's aggregate, and the
/// nodes of each aggregate as offsets and a list.
pub(super) struct AggBuffers {
    pub(super) of_node: wgpu::Buffer,
    pub(super) ptr: wgpu::Buffer,
    pub(super) nodes: wgpu::Buffer,
}

/// Type-independent data of the system on the device.
pub(super) struct Shared {
    /// Block size d.
    pub(super) dim: usize,
    pub(super) agg: Option<AggBuffers>,
    pub(super) params: wgpu::Buffer,
    /// Block pattern (assembled) or spring adjacency (matrix-free), columns packed with
    /// masks; assembled columns are bound per row chunk like the blocks.
    pub(super) row_ptr: wgpu::Buffer,
    pub(super) col: wgpu::Buffer,
    pub(super) mask: Option<wgpu::Buffer>,
    pub(super) rot_index: Option<wgpu::Buffer>,
    pub(super) rot_nodes: Option<wgpu::Buffer>,
    /// Springs: the identity pattern of the host-computed diagonal blocks (columns bound
    /// per row chunk).
    pub(super) diag_row_ptr: Option<wgpu::Buffer>,
    pub(super) diag_col: Option<wgpu::Buffer>,
    /// Bound where a kernel's specialization never touches the binding.
    pub(super) placeholder: wgpu::Buffer,
}

impl Shared {
    pub(super) fn mask_or(&self) -> &wgpu::Buffer {
        self.mask.as_ref().unwrap_or(&self.placeholder)
    }
}

/// Values per block in each of the three block planes (see matvec.wgsl): D = 3 splits the
/// row-major 3×3 block as (e0..e3), (e4..e7), (e8); D = 2 keeps the 2×2 block in plane 0.
pub(super) fn plane_widths(d: usize) -> [usize; 3] {
    if d == 3 {
        [4, 4, 1]
    } else {
        [4, 0, 0]
    }
}

/// Row-major d×d blocks → the three planes.
pub(super) fn to_planes(d: usize, values: &[f64]) -> [Vec<f64>; 3] {
    let w = plane_widths(d);
    let dd = d * d;
    let n = values.len() / dd;
    let mut out = [
        Vec::with_capacity(n * w[0]),
        Vec::with_capacity(n * w[1]),
        Vec::with_capacity(n * w[2]),
    ];
    for b in values.chunks_exact(dd) {
        let mut o = 0;
        for (p, &wp) in out.iter_mut().zip(&w) {
            p.extend_from_slice(&b[o..o + wp]);
            o += wp;
        }
    }
    out
}

/// The three planes → row-major d×d blocks.
pub(super) fn from_planes(d: usize, n_blocks: usize, planes: &[Vec<f64>; 3]) -> Vec<f64> {
    let w = plane_widths(d);
    let mut out = Vec::with_capacity(n_blocks * d * d);
    for k in 0..n_blocks {
        for (p, &wp) in planes.iter().zip(&w) {
            out.extend_from_slice(&p[k * wp..(k + 1) * wp]);
        }
    }
    out
}

/// Allocates the three block planes `{label}`, `{label}_b`, `{label}_c` (bound per row
/// chunk, so only the buffer limit applies; unused planes take one vec4).
pub(super) fn plane_buffers(
    bld: &mut Builder,
    label: &str,
    d: usize,
    n_blocks: usize,
    real: Real,
) -> Result<[wgpu::Buffer; 3], GpuError> {
    let w = plane_widths(d);
    // An unused plane still binds as one vec4<real> (32 bytes for f64).
    let bytes = |wp: usize| ((n_blocks * wp) as u64 * real.size()).max(4 * real.size());
    Ok([
        bld.split_buffer(label, bytes(w[0]))?,
        bld.split_buffer(&format!("{label}_b"), bytes(w[1]))?,
        bld.split_buffer(&format!("{label}_c"), bytes(w[2]))?,
    ])
}

pub(super) fn u32s(v: impl IntoIterator<Item = u32>) -> Vec<u8> {
    let w: Vec<u32> = v.into_iter().collect();
    bytemuck::cast_slice(&w).to_vec()
}

#[cfg(test)]
mod tests {
    use super::{plan_chunks, ChunkShape};

    /// Chunks cover the rows in order, each piece (from its aligned base) fits the limit,
    /// bases are multiples of the alignment, and one chunk is used when all fits.
    #[test]
    fn chunks_cover_the_rows_within_the_limit() {
        // Rows of 1..=20 blocks, 500 rows.
        let mut rp = vec![0u32];
        for i in 0..500u32 {
            rp.push(rp[i as usize] + 1 + (i * 7) % 20);
        }
        let total = u64::from(*rp.last().expect("rows"));
        let sh = |elem, base, row_elem, row_multiple| ChunkShape {
            elem,
            base_multiple: base,
            row_elem,
            row_multiple,
        };
        assert_eq!(
            plan_chunks(&rp, &sh(32, 64, 0, 1), total * 32),
            Ok(vec![(0, 500, 0, total)])
        );
        for (elem, limit, base, row_elem, step) in [
            (32u64, 4096u64, 64u64, 0u64, 1usize),
            (16, 1000, 1, 0, 1),
            (4, 300, 8, 0, 1),
            (16, 16384, 16, 36, 64),
            (16, 4096, 16, 36, 16),
        ] {
            let c = plan_chunks(&rp, &sh(elem, base, row_elem, step as u64), limit)
                .expect("every row fits");
            assert!(c.len() > 1);
            assert_eq!(c[0].0, 0);
            assert_eq!(c.last().map(|c| c.1), Some(500));
            for w in c.windows(2) {
                assert_eq!(w[0].1, w[1].0, "contiguous");
            }
            for &(r0, r1, kb, ke) in &c {
                assert!(r1 > r0);
                assert_eq!(kb % base, 0);
                assert!(kb <= u64::from(rp[r0 as usize]));
                assert_eq!(ke, u64::from(rp[r1 as usize]));
                assert!((ke - kb) * elem <= limit, "{kb}..{ke} × {elem} > {limit}");
                assert!(u64::from(r1 - r0) * row_elem <= limit);
                assert!(r0 as usize % step == 0, "row {r0} off the step {step}");
            }
        }
        // A 20-block row cannot fit 19 blocks' bytes.
        assert!(plan_chunks(&rp, &sh(4, 1, 0, 1), 19 * 4).is_err());
        // Offsets of 36-byte rows meet a 256-byte alignment every 64 rows.
        assert_eq!(ChunkShape::new(256, 32, 36).row_multiple, 64);
        assert_eq!(ChunkShape::new(256, 32, 36).base_multiple, 64);
        assert_eq!(ChunkShape::new(16, 16, 0).base_multiple, 4);
    }
}
