// The partials of E = ZᵀĤZ = Σ_i Q_i (Σ_j H_ij Q_j), D² slots (Ĥ's identity on the
// constrained components never meets Z), and of the D absolute row sums 2^-64 ·
// Σ_j |(Q_i H_ij Q_j)_a·| (each block projected on its own, as src/solve/coarse.rs sums
// them; scaled so that rows near the top of the range do not overflow). Row i's blocks are
// summed before Q_i is applied, as src/solve/coarse.rs does: for a nearly free body they
// cancel to the mass term, and summing every block into E would carry the rounding of the
// stiffness into the small E.
@compute @workgroup_size(WG)
fn coarse_e(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let n_sums = dd + D;
    let np = params.n_partials;
    let segs = chunk_segments();
    for (var s = segs.x + group_index(wid, nwg); s < segs.y; s += group_count(nwg)) {
        // E's D² entries, then the D absolute row sums.
        var e: array<acc, 12>;
        if (segment_begun(s)) {
            for (var m = 0u; m < n_sums; m++) {
                e[m] = partials[carry(params.chunk - 1u, lid.x, m)];
            }
        }
        for (var mi = 0u; mi < ITEMS; mi++) {
            let i = (s * ITEMS + mi) * WG + lid.x;
            if (i >= params.row_end) {
                break;
            }
            if (i < params.row_begin || all_fixed(i)) {
                continue;
            }
            var part: array<real, 9>;
            for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
                let j = pattern[params.col_at + k];
                if (all_fixed(j)) {
                    continue;
                }
                var t: array<real, 9>;
                for (var m = 0u; m < dd; m++) {
                    t[m] = hvals[(k - params.block_first) * dd + m];
                }
                if (!plain(j)) {
                    t = mat_mul(t, proj(j));
                }
                for (var m = 0u; m < dd; m++) {
                    part[m] += t[m];
                }
                var b = t;
                if (!plain(i)) {
                    b = mat_mul(proj(i), t);
                }
                for (var a = 0u; a < D; a++) {
                    var sa = real(0.0);
                    for (var c = 0u; c < D; c++) {
                        sa += abs(b[a * D + c]) * ABS_SUM_SCALE;
                    }
                    e[dd + a] += acc(sa);
                }
            }
            if (!plain(i)) {
                part = mat_mul(proj(i), part);
            }
            for (var m = 0u; m < dd; m++) {
                e[m] += acc(part[m]);
            }
        }
        if (segment_goes_on(s)) {
            for (var m = 0u; m < n_sums; m++) {
                partials[carry(params.chunk, lid.x, m)] = e[m];
            }
            continue;
        }
        // The sums in trees of at most five.
        for (var base = 0u; base < n_sums; base += 5u) {
            let n = min(n_sums - base, 5u);
            var v: array<acc, 5>;
            for (var m = 0u; m < n; m++) {
                v[m] = e[base + m];
            }
            workgroup_sum(lid.x, v, n);
            if (lid.x == 0u) {
                for (var m = 0u; m < n; m++) {
                    partials[(PART_E + base + m) * np + s] = summed(m);
                }
            }
            workgroupBarrier();
        }
    }
}

// E and the absolute row sums from coarse_e's partials (one workgroup, fixed order) into
// scal, for the host, which symmetrizes and pseudo-inverts E as the CPU does
// (src/solve/coarse.rs).
@compute @workgroup_size(WG)
fn coarse_e_sum(@builtin(local_invocation_id) lid: vec3<u32>) {
    let dd = D * D;
    let n_sums = dd + D;
    let np = params.n_partials;
    for (var base = 0u; base < n_sums; base += 5u) {
        let n = min(n_sums - base, 5u);
        var v: array<acc, 5>;
        for (var t = lid.x; t < np; t += WG) {
            for (var m = 0u; m < n; m++) {
                v[m] += partials[(PART_E + base + m) * np + t];
            }
        }
        let s = workgroup_sum_uniform(lid.x, v, n);
        if (lid.x == 0u) {
            for (var m = 0u; m < n; m++) {
                let at = base + m;
                if (at < dd) {
                    scal[SCAL_E + at] = s[m];
                } else {
                    scal[SCAL_EABS + at - dd] = s[m];
                }
            }
        }
    }
}

