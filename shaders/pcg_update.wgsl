// b̂ = −P Vᵀ g into b, or (`form` false) b as the host wrote it, with the ‖b̂‖² partials.
fn rhs_partials(lid: u32, wid: vec3<u32>, nwg: vec3<u32>, form: bool) {
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var bb = acc(0.0);
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid;
            if (i >= params.n_nodes) {
                break;
            }
            if (form) {
                var g: array<real, 3>;
                for (var a = 0u; a < D; a++) {
                    g[a] = grad[i * D + a];
                }
                let t = to_frame(i, g);
                for (var a = 0u; a < D; a++) {
                    b[i * D + a] = select(-t[a], real(0.0), fixed(i, a));
                }
            }
            for (var a = 0u; a < D; a++) {
                let v = b[i * D + a];
                bb += acc(v) * acc(v);
            }
        }
        workgroup_sum(lid, sum1(bb), 1u);
        if (lid == 0u) {
            partials[PART_BB * params.n_partials + s] = summed(0u);
        }
        // The tree's memory is reused by the next segment.
        workgroupBarrier();
    }
}

@compute @workgroup_size(WG)
fn rhs(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    rhs_partials(lid.x, wid, nwg, true);
}

@compute @workgroup_size(WG)
fn rhs_given(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    rhs_partials(lid.x, wid, nwg, false);
}

// The preconditioners from the diagonal blocks of Ĥ: B = P V_iᵀ H_ii V_i P + (I − P).
// Jacobi and block Jacobi by the one specification (common.wgsl, block_jacobi_inverse).
@compute @workgroup_size(WG)
fn precond(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var i = params.row_begin + grid_index(gid, nwg); i < params.row_end; i += grid_stride(nwg)) {
        let k = pattern[params.diag_at + i] - params.block_first;
        var h: array<real, 9>;
        for (var t = 0u; t < dd; t++) {
            h[t] = hvals[k * dd + t];
        }
        let ri = rot_of(i);
        if (ri != NO_ROTATION) {
            // h := V_iᵀ h V_i.
            var t1: array<real, 9>;
            for (var a = 0u; a < D; a++) {
                for (var c = 0u; c < D; c++) {
                    var s = real(0.0);
                    for (var m = 0u; m < D; m++) {
                        s += h[a * D + m] * rotations[ri * dd + m * D + c];
                    }
                    t1[a * D + c] = s;
                }
            }
            for (var a = 0u; a < D; a++) {
                for (var c = 0u; c < D; c++) {
                    var s = real(0.0);
                    for (var m = 0u; m < D; m++) {
                        s += rotations[ri * dd + m * D + a] * t1[m * D + c];
                    }
                    h[a * D + c] = s;
                }
            }
        }
        for (var a = 0u; a < D; a++) {
            for (var c = 0u; c < D; c++) {
                if (fixed(i, a) || fixed(i, c)) {
                    h[a * D + c] = select(real(0.0), real(1.0), a == c);
                }
            }
        }
        for (var a = 0u; a < D; a++) {
            minv[params.n_nodes * dd + i * D + a] = jacobi_inverse(h[a * D + a]);
        }
        let inv = block_jacobi_inverse(h, D);
        for (var e = 0u; e < dd; e++) {
            minv[i * dd + e] = inv[e];
        }
    }
}

// α = ρ / p·q from the product's partials, summed by every workgroup of update_yr in the
// same fixed order (the same bits everywhere), so no one-workgroup kernel and no wait sits
// between the product and the updates. A non-positive p·q halts, a NaN one is a breakdown:
// every workgroup sees it and returns; the first also raises the flags. Returns α, or a
// negative value when the iteration stops here. The first workgroup also keeps p·q, α and
// the ρ this α used (SCAL_RHO_OLD: update_p's β divides by it, while its first workgroup
// replaces SCAL_RHO).
fn fused_alpha(lid: u32, first: bool) -> acc {
    let pq = reduce_slot(PART_PQ, lid);
    let rho = scal[SCAL_RHO];
    let go = pq > acc(0.0);
    if (first && lid == 0u) {
        scal[SCAL_PQ] = pq;
        if (go) {
            scal[SCAL_ALPHA] = rho / pq;
            scal[SCAL_RHO_OLD] = rho;
        } else {
            state[STATE_DONE] = 1u;
            if (pq <= acc(0.0)) {
                state[STATE_HALT] = 1u;
            } else {
                state[STATE_BREAKDOWN] = 1u;
            }
        }
    }
    if (!go) {
        return acc(-1.0);
    }
    return rho / pq;
}

