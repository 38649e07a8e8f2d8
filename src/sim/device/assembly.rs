//! Assembly of the Newton system on the device (shaders/assemble.wgsl) from the
//! per-element arrays [`GpuElements`] leaves there, and the two ways to multiply by it:
//! the assembled block matrix, or matrix-free over the element Hessians.
//!
//! H = M + s·(Σ_sets K_e + B) in the block pattern of [`Model::pattern`] (the CPU's
//! `BlockCsr` order, both triangles), and g = M(x − x̃) + s·(Σ_sets g_e + g_gravity +
//! g_barrier), s set by [`GpuAssembly::set_scale`] (h² in a time step).
//!
//! The host builds, once per mesh, for every block the list of element sub-blocks that add
//! to it and for every node the list of element gradient entries, CSR-like, in element
//! order. Every output block or node is then one invocation summing its own list: no
//! atomics, a fixed summation order, the CPU's (inertia, the sets in order with their
//! elements in order, then gravity and barrier), so in f64 the result is the CPU
//! assembly's of the same element arrays up to the contraction of multiply-adds.
//!
//! A term [`GpuElements`] split into chunks (consecutive elements or nodes, each its own
//! buffers) gets gather lists and passes per chunk, offsets relative to the chunk's own
//! arrays; each chunk's pass continues the sums of the chunk before, so H and g are the
//! same bits as without the split. The assembled values are split too, by rows
//! ([`ValuesChunk`]): consecutive block rows whose blocks fit one storage binding, one
//! buffer each. Every pass that writes blocks runs once per values chunk with the same
//! gather lists, so every block receives the same additions in the same order: the values
//! are those of one buffer, bit for bit. Only a single row whose blocks exceed one binding
//! is refused ([`GpuError::BufferTooLarge`] naming it); the column indices, row pointers
//! and per-block gather lists (4 bytes per block or entry) stay whole and are refused by
//! name when they exceed a binding.

mod plan;

use super::elements::{from_bytes, to_bytes};
use super::elements::{GpuElements, WORKGROUP};
use crate::core::sparse::BlockCsr;
use crate::gpu::blocks::{values_chunks, BlockMatrix, ValuesChunk};
use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::{GpuContext, GpuError};
use crate::sim::energy::Model;
pub use plan::{set_gathers, Gather, ProductBytes};
use plan::{AssemblyPlan, SetPlan, TermData};

use Access::{Read as R, ReadWrite as W, Uniform as U};

/// Bind group 0 of shaders/assemble.wgsl, shared by all its entry points.
pub const ASSEMBLE: Layout = Layout {
    file: "assemble.wgsl",
    source: include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/shaders/assemble.wgsl"
    )),
    bindings: &[
        ("params", U),
        ("offsets", R),
        ("gather", R),
        ("src", R),
        ("coef", R),
        ("x", R),
        ("nodes", R),
        ("out", W),
    ],
};

/// Uniform parameters of one dispatch (mirrors `AssemblyParams` in shaders/assemble.wgsl).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct AssemblyParams {
    count: u32,
    nl: u32,
    arity: u32,
    coef_slot: u32,
    /// Node passes and the assembled product: the mesh node of the dispatch's item 0.
    first: u32,
    /// Block passes: the global index of the values chunk's block 0 (items are local).
    block_first: u32,
    /// Node-block passes: the term chunk's item of the dispatch's item 0.
    src_first: u32,
    pad: u32,
}
const _: () = assert!(std::mem::size_of::<AssemblyParams>() == 32);

/// Entry points, in the order of [`GpuAssembly`]'s pipelines.
const ENTRIES: [&str; 11] = [
    "blocks_init",
    "blocks_set_nodes",
    "blocks_add_elements",
    "blocks_add_nodes",
    "grad_init",
    "grad_add_elements",
    "grad_add_nodes",
    "matvec_blocks",
    "matfree_init",
    "matfree_add_nodes",
    "matfree_add_elements",
];