// Row i's share of E = ZᵀĤZ over the aggregates: per slot (one per column aggregate b of
// the row, in the order of first appearance) Q_i Σ_{j∈b} H_ij Q_j, D² values. The row's
// blocks are summed per column aggregate before Q_i is applied, as
// src/solve/coarse.rs does: for a nearly free body they cancel to the mass term, and
// summing each block into E would carry the rounding of the stiffness into a small E.
// One invocation per block row of the values chunk; no reduction.
@compute @workgroup_size(WG)
fn agg_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let slot_ptr = aggregates[AGG_SLOT_PTR];
    let slot_of = aggregates[AGG_SLOT_OF];
    for (var i = params.row_begin + grid_index(gid, nwg); i < params.row_end; i += grid_stride(nwg)) {
        let s0 = aggregates[slot_ptr + i];
        let s1 = aggregates[slot_ptr + i + 1u];
        if (s0 == s1) {
            continue;
        }
        for (var t = s0 * dd; t < s1 * dd; t++) {
            coarse[t] = acc(0.0);
        }
        for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
            let sl = aggregates[slot_of + k];
            if (sl == NO_AGGREGATE) {
                continue;
            }
            let j = pattern[params.col_at + k];
            var t: array<real, 9>;
            for (var m = 0u; m < dd; m++) {
                t[m] = hvals[(k - params.block_first) * dd + m];
            }
            if (!plain(j)) {
                t = mat_mul(t, proj(j));
            }
            for (var m = 0u; m < dd; m++) {
                coarse[sl * dd + m] += acc(t[m]);
            }
        }
        if (!plain(i)) {
            let qi = proj(i);
            for (var sl = s0; sl < s1; sl++) {
                var t: array<real, 9>;
                for (var m = 0u; m < dd; m++) {
                    t[m] = real(coarse[sl * dd + m]);
                }
                t = mat_mul(qi, t);
                for (var m = 0u; m < dd; m++) {
                    coarse[sl * dd + m] = acc(t[m]);
                }
            }
        }
    }
}

// E (K×K, row-major, not symmetrized: coarse_factor.wgsl does that): entry (a·D + x, b·D + y) sums
// component (x, y) of the slots of aggregate pair (a, b) in row order, as the CPU adds
// them. One invocation per entry.
@compute @workgroup_size(WG)
fn agg_e(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n_agg = aggregates[AGG_COUNT];
    let k = aggregates[AGG_K];
    let pair_ptr = aggregates[AGG_PAIR_PTR];
    let pair_slots = aggregates[AGG_PAIR_SLOTS];
    for (var t = grid_index(gid, nwg); t < k * k; t += grid_stride(nwg)) {
        let row = t / k;
        let col = t % k;
        let pair = aggregates[aggregates[AGG_PAIR_OF] + (row / D) * n_agg + col / D];
        var s = acc(0.0);
        if (pair != NO_AGGREGATE) {
            let at = (row % D) * D + col % D;
            for (var m = aggregates[pair_ptr + pair]; m < aggregates[pair_ptr + pair + 1u]; m++) {
                s += coarse[aggregates[pair_slots + m] * D * D + at];
            }
        }
        coarse[aggregates[AGG_E] + t] = s;
    }
}

// w = Zᵀr per aggregate (COARSE = 2): one workgroup per aggregate over its nodes, in a
// fixed order.
@compute @workgroup_size(WG)
fn agg_restrict(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    let n_agg = aggregates[AGG_COUNT];
    let ptr = aggregates[AGG_PTR];
    let nodes = aggregates[AGG_NODES];
    for (var a = group_index(wid, nwg); a < n_agg; a += group_count(nwg)) {
        var s: array<acc, 5>;
        for (var t = aggregates[ptr + a] + lid.x; t < aggregates[ptr + a + 1u]; t += WG) {
            let i = aggregates[nodes + t];
            var rv: array<real, 3>;
            for (var x = 0u; x < D; x++) {
                rv[x] = r[i * D + x];
            }
            let w = zt(i, rv);
            for (var x = 0u; x < D; x++) {
                s[x] += acc(w[x]);
            }
        }
        workgroup_sum(lid.x, s, D);
        if (lid.x < D) {
            coarse[aggregates[AGG_W] + a * D + lid.x] = summed(lid.x);
        }
        // The tree's memory is reused by the next aggregate.
        workgroupBarrier();
    }
}

// c = E⁺w (COARSE = 2), one workgroup per coarse row: its lanes take the columns
// lid, lid + WG, … (a fixed order) and one tree sums them, so a row costs K/WG loads in
// sequence, not K. E⁺ is symmetric: row `row` is read as column `row`.
@compute @workgroup_size(WG)
fn agg_solve(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    let k = aggregates[AGG_K];
    let einv = aggregates[AGG_EINV];
    let w = aggregates[AGG_W];
    for (var row = group_index(wid, nwg); row < k; row += group_count(nwg)) {
        var s = acc(0.0);
        for (var col = lid.x; col < k; col += WG) {
            s += coarse[einv + col * k + row] * coarse[w + col];
        }
        workgroup_sum(lid.x, sum1(s), 1u);
        if (lid.x == 0u) {
            coarse[aggregates[AGG_C] + row] = summed(0u);
        }
        workgroupBarrier();
    }
}

