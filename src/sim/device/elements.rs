//! Element energies, gradients and PSD-projected Hessians on the device
//! (shaders/elements.wgsl): the per-element part of a Newton step, for every energy a
//! [`Model`] can hold (neo-Hookean triangles and tetrahedra, springs), the lumped inertia,
//! gravity and the half-space barrier.
//!
//! Mesh data is uploaded once ([`GpuElements::new`]): per element set the element-to-node
//! indices (u32, nodes per element each) and the rest data (neo-Hookean: Dm⁻¹, rest
//! volume, μ, λ, law: 1 classical, 0 stable; springs: rest length, stiffness), per node
//! the lumped mass and contact
//! weight, and the gravity and half-spaces. Per evaluation only the positions (and the
//! inertia target, the half-spaces when they move) are written. Each term leaves its own
//! per-item arrays on the device, in the layout of the CPU's element buffers
//! (`energy::Model`), ready for a device assembly:
//!
//! - `energy[e]`,
//! - `gradient[e·nl + a·d + c]` (node a of the element, axis c; nl = nodes·d),
//! - `hessian[e·nl² + (a·d + c)·nl + b·d + k]` (row-major nl×nl, exactly symmetric),
//!
//! with a node term (inertia, gravity, barrier) as an element of one node; gravity has no
//! Hessian, and the barrier adds `flags[i]` = 1 where a weighted node touches or crosses a
//! half-space (its energy is +∞ there, which WGSL cannot write portably), as a set of
//! classical neo-Hookean elements does where J ≤ 0 (energy written as 0, gradient and
//! Hessian as 0).
//!
//! One storage binding is capped (`max_storage_buffer_binding_size`: 128 MiB on lavapipe,
//! 2³¹ − 1 bytes at most under wgpu), and a tetrahedron's Hessian alone is 1152 B. A term whose
//! largest per-item array would exceed the cap is split into chunks of consecutive items
//! (elements of its set, or nodes), each a term of its own with its own buffers, bind group
//! and dispatch: [`GpuElements::kinds`] lists one entry per chunk, in item order, and
//! [`GpuElements::term_range`] says which items a chunk holds. Every chunk reads the
//! positions of the whole mesh, so only the per-item arrays are split.
//!
//! The neo-Hookean Hessian is (∂F/∂x)ᵀ proj(∂²Ψ/∂F²) (∂F/∂x) with proj the clamp of the
//! analytic eigensystem (`energy::eigensystem`), computed from a signed one-sided Jacobi
//! SVD of F in the shader; values are unscaled (no h²).
//!
//! f64 needs SHADER_F64; f32 runs the same source with `real = f32`.

use crate::gpu::gate::Dispatch;
use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::{GpuContext, GpuError, Precision};
use crate::sim::energy::barrier::{Barrier, HalfSpace};
use crate::sim::energy::{ElementSet, Law, Model};

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/elements.wgsl, shared by all its entry points.
pub const ELEMENTS: Layout = Layout {
    file: "elements.wgsl",
    source: include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/shaders/elements.wgsl"
    )),
    bindings: &[
        ("params", U),
        ("x", R),
        ("nodes", R),
        ("rest", R),
        ("consts", R),
        ("x_tilde", R),
        ("energy", W),
        ("gradient", W),
        ("hessian", W),
        ("flags", W),
    ],
};

/// Uniform parameters of one dispatch (mirrors `ElementParams` in shaders/elements.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ElementParams {
    count: u32,
    project: u32,
    n_planes: u32,
    energy_only: u32,
    /// Node terms: the mesh node of the chunk's item 0.
    first: u32,
    pad: [u32; 3],
}
const _: () = assert!(std::mem::size_of::<ElementParams>() == 32);

/// Workgroup size of the element kernels.
pub const WORKGROUP: u32 = 64;

/// Reals per half-space in the constants buffer (normal xyz, offset, d̂, κ), after the
/// three gravity entries.
pub(crate) const PLANE_STRIDE: usize = 6;

/// Reals per neo-Hookean element of the rest data after its Dm⁻¹: volume, μ, λ, law.
pub(crate) const NH_REST_EXTRA: usize = 4;
const GRAVITY_SLOTS: usize = 3;

/// One energy term of a scene on the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TermKind {
    NeoHookean,
    Springs,
    Inertia,
    Gravity,
    Barrier,
}

impl TermKind {
    const ALL: [TermKind; 5] = [
        TermKind::NeoHookean,
        TermKind::Springs,
        TermKind::Inertia,
        TermKind::Gravity,
        TermKind::Barrier,
    ];

