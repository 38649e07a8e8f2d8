// (H pw)_i, D = 3: Σ_k H_ik pw_j over the row's blocks in this chunk's buffer, each entry
// summed in column order. Straight-line vector code: llvmpipe runs loops over
// dynamically indexed private arrays far slower (2.3× on this product).
fn hrow3(i: u32) -> vec3<real> {
    if (DIFF) {
        return hrow3_difference(i);
    }
    var s = vec3<real>(real(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 9u;
        let w = vec3<real>(pw[3u * j], pw[3u * j + 1u], pw[3u * j + 2u]);
        s += vec3<real>(hvals[o], hvals[o + 3u], hvals[o + 6u]) * w.x;
        s += vec3<real>(hvals[o + 1u], hvals[o + 4u], hvals[o + 7u]) * w.y;
        s += vec3<real>(hvals[o + 2u], hvals[o + 5u], hvals[o + 8u]) * w.z;
    }
    return s;
}

// (H pw)_i, D = 2.
fn hrow2(i: u32) -> vec2<real> {
    if (DIFF) {
        return hrow2_difference(i);
    }
    var s = vec2<real>(real(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 4u;
        let w = vec2<real>(pw[2u * j], pw[2u * j + 1u]);
        s += vec2<real>(hvals[o], hvals[o + 2u]) * w.x;
        s += vec2<real>(hvals[o + 1u], hvals[o + 3u]) * w.y;
    }
    return s;
}

// (H pw)_i in the difference form (DIFF), D = 3.
fn hrow3_difference(i: u32) -> vec3<real> {
    let wi = vec3<real>(pw[3u * i], pw[3u * i + 1u], pw[3u * i + 2u]);
    var s = vec3<acc>(acc(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 9u;
        let w = vec3<real>(pw[3u * j], pw[3u * j + 1u], pw[3u * j + 2u]) - wi;
        s += vec3<acc>(vec3<real>(hvals[o], hvals[o + 3u], hvals[o + 6u])) * acc(w.x);
        s += vec3<acc>(vec3<real>(hvals[o + 1u], hvals[o + 4u], hvals[o + 7u])) * acc(w.y);
        s += vec3<acc>(vec3<real>(hvals[o + 2u], hvals[o + 5u], hvals[o + 8u])) * acc(w.z);
    }
    let m = 9u * i;
    let a = vec3<acc>(wi);
    s += vec3<acc>(vec3<real>(rowsum[m], rowsum[m + 3u], rowsum[m + 6u])) * a.x;
    s += vec3<acc>(vec3<real>(rowsum[m + 1u], rowsum[m + 4u], rowsum[m + 7u])) * a.y;
    s += vec3<acc>(vec3<real>(rowsum[m + 2u], rowsum[m + 5u], rowsum[m + 8u])) * a.z;
    return vec3<real>(s);
}

// (H pw)_i in the difference form (DIFF), D = 2.
fn hrow2_difference(i: u32) -> vec2<real> {
    let wi = vec2<real>(pw[2u * i], pw[2u * i + 1u]);
    var s = vec2<acc>(acc(0.0));
    for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
        let j = pattern[params.col_at + k];
        let o = (k - params.block_first) * 4u;
        let w = vec2<real>(pw[2u * j], pw[2u * j + 1u]) - wi;
        s += vec2<acc>(vec2<real>(hvals[o], hvals[o + 2u])) * acc(w.x);
        s += vec2<acc>(vec2<real>(hvals[o + 1u], hvals[o + 3u])) * acc(w.y);
    }
    let m = 4u * i;
    let a = vec2<acc>(wi);
    s += vec2<acc>(vec2<real>(rowsum[m], rowsum[m + 2u])) * a.x;
    s += vec2<acc>(vec2<real>(rowsum[m + 1u], rowsum[m + 3u])) * a.y;
    return vec2<real>(s);
}

// q = Ĥp = P Vᵀ H V P p + (I − P) p, one invocation per block row, with the p·q partials.
@compute @workgroup_size(WG)
fn matvec(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    let segs = chunk_segments();
    for (var s = segs.x + group_index(wid, nwg); s < segs.y; s += group_count(nwg)) {
        var pq = acc(0.0);
        if (segment_begun(s)) {
            pq = partials[carry(params.chunk - 1u, lid.x, 0u)];
        }
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid.x;
            if (i >= params.row_end) {
                break;
            }
            if (i < params.row_begin) {
                continue;
            }
            let m = frame[2u * i];
            let ri = rot_of(i);
            if (D == 3u) {
                var v = hrow3(i);
                if (ri != NO_ROTATION) {
                    // V_iᵀ v: the columns of this matrix are the rows of V_i.
                    let o = ri * 9u;
                    v = mat3x3<real>(
                        vec3<real>(rotations[o], rotations[o + 1u], rotations[o + 2u]),
                        vec3<real>(rotations[o + 3u], rotations[o + 4u], rotations[o + 5u]),
                        vec3<real>(rotations[o + 6u], rotations[o + 7u], rotations[o + 8u]),
                    ) * v;
                }
                let pi = vec3<real>(p[3u * i], p[3u * i + 1u], p[3u * i + 2u]);
                let qv = select(v, pi, mask_bits3(m));
                q[3u * i] = qv.x;
                q[3u * i + 1u] = qv.y;
                q[3u * i + 2u] = qv.z;
                pq += acc(pi.x) * acc(qv.x);
                pq += acc(pi.y) * acc(qv.y);
                pq += acc(pi.z) * acc(qv.z);
            } else {
                var v = hrow2(i);
                if (ri != NO_ROTATION) {
                    let o = ri * 4u;
                    v = mat2x2<real>(
                        vec2<real>(rotations[o], rotations[o + 1u]),
                        vec2<real>(rotations[o + 2u], rotations[o + 3u]),
                    ) * v;
                }
                let pi = vec2<real>(p[2u * i], p[2u * i + 1u]);
                let qv = select(v, pi, mask_bits2(m));
                q[2u * i] = qv.x;
                q[2u * i + 1u] = qv.y;
                pq += acc(pi.x) * acc(qv.x);
                pq += acc(pi.y) * acc(qv.y);
            }
        }
        if (segment_goes_on(s)) {
            partials[carry(params.chunk, lid.x, 0u)] = pq;
            continue;
        }
        workgroup_sum(lid.x, sum1(pq), 1u);
        if (lid.x == 0u) {
            partials[PART_PQ * params.n_partials + s] = summed(0u);
        }
        workgroupBarrier();
    }
}

// p = y and pw = V P y for every node: the true residual's product (matvec then gives
// q = Ĥy).
@compute @workgroup_size(WG)
fn world_y(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!starting(lid.x)) {
        return;
    }
    for (var i = grid_index(gid, nwg); i < params.n_nodes; i += grid_stride(nwg)) {
        for (var a = 0u; a < D; a++) {
            p[i * D + a] = y[i * D + a];
        }
        write_world(i);
    }
}

