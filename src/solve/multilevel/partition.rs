//! The clusters of one level: a METIS k-way partition of the level's graph.

use crate::solve::ordering::METIS_LOCK;

/// Nodes (or clusters of the level below) per cluster, aimed at.
pub const CLUSTER_NODES: usize = 16;

/// METIS's k-way partition runs with one initial partition (its default: the best of
/// four) and one refinement pass per uncoarsening level (default: ten). With ~16 items
/// per part METIS hardly coarsens, and each initial partition is a recursive bisection of
/// the whole graph: the defaults took 0.7–0.8 s of the hierarchy on 44,541 nodes, these
/// 0.45–0.5 s, with the same V-cycle iterations (84 against 85 on four captured twist
/// systems; docs/design/multilevel.md, "Fixed costs").
const METIS_TRIES: metis_sys::idx_t = 1;
/// See [`METIS_TRIES`].
const METIS_REFINE_PASSES: metis_sys::idx_t = 1;

/// Cluster of each of `n` items: a METIS k-way partition into ⌈n / CLUSTER_NODES⌉ parts
/// of the graph (self-loops dropped), empty parts removed ([`METIS_TRIES`]).
/// Consecutive runs of items where METIS fails or the graph exceeds its 32-bit indices.
pub(super) fn partition(n: usize, row_ptr: &[usize], col_idx: &[usize]) -> Vec<u32> {
    let parts = n.div_ceil(CLUSTER_NODES);
    let runs = || (0..n).map(|i| (i / CLUSTER_NODES) as u32).collect();
    if parts <= 1 {
        return vec![0; n];
    }
    let Some((mut xadj, mut adjncy)) = metis_graph(n, row_ptr, col_idx) else {
        return runs();
    };
    let mut nvtxs = n as metis_sys::idx_t;
    let mut ncon: metis_sys::idx_t = 1;
    let mut nparts = parts as metis_sys::idx_t;
    let mut objval: metis_sys::idx_t = 0;
    let mut part = vec![0 as metis_sys::idx_t; n];
    let mut options = [0 as metis_sys::idx_t; metis_sys::METIS_NOPTIONS as usize];
    let status = {
        let _guard = METIS_LOCK.lock().unwrap_or_else(|p| p.into_inner());
        // SAFETY: xadj has n + 1 entries, adjncy xadj[n], part n, options
        // METIS_NOPTIONS; the graph is symmetric without self-loops; null pointers are
        // METIS's documented "absent" for the weights and target fractions.
        unsafe {
            metis_sys::METIS_SetDefaultOptions(options.as_mut_ptr());
            options[metis_sys::moptions_et_METIS_OPTION_NIPARTS as usize] = METIS_TRIES;
            options[metis_sys::moptions_et_METIS_OPTION_NITER as usize] = METIS_REFINE_PASSES;
            metis_sys::METIS_PartGraphKway(
                &mut nvtxs,
                &mut ncon,
                xadj.as_mut_ptr(),
                adjncy.as_mut_ptr(),
                std::ptr::null_mut(),
                std::ptr::null_mut(),
                std::ptr::null_mut(),
                &mut nparts,
                std::ptr::null_mut(),
                std::ptr::null_mut(),
                options.as_mut_ptr(),
                &mut objval,
                part.as_mut_ptr(),
            )
        }
    };
    if status != metis_sys::rstatus_et_METIS_OK || part.iter().any(|&p| p < 0 || p >= nparts) {
        return runs();
    }
    // Number the non-empty parts in order of their first item.
    let mut id = vec![u32::MAX; parts];
    let mut next = 0u32;
    part.iter()
        .map(|&p| {
            let p = p as usize;
            if id[p] == u32::MAX {
                id[p] = next;
                next += 1;
            }
            id[p]
        })
        .collect()
}

/// METIS's CSR adjacency of the pattern, self-loops dropped; None past 32-bit indices.
fn metis_graph(
    n: usize,
    row_ptr: &[usize],
    col_idx: &[usize],
) -> Option<(Vec<metis_sys::idx_t>, Vec<metis_sys::idx_t>)> {
    metis_sys::idx_t::try_from(n).ok()?;
    let mut xadj = Vec::with_capacity(n + 1);
    let mut adjncy = Vec::with_capacity(col_idx.len());
    xadj.push(0);
    for i in 0..n {
        for &j in &col_idx[row_ptr[i]..row_ptr[i + 1]] {
            if j != i {
                adjncy.push(j as metis_sys::idx_t);
            }
        }
        xadj.push(metis_sys::idx_t::try_from(adjncy.len()).ok()?);
    }
    Some((xadj, adjncy))
}