// The r·z and r·r partials of one workgroup and, with COARSE, those of Zᵀr (one tree).
// `sums`: r·z, r·r, then (COARSE = 1) Zᵀr.
fn write_rz_rr(lid: u32, wg: u32, sums: array<acc, 5>) {
    let n = select(2u, 2u + D, COARSE == 1u);
    workgroup_sum(lid, sums, n);
    if (lid == 0u) {
        let np = params.n_partials;
        partials[PART_RZ * np + wg] = summed(0u);
        partials[PART_RR * np + wg] = summed(1u);
        for (var a = 0u; a + 2u < n; a++) {
            partials[(PART_ZR + a) * np + wg] = summed(2u + a);
        }
    }
}

// z_i = M⁻¹r_i (and p_i = z_i at a start), with node i's shares of r·z and r·r and
// (COARSE = 1) Zᵀr added to sums[0], sums[1] and sums[2..].
fn precondition(i: u32, rv: array<real, 3>, start: bool, sums: ptr<function, array<acc, 5>>) {
    if (PRECOND == 3u) {
        for (var a = 0u; a < D; a++) {
            (*sums)[1] += acc(rv[a]) * acc(rv[a]);
        }
        return;
    }
    let zv = apply_precond(i, rv);
    for (var a = 0u; a < D; a++) {
        z[i * D + a] = zv[a];
        if (start) {
            p[i * D + a] = zv[a];
        }
        (*sums)[0] += acc(rv[a]) * acc(zv[a]);
        (*sums)[1] += acc(rv[a]) * acc(rv[a]);
    }
    if (COARSE == 1u) {
        let w = zt(i, rv);
        for (var a = 0u; a < D; a++) {
            (*sums)[2u + a] += acc(w[a]);
        }
    }
}

// α (fused_alpha), then y += αp, r −= αq, z = M⁻¹r, with the r·z and r·r partials.
@compute @workgroup_size(WG)
fn update_yr(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    let a = fused_alpha(lid.x, group_index(wid, nwg) == 0u);
    if (a < acc(0.0)) {
        return;
    }
    let alpha = real(a);
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var sums: array<acc, 5>;
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid.x;
            if (i >= params.n_nodes) {
                break;
            }
            var rv: array<real, 3>;
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                y[k] += alpha * p[k];
                rv[a] = r[k] - alpha * q[k];
                r[k] = rv[a];
            }
            precondition(i, rv, false, &sums);
        }
        write_rz_rr(lid.x, s, sums);
        workgroupBarrier();
    }
}

// ρ' = r·z (with COARSE r·M_J⁻¹r + Zᵀr·c, and c = E⁺Zᵀr) and r·r from update_yr's
// partials (ml_dot's r·z under the multilevel preconditioner), summed by every workgroup
// of update_p in the same fixed order. Stops on r·r ≤ tol²‖b̂‖² (the recurrence residual)
// or a non-finite value, else β = ρ'/ρ with ρ the one α used (SCAL_RHO_OLD). The first
// workgroup counts the iteration, records the Lanczos pair and keeps r·r, β, ρ' and c.
// Returns β (every workgroup, uniform) and c in `c` (COARSE = 1), or a negative β when
// the run stops here.
fn fused_beta(lid: u32, first: bool, c: ptr<function, array<acc, 3>>) -> acc {
    var v = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    let np = params.n_partials;
    var n = 2u;
    if (COARSE == 1u) {
        n = 2u + D;
    } else if (COARSE == 2u) {
        n = 3u;
        v[2] = agg_wc(lid);
    }
    for (var t = lid; t < np; t += WG) {
        v[0] += partials[PART_RZ * np + t];
        v[1] += partials[PART_RR * np + t];
        if (COARSE == 1u) {
            for (var a = 0u; a < D; a++) {
                v[2u + a] += partials[(PART_ZR + a) * np + t];
            }
        }
    }
    let s = workgroup_sum_uniform(lid, v, n);
    var rz = s[0];
    let rr = s[1];
    if (COARSE == 1u) {
        rz += coarse_c(array<acc, 3>(s[2], s[3], s[4]), c);
    } else if (COARSE == 2u) {
        rz += s[2];
    }
    // NaN fails every comparison: a non-finite ρ or r·r is a breakdown.
    let broken = !(rz >= acc(0.0)) || !(rr >= acc(0.0));
    let converged = !broken && rr <= scal[SCAL_TOL2] * scal[SCAL_BB];
    let beta = rz / scal[SCAL_RHO_OLD];
    if (first && lid == 0u) {
        let it = state[STATE_ITERS];
        state[STATE_ITERS] = it + 1u;
        if (it < HIST) {
            scal[SCAL_HIST + 2u * it] = scal[SCAL_ALPHA];
        }
        scal[SCAL_RR] = rr;
        if (COARSE == 1u) {
            for (var a = 0u; a < D; a++) {
                scal[SCAL_C + a] = (*c)[a];
            }
        }
        if (broken) {
            state[STATE_DONE] = 1u;
            state[STATE_BREAKDOWN] = 1u;
        } else if (converged) {
            state[STATE_DONE] = 1u;
            state[STATE_CONVERGED] = 1u;
        } else {
            scal[SCAL_BETA] = beta;
            scal[SCAL_RHO] = rz;
            if (it < HIST) {
                scal[SCAL_HIST + 2u * it + 1u] = beta;
            }
        }
    }
    if (broken || converged) {
        return acc(-1.0);
    }
    return beta;
}

