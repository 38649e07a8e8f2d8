//! Fill-reducing orderings of Ĥ for the sparse Cholesky oracle.
//!
//! Two orderings: faer's approximate minimum degree (AMD) on the scalar pattern, and
//! nested dissection (METIS's `METIS_NodeND`, built from the vendored METIS source) on the
//! NODE graph of H, expanded to DOFs node by node. The node graph is d times smaller
//! than the scalar one, and ordering a node's components together keeps the d×d blocks
//! inside one supernode. On the generated 3D meshes nested dissection gives about half of
//! AMD's nnz(L) and a third to a half of its numeric time, on 2D meshes from a few thousand
//! nodes 15–25% less nnz(L) (BENCHMARKS.md, "Cholesky orderings"); below that AMD is as
//! good and cheaper to compute.
//!
//! [`CholeskyOrdering::Auto`] computes both on graphs of [`AUTO_MIN_NODES`] nodes or more
//! and keeps the one whose factor takes fewer flops ([`auto_tries_nested_dissection`]).

pub use crate::solve::options::CholeskyOrdering;
use std::sync::Mutex;

/// `Auto` computes nested dissection too from this many nodes with a free component on.
pub const AUTO_MIN_NODES: usize = 2_000;

/// The `Auto` rule, part one: whether to compute nested dissection besides AMD (a graph
/// of at least [`AUTO_MIN_NODES`] nodes with a free component). Part two, in the oracle:
/// of the orderings computed, keep the one whose factor needs fewer flops, counted as AMD
/// counts them (d + d(d + 1)/2 for a column with d off-diagonal entries; AMD's from its
/// own estimate, nested dissection's from exact column counts), AMD on a tie. Below the
/// size both orderings factor in milliseconds and AMD alone is cheaper to compute.
pub fn auto_tries_nested_dissection(g: &NodeGraph) -> bool {
    g.free_nodes.len() >= AUTO_MIN_NODES
}

/// The graph of the nodes with at least one free component: an edge where H has a block
/// between two such nodes. Nodes with every component constrained are isolated in Ĥ
/// (their rows hold only the diagonal D) and stay out of it.
#[derive(Debug, Clone)]
pub struct NodeGraph {
    /// The original node of each graph vertex, ascending.
    pub free_nodes: Vec<usize>,
    /// METIS's CSR adjacency (no self-loops, symmetric).
    pub xadj: Vec<i32>,
    pub adjncy: Vec<i32>,
    /// Free components per vertex: separators balance DOFs, not nodes.
    pub vwgt: Vec<i32>,
}

impl NodeGraph {
    /// Builds the graph from H's block pattern (both triangles stored) and the masks.
    /// Fails only when the graph exceeds METIS's 32-bit indices.
    pub fn new(
        dim: usize,
        row_ptr: &[usize],
        col_idx: &[usize],
        mask: &[u8],
    ) -> Result<Self, String> {
        let n = mask.len();
        let full = (1u8 << dim) - 1;
        let mut vertex = vec![usize::MAX; n];
        let mut free_nodes = Vec::new();
        for (i, &m) in mask.iter().enumerate() {
            if m & full != full {
                vertex[i] = free_nodes.len();
                free_nodes.push(i);
            }
        }
        let too_big = |what: &str, v: usize| {
            format!("nested dissection: {what} = {v} exceeds METIS's 32-bit indices")
        };
        i32::try_from(free_nodes.len()).map_err(|_| too_big("nodes", free_nodes.len()))?;
        let mut xadj = Vec::with_capacity(free_nodes.len() + 1);
        let mut adjncy = Vec::new();
        let mut vwgt = Vec::with_capacity(free_nodes.len());
        xadj.push(0i32);
        for &i in &free_nodes {
            for &j in &col_idx[row_ptr[i]..row_ptr[i + 1]] {
                let v = vertex[j];
                if j != i && v != usize::MAX {
                    // v < free_nodes.len(), which fits i32 (checked above).
                    adjncy.push(v as i32);
                }
            }
            let len = i32::try_from(adjncy.len()).map_err(|_| too_big("edges", adjncy.len()))?;
            xadj.push(len);
            vwgt.push((dim as u32 - (mask[i] & full).count_ones()) as i32);
        }
        Ok(NodeGraph {
            free_nodes,
            xadj,
            adjncy,
            vwgt,
        })
    }
}

/// METIS keeps per-call state behind signal handlers that it installs and removes around
/// each call; one call at a time keeps two threads from undoing each other's handlers.
pub(crate) static METIS_LOCK: Mutex<()> = Mutex::new(());

