// Device-resident PCG updates. Per iteration the host records three dispatches:
//   update_p   (A): ρ = r·z and r·r reduced from the partials of C; stop flags; p = z + βp
//   matvec     (B): q = Ĥp fused with p·q partials (matvec.wgsl or springs.wgsl)
//   update_xrz (C): α = ρ / p·q reduced from B's partials; x += αp; r −= αq; z = M⁻¹r;
//                   r·z and r·r partials
// Reductions are deterministic two-pass sums: a fixed number G of workgroups writes one
// partial each, and every workgroup of the next dispatch sums the same G partials in the
// same fixed order (so all workgroups agree on α, β and the stop decision bit for bit).
// Scalars never leave the device; the host reads `scal` and `state` once per chunk.
//
// Slot discipline (no workgroup reads a slot another workgroup of the same dispatch writes;
// the slot names are constants shared with the host, `gpu::kernels::slots`):
//   scal:  SCAL_RHO ρ (A writes, C reads)  SCAL_RHO_PREV ρ_prev (C writes, A reads)
//          SCAL_PQ p·q (C)  SCAL_ALPHA α (C)  SCAL_RR r·r (A)
//          SCAL_THRESH threshold tol²‖b‖² (host)  SCAL_PSCALE direction scale kept by
//          init (host)  SCAL_BETA0 β of the first update_p of a run (A, workgroup 0)
//          SCAL_HIST + 2j: α_j (C)   SCAL_HIST + 2j + 1: β_{j+1} (A), for j < HIST: the
//          Lanczos coefficients of this run, from which the host estimates κ(M⁻¹Ĥ)
//   partials: PART_PQ p·q (B), PART_RZ r·z, PART_RR r·r (C or init), PART_ZR..+D Zᵀr
//          (C or init, COARSE)
//   state: STATE_DONE (A writes, B/C read)  STATE_HALT non-positive curvature (C writes,
//          A reads)  STATE_ITERS iterations (C, workgroup 0 only)  STATE_CONVERGED (A)
//          STATE_BREAKDOWN (A)

override D: u32 = 3u;
override PRECOND: u32 = 1u;   // 0 none, 1 Jacobi, 2 block-Jacobi
override HIST: u32 = 0u;      // Lanczos coefficients recorded per run (0: none)
// Coarse correction on the rigid translations (src/coarse.rs): z = M⁻¹r + Z E⁺ Zᵀr with
// Z_i = P_i V_iᵀ computed on the fly from the mask and the rotations (no basis stored).
// C and init write the partials of r·M⁻¹r and Zᵀr; A reduces them, forms c = E⁺Zᵀr and
// ρ = r·M⁻¹r + Zᵀr·c, and adds Z_i c to p. z holds M⁻¹r only.
override COARSE: bool = false;
// Coarse correction on the translations of N_AGG aggregates (coarse.wgsl): C and init
// write r·M⁻¹r only; the restrict and solve dispatches that follow them leave w = Zᵀr and
// c = E⁺w in `wc`, and A adds w·c to ρ and Z_i c_{agg(i)} to p.
override AGG: bool = false;
override N_AGG: u32 = 1u;
override MASKED: bool = false;
override ROTATED: bool = false;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> x: array<real>;
@group(0) @binding(2) var<storage, read_write> r: array<real>;
@group(0) @binding(3) var<storage, read_write> z: array<real>;
@group(0) @binding(4) var<storage, read_write> p: array<real>;
@group(0) @binding(5) var<storage, read> q: array<real>;
@group(0) @binding(6) var<storage, read> b: array<real>;
@group(0) @binding(7) var<storage, read> minv: array<real>;
@group(0) @binding(8) var<storage, read_write> partials: array<acc>;
@group(0) @binding(9) var<storage, read_write> scal: array<acc>;
@group(0) @binding(10) var<storage, read_write> state: array<u32>;
@group(0) @binding(11) var<storage, read> cmask: array<u32>;
@group(0) @binding(12) var<storage, read> rot_index: array<u32>;
@group(0) @binding(13) var<storage, read> rotations: array<real>;
@group(0) @binding(14) var<storage, read> einv: array<acc>;
@group(0) @binding(15) var<storage, read> agg_of: array<u32>;
@group(0) @binding(16) var<storage, read> wc: array<acc>;