// The r·z partials after the V-cycle (PRECOND = 3); at a start (ml_start) also p = z and
// pw = V P p.
fn ml_rz(lid: u32, wid: vec3<u32>, nwg: vec3<u32>, start: bool) {
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var rz = acc(0.0);
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid;
            if (i >= params.n_nodes) {
                break;
            }
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                rz += acc(r[k]) * acc(z[k]);
                if (start) {
                    p[k] = z[k];
                }
            }
            if (start) {
                write_world(i);
            }
        }
        workgroup_sum(lid, sum1(rz), 1u);
        if (lid == 0u) {
            partials[PART_RZ * params.n_partials + s] = summed(0u);
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(WG)
fn ml_dot(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    ml_rz(lid.x, wid, nwg, false);
}

@compute @workgroup_size(WG)
fn ml_start(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!starting(lid.x)) {
        return;
    }
    ml_rz(lid.x, wid, nwg, true);
}

// p = z + βp (and pw); with COARSE p = (z + Zc) + βp, the preconditioned residual
// completed. `c` is c = E⁺Zᵀr under COARSE = 1 (the aggregates' c is in `coarse`).
fn new_direction(lid: u32, wid: vec3<u32>, nwg: vec3<u32>, beta: real, c1: array<acc, 3>) {
    if (COARSE == 0u) {
        for (var i = group_index(wid, nwg) * WG + lid; i < params.n_nodes; i += grid_stride(nwg)) {
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                p[k] = z[k] + beta * p[k];
            }
            write_world(i);
        }
        return;
    }
    var c: array<real, 3>;
    if (COARSE == 1u) {
        for (var a = 0u; a < D; a++) {
            c[a] = real(c1[a]);
        }
    }
    for (var i = group_index(wid, nwg) * WG + lid; i < params.n_nodes; i += grid_stride(nwg)) {
        if (COARSE == 2u) {
            let ag = aggregates[aggregates[AGG_OF] + i];
            for (var a = 0u; a < D; a++) {
                c[a] = real(0.0);
                if (ag != NO_AGGREGATE) {
                    c[a] = real(coarse[aggregates[AGG_C] + ag * D + a]);
                }
            }
        }
        let w = zc(i, c);
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            p[k] = (z[k] + w[a]) + beta * p[k];
        }
        write_world(i);
    }
}

// The iteration's last dispatch: β (fused_beta), then p = z (+ Zc) + βp and pw.
@compute @workgroup_size(WG)
fn update_p(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    var c: array<acc, 3>;
    let beta = fused_beta(lid.x, group_index(wid, nwg) == 0u, &c);
    if (beta < acc(0.0)) {
        return;
    }
    new_direction(lid.x, wid, nwg, real(beta), c);
}

// After scalar_start: p = z (+ Zc) + βp with the β and c scalar_start left in scal (β = 0
// at a fresh start under COARSE, a resumed segment's β otherwise).
@compute @workgroup_size(WG)
fn start_p(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!running(lid.x)) {
        return;
    }
    var c: array<acc, 3>;
    if (COARSE == 1u) {
        for (var a = 0u; a < D; a++) {
            c[a] = scal[SCAL_C + a];
        }
    }
    new_direction(lid.x, wid, nwg, real(scal[SCAL_BETA]), c);
}

// A (re)start from y, with q = Ĥy already in q: r = b̂ − q, z = M⁻¹r, p = z, and the r·z
// and r·r partials (r·r of the true residual); with COARSE z = M_J⁻¹r and the Zᵀr
// partials too, and update_p (β = 0) then adds Zc to p.
@compute @workgroup_size(WG)
fn init(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (!starting(lid.x)) {
        return;
    }
    for (var s = group_index(wid, nwg); s < params.n_partials; s += group_count(nwg)) {
        var sums: array<acc, 5>;
        for (var m = 0u; m < ITEMS; m++) {
            let i = (s * ITEMS + m) * WG + lid.x;
            if (i >= params.n_nodes) {
                break;
            }
            var rv: array<real, 3>;
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                rv[a] = b[k] - q[k];
                r[k] = rv[a];
            }
            // A resumed segment keeps p: update_p then forms p = z + βp and writes pw.
            let fresh = !resuming();
            precondition(i, rv, fresh, &sums);
            // With COARSE, the update_p that completes p writes pw; with the multilevel
            // preconditioner ml_start does.
            if (COARSE == 0u && PRECOND != 3u && fresh) {
                write_world(i);
            }
        }
        write_rz_rr(lid.x, s, sums);
        workgroupBarrier();
    }
}