    fn entry(self) -> &'static str {
        match self {
            TermKind::NeoHookean => "neohookean_elements",
            TermKind::Springs => "spring_elements",
            TermKind::Inertia => "inertia_nodes",
            TermKind::Gravity => "gravity_nodes",
            TermKind::Barrier => "barrier_nodes",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// Arithmetic of the element kernels: f64 or f32 (the same WGSL source).
fn is_f64(precision: Precision) -> Result<bool, GpuError> {
    match precision {
        Precision::F64 => Ok(true),
        Precision::F32 => Ok(false),
        Precision::Mixed => Err(GpuError::Unsupported(
            "element kernels run in f32 or f64, not mixed".into(),
        )),
    }
}

fn real_name(f64: bool) -> &'static str {
    if f64 {
        "f64"
    } else {
        "f32"
    }
}

pub(super) fn to_bytes(f64: bool, v: &[f64]) -> Vec<u8> {
    if f64 {
        bytemuck::cast_slice(v).to_vec()
    } else {
        let w: Vec<f32> = v.iter().map(|&x| x as f32).collect();
        bytemuck::cast_slice(&w).to_vec()
    }
}

pub(super) fn from_bytes(f64: bool, b: &[u8]) -> Vec<f64> {
    if f64 {
        b.chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect()
    } else {
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
            .collect()
    }
}

/// The compiled entry points of shaders/elements.wgsl for one dimension and precision,
/// with their shared bind-group layout; built once, used by every mesh of that kind
/// (cloning shares the compiled pipelines).
#[derive(Clone)]
pub struct ElementKernels {
    dim: usize,
    f64: bool,
    layout: wgpu::BindGroupLayout,
    /// One per [`TermKind`], in its order.
    pipelines: Vec<wgpu::ComputePipeline>,
}

impl ElementKernels {
    pub fn new(ctx: &GpuContext, dim: usize, precision: Precision) -> Result<Self, GpuError> {
        let f64 = is_f64(precision)?;
        if !(dim == 2 || dim == 3) {
            return Err(GpuError::Unsupported(format!(
                "element kernels take 2D or 3D, not {dim}D"
            )));
        }
        if f64 && !ctx.has_f64() {
            return Err(GpuError::NoF64 {
                adapter: ctx.adapter_name().to_string(),
                precision: precision.name(),
            });
        }
        let real = real_name(f64);
        // Unit roundoff of the real type: exact powers of two, so exact as f32 too.
        let eps = if f64 {
            f64::EPSILON
        } else {
            f32::EPSILON as f64
        };
        let entries: Vec<&str> = TermKind::ALL.iter().map(|k| k.entry()).collect();
        let (layout, pipelines) = ELEMENTS.pipelines(
            ctx,
            (real, real),
            &format!("elements {dim}D"),
            &entries,
            &[("D", dim as f64), ("WG", WORKGROUP as f64), ("EPS", eps)],
        )?;
        ctx.check("building the element kernels")?;
        Ok(ElementKernels {
            dim,
            f64,
            layout,
            pipelines,
        })
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn is_f64(&self) -> bool {
        self.f64
    }
}

/// One term's (or chunk's) device data and outputs.
struct Term {
    kind: TermKind,
    /// First item (element of its set, or node) of the chunk.
    first: usize,
    count: usize,
    /// Gradient and Hessian entries per element (or node).
    grad_len: usize,
    hess_len: usize,
    params: wgpu::Buffer,
    group: wgpu::BindGroup,
    energy: wgpu::Buffer,
    gradient: wgpu::Buffer,
    hessian: Option<wgpu::Buffer>,
    flags: Option<wgpu::Buffer>,
    /// Element chunks: their node indices and rest data (None for node terms).
    mesh: Option<(wgpu::Buffer, wgpu::Buffer)>,
}

/// One term's outputs read back to the host (f64 whatever the device precision).
#[derive(Debug, Clone, PartialEq)]
pub struct TermValues {
    pub kind: TermKind,
    /// Per element (node terms: per node).
    pub energy: Vec<f64>,
    /// Per element nodes·d entries (node terms: d).
    pub gradient: Vec<f64>,
    /// Per element (nodes·d)² row-major (node terms: d²); empty for gravity.
    pub hessian: Vec<f64>,
    /// Barrier: 1 where a weighted node touches or crosses a half-space; classical
    /// neo-Hookean elements: 1 where J ≤ 0 (the energy is +∞ there); else empty.
    pub flags: Vec<u32>,
}

/// The element terms of one scene on the device: mesh data uploaded once, positions per
/// evaluation, per-element outputs left on the device.
pub struct GpuElements {
    ctx: GpuContext,
    kernels: ElementKernels,
    n_nodes: usize,
    n_planes: usize,
    gravity: [f64; 3],
    x: wgpu::Buffer,
    x_tilde: wgpu::Buffer,
    consts: wgpu::Buffer,
    /// Per node (lumped mass, contact weight).
    node_data: wgpu::Buffer,
    terms: Vec<Term>,
}

/// Buffers with the adapter's limits checked first (a too-large mesh is an error, not a
/// device fault): the context's one allocator ([`GpuContext::storage_with`]).
struct Alloc<'a> {
    ctx: &'a GpuContext,
}

impl Alloc<'_> {
    fn init(&self, label: &str, data: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        self.ctx.storage_with(label, data)
    }