#[derive(Clone, Copy)]
enum Entry {
    BlocksInit,
    BlocksSetNodes,
    BlocksAddElements,
    BlocksAddNodes,
    GradInit,
    GradAddElements,
    GradAddNodes,
    MatvecBlocks,
    MatfreeInit,
    MatfreeAddNodes,
    MatfreeAddElements,
}

/// One dispatch: its pipeline, bind group (built once) and item count.
struct Pass {
    entry: Entry,
    count: usize,
    group: wgpu::BindGroup,
    /// Kept alive with the bind group.
    _params: wgpu::Buffer,
}

/// One element term's node gather lists on the device: per node i, `entries[offsets[i] ..
/// offsets[i + 1]]` are the offsets e·nl + a·d, in element order, of its entries in the
/// term's per-element gradient buffer ([`GpuElements::term_buffers`]).
pub struct NodeGather {
    /// The element term, in [`GpuElements::kinds`] order.
    pub term: usize,
    pub offsets: wgpu::Buffer,
    pub entries: wgpu::Buffer,
}

/// The Newton system's assembly and products on the device for one mesh: pattern, gather
/// lists and bind groups built once; per Newton iteration [`GpuAssembly::assemble`] after
/// [`GpuElements::evaluate`].
pub struct GpuAssembly {
    ctx: GpuContext,
    dim: usize,
    f64: bool,
    n_nodes: usize,
    row_ptr: Vec<usize>,
    col_idx: Vec<usize>,
    pipelines: Vec<wgpu::ComputePipeline>,
    coef: wgpu::Buffer,
    values: Vec<ValuesChunk>,
    gradient: wgpu::Buffer,
    x: wgpu::Buffer,
    y_assembled: wgpu::Buffer,
    y_matrix_free: wgpu::Buffer,
    hessian_passes: Vec<Pass>,
    gradient_passes: Vec<Pass>,
    matvec_passes: Vec<Pass>,
    matfree_passes: Vec<Pass>,
    /// The element terms' node gather lists, in term order.
    node_gathers: Vec<NodeGather>,
    /// Bytes the two products read and write per call (see [`ProductBytes`]).
    bytes: ProductBytes,
}

impl GpuAssembly {
    /// Builds the pattern, gather lists, buffers and bind groups for the terms of
    /// `elements`, which must have been built from `model`.
    pub fn new(elements: &GpuElements, model: &Model) -> Result<Self, GpuError> {
        Self::build(elements, model, None)
    }

    /// [`GpuAssembly::new`] with the assembled values' chunks capped at `binding_limit`
    /// bytes (the adapter's limits still apply), so that small meshes take the split path
    /// of large ones (tests).
    #[doc(hidden)]
    pub fn with_binding_limit(
        elements: &GpuElements,
        model: &Model,
        binding_limit: u64,
    ) -> Result<Self, GpuError> {
        Self::build(elements, model, Some(binding_limit))
    }

    fn build(
        elements: &GpuElements,
        model: &Model,
        binding_limit: Option<u64>,
    ) -> Result<Self, GpuError> {
        let ctx = elements.context().clone();
        let plan = AssemblyPlan::new(elements, model)?;
        let dim = plan.dim;
        let real = if plan.f64 { "f64" } else { "f32" };
        let (layout, pipelines) = ASSEMBLE.pipelines(
            &ctx,
            (real, real),
            &format!("assembly {dim}D"),
            &ENTRIES,
            &[("D", dim as f64), ("WG", WORKGROUP as f64)],
        )?;
        let buffers = AssemblyBuffers::allocate(&ctx, &plan, &model.pattern, binding_limit)?;
        let passes = Binder {
            ctx: &ctx,
            layout: &layout,
            buf: &buffers,
            plan: &plan,
        }
        .bind(elements)?;
        ctx.check("building the device assembly")?;
        let AssemblyBuffers {
            values,
            gradient,
            x,
            y_assembled,
            y_matrix_free,
            coef,
            ..
        } = buffers;
        Ok(GpuAssembly {
            ctx,
            dim,
            f64: plan.f64,
            n_nodes: plan.n,
            row_ptr: model.pattern.row_ptr.clone(),
            col_idx: model.pattern.col_idx.clone(),
            pipelines,
            coef,
            values,
            gradient,
            x,
            y_assembled,
            y_matrix_free,
            hessian_passes: passes.hessian,
            gradient_passes: passes.gradient,
            matvec_passes: passes.matvec,
            matfree_passes: passes.matfree,
            node_gathers: passes.node_gathers,
            bytes: plan.bytes,
        })
    }