// After init (one workgroup): ρ, the true r·r and ‖b̂‖²; stops when the true residual
// meets the tolerance (always when b̂ = 0 and y = 0). With COARSE also c = E⁺Zᵀr (Zᵀr in
// a second tree), ρ += Zᵀr·c, and β = 0 for the update_p that completes p = z + Zc.
// Resuming, β = s·ρ/ρ_prev (s = SCAL_PSCALE, the old direction's rescaling, ρ_prev
// already in the new scaling) for the update_p that forms p = z (+ Zc) + β p_old.
@compute @workgroup_size(WG)
fn scalar_start(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (!starting(lid.x)) {
        return;
    }
    var v = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    var w = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    let np = params.n_partials;
    for (var t = lid.x; t < np; t += WG) {
        v[0] += partials[PART_RZ * np + t];
        v[1] += partials[PART_RR * np + t];
        v[2] += partials[PART_BB * np + t];
        if (COARSE == 1u) {
            for (var a = 0u; a < D; a++) {
                w[a] += partials[(PART_ZR + a) * np + t];
            }
        }
    }
    let s = workgroup_sum_uniform(lid.x, v, 3u);
    var zr: array<acc, 3>;
    if (COARSE == 1u) {
        let sw = workgroup_sum_uniform(lid.x, w, D);
        zr = array<acc, 3>(sw[0], sw[1], sw[2]);
    }
    var wc = acc(0.0);
    if (COARSE == 2u) {
        wc = workgroup_sum_uniform1(lid.x, agg_wc(lid.x));
    }
    if (lid.x == 0u) {
        var rz = s[0];
        let rr = s[1];
        let bb = s[2];
        if (COARSE == 1u) {
            var c: array<acc, 3>;
            rz += coarse_c(zr, &c);
            for (var a = 0u; a < D; a++) {
                scal[SCAL_C + a] = c[a];
            }
        } else if (COARSE == 2u) {
            rz += wc;
        }
        if (resuming()) {
            scal[SCAL_BETA] = scal[SCAL_PSCALE] * rz / scal[SCAL_RHO_PREV];
        } else if (COARSE != 0u) {
            scal[SCAL_BETA] = acc(0.0);
        }
        scal[SCAL_RHO] = rz;
        scal[SCAL_RR] = rr;
        scal[SCAL_BB] = bb;
        if (!VERIFY && scal[SCAL_RULE_ON] > acc(0.0)) {
            let eta = rule_tolerance(bb);
            scal[SCAL_TOL2] = eta * eta;
            scal[SCAL_ETA] = eta;
            scal[SCAL_RULE_ON] = acc(0.0);
        }
        let finite = rz >= acc(0.0) && rr >= acc(0.0) && bb >= acc(0.0);
        if (!finite) {
            state[STATE_DONE] = 1u;
            state[STATE_BREAKDOWN] = 1u;
        } else if (rr <= scal[SCAL_TOL2] * bb) {
            state[STATE_DONE] = 1u;
            state[STATE_CONVERGED] = 1u;
        }
        if (VERIFY) {
            state[STATE_TRUE_OK] = select(0u, 1u, finite && rr <= scal[SCAL_TOL2] * bb);
        }
    }
}

// The tolerance of a solve from the rule the host gave (src/solve/tolerance.rs,
// ToleranceRule::eval, the one specification; the same operations in the same order):
// η = γ (‖b̂‖/‖b̂_prev‖)², raised to the guard where one is given (> 0; a NaN η takes it
// too), η_hi where η is not a number, else clamped to [η_lo, η_hi].
fn rule_tolerance(bb: acc) -> acc {
    let ratio = sqrt(bb) / scal[SCAL_RULE_PREV];
    var eta = scal[SCAL_RULE_GAMMA] * (ratio * ratio);
    let guard = scal[SCAL_RULE_GUARD];
    if (guard > acc(0.0) && !(eta >= guard)) {
        eta = guard;
    }
    let lo = scal[SCAL_RULE_LO];
    let hi = scal[SCAL_RULE_HI];
    if (!(eta >= acc(0.0))) {
        return hi;
    }
    if (eta < lo) {
        return lo;
    }
    if (eta > hi) {
        return hi;
    }
    return eta;
}

// A verification's end (one workgroup): its true residual is known, so no later
// verification kernel of the submit runs again.
@compute @workgroup_size(WG)
fn verified(@builtin(local_invocation_id) lid: vec3<u32>) {
    let on = starting(lid.x);
    if (on && lid.x == 0u) {
        state[STATE_VERIFIED] = 1u;
    }
}