/// Nested dissection of the node graph, expanded to DOFs: the forward permutation
/// (`perm[new] = old` DOF) of length `dim · n`. Fully constrained nodes come first (they
/// are isolated and create no fill); every node's components stay consecutive.
pub fn nested_dissection(g: &NodeGraph, dim: usize, n: usize) -> Result<Vec<usize>, String> {
    let nv = g.free_nodes.len();
    let mut order = Vec::with_capacity(nv);
    if nv > 0 {
        let mut nvtxs = nv as i32;
        let mut xadj = g.xadj.clone();
        let mut adjncy = g.adjncy.clone();
        let mut vwgt = g.vwgt.clone();
        let mut options = [0 as metis_sys::idx_t; metis_sys::METIS_NOPTIONS as usize];
        let mut perm = vec![0 as metis_sys::idx_t; nv];
        let mut iperm = vec![0 as metis_sys::idx_t; nv];
        let status = {
            // A poisoned lock only means another call panicked; METIS holds no state.
            let _guard = METIS_LOCK.lock().unwrap_or_else(|p| p.into_inner());
            // SAFETY: every array has the length METIS_NodeND reads or writes: xadj nv+1,
            // adjncy xadj[nv], vwgt nv, options METIS_NOPTIONS, perm and iperm nv. The
            // graph is symmetric without self-loops (built from H's symmetric pattern).
            unsafe {
                metis_sys::METIS_SetDefaultOptions(options.as_mut_ptr());
                metis_sys::METIS_NodeND(
                    &mut nvtxs,
                    xadj.as_mut_ptr(),
                    adjncy.as_mut_ptr(),
                    vwgt.as_mut_ptr(),
                    options.as_mut_ptr(),
                    perm.as_mut_ptr(),
                    iperm.as_mut_ptr(),
                )
            }
        };
        if status != metis_sys::rstatus_et_METIS_OK {
            return Err(format!("nested dissection: METIS_NodeND returned {status}"));
        }
        // Check what came back before trusting it as a permutation.
        let mut seen = vec![false; nv];
        for &p in &perm {
            let p = usize::try_from(p)
                .ok()
                .filter(|&p| p < nv && !seen[p])
                .ok_or("nested dissection: METIS_NodeND returned an invalid permutation")?;
            seen[p] = true;
            order.push(g.free_nodes[p]);
        }
    }
    let mut is_free = vec![false; n];
    for &i in &g.free_nodes {
        is_free[i] = true;
    }
    let mut dofs = Vec::with_capacity(dim * n);
    for i in (0..n).filter(|&i| !is_free[i]).chain(order) {
        dofs.extend(i * dim..(i + 1) * dim);
    }
    Ok(dofs)
}

/// The inverse of a permutation (`inv[perm[k]] = k`), or None when `perm` is not one.
pub fn inverse(perm: &[usize]) -> Option<Vec<usize>> {
    let mut inv = vec![usize::MAX; perm.len()];
    for (k, &p) in perm.iter().enumerate() {
        if p >= perm.len() || inv[p] != usize::MAX {
            return None;
        }
        inv[p] = k;
    }
    Some(inv)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cases::generate::{random_system, ConstraintMix, SystemSpec};

    /// The expanded nested-dissection order is a permutation of the DOFs: each once, a
    /// node's components consecutive and in order, fully constrained nodes first.
    #[test]
    fn nested_dissection_is_a_valid_permutation() {
        for (dim, nodes, seed) in [(2, 400, 1), (3, 343, 2), (3, 1000, 3), (2, 9, 4)] {
            let mut spec = SystemSpec::with_nodes(dim, nodes, seed);
            spec.mix = ConstraintMix::Random;
            let s = random_system(&spec);
            let f = &s.frames;
            let g = NodeGraph::new(dim, &s.h.row_ptr, &s.h.col_idx, &f.mask).unwrap();
            let full = (1u8 << dim) - 1;
            let fixed = f.mask.iter().filter(|&&m| m == full).count();
            assert!(fixed > 0, "{dim}D {nodes}: no fully constrained node");
            assert_eq!(g.free_nodes.len() + fixed, s.h.n);
            let perm = nested_dissection(&g, dim, s.h.n).unwrap();
            assert_eq!(perm.len(), dim * s.h.n);
            assert!(
                inverse(&perm).is_some(),
                "{dim}D {nodes}: not a permutation"
            );
            for (k, node) in perm.chunks(dim).enumerate() {
                let i = node[0] / dim;
                assert_eq!(node[0], i * dim, "a node's components start at component 0");
                for (a, &dof) in node.iter().enumerate() {
                    assert_eq!(dof, i * dim + a, "components of node {i} not consecutive");
                }
                assert_eq!(
                    f.mask[i] == full,
                    k < fixed,
                    "fully constrained nodes first"
                );
            }
        }
    }

    /// No node free: only the constrained diagonal, in node order.
    #[test]
    fn nested_dissection_of_an_all_constrained_system() {
        let dim = 3;
        let mask = vec![0b111u8; 4];
        let row_ptr = vec![0, 2, 4, 6, 8];
        let col_idx = vec![0, 1, 0, 1, 2, 3, 2, 3];
        let g = NodeGraph::new(dim, &row_ptr, &col_idx, &mask).unwrap();
        assert!(g.free_nodes.is_empty());
        let perm = nested_dissection(&g, dim, 4).unwrap();
        assert_eq!(perm, (0..12).collect::<Vec<_>>());
    }

    #[test]
    fn inverse_refuses_a_non_permutation() {
        assert_eq!(inverse(&[2, 0, 1]), Some(vec![1, 2, 0]));
        assert_eq!(inverse(&[0, 0, 1]), None);
        assert_eq!(inverse(&[0, 3, 1]), None);
    }

    #[test]
    fn names_round_trip() {
        for o in [
            CholeskyOrdering::Auto,
            CholeskyOrdering::Amd,
            CholeskyOrdering::NestedDissection,
        ] {
            assert_eq!(o.name().parse::<CholeskyOrdering>(), Ok(o));
            let json = serde_json::to_string(&o).unwrap();
            assert_eq!(json, format!("\"{}\"", o.name()));
        }
        assert!("metis".parse::<CholeskyOrdering>().is_err());
    }
}