var<workgroup> wg_u: u32;

// Sum of partial slot `slot` in a fixed order, identical in every workgroup.
fn reduce_slot(slot: u32, lid: u32) -> acc {
    var s = acc(0.0);
    for (var t = lid; t < params.n_partials; t += WG) {
        s += partials[slot * params.n_partials + t];
    }
    return workgroup_sum_uniform1(lid, s);
}

// The partials of C and init: r·z and r·r and, with COARSE, Zᵀr, in one tree.
fn write_partials(lid: u32, wg: u32, prz: acc, prr: acc, zr: vec3<acc>) {
    let n = select(2u, 2u + D, COARSE);
    workgroup_sum(lid, array<acc, 5>(prz, prr, zr.x, zr.y, zr.z), n);
    if (lid == 0u) {
        let np = params.n_partials;
        partials[PART_RZ * np + wg] = summed(0u);
        partials[PART_RR * np + wg] = summed(1u);
        for (var a = 0u; a + 2u < n; a++) {
            partials[(PART_ZR + a) * np + wg] = summed(2u + a);
        }
    }
}

// COARSE: r·z, r·r and Zᵀr summed in one pass and one tree, identical in every workgroup:
// (r·z, r·r, Zᵀr.x, Zᵀr.y) and Zᵀr.z.
fn reduce_coarse(lid: u32) -> array<acc, 5> {
    let np = params.n_partials;
    var v = vec4<acc>(acc(0.0));
    var w = acc(0.0);
    for (var t = lid; t < np; t += WG) {
        v += vec4<acc>(
            partials[PART_RZ * np + t],
            partials[PART_RR * np + t],
            partials[PART_ZR * np + t],
            partials[(PART_ZR + 1u) * np + t],
        );
        if (D == 3u) {
            w += partials[(PART_ZR + 2u) * np + t];
        }
    }
    return workgroup_sum_uniform(lid, array<acc, 5>(v.x, v.y, v.z, v.w, w), 2u + D);
}

// AGG: w·c = Zᵀr·E⁺Zᵀr from coarse.wgsl's output, identical in every workgroup.
fn wc_dot(lid: u32) -> acc {
    let kc = D * N_AGG;
    var s = acc(0.0);
    for (var t = lid; t < kc; t += WG) {
        s += wc[t] * wc[kc + t];
    }
    return workgroup_sum_uniform1(lid, s);
}

// Component a of node i is constrained (bit a of its mask).
fn cbits3(i: u32) -> vec3<bool> {
    if (!MASKED) {
        return vec3<bool>(false);
    }
    let m = cmask[i];
    return ((vec3<u32>(m) >> vec3<u32>(0u, 1u, 2u)) & vec3<u32>(1u)) != vec3<u32>(0u);
}

fn cbits2(i: u32) -> vec2<bool> {
    if (!MASKED) {
        return vec2<bool>(false);
    }
    let m = cmask[i];
    return ((vec2<u32>(m) >> vec2<u32>(0u, 1u)) & vec2<u32>(1u)) != vec2<u32>(0u);
}

// V_r[a][b], row-major: its columns are the frame basis.
fn rv_at(ri: u32, a: u32, b: u32) -> real {
    return rotations[ri * D * D + a * D + b];
}