    fn zeroed(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        self.ctx.storage_zeroed(label, bytes)
    }
}

/// What one term (or chunk) binds besides the shared positions and constants.
struct TermData<'a> {
    kind: TermKind,
    label: String,
    first: usize,
    count: usize,
    /// Element chunks: their own node indices and rest data; node chunks: none, and the
    /// node data of the whole mesh.
    nodes: Option<wgpu::Buffer>,
    rest: Option<wgpu::Buffer>,
    shared_rest: Option<&'a wgpu::Buffer>,
    grad_len: usize,
    hess_len: usize,
    /// The term writes per-item flags (the barrier; classical neo-Hookean elements).
    flagged: bool,
}

/// Splits `len` items whose largest per-item array takes `item_bytes` into consecutive
/// chunks whose arrays each fit in `limit` bytes (every buffer is padded to 16 bytes): as
/// few chunks as fit, of nearly equal length; one empty chunk when `len` is 0. None when a
/// single item does not fit.
fn plan_chunks(len: usize, item_bytes: u64, limit: u64) -> Option<Vec<std::ops::Range<usize>>> {
    let per = (limit / 16 * 16) / item_bytes.max(1);
    if len == 0 {
        return Some(std::iter::once(0..0).collect());
    }
    if per == 0 {
        return None;
    }
    let chunks = (len as u64).div_ceil(per);
    let size = (len as u64).div_ceil(chunks) as usize;
    Some(
        (0..len)
            .step_by(size)
            .map(|a| a..(a + size).min(len))
            .collect(),
    )
}

/// The buffers every term reads (positions, inertia target, constants, node data), with
/// the values they were built from.
struct SharedBuffers {
    gravity: [f64; 3],
    n_planes: usize,
    x: wgpu::Buffer,
    x_tilde: wgpu::Buffer,
    consts: wgpu::Buffer,
    node_data: wgpu::Buffer,
}

impl SharedBuffers {
    /// Checks the model against the kernels and the barrier, and uploads the mesh-wide
    /// data.
    fn allocate(
        ctx: &GpuContext,
        kernels: &ElementKernels,
        model: &Model,
        barrier: Option<(&Barrier, &[HalfSpace])>,
    ) -> Result<Self, GpuError> {
        let d = model.dim;
        if kernels.dim != d {
            return Err(GpuError::Mismatch(format!(
                "element kernels are {}D, the model {d}D",
                kernels.dim
            )));
        }
        let n = model.n_nodes;
        // Shader indices are u32: the largest is an entry of a chunk's per-element Hessian,
        // which the binding limit keeps below 2³²/4; node coordinates are checked here.
        if n.checked_mul(d).is_none_or(|v| v > u32::MAX as usize) {
            return Err(GpuError::Unsupported(format!(
                "{n} nodes exceed the element kernels' u32 indices"
            )));
        }
        let f64 = kernels.f64;
        let rs = if f64 { 8u64 } else { 4 };
        let a = Alloc { ctx };
        let x = a.zeroed("elements positions", (n * d) as u64 * rs)?;
        let x_tilde = a.zeroed("elements inertia target", (n * d) as u64 * rs)?;
        let mut gravity = [0.0; 3];
        if let Some(g) = &model.gravity {
            gravity[..d].copy_from_slice(&g[..d]);
        }
        let planes: &[HalfSpace] = barrier.map_or(&[], |b| b.1);
        let consts = a.init(
            "elements constants",
            &to_bytes(f64, &constants(&gravity, planes)),
        )?;
        let weight: Vec<f64> = match barrier {
            Some((b, _)) => {
                if b.weight.len() != n || b.dim != d {
                    return Err(GpuError::Mismatch(format!(
                        "the barrier has {} {}D nodes, the model {n} {d}D",
                        b.weight.len(),
                        b.dim
                    )));
                }
                b.weight.clone()
            }
            None => vec![0.0; n],
        };
        let node_data: Vec<f64> = (0..n).flat_map(|i| [model.mass[i], weight[i]]).collect();
        let node_data = a.init("elements node data", &to_bytes(f64, &node_data))?;
        Ok(SharedBuffers {
            gravity,
            n_planes: planes.len(),
            x,
            x_tilde,
            consts,
            node_data,
        })
    }

