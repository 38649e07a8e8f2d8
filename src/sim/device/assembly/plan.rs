//! What [`GpuAssembly`](super::GpuAssembly) computes on the host, once per mesh, before
//! anything goes to the device: the pattern's index arrays in u32, every element set
//! chunk's gather lists and the products' memory traffic.

use crate::core::sparse::BlockCsr;
use crate::gpu::GpuError;
use crate::sim::device::elements::{GpuElements, TermKind};
use crate::sim::energy::Model;

/// Marks a block that is not on the diagonal (`NONE` in the shader).
const NONE: u32 = u32::MAX;

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

/// Device memory traffic of one product y = H x, counted from the data each reads once
/// (vectors x counted once, as if cached) and the y it writes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProductBytes {
    pub assembled: u64,
    pub matrix_free: u64,
}

/// Converts indices to the shader's u32, refusing one that does not fit.
fn u32s(v: &[usize]) -> Result<Vec<u32>, GpuError> {
    v.iter()
        .map(|&k| {
            u32::try_from(k)
                .map_err(|_| GpuError::Unsupported(format!("index {k} exceeds the assembly's u32")))
        })
        .collect()
}

/// What the host computes once per mesh from the model's pattern and the element terms,
/// before anything goes to the device.
pub(super) struct AssemblyPlan {
    pub(super) dim: usize,
    pub(super) f64: bool,
    /// Mesh nodes (block rows).
    pub(super) n: usize,
    /// Bytes per real.
    pub(super) rs: u64,
    pub(super) row_ptr: Vec<u32>,
    pub(super) col_idx: Vec<u32>,
    /// Per node, the index of its diagonal block in the pattern.
    pub(super) diag: Vec<u32>,
    /// The element terms (or chunks of one), in [`GpuElements::kinds`] order.
    pub(super) terms: Vec<TermPlan>,
    pub(super) bytes: ProductBytes,
}

/// One element term or chunk: its index in [`GpuElements::kinds`], the elements or nodes
/// it covers, and the host data its passes need.
pub(super) struct TermPlan {
    pub(super) t: usize,
    pub(super) range: std::ops::Range<usize>,
    pub(super) data: TermData,
}

pub(super) enum TermData {
    Set(SetPlan),
    /// `block_node`, in the chunk starting at node 0 only: per block, the node whose
    /// inertia initializes it ([`NONE`] for all other blocks, set to zero).
    Inertia {
        block_node: Option<Vec<u32>>,
    },
    Gravity,
    Barrier,
}

/// The gather lists of one element set's chunk, offsets relative to the chunk's arrays.
pub(super) struct SetPlan {
    /// Index into `model.sets`.
    pub(super) k: usize,
    /// Prefix of its buffers' labels.
    pub(super) label: String,
    pub(super) arity: usize,
    pub(super) nl: usize,
    pub(super) blocks: Gather,
    pub(super) nodes: Gather,
    /// The chunk's elements' nodes, element by element.
    pub(super) element_nodes: Vec<u32>,
}

impl AssemblyPlan {
    /// Checks that `elements` were built from `model` and computes the index arrays, the
    /// gather lists of every element set chunk and the products' traffic.
    pub(super) fn new(elements: &GpuElements, model: &Model) -> Result<Self, GpuError> {
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
        let row_ptr = u32s(&pattern.row_ptr)?;
        let col_idx = u32s(&pattern.col_idx)?;
        let diag: Vec<u32> = (0..n)
            .map(|i| {
                pattern
                    .diag_index(i)
                    .map(|k| k as u32)
                    .ok_or_else(|| GpuError::Mismatch(format!("node {i} has no diagonal block")))
            })
            .collect::<Result<_, _>>()?;
        let mut terms = Vec::with_capacity(kinds.len());
        let mut mf_bytes = 0u64;
        // Index into model.sets of the current element term (advanced by each first chunk).
        let mut set: Option<usize> = None;
        for (t, (kind, r)) in kinds.iter().zip(ranges).enumerate() {
            let len = r.len();
            let data = match kind {
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
                    let s = SetPlan::new(model, t, k, &r)?;
                    // Matrix-free reads per product: every element Hessian entry once, the
                    // node lists, and each element's node indices once per its node.
                    mf_bytes += (len * s.nl * s.nl) as u64 * rs
                        + 4 * (s.nodes.offsets.len() + s.nodes.entries.len()) as u64
                        + 4 * (len * s.arity * s.arity) as u64;
                    TermData::Set(s)
                }
                TermKind::Inertia => {
                    mf_bytes += (len * dd) as u64 * rs;
                    let block_node = (r.start == 0).then(|| {
                        let mut block_node = vec![NONE; nb];
                        for (i, &k) in diag[..r.end.min(n)].iter().enumerate() {
                            block_node[k as usize] = i as u32;
                        }
                        block_node
                    });
                    TermData::Inertia { block_node }
                }
                TermKind::Gravity => TermData::Gravity,
                TermKind::Barrier => {
                    mf_bytes += (len * dd) as u64 * rs;
                    TermData::Barrier
                }
            };
            terms.push(TermPlan { t, range: r, data });
        }
        let vec_bytes = 2 * (n * dim) as u64 * rs;
        let bytes = ProductBytes {
            assembled: (nb * dd) as u64 * rs + 4 * (nb + n + 1) as u64 + vec_bytes,
            matrix_free: mf_bytes + vec_bytes,
        };
        Ok(AssemblyPlan {
            dim,
            f64,
            n,
            rs,
            row_ptr,
            col_idx,
            diag,
            terms,
            bytes,
        })
    }
}

impl SetPlan {
    /// The gather lists of elements `r` of `model.sets[k]`, element term `t`.
    pub(super) fn new(
        model: &Model,
        t: usize,
        k: usize,
        r: &std::ops::Range<usize>,
    ) -> Result<Self, GpuError> {
        let dim = model.dim;
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
        // Offsets relative to the chunk's own arrays, elements in order.
        let (blocks, nodes) = set_gathers(
            &model.pattern,
            dim,
            |e| s.nodes(r.start + e).to_vec(),
            r.len(),
            arity,
        )?;
        let idx: Vec<usize> = r.clone().flat_map(|e| s.nodes(e).to_vec()).collect();
        let label = if r.start == 0 && r.end == s.len() {
            format!("assembly set {k}")
        } else {
            format!("assembly set {k} elements {}..{}", r.start, r.end)
        };
        Ok(SetPlan {
            k,
            label,
            arity,
            nl: arity * dim,
            blocks,
            nodes,
            element_nodes: u32s(&idx)?,
        })
    }
}