// Z_iᵀ r_i = V_i P_i r_i (the node's share of Zᵀr), D = 3.
fn zt3(i: u32, rv: vec3<real>) -> vec3<acc> {
    var w = select(rv, vec3<real>(real(0.0)), cbits3(i));
    if (ROTATED) {
        let ri = rot_index[i];
        if (ri != NO_ROTATION) {
            w = vec3<real>(
                rv_at(ri, 0u, 0u) * w.x + rv_at(ri, 0u, 1u) * w.y + rv_at(ri, 0u, 2u) * w.z,
                rv_at(ri, 1u, 0u) * w.x + rv_at(ri, 1u, 1u) * w.y + rv_at(ri, 1u, 2u) * w.z,
                rv_at(ri, 2u, 0u) * w.x + rv_at(ri, 2u, 1u) * w.y + rv_at(ri, 2u, 2u) * w.z,
            );
        }
    }
    return vec3<acc>(w);
}

fn zt2(i: u32, rv: vec2<real>) -> vec3<acc> {
    var w = select(rv, vec2<real>(real(0.0)), cbits2(i));
    if (ROTATED) {
        let ri = rot_index[i];
        if (ri != NO_ROTATION) {
            w = vec2<real>(
                rv_at(ri, 0u, 0u) * w.x + rv_at(ri, 0u, 1u) * w.y,
                rv_at(ri, 1u, 0u) * w.x + rv_at(ri, 1u, 1u) * w.y,
            );
        }
    }
    return vec3<acc>(acc(w.x), acc(w.y), acc(0.0));
}

// Z_i c = P_i V_iᵀ c, D = 3.
fn zc3(i: u32, c: vec3<real>) -> vec3<real> {
    var t = c;
    if (ROTATED) {
        let ri = rot_index[i];
        if (ri != NO_ROTATION) {
            t = vec3<real>(
                rv_at(ri, 0u, 0u) * c.x + rv_at(ri, 1u, 0u) * c.y + rv_at(ri, 2u, 0u) * c.z,
                rv_at(ri, 0u, 1u) * c.x + rv_at(ri, 1u, 1u) * c.y + rv_at(ri, 2u, 1u) * c.z,
                rv_at(ri, 0u, 2u) * c.x + rv_at(ri, 1u, 2u) * c.y + rv_at(ri, 2u, 2u) * c.z,
            );
        }
    }
    return select(t, vec3<real>(real(0.0)), cbits3(i));
}

fn zc2(i: u32, c: vec2<real>) -> vec2<real> {
    var t = c;
    if (ROTATED) {
        let ri = rot_index[i];
        if (ri != NO_ROTATION) {
            t = vec2<real>(
                rv_at(ri, 0u, 0u) * c.x + rv_at(ri, 1u, 0u) * c.y,
                rv_at(ri, 0u, 1u) * c.x + rv_at(ri, 1u, 1u) * c.y,
            );
        }
    }
    return select(t, vec2<real>(real(0.0)), cbits2(i));
}

// z_i = M_i⁻¹ r_i for any PRECOND, node-wise (the COARSE and block-Jacobi paths).
fn pz3(i: u32, rv: vec3<real>) -> vec3<real> {
    if (PRECOND == 2u) {
        return block3(i, rv);
    }
    if (PRECOND == 1u) {
        let k = 3u * i;
        return vec3<real>(minv[k], minv[k + 1u], minv[k + 2u]) * rv;
    }
    return rv;
}

fn pz2(i: u32, rv: vec2<real>) -> vec2<real> {
    if (PRECOND == 2u) {
        return block2(i, rv);
    }
    if (PRECOND == 1u) {
        let k = 2u * i;
        return vec2<real>(minv[k], minv[k + 1u]) * rv;
    }
    return rv;
}

// Block-Jacobi z_i = M_i⁻¹ r_i, explicit 3- and 2-component paths (no private arrays).
fn block3(i: u32, rv: vec3<real>) -> vec3<real> {
    let m = 9u * i;
    return vec3<real>(
        minv[m] * rv.x + minv[m + 1u] * rv.y + minv[m + 2u] * rv.z,
        minv[m + 3u] * rv.x + minv[m + 4u] * rv.y + minv[m + 5u] * rv.z,
        minv[m + 6u] * rv.x + minv[m + 7u] * rv.y + minv[m + 8u] * rv.z,
    );
}