    /// Sets s, the factor of the potential terms (h² in a time step; inertia has 1).
    pub fn set_scale(&self, scale: f64) {
        self.ctx
            .write_buffer(&self.coef, 0, &to_bytes(self.f64, &[1.0, scale]));
    }

    /// The assembled H's values: per chunk of consecutive block rows, its blocks in the
    /// pattern's order, row-major d×d each (`real`). One chunk unless the values exceed
    /// one storage binding (or the limit of [`GpuAssembly::with_binding_limit`]).
    pub fn values_chunks(&self) -> &[ValuesChunk] {
        &self.values
    }

    /// The device PCG on this assembly's H and g (its b̂ formed from g on the device).
    pub fn device_cg(&self) -> Result<crate::gpu::pcg::DeviceCg, GpuError> {
        crate::gpu::pcg::DeviceCg::new(&self.ctx, self.matrix(), Some(&self.gradient), false, false)
    }

    /// The assembled H as the device PCG reads it.
    pub fn matrix(&self) -> BlockMatrix<'_> {
        BlockMatrix {
            dim: self.dim,
            row_ptr: &self.row_ptr,
            col_idx: &self.col_idx,
            chunks: &self.values,
            f64: self.f64,
        }
    }

    /// The assembled gradient (node-major, `real`).
    pub fn gradient_buffer(&self) -> &wgpu::Buffer {
        &self.gradient
    }

    /// The element terms' node gather lists (the gradient's), in term order.
    pub fn node_gathers(&self) -> &[NodeGather] {
        &self.node_gathers
    }

    /// The block pattern: row pointers and column indices (the CPU's `BlockCsr` order).
    pub fn pattern(&self) -> (&[usize], &[usize]) {
        (&self.row_ptr, &self.col_idx)
    }

    /// The device context the assembly runs on.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// The dimension d of the blocks and nodes.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Whether the blocks and gradient are f64 (else f32).
    pub fn is_f64(&self) -> bool {
        self.f64
    }

    /// Bytes one product reads and writes, assembled and matrix-free.
    pub fn product_bytes(&self) -> ProductBytes {
        self.bytes
    }

    fn run(&self, label: &str, passes: &[&Pass]) -> Result<(), GpuError> {
        let launch = self.ctx.launch();
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        {
            let mut cp = self.ctx.compute_pass(&mut enc, label, None);
            for p in passes.iter().filter(|p| p.count > 0) {
                cp.set_pipeline(&self.pipelines[p.entry as usize]);
                cp.set_bind_group(0, &p.group);
                // Grid-stride kernels: one invocation per item up to the limits.
                cp.dispatch(launch.grid(p.count as u64, WORKGROUP));
            }
        }
        self.ctx.submit(enc);
        self.ctx.check(label)
    }

    /// Assembles H and g from the element terms' current outputs (after
    /// [`GpuElements::evaluate`]).
    pub fn assemble(&self) -> Result<(), GpuError> {
        let passes: Vec<&Pass> = self
            .hessian_passes
            .iter()
            .chain(&self.gradient_passes)
            .collect();
        self.run("assembly", &passes)
    }

    /// Writes the vector x of the products.
    pub fn set_x(&self, x: &[f64]) -> Result<(), GpuError> {
        if x.len() != self.n_nodes * self.dim {
            return Err(GpuError::Mismatch(format!(
                "the product vector has {} entries, the mesh {}",
                x.len(),
                self.n_nodes * self.dim
            )));
        }
        self.ctx.write_buffer(&self.x, 0, &to_bytes(self.f64, x));
        Ok(())
    }

    /// y = H x with the assembled blocks (after [`GpuAssembly::assemble`]).
    pub fn matvec_assembled(&self) -> Result<(), GpuError> {
        let passes: Vec<&Pass> = self.matvec_passes.iter().collect();
        self.run("assembled product", &passes)
    }

    /// y = H x from the element Hessians, H never formed.
    pub fn matvec_matrix_free(&self) -> Result<(), GpuError> {
        let passes: Vec<&Pass> = self.matfree_passes.iter().collect();
        self.run("matrix-free product", &passes)
    }

    /// Waits until the device has finished all submitted work.
    pub fn wait(&self) -> Result<(), GpuError> {
        self.ctx.wait("the assembly")?;
        self.ctx.check("waiting for the assembly")
    }

    /// The assembled H, read back (f64 whatever the device precision).
    pub fn read_matrix(&self) -> Result<BlockCsr, GpuError> {
        let dd = self.dim * self.dim;
        let mut values = Vec::with_capacity(self.col_idx.len() * dd);
        for c in &self.values {
            values.extend(self.read_reals(&c.buffer, c.blocks.len() * dd)?);
        }
        Ok(BlockCsr {
            dim: self.dim,
            n: self.n_nodes,
            row_ptr: self.row_ptr.clone(),
            col_idx: self.col_idx.clone(),
            values,
        })
    }

    /// The assembled gradient, node-major.
    pub fn read_gradient(&self) -> Result<Vec<f64>, GpuError> {
        self.read_reals(&self.gradient, self.n_nodes * self.dim)
    }

    /// The last assembled and matrix-free products.
    pub fn read_products(&self) -> Result<(Vec<f64>, Vec<f64>), GpuError> {
        let nd = self.n_nodes * self.dim;
        Ok((
            self.read_reals(&self.y_assembled, nd)?,
            self.read_reals(&self.y_matrix_free, nd)?,
        ))
    }

    fn read_reals(&self, buf: &wgpu::Buffer, len: usize) -> Result<Vec<f64>, GpuError> {
        let bytes = len as u64 * if self.f64 { 8 } else { 4 };
        let v = self
            .ctx
            .download(buf, 0, bytes, "reading back the assembly")?;
        Ok(from_bytes(self.f64, &v))
    }
}