// pw = V P z: the multilevel V-cycle's product at level 0 (then `matvec`, whose q = Ĥz
// and throw-away p·q partials the V-cycle reads before the next iteration's product).
@compute @workgroup_size(WG)
fn world_z(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    var off = state[STATE_DONE] != 0u;
    if (VERIFY) {
        off = !verifying();
    }
    if (off) {
        return;
    }
    for (var i = grid_index(gid, nwg); i < params.n_nodes; i += grid_stride(nwg)) {
        var w: array<real, 3>;
        for (var c = 0u; c < D; c++) {
            w[c] = select(z[i * D + c], real(0.0), fixed(i, c));
        }
        let o = from_frame(i, w);
        for (var c = 0u; c < D; c++) {
            pw[i * D + c] = o[c];
        }
    }
}

// Δx = V P y (the prescribed part is zero in a Newton step); VERIFY: only where the
// verification just recorded found the true residual within the tolerance.
@compute @workgroup_size(WG)
fn recover(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (VERIFY && state[STATE_TRUE_OK] == 0u) {
        return;
    }
    for (var i = grid_index(gid, nwg); i < params.n_nodes; i += grid_stride(nwg)) {
        var w: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            w[a] = select(y[i * D + a], real(0.0), fixed(i, a));
        }
        let o = from_frame(i, w);
        for (var a = 0u; a < D; a++) {
            dx[i * D + a] = o[a];
        }
    }
}