    /// Allocates one term's (or chunk's) parameters and outputs and binds them with its
    /// inputs and the shared buffers.
    fn bind(
        &self,
        ctx: &GpuContext,
        kernels: &ElementKernels,
        t: TermData,
    ) -> Result<Term, GpuError> {
        let rs = if kernels.f64 { 8u64 } else { 4 };
        let a = Alloc { ctx };
        let label = &t.label;
        let params = ElementParams {
            count: t.count as u32,
            project: 1,
            n_planes: self.n_planes as u32,
            energy_only: 0,
            first: t.first as u32,
            pad: [0; 3],
        };
        let params = ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{label} params")),
            contents: bytemuck::bytes_of(&params),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let energy = a.zeroed(&format!("{label} energy"), t.count as u64 * rs)?;
        let gradient = a.zeroed(
            &format!("{label} gradient"),
            (t.count * t.grad_len) as u64 * rs,
        )?;
        let hessian = (t.hess_len > 0)
            .then(|| {
                a.zeroed(
                    &format!("{label} hessian"),
                    (t.count * t.hess_len) as u64 * rs,
                )
            })
            .transpose()?;
        let flags = t
            .flagged
            .then(|| a.zeroed(&format!("{label} flags"), t.count as u64 * 4))
            .transpose()?;
        // Bindings the entry point never touches still need a buffer: small ones of
        // their own, so no buffer is bound both read-only and writable.
        let unused_read = a.zeroed(&format!("{label} unused input"), 16)?;
        let unused_hessian = a.zeroed(&format!("{label} unused hessian"), 16)?;
        let unused_flags = a.zeroed(&format!("{label} unused flags"), 16)?;
        let rest = t
            .rest
            .as_ref()
            .or(t.shared_rest)
            .ok_or_else(|| GpuError::Mismatch(format!("{label} has no rest data")))?;
        let bufs: [&wgpu::Buffer; 10] = [
            &params,
            &self.x,
            t.nodes.as_ref().unwrap_or(&unused_read),
            rest,
            &self.consts,
            &self.x_tilde,
            &energy,
            &gradient,
            hessian.as_ref().unwrap_or(&unused_hessian),
            flags.as_ref().unwrap_or(&unused_flags),
        ];
        let group = kernels::bind_group(
            &ctx.device,
            &kernels.layout,
            &format!("{label} bind group"),
            &bufs,
        );
        Ok(Term {
            kind: t.kind,
            first: t.first,
            count: t.count,
            grad_len: t.grad_len,
            hess_len: t.hess_len,
            params,
            group,
            energy,
            gradient,
            hessian,
            flags,
            mesh: t.nodes.clone().zip(t.rest.clone()),
        })
    }
}

/// Splits the element sets and node terms into chunks within the binding cap, uploading
/// each element chunk's node indices and rest data.
struct ChunkPlanner<'a> {
    ctx: &'a GpuContext,
    d: usize,
    f64: bool,
    /// Bytes per real.
    rs: u64,
    /// The cap on one chunk's arrays: the adapter's binding and buffer limits, or less.
    limit: u64,
}

impl<'a> ChunkPlanner<'a> {
    fn new(
        ctx: &'a GpuContext,
        kernels: &ElementKernels,
        d: usize,
        binding_limit: Option<u64>,
    ) -> Self {
        let l = &ctx.limits;
        let limit = l
            .max_storage_buffer_binding_size
            .min(l.max_buffer_size)
            .min(binding_limit.unwrap_or(u64::MAX));
        ChunkPlanner {
            ctx,
            d,
            f64: kernels.f64,
            rs: if kernels.f64 { 8 } else { 4 },
            limit,
        }
    }

    /// [`plan_chunks`] under the cap, with an error naming the term when one item exceeds
    /// it.
    fn ranges(
        &self,
        label: &str,
        len: usize,
        item_bytes: u64,
    ) -> Result<Vec<std::ops::Range<usize>>, GpuError> {
        plan_chunks(len, item_bytes, self.limit).ok_or_else(|| GpuError::BufferTooLarge {
            label: format!("{label} (one item)"),
            bytes: item_bytes,
            limit: self.limit,
            what: "storage binding",
            adapter: self.ctx.adapter_name().to_string(),
        })
    }