/// The buffers every pass shares, allocated (limits checked first) in this order.
struct AssemblyBuffers {
    /// The assembled values: one buffer per run of rows that fits one binding.
    values: Vec<ValuesChunk>,
    gradient: wgpu::Buffer,
    x: wgpu::Buffer,
    y_assembled: wgpu::Buffer,
    y_matrix_free: wgpu::Buffer,
    coef: wgpu::Buffer,
    row_ptr: wgpu::Buffer,
    col_idx: wgpu::Buffer,
    diag: wgpu::Buffer,
    dummy_u32: wgpu::Buffer,
    dummy_real: wgpu::Buffer,
}

impl AssemblyBuffers {
    fn allocate(
        ctx: &GpuContext,
        plan: &AssemblyPlan,
        pattern: &BlockCsr,
        binding_limit: Option<u64>,
    ) -> Result<Self, GpuError> {
        let (n, dim, rs) = (plan.n, plan.dim, plan.rs);
        let init = |label: &str, data: &[u8]| ctx.storage_with(label, data);
        let zeroed = |label: &str, bytes: u64| ctx.storage_zeroed(label, bytes);
        let values = values_chunks(
            ctx,
            &pattern.row_ptr,
            (dim * dim) as u64 * rs,
            binding_limit,
            "assembly blocks",
            None,
        )?;
        Ok(AssemblyBuffers {
            values,
            gradient: zeroed("assembly gradient", (n * dim) as u64 * rs)?,
            x: zeroed("assembly product input", (n * dim) as u64 * rs)?,
            y_assembled: zeroed("assembly assembled product", (n * dim) as u64 * rs)?,
            y_matrix_free: zeroed("assembly matrix-free product", (n * dim) as u64 * rs)?,
            coef: init("assembly factors", &to_bytes(plan.f64, &[1.0, 0.0]))?,
            row_ptr: init("assembly row pointers", bytemuck::cast_slice(&plan.row_ptr))?,
            col_idx: init(
                "assembly column indices",
                bytemuck::cast_slice(&plan.col_idx),
            )?,
            diag: init("assembly diagonal blocks", bytemuck::cast_slice(&plan.diag))?,
            dummy_u32: zeroed("assembly unused indices", 16)?,
            dummy_real: zeroed("assembly unused reals", 16)?,
        })
    }
}

