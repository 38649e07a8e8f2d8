//! The index arrays of the aggregate coarse space in the device PCG
//! (shaders/pcg_coarse.wgsl, `COARSE = 2`): which aggregate each node is in, the nodes of
//! each aggregate, and how the blocks of H add up to E = ZᵀĤZ without atomics.
//!
//! E's block (a, b) is Σ_{i∈a} Q_i Σ_{j∈b, j~i} H_ij Q_j (src/solve/coarse.rs). Each block
//! row i gets one *slot* per column aggregate b among its neighbours (in the order of
//! first appearance, as the CPU's row buffer): `agg_rows` sums the row's blocks into its
//! slots and applies Q_i, one invocation per row. Each aggregate pair (a, b) lists its
//! slots in row order, and `agg_e` sums them per entry of E: the CPU's additions in the
//! CPU's order, and no two invocations write one value.

use crate::core::constraints::Frames;
use crate::gpu::GpuError;
use crate::solve::coarse::{aggregate_projections, Aggregation, NO_AGGREGATE};

/// Words of the header of the index buffer (the `AGG_*` constants of the WGSL).
pub const HEADER: usize = 16;

/// Header entries, mirrored by `AGG_*` in shaders/pcg_common.wgsl (checked by a test in
/// `gpu::pcg`).
pub mod header {
    pub const COUNT: u32 = 0;
    pub const K: u32 = 1;
    pub const OF: u32 = 2;
    pub const PTR: u32 = 3;
    pub const NODES: u32 = 4;
    pub const SLOT_PTR: u32 = 5;
    pub const SLOT_OF: u32 = 6;
    pub const PAIR_PTR: u32 = 7;
    pub const PAIR_SLOTS: u32 = 8;
    pub const PAIR_OF: u32 = 9;
    pub const E: u32 = 10;
    pub const EINV: u32 = 11;
    pub const W: u32 = 12;
    pub const C: u32 = 13;
}

/// The aggregate coarse space of one constraint set, ready to upload.
#[derive(Debug, Clone)]
pub struct AggregateIndex {
    /// The header, then the index arrays (u32); emptied once uploaded.
    pub words: Vec<u32>,
    /// Aggregates, and K = D · aggregates (E is K×K).
    pub count: usize,
    pub k: usize,
    /// f64 values of the `coarse` buffer: the slots' D² sums, E, E⁺, w, c.
    pub values: usize,
    /// Where E and E⁺ start in `coarse` (f64 index).
    pub e_at: usize,
    pub einv_at: usize,
    /// G_a = Σ_{i∈a} Q_i per aggregate (for E⁺, as the CPU computes it).
    pub gram: Vec<f64>,
}