    /// Element sets: per chunk its node indices and rest data.
    fn element_chunks<'b>(&self, model: &Model) -> Result<Vec<TermData<'b>>, GpuError> {
        let (d, rs) = (self.d, self.rs);
        let a = Alloc { ctx: self.ctx };
        let mut data: Vec<TermData> = Vec::new();
        for (k, s) in model.sets.iter().enumerate() {
            let (kind, stride) = match s {
                ElementSet::NeoHookean(_) => (TermKind::NeoHookean, d * d + NH_REST_EXTRA),
                ElementSet::Springs(_) => (TermKind::Springs, 2),
            };
            let arity = s.arity();
            let nl = arity * d;
            // The largest per-element array: the Hessian, unless a tiny element has more
            // rest data or node indices than Hessian entries.
            let item_bytes = [nl * nl, nl, stride, 1]
                .iter()
                .map(|&v| v as u64 * rs)
                .chain([arity as u64 * 4])
                .max()
                .unwrap_or(0);
            let base = format!("elements set {k}");
            let ranges = self.ranges(&base, s.len(), item_bytes)?;
            for (c, r) in ranges.iter().enumerate() {
                let rest = rest_data(s, r.clone(), d, stride);
                let idx: Vec<u32> = r
                    .clone()
                    .flat_map(|e| s.nodes(e).iter().map(|&v| v as u32))
                    .collect();
                let label = chunk_label(&base, c, ranges.len());
                let nodes = a.init(&format!("{label} nodes"), bytemuck::cast_slice(&idx))?;
                let rest = a.init(&format!("{label} rest"), &to_bytes(self.f64, &rest))?;
                data.push(TermData {
                    kind,
                    label,
                    first: r.start,
                    count: r.len(),
                    nodes: Some(nodes),
                    rest: Some(rest),
                    shared_rest: None,
                    grad_len: nl,
                    hess_len: nl * nl,
                    flagged: matches!(s, ElementSet::NeoHookean(nh) if nh.law == Law::NeoHookean),
                });
            }
        }
        Ok(data)
    }

    /// Node terms: chunks of consecutive nodes, all reading the whole mesh's node data.
    fn node_chunks<'b>(
        &self,
        model: &Model,
        with_barrier: bool,
        node_data: &'b wgpu::Buffer,
    ) -> Result<Vec<TermData<'b>>, GpuError> {
        let (d, rs, n) = (self.d, self.rs, model.n_nodes);
        let mut node_terms = vec![(TermKind::Inertia, "elements inertia", d * d)];
        if model.gravity.is_some() {
            node_terms.push((TermKind::Gravity, "elements gravity", 0));
        }
        if with_barrier {
            node_terms.push((TermKind::Barrier, "elements barrier", d * d));
        }
        let mut data = Vec::new();
        for (kind, base, hess_len) in node_terms {
            let item_bytes = (hess_len.max(d) as u64 * rs).max(4);
            let ranges = self.ranges(base, n, item_bytes)?;
            for (c, r) in ranges.iter().enumerate() {
                data.push(TermData {
                    kind,
                    label: chunk_label(base, c, ranges.len()),
                    first: r.start,
                    count: r.len(),
                    nodes: None,
                    rest: None,
                    shared_rest: Some(node_data),
                    grad_len: d,
                    hess_len,
                    flagged: kind == TermKind::Barrier,
                });
            }
        }
        Ok(data)
    }
}

/// A chunk's label: the term's own when it is not split.
fn chunk_label(base: &str, c: usize, chunks: usize) -> String {
    if chunks == 1 {
        base.to_string()
    } else {
        format!("{base} chunk {c}")
    }
}

/// The rest data of elements `r` of set `s`, `stride` reals each (neo-Hookean: Dm⁻¹,
/// volume, μ, λ, law; springs: rest length, stiffness).
fn rest_data(s: &ElementSet, r: std::ops::Range<usize>, d: usize, stride: usize) -> Vec<f64> {
    let mut rest = Vec::with_capacity(r.len() * stride);
    match s {
        ElementSet::NeoHookean(nh) => {
            for e in r.clone() {
                // Rows 1..=d of the shape gradients are Dm⁻¹.
                rest.extend_from_slice(&nh.grads(e)[d..]);
                let law = match nh.law {
                    Law::NeoHookean => 1.0,
                    Law::StableNeoHookean => 0.0,
                };
                rest.extend_from_slice(&[nh.volume[e], nh.mu, nh.lambda, law]);
            }
        }
        ElementSet::Springs(sp) => {
            rest.extend(sp.rest[r.clone()].iter().flat_map(|&l| [l, sp.stiffness]))
        }
    }
    debug_assert_eq!(rest.len(), r.len() * stride);
    rest
}

