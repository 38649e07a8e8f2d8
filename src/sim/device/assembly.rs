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

use super::elements::{from_bytes, to_bytes};
use super::elements::{GpuElements, TermKind, WORKGROUP};
use crate::core::sparse::BlockCsr;
use crate::gpu::blocks::{values_chunks, BlockMatrix, ValuesChunk};
use crate::gpu::kernels::{self, Access, Layout};
use crate::gpu::{GpuContext, GpuError};
use crate::sim::energy::Model;

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

/// Marks a block that is not on the diagonal (`NONE` in the shader).
const NONE: u32 = u32::MAX;

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

/// For each output item (block or node), the `src` offsets of its contributions.
#[derive(Debug, Clone, PartialEq)]
pub struct Gather {
    pub offsets: Vec<u32>,
    pub entries: Vec<u32>,
}

impl Gather {
    /// Groups (item, offset) pairs by item, keeping their order within an item.
    fn from_pairs(items: usize, pairs: &[(usize, u32)]) -> Self {
        let mut offsets = vec![0u32; items + 1];
        for &(k, _) in pairs {
            offsets[k + 1] += 1;
        }
        for k in 0..items {
            offsets[k + 1] += offsets[k];
        }
        let mut next: Vec<u32> = offsets[..items].to_vec();
        let mut entries = vec![0u32; pairs.len()];
        for &(k, v) in pairs {
            entries[next[k] as usize] = v;
            next[k] += 1;
        }
        Gather { offsets, entries }
    }
}