/// The items of one dispatch, [`AssemblyParams`] before the cast to u32.
struct Dispatch {
    entry: Entry,
    count: usize,
    first: usize,
    /// (block_first, src_first) of a values chunk's pass.
    at: (usize, usize),
    nl: usize,
    arity: usize,
    coef_slot: u32,
}

impl Dispatch {
    /// A pass over `count` nodes from `first`, outside the values chunks.
    fn nodes(entry: Entry, count: usize, first: usize, coef_slot: u32) -> Self {
        Dispatch {
            entry,
            count,
            first,
            at: (0, 0),
            nl: 0,
            arity: 1,
            coef_slot,
        }
    }
}

/// The buffers bound to one pass besides its parameters and the factors.
struct Binds<'a> {
    offsets: &'a wgpu::Buffer,
    gather: &'a wgpu::Buffer,
    src: &'a wgpu::Buffer,
    x: &'a wgpu::Buffer,
    nodes: &'a wgpu::Buffer,
    out: &'a wgpu::Buffer,
}

/// The passes of the four operations, each list in its order of dispatch.
struct AssemblyPasses {
    hessian: Vec<Pass>,
    gradient: Vec<Pass>,
    matvec: Vec<Pass>,
    matfree: Vec<Pass>,
    node_gathers: Vec<NodeGather>,
}

/// A set chunk's passes: on each values chunk, on the gradient, on the matrix-free product.
type SetPasses = (Vec<Pass>, Pass, Pass);

/// A node term's passes: on the blocks and the matrix-free product (the barrier's; none
/// for gravity), and on the gradient.
type NodePasses = (Option<(Vec<Pass>, Pass)>, Pass);

/// Builds the passes' parameters and bind groups over the shared buffers, uploading each
/// term's own buffers as it reaches it.
struct Binder<'a> {
    ctx: &'a GpuContext,
    layout: &'a wgpu::BindGroupLayout,
    buf: &'a AssemblyBuffers,
    plan: &'a AssemblyPlan,
}