impl GpuElements {
    /// Uploads the mesh data of `model` (every element set, the lumped masses and the
    /// gravity) and, with `barrier`, the contact weights and the half-spaces (their number
    /// is fixed from here on; [`GpuElements::set_planes`] moves them).
    pub fn new(
        ctx: &GpuContext,
        model: &Model,
        barrier: Option<(&Barrier, &[HalfSpace])>,
        precision: Precision,
    ) -> Result<Self, GpuError> {
        let kernels = ElementKernels::new(ctx, model.dim, precision)?;
        Self::with_kernels(ctx, &kernels, model, barrier)
    }

    /// [`GpuElements::new`] with kernels built before (of the model's dimension), so that
    /// several meshes share one compilation.
    pub fn with_kernels(
        ctx: &GpuContext,
        kernels: &ElementKernels,
        model: &Model,
        barrier: Option<(&Barrier, &[HalfSpace])>,
    ) -> Result<Self, GpuError> {
        Self::build(ctx, kernels, model, barrier, None)
    }

    /// [`GpuElements::with_kernels`] with the per-item arrays of every term capped at
    /// `binding_limit` bytes (the adapter's limits still apply), so that small meshes take
    /// the chunked path of large ones (tests). Shared buffers (positions, node data) are
    /// not capped.
    #[doc(hidden)]
    pub fn with_binding_limit(
        ctx: &GpuContext,
        kernels: &ElementKernels,
        model: &Model,
        barrier: Option<(&Barrier, &[HalfSpace])>,
        binding_limit: u64,
    ) -> Result<Self, GpuError> {
        Self::build(ctx, kernels, model, barrier, Some(binding_limit))
    }

    fn build(
        ctx: &GpuContext,
        kernels: &ElementKernels,
        model: &Model,
        barrier: Option<(&Barrier, &[HalfSpace])>,
        binding_limit: Option<u64>,
    ) -> Result<Self, GpuError> {
        let shared = SharedBuffers::allocate(ctx, kernels, model, barrier)?;
        let planner = ChunkPlanner::new(ctx, kernels, model.dim, binding_limit);
        let mut data = planner.element_chunks(model)?;
        data.extend(planner.node_chunks(model, barrier.is_some(), &shared.node_data)?);
        let mut terms = Vec::with_capacity(data.len());
        for t in data {
            terms.push(shared.bind(ctx, kernels, t)?);
        }
        ctx.check("uploading the element data")?;
        Ok(GpuElements {
            ctx: ctx.clone(),
            kernels: kernels.clone(),
            n_nodes: model.n_nodes,
            n_planes: shared.n_planes,
            gravity: shared.gravity,
            x: shared.x,
            x_tilde: shared.x_tilde,
            consts: shared.consts,
            node_data: shared.node_data,
            terms,
        })
    }

    /// The terms in evaluation order: the model's element sets, inertia, gravity (when
    /// the model has it), barrier (when given); a term split into chunks (see the module
    /// documentation) has one entry per chunk, in item order.
    pub fn kinds(&self) -> Vec<TermKind> {
        self.terms.iter().map(|t| t.kind).collect()
    }

    /// The items term `t` (in [`GpuElements::kinds`] order) holds: elements of its set, or
    /// nodes. A range starting at 0 begins a new element set or node term; the chunks of
    /// one follow it in order.
    pub fn term_range(&self, t: usize) -> Option<std::ops::Range<usize>> {
        self.terms.get(t).map(|t| t.first..t.first + t.count)
    }

    /// The device context the terms live on.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// The compiled kernels (dimension, precision) of these terms.
    pub fn kernels(&self) -> &ElementKernels {
        &self.kernels
    }

    /// Term `t`'s (in [`GpuElements::kinds`] order) per-item gradient buffer, and its
    /// Hessian buffer (None for gravity): the inputs of a device assembly.
    pub fn term_buffers(&self, t: usize) -> Option<(&wgpu::Buffer, Option<&wgpu::Buffer>)> {
        self.terms.get(t).map(|t| (&t.gradient, t.hessian.as_ref()))
    }