fn block2(i: u32, rv: vec2<real>) -> vec2<real> {
    let m = 4u * i;
    return vec2<real>(minv[m] * rv.x + minv[m + 1u] * rv.y, minv[m + 2u] * rv.x + minv[m + 3u] * rv.y);
}

// z_k = M⁻¹ r_k for the diagonal preconditioners (0 none, 1 Jacobi), one component.
fn diag_z(k: u32, rk: real) -> real {
    if (PRECOND == 1u) {
        return minv[k] * rk;
    }
    return rk;
}

@compute @workgroup_size(WG)
fn update_p(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    var rz: acc;
    var rr: acc;
    // Coarse coefficients c = E⁺Zᵀr (zero without COARSE).
    var cc = vec3<acc>(acc(0.0));
    if (AGG) {
        rz = reduce_slot(PART_RZ, lid.x) + wc_dot(lid.x);
        rr = reduce_slot(PART_RR, lid.x);
    } else if (!COARSE) {
        rz = reduce_slot(PART_RZ, lid.x);
        rr = reduce_slot(PART_RR, lid.x);
    } else {
        let red = reduce_coarse(lid.x);
        rz = red[0];
        rr = red[1];
        let zr = vec3<acc>(red[2], red[3], red[4]);
        for (var a = 0u; a < D; a++) {
            var s = acc(0.0);
            for (var b = 0u; b < D; b++) {
                s += einv[a * D + b] * zr[b];
            }
            cc[a] = s;
        }
        rz += dot(zr, cc);
    }
    if (lid.x == 0u) {
        wg_u = state[STATE_HALT];
    }
    let halt = workgroupUniformLoad(&wg_u);
    let conv = rr <= scal[SCAL_THRESH];
    // NaN fails every comparison: a non-finite ρ or r·r is a breakdown, never convergence.
    let bad = !(rz >= acc(0.0)) || !(rr >= acc(0.0));
    let stop = halt != 0u || conv || bad;
    if (group_index(wid, nwg) == 0u && lid.x == 0u) {
        scal[SCAL_RHO] = rz;
        scal[SCAL_RR] = rr;
        if (stop) {
            state[STATE_DONE] = 1u;
            if (halt == 0u && !bad && conv) {
                state[STATE_CONVERGED] = 1u;
            }
            if (halt == 0u && bad) {
                state[STATE_BREAKDOWN] = 1u;
            }
        }
    }
    if (stop) {
        return;
    }
    let beta_acc = rz / scal[SCAL_RHO_PREV];
    let beta = real(beta_acc);
    if (group_index(wid, nwg) == 0u && lid.x == 0u) {
        let it = state[STATE_ITERS];
        if (it == 0u) {
            scal[SCAL_BETA0] = beta_acc;
        } else if (it <= HIST) {
            scal[SCAL_HIST + 2u * (it - 1u) + 1u] = beta_acc;
        }
    }
    let stride = params.n_partials * WG;
    if (AGG) {
        let kc = D * N_AGG;
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let g = agg_of[i];
            var c = vec3<real>(real(0.0));
            if (g != NO_AGGREGATE) {
                let o = kc + g * D;
                c = vec3<real>(real(wc[o]), real(wc[o + 1u]), real(wc[o + D - 1u]));
            }
            if (D == 3u) {
                let k = 3u * i;
                let zv = vec3<real>(z[k], z[k + 1u], z[k + 2u]) + zc3(i, c);
                p[k] = zv.x + beta * p[k];
                p[k + 1u] = zv.y + beta * p[k + 1u];
                p[k + 2u] = zv.z + beta * p[k + 2u];
            } else {
                let k = 2u * i;
                let zv = vec2<real>(z[k], z[k + 1u]) + zc2(i, c.xy);
                p[k] = zv.x + beta * p[k];
                p[k + 1u] = zv.y + beta * p[k + 1u];
            }
        }
    } else if (!COARSE) {
        let n = params.n_nodes * D;
        for (var k = group_index(wid, nwg) * WG + lid.x; k < n; k += stride) {
            p[k] = z[k] + beta * p[k];
        }
    } else if (D == 3u) {
        let c = vec3<real>(cc);
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 3u * i;
            let zv = vec3<real>(z[k], z[k + 1u], z[k + 2u]) + zc3(i, c);
            p[k] = zv.x + beta * p[k];
            p[k + 1u] = zv.y + beta * p[k + 1u];
            p[k + 2u] = zv.z + beta * p[k + 2u];
        }
    } else {
        let c = vec2<real>(real(cc.x), real(cc.y));
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 2u * i;
            let zv = vec2<real>(z[k], z[k + 1u]) + zc2(i, c);
            p[k] = zv.x + beta * p[k];
            p[k + 1u] = zv.y + beta * p[k + 1u];
        }
    }
}