impl Binder<'_> {
    fn pass(&self, d: Dispatch, b: Binds) -> Pass {
        let p = AssemblyParams {
            count: d.count as u32,
            nl: d.nl as u32,
            arity: d.arity as u32,
            coef_slot: d.coef_slot,
            first: d.first as u32,
            block_first: d.at.0 as u32,
            src_first: d.at.1 as u32,
            pad: 0,
        };
        let params = self.ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{} params", ENTRIES[d.entry as usize])),
            contents: bytemuck::bytes_of(&p),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let bufs: [&wgpu::Buffer; 8] = [
            &params,
            b.offsets,
            b.gather,
            b.src,
            &self.buf.coef,
            b.x,
            b.nodes,
            b.out,
        ];
        let group = kernels::bind_group(
            &self.ctx.device,
            self.layout,
            &format!("{} bind group", ENTRIES[d.entry as usize]),
            &bufs,
        );
        Pass {
            entry: d.entry,
            count: d.count,
            group,
            _params: params,
        }
    }

    /// Binds for a pass on node arrays only: no gather lists, element nodes or input.
    fn node_binds<'b>(&'b self, src: &'b wgpu::Buffer, out: &'b wgpu::Buffer) -> Binds<'b> {
        Binds {
            offsets: &self.buf.dummy_u32,
            gather: &self.buf.dummy_u32,
            src,
            x: &self.buf.dummy_real,
            nodes: &self.buf.dummy_u32,
            out,
        }
    }

    /// All passes, in the CPU's order of summation: inertia, the sets, then gravity and
    /// barrier.
    fn bind(&self, elements: &GpuElements) -> Result<AssemblyPasses, GpuError> {
        let buf = self.buf;
        let mut hessian = Vec::new();
        let mut gradient = Vec::new();
        let mut matfree = Vec::new();
        let mut matfree_nodes: Vec<NodePasses> = Vec::new();
        let mut set_passes: Vec<SetPasses> = Vec::new();
        let mut node_gathers = Vec::new();
        for term in &self.plan.terms {
            let t = term.t;
            let (grad, hess) = elements
                .term_buffers(t)
                .ok_or_else(|| GpuError::Mismatch(format!("no element term {t}")))?;
            let (r, len) = (&term.range, term.range.len());
            match &term.data {
                TermData::Set(s) => {
                    let (passes, node_gather) = self.set_passes(t, s, grad, hess)?;
                    node_gathers.push(node_gather);
                    set_passes.push(passes);
                }
                TermData::Inertia { block_node } => {
                    let hess =
                        hess.ok_or_else(|| GpuError::Mismatch("inertia has no Hessian".into()))?;
                    hessian.extend(self.inertia_block_passes(r, block_node.as_deref(), hess)?);
                    gradient.push(self.pass(
                        Dispatch::nodes(Entry::GradInit, len, r.start, 0),
                        self.node_binds(grad, &buf.gradient),
                    ));
                    matfree.push(self.pass(
                        Dispatch::nodes(Entry::MatfreeInit, len, r.start, 0),
                        Binds {
                            x: &buf.x,
                            ..self.node_binds(hess, &buf.y_matrix_free)
                        },
                    ));
                }
                TermData::Gravity => {
                    matfree_nodes.push((
                        None,
                        self.pass(
                            Dispatch::nodes(Entry::GradAddNodes, len, r.start, 1),
                            self.node_binds(grad, &buf.gradient),
                        ),
                    ));
                }
                TermData::Barrier => {
                    let hess = hess
                        .ok_or_else(|| GpuError::Mismatch("the barrier has no Hessian".into()))?;
                    let blocks = self.node_block_passes(
                        Entry::BlocksAddNodes,
                        "assembly barrier chunk",
                        r,
                        1,
                        hess,
                    )?;
                    let product = self.pass(
                        Dispatch::nodes(Entry::MatfreeAddNodes, len, r.start, 1),
                        Binds {
                            x: &buf.x,
                            ..self.node_binds(hess, &buf.y_matrix_free)
                        },
                    );
                    let grad = self.pass(
                        Dispatch::nodes(Entry::GradAddNodes, len, r.start, 1),
                        self.node_binds(grad, &buf.gradient),
                    );
                    matfree_nodes.push((Some((blocks, product)), grad));
                }
            }
        }
        if hessian.is_empty() {
            return Err(GpuError::Mismatch(
                "the element terms have no inertia".into(),
            ));
        }
        for (h, g, m) in set_passes {
            hessian.extend(h);
            gradient.push(g);
            matfree.push(m);
        }
        for (hm, g) in matfree_nodes {
            if let Some((h, m)) = hm {
                hessian.extend(h);
                matfree.push(m);
            }
            gradient.push(g);
        }
        // One product pass per values chunk, over its rows (no sum crosses a row).
        let matvec = buf
            .values
            .iter()
            .map(|c| {
                self.pass(
                    Dispatch {
                        entry: Entry::MatvecBlocks,
                        count: c.rows.len(),
                        first: c.rows.start,
                        at: (c.blocks.start, 0),
                        nl: 0,
                        arity: 1,
                        coef_slot: 0,
                    },
                    Binds {
                        offsets: &buf.row_ptr,
                        gather: &buf.col_idx,
                        src: &c.buffer,
                        x: &buf.x,
                        nodes: &buf.dummy_u32,
                        out: &buf.y_assembled,
                    },
                )
            })
            .collect();
        Ok(AssemblyPasses {
            hessian,
            gradient,
            matvec,
            matfree,
            node_gathers,
        })
    }

    /// Uploads a set chunk's gather lists and element nodes, and binds its passes.
    fn set_passes(
        &self,
        t: usize,
        s: &SetPlan,
        grad: &wgpu::Buffer,
        hess: Option<&wgpu::Buffer>,
    ) -> Result<(SetPasses, NodeGather), GpuError> {
        let (buf, label) = (self.buf, &s.label);
        let init = |suffix: &str, data: &[u32]| {
            self.ctx
                .storage_with(&format!("{label} {suffix}"), bytemuck::cast_slice(data))
        };
        let b_off = init("block offsets", &s.blocks.offsets)?;
        let b_ent = init("block entries", &s.blocks.entries)?;
        let n_off = init("node offsets", &s.nodes.offsets)?;
        let n_ent = init("node entries", &s.nodes.entries)?;
        let nodes = init("element nodes", &s.element_nodes)?;
        let node_gather = NodeGather {
            term: t,
            offsets: n_off.clone(),
            entries: n_ent.clone(),
        };
        let k = s.k;
        let hess = hess.ok_or_else(|| GpuError::Mismatch(format!("set {k} has no Hessian")))?;
        let (nl, arity) = (s.nl, s.arity);
        let blocks = buf
            .values
            .iter()
            .map(|c| {
                self.pass(
                    Dispatch {
                        entry: Entry::BlocksAddElements,
                        count: c.blocks.len(),
                        first: 0,
                        at: (c.blocks.start, 0),
                        nl,
                        arity,
                        coef_slot: 1,
                    },
                    Binds {
                        offsets: &b_off,
                        gather: &b_ent,
                        src: hess,
                        x: &buf.dummy_real,
                        nodes: &buf.dummy_u32,
                        out: &c.buffer,
                    },
                )
            })
            .collect::<Vec<_>>();
        let over_nodes = |entry| Dispatch {
            entry,
            count: self.plan.n,
            first: 0,
            at: (0, 0),
            nl,
            arity,
            coef_slot: 1,
        };
        let grad = self.pass(
            over_nodes(Entry::GradAddElements),
            Binds {
                offsets: &n_off,
                gather: &n_ent,
                src: grad,
                x: &buf.dummy_real,
                nodes: &buf.dummy_u32,
                out: &buf.gradient,
            },
        );
        let product = self.pass(
            over_nodes(Entry::MatfreeAddElements),
            Binds {
                offsets: &n_off,
                gather: &n_ent,
                src: hess,
                x: &buf.x,
                nodes: &nodes,
                out: &buf.y_matrix_free,
            },
        );
        Ok(((blocks, grad, product), node_gather))
    }

    /// The inertia chunk's block passes: the first chunk (`block_node` given) initializes
    /// every block, its nodes' diagonal blocks to their inertia and all others (including
    /// later chunks' nodes, set by theirs) to zero.
    fn inertia_block_passes(
        &self,
        r: &std::ops::Range<usize>,
        block_node: Option<&[u32]>,
        hess: &wgpu::Buffer,
    ) -> Result<Vec<Pass>, GpuError> {
        let Some(block_node) = block_node else {
            return self.node_block_passes(
                Entry::BlocksSetNodes,
                "assembly inertia chunk",
                r,
                0,
                hess,
            );
        };
        let buf = self.buf;
        let block_node = self
            .ctx
            .storage_with("assembly block nodes", bytemuck::cast_slice(block_node))?;
        Ok(buf
            .values
            .iter()
            .map(|c| {
                self.pass(
                    Dispatch {
                        entry: Entry::BlocksInit,
                        count: c.blocks.len(),
                        first: 0,
                        at: (c.blocks.start, 0),
                        nl: 0,
                        arity: 1,
                        coef_slot: 0,
                    },
                    Binds {
                        offsets: &buf.dummy_u32,
                        gather: &block_node,
                        src: hess,
                        x: &buf.dummy_real,
                        nodes: &buf.dummy_u32,
                        out: &c.buffer,
                    },
                )
            })
            .collect())
    }

    /// A node term's pass on the diagonal blocks of nodes `r` (the term chunk's items from
    /// 0), once per values chunk holding some of them, each with its nodes' diagonal
    /// blocks relative to the chunk.
    fn node_block_passes(
        &self,
        entry: Entry,
        label: &str,
        r: &std::ops::Range<usize>,
        coef_slot: u32,
        src: &wgpu::Buffer,
    ) -> Result<Vec<Pass>, GpuError> {
        let (buf, n) = (self.buf, self.plan.n);
        let single = buf.values.len() == 1;
        let mut out = Vec::new();
        for c in &buf.values {
            let (s, e) = (r.start.max(c.rows.start), r.end.min(c.rows.end));
            if s >= e {
                continue;
            }
            let list: Vec<u32> = self
                .plan
                .diag
                .get(s..e)
                .ok_or_else(|| GpuError::Mismatch(format!("{label} covers nodes {r:?} of {n}")))?
                .iter()
                .map(|&k| k - c.blocks.start as u32)
                .collect();
            let own;
            let d = if single && (s, e) == (0, n) {
                &buf.diag
            } else {
                own = self.ctx.storage_with(
                    &format!("{label} diagonal blocks of nodes {s}..{e}"),
                    bytemuck::cast_slice(&list),
                )?;
                &own
            };
            out.push(self.pass(
                Dispatch {
                    entry,
                    count: e - s,
                    first: s,
                    at: (c.blocks.start, s - r.start),
                    nl: 0,
                    arity: 1,
                    coef_slot,
                },
                Binds {
                    gather: d,
                    ..self.node_binds(src, &c.buffer)
                },
            ));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The WGSL declarations of bind group 0 are [`ASSEMBLE`]'s bindings, in order, with
    /// their access; `AssemblyParams` is four u32 in WGSL as in Rust; every entry point
    /// exists.
    #[test]
    fn layout_and_params_match_the_wgsl() {
        let size = std::mem::size_of::<AssemblyParams>();
        kernels::check::layout(&ASSEMBLE, "AssemblyParams", size, &ENTRIES);
    }

    /// Gather lists keep element order within a block and cover every (element, a, b)
    /// exactly once.
    #[test]
    fn gathers_cover_every_element_pair_in_order() {
        // Two triangles sharing the edge (1, 2).
        let els = [vec![0usize, 1, 2], vec![2, 1, 3]];
        let mut rows: Vec<Vec<usize>> = (0..4).map(|i| vec![i]).collect();
        for e in &els {
            for &a in e {
                rows[a].extend_from_slice(e);
            }
        }
        for r in rows.iter_mut() {
            r.sort_unstable();
            r.dedup();
        }
        let pattern = BlockCsr::from_pattern(2, &rows);
        let (bg, ng) = set_gathers(&pattern, 2, |e| els[e].clone(), 2, 3).expect("gathers");
        assert_eq!(bg.entries.len(), 18);
        assert_eq!(ng.entries.len(), 6);
        let k12 = pattern.find(1, 2).expect("block");
        let list = &bg.entries[bg.offsets[k12] as usize..bg.offsets[k12 + 1] as usize];
        // Element 0: (a, b) = (1, 2) → 0·36 + 1·2·6 + 2·2; element 1: (1, 0) → 36 + 12 + 0.
        assert_eq!(list, [16, 48]);
        let n2 = &ng.entries[ng.offsets[2] as usize..ng.offsets[3] as usize];
        assert_eq!(n2, [4, 6]);
    }
}
