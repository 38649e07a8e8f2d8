// E⁺ of the aggregates' translations formed on the device (src/gpu/pcg/coarse_factor.rs)
// from the E = ZᵀĤZ that pcg_coarse.wgsl's agg_e reduced, recorded after it by `prepare`:
//
//   agg_er      Er = Wᵀ sym(E) W            a grid, one invocation per entry (p ≥ q)
//   agg_chol    Er = L Lᵀ in place          one workgroup, column by column: the column
//                                           scaled, then the trailing update in parallel
//   agg_linv    X = L⁻¹                      a grid, one invocation per column of X
//   agg_cinv    C = XᵀX = Er⁻¹               a grid, one invocation per entry (p ≥ q)
//   agg_expand  E⁺ = W C Wᵀ                  a grid, one invocation per entry (r ≥ c),
//                                           written at (r, c) and (c, r)
//
// Each entry is computed by the operations, in the order, of the host's specification
// (src/solve/coarse/einv.rs, `aggregates_einv_with_basis`): the CPU CG and this PCG
// precondition with the same bits where the device does IEEE arithmetic as written.
// agg_chol sets state[STATE_COARSE_FAILED] (0 or 1, every prepare) when a pivot is not
// positive and finite (Ĥ indefinite on the coarse space); agg_cinv and agg_expand then
// write nothing and zeros, and the host, which reads the flag with the start's status,
// writes E⁺ itself (src/gpu/pcg/cg/coarse.rs, `upload_aggregate_einv`).
//
// Storage (`work`, acc): W (m columns of D values), then three m×m row-major matrices:
// Er and L in place (lower triangle); X transposed (X_ic at (c, i), upper triangle: a
// column of X is a contiguous row); C (lower triangle).