@compute @workgroup_size(WG)
fn update_xrz(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (lid.x == 0u) {
        wg_u = state[STATE_DONE];
    }
    if (workgroupUniformLoad(&wg_u) != 0u) {
        return;
    }
    let pq = reduce_slot(PART_PQ, lid.x);
    if (!(pq > acc(0.0))) {
        if (group_index(wid, nwg) == 0u && lid.x == 0u) {
            state[STATE_HALT] = 1u;
            scal[SCAL_PQ] = pq;
        }
        return;
    }
    let alpha_acc = scal[SCAL_RHO] / pq;
    let alpha = real(alpha_acc);
    var prz = acc(0.0);
    var prr = acc(0.0);
    var zr = vec3<acc>(acc(0.0));
    let stride = params.n_partials * WG;
    if (PRECOND != 2u && !COARSE) {
        // Diagonal preconditioners: element-wise over the d·n components.
        let n = params.n_nodes * D;
        for (var k = group_index(wid, nwg) * WG + lid.x; k < n; k += stride) {
            x[k] += alpha * p[k];
            let rk = r[k] - alpha * q[k];
            r[k] = rk;
            let zk = diag_z(k, rk);
            z[k] = zk;
            prz += acc(rk) * acc(zk);
            prr += acc(rk) * acc(rk);
        }
    } else if (D == 3u) {
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 3u * i;
            let pv = vec3<real>(p[k], p[k + 1u], p[k + 2u]);
            let xv = vec3<real>(x[k], x[k + 1u], x[k + 2u]) + alpha * pv;
            let qv = vec3<real>(q[k], q[k + 1u], q[k + 2u]);
            let rv = vec3<real>(r[k], r[k + 1u], r[k + 2u]) - alpha * qv;
            let zv = pz3(i, rv);
            if (COARSE) {
                zr += zt3(i, rv);
            }
            x[k] = xv.x;
            x[k + 1u] = xv.y;
            x[k + 2u] = xv.z;
            r[k] = rv.x;
            r[k + 1u] = rv.y;
            r[k + 2u] = rv.z;
            z[k] = zv.x;
            z[k + 1u] = zv.y;
            z[k + 2u] = zv.z;
            prz += acc(rv.x) * acc(zv.x) + acc(rv.y) * acc(zv.y) + acc(rv.z) * acc(zv.z);
            prr += acc(rv.x) * acc(rv.x) + acc(rv.y) * acc(rv.y) + acc(rv.z) * acc(rv.z);
        }
    } else {
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 2u * i;
            let pv = vec2<real>(p[k], p[k + 1u]);
            let xv = vec2<real>(x[k], x[k + 1u]) + alpha * pv;
            let qv = vec2<real>(q[k], q[k + 1u]);
            let rv = vec2<real>(r[k], r[k + 1u]) - alpha * qv;
            let zv = pz2(i, rv);
            if (COARSE) {
                zr += zt2(i, rv);
            }
            x[k] = xv.x;
            x[k + 1u] = xv.y;
            r[k] = rv.x;
            r[k + 1u] = rv.y;
            z[k] = zv.x;
            z[k + 1u] = zv.y;
            prz += acc(rv.x) * acc(zv.x) + acc(rv.y) * acc(zv.y);
            prr += acc(rv.x) * acc(rv.x) + acc(rv.y) * acc(rv.y);
        }
    }
    write_partials(lid.x, group_index(wid, nwg), prz, prr, zr);
    if (group_index(wid, nwg) == 0u && lid.x == 0u) {
        scal[SCAL_RHO_PREV] = scal[SCAL_RHO];
        scal[SCAL_PQ] = pq;
        scal[SCAL_ALPHA] = alpha_acc;
        let it = state[STATE_ITERS];
        if (it < HIST) {
            scal[SCAL_HIST + 2u * it] = alpha_acc;
        }
        state[STATE_ITERS] = it + 1u;
    }
}