    /// Term `t`'s (in [`GpuElements::kinds`] order) element-to-node indices (u32, nodes per
    /// element each) and rest data (neohookean: Dm⁻¹, rest volume, μ, λ, law per element;
    /// springs: l₀, k), for the elements of its chunk; None for node terms.
    pub fn term_mesh(&self, t: usize) -> Option<(&wgpu::Buffer, &wgpu::Buffer)> {
        self.terms
            .get(t)
            .and_then(|t| t.mesh.as_ref().map(|(n, r)| (n, r)))
    }

    /// Per node (lumped mass, contact weight), `real`, for every node of the mesh.
    pub fn node_data_buffer(&self) -> &wgpu::Buffer {
        &self.node_data
    }

    /// The constants every term reads (`real`): the gravity (3 entries), then per
    /// half-space its normal (3), offset, d̂ and κ.
    pub fn constants_buffer(&self) -> &wgpu::Buffer {
        &self.consts
    }

    /// The positions buffer every term reads (node-major, `real`): a device Newton loop
    /// writes its iterates here.
    pub fn positions_buffer(&self) -> &wgpu::Buffer {
        &self.x
    }

    /// The inertia target buffer (node-major, `real`).
    pub fn inertia_target_buffer(&self) -> &wgpu::Buffer {
        &self.x_tilde
    }

    /// Term `t`'s per-item energy buffer with its item count, and its flags buffer (the
    /// barrier's contact flags; None for other terms).
    pub fn term_energy(&self, t: usize) -> Option<(&wgpu::Buffer, usize, Option<&wgpu::Buffer>)> {
        self.terms
            .get(t)
            .map(|t| (&t.energy, t.count, t.flags.as_ref()))
    }

    /// Nodes of the mesh.
    pub fn n_nodes(&self) -> usize {
        self.n_nodes
    }

    /// Half-spaces of the barrier (0 without one).
    pub fn n_planes(&self) -> usize {
        self.n_planes
    }

    fn write_nodal(&self, buf: &wgpu::Buffer, v: &[f64], what: &str) -> Result<(), GpuError> {
        let want = self.n_nodes * self.kernels.dim;
        if v.len() != want {
            return Err(GpuError::Mismatch(format!(
                "{what} has {} entries, the mesh {want}",
                v.len()
            )));
        }
        self.ctx
            .write_buffer(buf, 0, &to_bytes(self.kernels.f64, v));
        Ok(())
    }

    /// Node positions x (node-major, d per node).
    pub fn set_positions(&self, x: &[f64]) -> Result<(), GpuError> {
        self.write_nodal(&self.x, x, "positions")
    }

    /// The inertia target x̃ (node-major).
    pub fn set_inertia_target(&self, x_tilde: &[f64]) -> Result<(), GpuError> {
        self.write_nodal(&self.x_tilde, x_tilde, "inertia target")
    }

    /// Moves the half-spaces (as many as given to [`GpuElements::new`]).
    pub fn set_planes(&self, planes: &[HalfSpace]) -> Result<(), GpuError> {
        if planes.len() != self.n_planes {
            return Err(GpuError::Mismatch(format!(
                "{} half-spaces given, the barrier was built with {}",
                planes.len(),
                self.n_planes
            )));
        }
        self.ctx.write_buffer(
            &self.consts,
            0,
            &to_bytes(self.kernels.f64, &constants(&self.gravity, planes)),
        );
        Ok(())
    }

    /// Dispatches every term at the current positions; with `project` the element
    /// Hessians are PSD-projected (the neo-Hookean ∂²Ψ/∂F² eigenvalues and the springs'
    /// transverse stiffness clamped at zero), else exact.
    pub fn evaluate(&self, project: bool) -> Result<(), GpuError> {
        self.dispatch(project, false)
    }

    /// Dispatches every term for its per-item energies (and the barrier's flags) only, the
    /// gradients and Hessians left as they were: what a line search needs.
    pub fn evaluate_energy(&self) -> Result<(), GpuError> {
        self.dispatch(true, true)
    }