// Mirrors `FactorParams` in src/gpu/pcg/coarse_factor.rs (size-asserted there).
struct FactorParams {
    // K = D · aggregates, the columns of W, the aggregates.
    k: u32,
    m: u32,
    count: u32,
    // Where E and E⁺ start in `coarse` (K×K each, row-major).
    e_at: u32,
    einv_at: u32,
    // Where W, L (Er), X and C start in `work`.
    w_at: u32,
    l_at: u32,
    x_at: u32,
    c_at: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

override D: u32 = 3u;

@group(0) @binding(0) var<uniform> fp: FactorParams;
// The PCG's aggregate data (pcg_common.wgsl, `coarse`): E read, E⁺ written.
@group(0) @binding(1) var<storage, read_write> coarse: array<acc>;
// W's columns per aggregate (count + 1 offsets), then the aggregate of each column.
@group(0) @binding(2) var<storage, read> basis: array<u32>;
@group(0) @binding(3) var<storage, read_write> work: array<acc>;
// The PCG's state: the failure flag.
@group(0) @binding(4) var<storage, read_write> state: array<u32>;

// The host's pivot test: positive and finite (1/∞ = 0, NaN fails both).
fn usable_pivot(v: acc) -> bool {
    return v > acc(0.0) && acc(1.0) / v > acc(0.0);
}

// sym(E)_rc: E's own on the diagonal, else the mean of E_rc and E_cr.
fn sym_e(r: u32, c: u32) -> acc {
    if (r == c) {
        return coarse[fp.e_at + r * fp.k + r];
    }
    return acc(0.5) * (coarse[fp.e_at + r * fp.k + c] + coarse[fp.e_at + c * fp.k + r]);
}

// Entry x of W's column p.
fn w_at(p: u32, x: u32) -> acc {
    return work[fp.w_at + p * D + x];
}

fn column_aggregate(p: u32) -> u32 {
    return basis[fp.count + 1u + p];
}

@compute @workgroup_size(WG)
fn agg_er(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let m = fp.m;
    for (var t = grid_index(gid, nwg); t < m * m; t += grid_stride(nwg)) {
        let p = t / m;
        let q = t % m;
        if (q > p) {
            continue;
        }
        let a = column_aggregate(p);
        let b = column_aggregate(q);
        var s = acc(0.0);
        for (var x = 0u; x < D; x++) {
            for (var y = 0u; y < D; y++) {
                s += w_at(p, x) * sym_e(a * D + x, b * D + y) * w_at(q, y);
            }
        }
        work[fp.l_at + p * m + q] = s;
    }
}

// Right-looking: at column j every invocation forms the pivot's root itself (the same
// bits), the column below it is divided by it, and after a barrier the rows below take
// the column's update, rows spread over the invocations; a second barrier ends the step.
// The flag is the conjunction of every pivot's test (the host stops at the first; the
// rest here runs on NaNs, uniformly, and is discarded).
@compute @workgroup_size(WG)
fn agg_chol(@builtin(local_invocation_id) lid: vec3<u32>) {
    let m = fp.m;
    let l = fp.l_at;
    var ok = true;
    for (var j = 0u; j < m; j++) {
        let piv = work[l + j * m + j];
        ok = ok && usable_pivot(piv);
        let ljj = sqrt(piv);
        for (var i = j + 1u + lid.x; i < m; i += WG) {
            work[l + i * m + j] = work[l + i * m + j] / ljj;
        }
        storageBarrier();
        if (lid.x == 0u) {
            work[l + j * m + j] = ljj;
        }
        for (var i = j + 1u + lid.x; i < m; i += WG) {
            let lij = work[l + i * m + j];
            for (var c = j + 1u; c <= i; c++) {
                work[l + i * m + c] = work[l + i * m + c] - lij * work[l + c * m + j];
            }
        }
        storageBarrier();
    }
    if (lid.x == 0u) {
        state[STATE_COARSE_FAILED] = select(1u, 0u, ok);
    }
}

// Column c of X = L⁻¹ per invocation, row by row (each row's sum in the specification's
// order): no barrier, and the chain of a column is its m − c rows.
@compute @workgroup_size(WG)
fn agg_linv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let m = fp.m;
    let l = fp.l_at;
    let x = fp.x_at;
    for (var c = grid_index(gid, nwg); c < m; c += grid_stride(nwg)) {
        work[x + c * m + c] = acc(1.0) / work[l + c * m + c];
        for (var i = c + 1u; i < m; i++) {
            var t = acc(0.0);
            for (var j = c; j < i; j++) {
                t = t - work[l + i * m + j] * work[x + c * m + j];
            }
            work[x + c * m + i] = t / work[l + i * m + i];
        }
    }
}

@compute @workgroup_size(WG)
fn agg_cinv(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (state[STATE_COARSE_FAILED] != 0u) {
        return;
    }
    let m = fp.m;
    let x = fp.x_at;
    for (var t = grid_index(gid, nwg); t < m * m; t += grid_stride(nwg)) {
        let p = t / m;
        let q = t % m;
        if (q > p) {
            continue;
        }
        // X_ip X_iq, X read transposed: rows p and q of the upper part.
        var s = acc(0.0);
        for (var i = p; i < m; i++) {
            s += work[x + p * m + i] * work[x + q * m + i];
        }
        work[fp.c_at + p * m + q] = s;
    }
}

@compute @workgroup_size(WG)
fn agg_expand(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let failed = state[STATE_COARSE_FAILED] != 0u;
    let k = fp.k;
    let m = fp.m;
    for (var t = grid_index(gid, nwg); t < k * k; t += grid_stride(nwg)) {
        let r = t / k;
        let c = t % k;
        if (c > r) {
            continue;
        }
        let a = r / D;
        let b = c / D;
        var s = acc(0.0);
        if (!failed) {
            for (var p = basis[a]; p < basis[a + 1u]; p++) {
                for (var q = basis[b]; q < basis[b + 1u]; q++) {
                    var cpq = work[fp.c_at + q * m + p];
                    if (p >= q) {
                        cpq = work[fp.c_at + p * m + q];
                    }
                    s += w_at(p, r % D) * cpq * w_at(q, c % D);
                }
            }
        }
        coarse[fp.einv_at + r * k + c] = s;
        coarse[fp.einv_at + c * k + r] = s;
    }
}