// (Re)start from the current x, with q = Ĥx already computed: r = b − q, z = M⁻¹r, the
// r·z, r·r partials, and p = s·p with s = scal[SCAL_PSCALE]. A restart has s = 0, so p = 0 and the next
// update_p sets p = z. Mixed precision's reliable update keeps the search direction
// instead: b is the new, renormalized true residual, x and q are zero, and s rescales
// p (and the host rescales ρ_prev) to the new normalization, so CG goes on, not over.
@compute @workgroup_size(WG)
fn init(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    var prz = acc(0.0);
    var prr = acc(0.0);
    let stride = params.n_partials * WG;
    let n = params.n_nodes * D;
    let keep = real(scal[SCAL_PSCALE]);
    for (var k = group_index(wid, nwg) * WG + lid.x; k < n; k += stride) {
        let rk = b[k] - q[k];
        r[k] = rk;
        // select, not 0·p: p may hold non-finite values after a breakdown.
        p[k] = select(real(0.0), keep * p[k], keep != real(0.0));
    }
    var zr = vec3<acc>(acc(0.0));
    if (PRECOND != 2u && !COARSE) {
        for (var k = group_index(wid, nwg) * WG + lid.x; k < n; k += stride) {
            let rk = b[k] - q[k];
            let zk = diag_z(k, rk);
            z[k] = zk;
            prz += acc(rk) * acc(zk);
            prr += acc(rk) * acc(rk);
        }
    } else if (D == 3u) {
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 3u * i;
            // Recomputed rather than read back: r[k] may come from another workgroup.
            let rv = vec3<real>(b[k], b[k + 1u], b[k + 2u]) - vec3<real>(q[k], q[k + 1u], q[k + 2u]);
            let zv = pz3(i, rv);
            if (COARSE) {
                zr += zt3(i, rv);
            }
            z[k] = zv.x;
            z[k + 1u] = zv.y;
            z[k + 2u] = zv.z;
            prz += acc(rv.x) * acc(zv.x) + acc(rv.y) * acc(zv.y) + acc(rv.z) * acc(zv.z);
            prr += acc(rv.x) * acc(rv.x) + acc(rv.y) * acc(rv.y) + acc(rv.z) * acc(rv.z);
        }
    } else {
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 2u * i;
            let rv = vec2<real>(b[k], b[k + 1u]) - vec2<real>(q[k], q[k + 1u]);
            let zv = pz2(i, rv);
            if (COARSE) {
                zr += zt2(i, rv);
            }
            z[k] = zv.x;
            z[k + 1u] = zv.y;
            prz += acc(rv.x) * acc(zv.x) + acc(rv.y) * acc(zv.y);
            prr += acc(rv.x) * acc(rv.x) + acc(rv.y) * acc(rv.y);
        }
    }
    write_partials(lid.x, group_index(wid, nwg), prz, prr, zr);
}