    fn dispatch(&self, project: bool, energy_only: bool) -> Result<(), GpuError> {
        let work = self.dispatches(project, energy_only);
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("elements evaluate"),
            });
        {
            let mut pass = self.ctx.compute_pass(&mut enc, "elements pass", None);
            for d in work {
                pass.set_pipeline(&d.pipeline);
                pass.set_bind_group(0, &d.group);
                pass.dispatch(d.launch);
            }
        }
        self.ctx.submit(enc);
        self.ctx.check("evaluating the element terms")
    }

    /// The dispatches of an evaluation (its parameters written for the next submit), for
    /// a caller that records them itself; [`GpuElements::evaluate_energy`]'s with
    /// `energy_only`.
    pub fn dispatches(&self, project: bool, energy_only: bool) -> Vec<Dispatch> {
        let launch = self.ctx.launch();
        for t in &self.terms {
            let p = ElementParams {
                count: t.count as u32,
                project: project as u32,
                n_planes: self.n_planes as u32,
                energy_only: energy_only as u32,
                first: t.first as u32,
                pad: [0; 3],
            };
            self.ctx.write_buffer(&t.params, 0, bytemuck::bytes_of(&p));
        }
        self.terms
            .iter()
            .filter(|t| t.count > 0)
            .map(|t| Dispatch {
                pipeline: self.kernels.pipelines[t.kind.index()].clone(),
                group: t.group.clone(),
                // Grid-stride kernels: one invocation per element or node up to the limits.
                launch: launch.grid(t.count as u64, WORKGROUP),
            })
            .collect()
    }

    /// Reads every term's outputs back (for tests and inspection; a device Newton loop
    /// keeps them on the device).
    pub fn read(&self) -> Result<Vec<TermValues>, GpuError> {
        let f64 = self.kernels.f64;
        let rs = if f64 { 8u64 } else { 4 };
        let mut out = Vec::with_capacity(self.terms.len());
        for t in &self.terms {
            let energy = from_bytes(f64, &self.download(&t.energy, t.count as u64 * rs)?);
            let gradient = from_bytes(
                f64,
                &self.download(&t.gradient, (t.count * t.grad_len) as u64 * rs)?,
            );
            let hessian = match &t.hessian {
                Some(h) => from_bytes(f64, &self.download(h, (t.count * t.hess_len) as u64 * rs)?),
                None => Vec::new(),
            };
            let flags = match &t.flags {
                Some(fl) => bytemuck::pod_collect_to_vec(&self.download(fl, t.count as u64 * 4)?),
                None => Vec::new(),
            };
            out.push(TermValues {
                kind: t.kind,
                energy,
                gradient,
                hessian,
                flags,
            });
        }
        Ok(out)
    }

    /// Copies the first `bytes` of `buf` to the host.
    fn download(&self, buf: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>, GpuError> {
        self.ctx
            .download(buf, 0, bytes, "reading back the element terms")
    }
}

/// The constants buffer: gravity (three entries), then per half-space its normal, offset,
/// d̂ and κ.
fn constants(gravity: &[f64; 3], planes: &[HalfSpace]) -> Vec<f64> {
    let mut c = Vec::with_capacity(GRAVITY_SLOTS + PLANE_STRIDE * planes.len());
    c.extend_from_slice(gravity);
    for p in planes {
        c.extend_from_slice(&p.normal);
        c.extend_from_slice(&[p.offset, p.dhat, p.kappa]);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The WGSL declarations of bind group 0 are [`ELEMENTS`]' bindings, in order, with
    /// their access; and `ElementParams` is four u32 in WGSL as in Rust.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let entries: Vec<&str> = TermKind::ALL.iter().map(|k| k.entry()).collect();
        let size = std::mem::size_of::<ElementParams>();
        let m = kernels::check::layout(&ELEMENTS, "ElementParams", size, &entries);
        assert_eq!(
            kernels::check::struct_members(&m, "ElementParams"),
            [
                "count",
                "project",
                "n_planes",
                "energy_only",
                "first",
                "_pad0",
                "_pad1",
                "_pad2"
            ]
        );
    }

    /// Chunks cover the items in order, each within the limit after padding, as few as
    /// fit; a single item over the limit is refused.
    #[test]
    fn chunks_cover_the_items_within_the_limit() {
        for (len, item, limit) in [
            (10usize, 100u64, 400u64),
            (7, 48, 160),
            (1000, 1152, 1 << 17),
            (5, 8, 1 << 20),
        ] {
            let r = plan_chunks(len, item, limit).expect("fits");
            let fit = (limit / 16 * 16) / item;
            assert_eq!(
                r.len() as u64,
                (len as u64).div_ceil(fit),
                "{len} items of {item} B in {limit} B"
            );
            assert_eq!(r[0].start, 0);
            assert_eq!(r.last().map(|c| c.end), Some(len));
            for w in r.windows(2) {
                assert_eq!(w[0].end, w[1].start);
            }
            for c in &r {
                assert!(!c.is_empty());
                assert!((c.len() as u64 * item).div_ceil(16) * 16 <= limit);
            }
        }
        let empty = plan_chunks(0, 1152, 1024).expect("no items fit");
        assert_eq!((empty.len(), empty[0].clone()), (1, 0..0));
        assert_eq!(plan_chunks(3, 1152, 1151), None);
    }
}