/// The aggregates of [`Aggregation::from_pattern`] on the block pattern (row pointers,
/// column indices; the diagonal block is in every row) with their slot and pair lists;
/// `None` when every node is fully constrained. Fails when an index would not fit a u32.
pub fn aggregate_index(
    row_ptr: &[usize],
    col_idx: &[usize],
    frames: &Frames,
) -> Result<Option<AggregateIndex>, GpuError> {
    let n = row_ptr.len().saturating_sub(1);
    let d = frames.dim;
    // Every node fixed: no translation is free, so there is nothing to correct.
    let full = (1u8 << d) - 1;
    if frames.mask.iter().all(|&m| m & full == full) {
        return Ok(None);
    }
    let agg = Aggregation::from_pattern(row_ptr, col_idx);
    if agg.count == 0 {
        return Ok(None);
    }
    let too_big = || {
        GpuError::Unsupported(
            "the aggregate coarse space's index arrays exceed the device CG's u32 indices".into(),
        )
    };
    let u = |v: usize| u32::try_from(v).map_err(|_| too_big());
    let of = &agg.of_node;
    let (ptr, nodes) = agg.lists();

    // Per row its slots (one per column aggregate, first appearance first), per block its
    // slot, per slot its pair (a, b).
    let mut slot_ptr = Vec::with_capacity(n + 1);
    slot_ptr.push(0u32);
    let mut slot_of = vec![NO_AGGREGATE; col_idx.len()];
    let mut slot_pair: Vec<(u32, u32)> = Vec::new();
    let mut row: Vec<u32> = Vec::new();
    for i in 0..n {
        let a = of[i];
        if a != NO_AGGREGATE {
            row.clear();
            for k in row_ptr[i]..row_ptr[i + 1] {
                let b = of[col_idx[k]];
                if b == NO_AGGREGATE {
                    continue;
                }
                let at = match row.iter().position(|&x| x == b) {
                    Some(p) => p,
                    None => {
                        row.push(b);
                        row.len() - 1
                    }
                };
                slot_of[k] = u(slot_pair.len() + at)?;
            }
            slot_pair.extend(row.iter().map(|&b| (a, b)));
        }
        slot_ptr.push(u(slot_pair.len())?);
    }

    // Per aggregate pair its slots in row order (slots are numbered row by row).
    let count = agg.count;
    let mut pair_of = vec![NO_AGGREGATE; count * count];
    let mut pair_len: Vec<u32> = Vec::new();
    for &(a, b) in &slot_pair {
        let p = &mut pair_of[a as usize * count + b as usize];
        if *p == NO_AGGREGATE {
            *p = u(pair_len.len())?;
            pair_len.push(0);
        }
        pair_len[*p as usize] += 1;
    }
    let mut pair_ptr = Vec::with_capacity(pair_len.len() + 1);
    pair_ptr.push(0u32);
    for l in &pair_len {
        pair_ptr.push(pair_ptr[pair_ptr.len() - 1] + l);
    }
    let mut fill = pair_ptr.clone();
    let mut pair_slots = vec![0u32; slot_pair.len()];
    for (s, &(a, b)) in slot_pair.iter().enumerate() {
        let p = pair_of[a as usize * count + b as usize] as usize;
        pair_slots[fill[p] as usize] = u(s)?;
        fill[p] += 1;
    }

    // The header, then the arrays in header order.
    let k = d * count;
    let mut words = vec![0u32; HEADER];
    let arrays: [(u32, &[u32]); 8] = [
        (header::OF, of),
        (header::PTR, &ptr),
        (header::NODES, &nodes),
        (header::SLOT_PTR, &slot_ptr),
        (header::SLOT_OF, &slot_of),
        (header::PAIR_PTR, &pair_ptr),
        (header::PAIR_SLOTS, &pair_slots),
        (header::PAIR_OF, &pair_of),
    ];
    for (h, a) in arrays {
        words[h as usize] = u(words.len())?;
        words.extend_from_slice(a);
    }
    let e_at = slot_pair.len().checked_mul(d * d).ok_or_else(too_big)?;
    let einv_at = e_at + k * k;
    let w_at = einv_at + k * k;
    let c_at = w_at + k;
    words[header::COUNT as usize] = u(count)?;
    words[header::K as usize] = u(k)?;
    words[header::E as usize] = u(e_at)?;
    words[header::EINV as usize] = u(einv_at)?;
    words[header::W as usize] = u(w_at)?;
    words[header::C as usize] = u(c_at)?;
    Ok(Some(AggregateIndex {
        words,
        count,
        k,
        values: c_at + k,
        e_at,
        einv_at,
        gram: aggregate_projections(frames, &agg),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::constraints::Frames;

    /// A path of n nodes (each linked to its neighbours), 2D, the first node fixed.
    fn path(n: usize) -> (Vec<usize>, Vec<usize>, Frames) {
        let mut row_ptr = vec![0];
        let mut col = Vec::new();
        for i in 0..n {
            for j in i.saturating_sub(1)..(i + 2).min(n) {
                col.push(j);
            }
            row_ptr.push(col.len());
        }
        let mut f = Frames::unconstrained(2, n);
        f.mask[0] = 0b11;
        (row_ptr, col, f)
    }

    /// Every node is in an aggregate (the fixed first one too), every block has a slot of
    /// its row whose pair is the two nodes' aggregates; each pair lists its slots in
    /// increasing row order; each aggregate lists its nodes.
    #[test]
    fn slots_and_pairs_cover_every_block_once() {
        let (row_ptr, col, f) = path(300);
        let ix = aggregate_index(&row_ptr, &col, &f).unwrap().unwrap();
        let w = &ix.words;
        let at = |h: u32| w[h as usize] as usize;
        let of = &w[at(header::OF)..at(header::OF) + 300];
        assert!(of.iter().all(|&a| (a as usize) < ix.count), "{of:?}");
        assert!(ix.count >= 2, "{} aggregates", ix.count);
        assert_eq!(ix.k, 2 * ix.count);
        let slot_ptr = &w[at(header::SLOT_PTR)..at(header::SLOT_PTR) + 301];
        let slot_of = &w[at(header::SLOT_OF)..at(header::SLOT_OF) + col.len()];
        let n_slots = slot_ptr[300] as usize;
        assert_eq!(ix.e_at, 4 * n_slots);
        let pair_of = &w[at(header::PAIR_OF)..at(header::PAIR_OF) + ix.count * ix.count];
        let n_pairs = pair_of.iter().filter(|p| **p != NO_AGGREGATE).count();
        let pair_ptr = &w[at(header::PAIR_PTR)..at(header::PAIR_PTR) + n_pairs + 1];
        let pair_slots = &w[at(header::PAIR_SLOTS)..at(header::PAIR_SLOTS) + n_slots];
        // The row of each slot.
        let mut slot_row = vec![0usize; n_slots];
        for i in 0..300 {
            for s in slot_ptr[i]..slot_ptr[i + 1] {
                slot_row[s as usize] = i;
            }
        }
        for i in 0..300 {
            for k in row_ptr[i]..row_ptr[i + 1] {
                let j = col[k];
                let s = slot_of[k];
                if of[i] == NO_AGGREGATE || of[j] == NO_AGGREGATE {
                    assert_eq!(s, NO_AGGREGATE, "block ({i}, {j})");
                    continue;
                }
                assert!(
                    (slot_ptr[i]..slot_ptr[i + 1]).contains(&s),
                    "block ({i}, {j})"
                );
                let p = pair_of[of[i] as usize * ix.count + of[j] as usize];
                let list =
                    &pair_slots[pair_ptr[p as usize] as usize..pair_ptr[p as usize + 1] as usize];
                assert!(list.contains(&s), "block ({i}, {j})");
            }
        }
        for p in 0..n_pairs {
            let list = &pair_slots[pair_ptr[p] as usize..pair_ptr[p + 1] as usize];
            assert!(list
                .windows(2)
                .all(|x| slot_row[x[0] as usize] < slot_row[x[1] as usize]));
        }
        let ptr = &w[at(header::PTR)..at(header::PTR) + ix.count + 1];
        assert_eq!(ptr[ix.count], 300);
    }

    /// Every node fixed: no coarse correction, no index.
    #[test]
    fn no_free_node_has_no_aggregates() {
        let (row_ptr, col, mut f) = path(10);
        f.mask.iter_mut().for_each(|m| *m = 0b11);
        assert!(aggregate_index(&row_ptr, &col, &f).unwrap().is_none());
    }
}