/// The gather lists of one element set: per block of `pattern` the offsets e·nl² +
/// a·d·nl + b·d of the element sub-blocks (a, b) adding to it, and per node the offsets
/// e·nl + a·d of the element gradient entries; both in element order, like the CPU's
/// scatter (`Model::add_potential_hessian`).
pub fn set_gathers(
    pattern: &BlockCsr,
    dim: usize,
    nodes: impl Fn(usize) -> Vec<usize>,
    len: usize,
    arity: usize,
) -> Result<(Gather, Gather), GpuError> {
    let nl = arity * dim;
    let too_big = || {
        GpuError::Unsupported(format!(
            "{len} elements of {arity} nodes exceed the assembly's u32 offsets"
        ))
    };
    if len
        .checked_mul(nl * nl)
        .is_none_or(|v| v > u32::MAX as usize)
    {
        return Err(too_big());
    }
    let mut block_pairs = Vec::with_capacity(len * arity * arity);
    let mut node_pairs = Vec::with_capacity(len * arity);
    for e in 0..len {
        let en = nodes(e);
        for (a, &na) in en.iter().enumerate() {
            for (b, &nb) in en.iter().enumerate() {
                let k = pattern.find(na, nb).ok_or_else(|| {
                    GpuError::Mismatch(format!(
                        "element {e} couples nodes {na} and {nb} outside the Hessian pattern"
                    ))
                })?;
                block_pairs.push((k, (e * nl * nl + a * dim * nl + b * dim) as u32));
            }
            node_pairs.push((na, (e * nl + a * dim) as u32));
        }
    }
    Ok((
        Gather::from_pairs(pattern.nnz_blocks(), &block_pairs),
        Gather::from_pairs(pattern.n, &node_pairs),
    ))
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

/// Device memory traffic of one product y = H x, counted from the data each reads once
/// (vectors x counted once, as if cached) and the y it writes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProductBytes {
    pub assembled: u64,
    pub matrix_free: u64,
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
        let dim = elements.kernels().dim();
        let f64 = elements.kernels().is_f64();
        if model.dim != dim {
            return Err(GpuError::Mismatch(format!(
                "the element terms are {dim}D, the model {}D",
                model.dim
            )));
        }
        let kinds = elements.kinds();
        let mut ranges = Vec::with_capacity(kinds.len());
        for t in 0..kinds.len() {
            ranges.push(
                elements
                    .term_range(t)
                    .ok_or_else(|| GpuError::Mismatch(format!("no element term {t}")))?,
            );
        }
        // A set's first chunk starts at element 0; its other chunks follow it.
        let n_sets = kinds
            .iter()
            .zip(&ranges)
            .filter(|(k, r)| matches!(k, TermKind::NeoHookean | TermKind::Springs) && r.start == 0)
            .count();
        if n_sets != model.sets.len() {
            return Err(GpuError::Mismatch(format!(
                "{n_sets} element sets on the device, {} in the model",
                model.sets.len()
            )));
        }
        let pattern = &model.pattern;
        let n = model.n_nodes;
        let nb = pattern.nnz_blocks();
        let dd = dim * dim;
        let rs = if f64 { 8u64 } else { 4 };
        let dev = &ctx.device;

        // Pipelines.
        let real = if f64 { "f64" } else { "f32" };
        let (layout, pipelines) = ASSEMBLE.pipelines(
            &ctx,
            (real, real),
            &format!("assembly {dim}D"),
            &ENTRIES,
            &[("D", dim as f64), ("WG", WORKGROUP as f64)],
        )?;

        // Buffers, limits checked first.
        let init = |label: &str, data: &[u8]| ctx.storage_with(label, data);
        let zeroed = |label: &str, bytes: u64| ctx.storage_zeroed(label, bytes);
        let u32s = |v: &[usize]| -> Result<Vec<u32>, GpuError> {
            v.iter()
                .map(|&k| {
                    u32::try_from(k).map_err(|_| {
                        GpuError::Unsupported(format!("index {k} exceeds the assembly's u32"))
                    })
                })
                .collect()
        };
        // The assembled values: one buffer per run of rows that fits one binding.
        let values = values_chunks(
            &ctx,
            &pattern.row_ptr,
            dd as u64 * rs,
            binding_limit,
            "assembly blocks",
            None,
        )?;
        let single = values.len() == 1;
        let gradient = zeroed("assembly gradient", (n * dim) as u64 * rs)?;
        let x = zeroed("assembly product input", (n * dim) as u64 * rs)?;
        let y_assembled = zeroed("assembly assembled product", (n * dim) as u64 * rs)?;
        let y_matrix_free = zeroed("assembly matrix-free product", (n * dim) as u64 * rs)?;
        let coef = init("assembly factors", &to_bytes(f64, &[1.0, 0.0]))?;
        let row_ptr = init(
            "assembly row pointers",
            bytemuck::cast_slice(&u32s(&pattern.row_ptr)?),
        )?;
        let col_idx = init(
            "assembly column indices",
            bytemuck::cast_slice(&u32s(&pattern.col_idx)?),
        )?;
        let diag_list: Vec<u32> = (0..n)
            .map(|i| {
                pattern
                    .diag_index(i)
                    .map(|k| k as u32)
                    .ok_or_else(|| GpuError::Mismatch(format!("node {i} has no diagonal block")))
            })
            .collect::<Result<_, _>>()?;
        let diag = init("assembly diagonal blocks", bytemuck::cast_slice(&diag_list))?;
        let dummy_u32 = zeroed("assembly unused indices", 16)?;
        let dummy_real = zeroed("assembly unused reals", 16)?;

        // Bind groups: one per pass.
        struct Binds<'a> {
            offsets: &'a wgpu::Buffer,
            gather: &'a wgpu::Buffer,
            src: &'a wgpu::Buffer,
            x: &'a wgpu::Buffer,
            nodes: &'a wgpu::Buffer,
            out: &'a wgpu::Buffer,
        }
        // `at`: (block_first, src_first) of a values chunk's pass.
        let pass_at = |entry: Entry,
                       count: usize,
                       first: usize,
                       at: (usize, usize),
                       nl: usize,
                       arity: usize,
                       coef_slot: u32,
                       b: Binds|
         -> Pass {
            let p = AssemblyParams {
                count: count as u32,
                nl: nl as u32,
                arity: arity as u32,
                coef_slot,
                first: first as u32,
                block_first: at.0 as u32,
                src_first: at.1 as u32,
                pad: 0,
            };
            let params = ctx.buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("{} params", ENTRIES[entry as usize])),
                contents: bytemuck::bytes_of(&p),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let bufs: [&wgpu::Buffer; 8] = [
                &params, b.offsets, b.gather, b.src, &coef, b.x, b.nodes, b.out,
            ];
            let group = kernels::bind_group(
                dev,
                &layout,
                &format!("{} bind group", ENTRIES[entry as usize]),
                &bufs,
            );
            Pass {
                entry,
                count,
                group,
                _params: params,
            }
        };
        let pass =
            |entry: Entry,
             count: usize,
             first: usize,
             nl: usize,
             arity: usize,
             coef_slot: u32,
             b: Binds|
             -> Pass { pass_at(entry, count, first, (0, 0), nl, arity, coef_slot, b) };
        // A node term's pass on the diagonal blocks of nodes `r` (the term chunk's items
        // from 0), once per values chunk holding some of them, each with its nodes'
        // diagonal blocks relative to the chunk.
        let node_block_passes = |entry: Entry,
                                 label: &str,
                                 r: &std::ops::Range<usize>,
                                 coef_slot: u32,
                                 src: &wgpu::Buffer|
         -> Result<Vec<Pass>, GpuError> {
            let mut out = Vec::new();
            for c in &values {
                let (s, e) = (r.start.max(c.rows.start), r.end.min(c.rows.end));
                if s >= e {
                    continue;
                }
                let list: Vec<u32> = diag_list
                    .get(s..e)
                    .ok_or_else(|| {
                        GpuError::Mismatch(format!("{label} covers nodes {r:?} of {n}"))
                    })?
                    .iter()
                    .map(|&k| k - c.blocks.start as u32)
                    .collect();
                let own;
                let d = if single && (s, e) == (0, n) {
                    &diag
                } else {
                    own = init(
                        &format!("{label} diagonal blocks of nodes {s}..{e}"),
                        bytemuck::cast_slice(&list),
                    )?;
                    &own
                };
                out.push(pass_at(
                    entry,
                    e - s,
                    s,
                    (c.blocks.start, s - r.start),
                    0,
                    1,
                    coef_slot,
                    Binds {
                        offsets: &dummy_u32,
                        gather: d,
                        src,
                        x: &dummy_real,
                        nodes: &dummy_u32,
                        out: &c.buffer,
                    },
                ));
            }
            Ok(out)
        };

        let mut hessian_passes = Vec::new();
        let mut gradient_passes = Vec::new();
        let mut matfree_passes = Vec::new();
        let mut matfree_nodes = Vec::new();
        let mut set_passes = Vec::new();
        let mut node_gathers = Vec::new();
        let mut mf_bytes = 0u64;
        // Index into model.sets of the current element term (advanced by each first chunk).
        let mut set: Option<usize> = None;
        for (t, (kind, r)) in kinds.iter().zip(&ranges).enumerate() {
            let (grad, hess) = elements
                .term_buffers(t)
                .ok_or_else(|| GpuError::Mismatch(format!("no element term {t}")))?;
            let len = r.len();
            match kind {
                TermKind::NeoHookean | TermKind::Springs => {
                    if r.start == 0 {
                        set = Some(set.map_or(0, |k| k + 1));
                    }
                    let k = set.ok_or_else(|| {
                        GpuError::Mismatch(format!(
                            "element term {t} starts at element {}",
                            r.start
                        ))
                    })?;
                    let s = model
                        .sets
                        .get(k)
                        .ok_or_else(|| GpuError::Mismatch(format!("no element set {k}")))?;
                    if r.end > s.len() {
                        return Err(GpuError::Mismatch(format!(
                            "element term {t} covers elements {r:?} of set {k}'s {}",
                            s.len()
                        )));
                    }
                    let arity = s.arity();
                    let nl = arity * dim;
                    // Offsets relative to the chunk's own arrays, elements in order.
                    let (bg, ng) =
                        set_gathers(pattern, dim, |e| s.nodes(r.start + e).to_vec(), len, arity)?;
                    let idx: Vec<usize> = r.clone().flat_map(|e| s.nodes(e).to_vec()).collect();
                    let label = if r.start == 0 && r.end == s.len() {
                        format!("assembly set {k}")
                    } else {
                        format!("assembly set {k} elements {}..{}", r.start, r.end)
                    };
                    let b_off = init(
                        &format!("{label} block offsets"),
                        bytemuck::cast_slice(&bg.offsets),
                    )?;
                    let b_ent = init(
                        &format!("{label} block entries"),
                        bytemuck::cast_slice(&bg.entries),
                    )?;
                    let n_off = init(
                        &format!("{label} node offsets"),
                        bytemuck::cast_slice(&ng.offsets),
                    )?;
                    let n_ent = init(
                        &format!("{label} node entries"),
                        bytemuck::cast_slice(&ng.entries),
                    )?;
                    let nodes = init(
                        &format!("{label} element nodes"),
                        bytemuck::cast_slice(&u32s(&idx)?),
                    )?;
                    node_gathers.push(NodeGather {
                        term: t,
                        offsets: n_off.clone(),
                        entries: n_ent.clone(),
                    });
                    let hess =
                        hess.ok_or_else(|| GpuError::Mismatch(format!("set {k} has no Hessian")))?;
                    // Matrix-free reads per product: every element Hessian entry once, the
                    // node lists, and each element's node indices once per its node.
                    mf_bytes += (len * nl * nl) as u64 * rs
                        + 4 * (ng.offsets.len() + ng.entries.len()) as u64
                        + 4 * (len * arity * arity) as u64;
                    set_passes.push((
                        values
                            .iter()
                            .map(|c| {
                                pass_at(
                                    Entry::BlocksAddElements,
                                    c.blocks.len(),
                                    0,
                                    (c.blocks.start, 0),
                                    nl,
                                    arity,
                                    1,
                                    Binds {
                                        offsets: &b_off,
                                        gather: &b_ent,
                                        src: hess,
                                        x: &dummy_real,
                                        nodes: &dummy_u32,
                                        out: &c.buffer,
                                    },
                                )
                            })
                            .collect::<Vec<_>>(),
                        pass(
                            Entry::GradAddElements,
                            n,
                            0,
                            nl,
                            arity,
                            1,
                            Binds {
                                offsets: &n_off,
                                gather: &n_ent,
                                src: grad,
                                x: &dummy_real,
                                nodes: &dummy_u32,
                                out: &gradient,
                            },
                        ),
                        pass(
                            Entry::MatfreeAddElements,
                            n,
                            0,
                            nl,
                            arity,
                            1,
                            Binds {
                                offsets: &n_off,
                                gather: &n_ent,
                                src: hess,
                                x: &x,
                                nodes: &nodes,
                                out: &y_matrix_free,
                            },
                        ),
                    ));
                }
                TermKind::Inertia => {
                    let hess =
                        hess.ok_or_else(|| GpuError::Mismatch("inertia has no Hessian".into()))?;
                    if r.start == 0 {
                        // The first chunk initializes every block: its nodes' diagonal
                        // blocks to their inertia, all others (including later chunks'
                        // nodes, set below) to zero.
                        let mut block_node = vec![NONE; nb];
                        for (i, &k) in diag_list[..r.end.min(n)].iter().enumerate() {
                            block_node[k as usize] = i as u32;
                        }
                        let block_node =
                            init("assembly block nodes", bytemuck::cast_slice(&block_node))?;
                        for c in &values {
                            hessian_passes.push(pass_at(
                                Entry::BlocksInit,
                                c.blocks.len(),
                                0,
                                (c.blocks.start, 0),
                                0,
                                1,
                                0,
                                Binds {
                                    offsets: &dummy_u32,
                                    gather: &block_node,
                                    src: hess,
                                    x: &dummy_real,
                                    nodes: &dummy_u32,
                                    out: &c.buffer,
                                },
                            ));
                        }
                    } else {
                        hessian_passes.extend(node_block_passes(
                            Entry::BlocksSetNodes,
                            "assembly inertia chunk",
                            r,
                            0,
                            hess,
                        )?);
                    }
                    gradient_passes.push(pass(
                        Entry::GradInit,
                        len,
                        r.start,
                        0,
                        1,
                        0,
                        Binds {
                            offsets: &dummy_u32,
                            gather: &dummy_u32,
                            src: grad,
                            x: &dummy_real,
                            nodes: &dummy_u32,
                            out: &gradient,
                        },
                    ));
                    matfree_passes.push(pass(
                        Entry::MatfreeInit,
                        len,
                        r.start,
                        0,
                        1,
                        0,
                        Binds {
                            offsets: &dummy_u32,
                            gather: &dummy_u32,
                            src: hess,
                            x: &x,
                            nodes: &dummy_u32,
                            out: &y_matrix_free,
                        },
                    ));
                    mf_bytes += (len * dd) as u64 * rs;
                }
                TermKind::Gravity => {
                    matfree_nodes.push((
                        None,
                        pass(
                            Entry::GradAddNodes,
                            len,
                            r.start,
                            0,
                            1,
                            1,
                            Binds {
                                offsets: &dummy_u32,
                                gather: &dummy_u32,
                                src: grad,
                                x: &dummy_real,
                                nodes: &dummy_u32,
                                out: &gradient,
                            },
                        ),
                    ));
                }
                TermKind::Barrier => {
                    let hess = hess
                        .ok_or_else(|| GpuError::Mismatch("the barrier has no Hessian".into()))?;
                    matfree_nodes.push((
                        Some((
                            node_block_passes(
                                Entry::BlocksAddNodes,
                                "assembly barrier chunk",
                                r,
                                1,
                                hess,
                            )?,
                            pass(
                                Entry::MatfreeAddNodes,
                                len,
                                r.start,
                                0,
                                1,
                                1,
                                Binds {
                                    offsets: &dummy_u32,
                                    gather: &dummy_u32,
                                    src: hess,
                                    x: &x,
                                    nodes: &dummy_u32,
                                    out: &y_matrix_free,
                                },
                            ),
                        )),
                        pass(
                            Entry::GradAddNodes,
                            len,
                            r.start,
                            0,
                            1,
                            1,
                            Binds {
                                offsets: &dummy_u32,
                                gather: &dummy_u32,
                                src: grad,
                                x: &dummy_real,
                                nodes: &dummy_u32,
                                out: &gradient,
                            },
                        ),
                    ));
                    mf_bytes += (len * dd) as u64 * rs;
                }
            }
        }
        if hessian_passes.is_empty() {
            return Err(GpuError::Mismatch(
                "the element terms have no inertia".into(),
            ));
        }
        // Order: inertia, the sets, then gravity and barrier.
        for (h, g, m) in set_passes {
            hessian_passes.extend(h);
            gradient_passes.push(g);
            matfree_passes.push(m);
        }
        for (hm, g) in matfree_nodes {
            if let Some((h, m)) = hm {
                hessian_passes.extend(h);
                matfree_passes.push(m);
            }
            gradient_passes.push(g);
        }
        // One product pass per values chunk, over its rows (no sum crosses a row).
        let matvec_passes: Vec<Pass> = values
            .iter()
            .map(|c| {
                pass_at(
                    Entry::MatvecBlocks,
                    c.rows.len(),
                    c.rows.start,
                    (c.blocks.start, 0),
                    0,
                    1,
                    0,
                    Binds {
                        offsets: &row_ptr,
                        gather: &col_idx,
                        src: &c.buffer,
                        x: &x,
                        nodes: &dummy_u32,
                        out: &y_assembled,
                    },
                )
            })
            .collect();
        let vec_bytes = 2 * (n * dim) as u64 * rs;
        let bytes = ProductBytes {
            assembled: (nb * dd) as u64 * rs + 4 * (nb + n + 1) as u64 + vec_bytes,
            matrix_free: mf_bytes + vec_bytes,
        };
        ctx.check("building the device assembly")?;
        Ok(GpuAssembly {
            ctx,
            dim,
            f64,
            n_nodes: n,
            row_ptr: pattern.row_ptr.clone(),
            col_idx: pattern.col_idx.clone(),
            pipelines,
            coef,
            values,
            gradient,
            x,
            y_assembled,
            y_matrix_free,
            hessian_passes,
            gradient_passes,
            matvec_passes,
            matfree_passes,
            node_gathers,
            bytes,
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
