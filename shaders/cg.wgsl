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
// Slot discipline (no workgroup reads a slot another workgroup of the same dispatch writes):
//   scal:  0 ρ (A writes, C reads)  1 ρ_prev (C writes, A reads)  2 p·q (C)  3 α (C)
//          4 r·r (A)  5 threshold tol²‖b‖² (host)  6 direction scale kept by init (host)
//          7 β of the first update_p of a run (A, workgroup 0)
//          8 + 2j: α_j (C)   8 + 2j + 1: β_{j+1} (A), for j < HIST: the Lanczos
//          coefficients of this run, from which the host estimates κ(M⁻¹Ĥ)
//   state: 0 done (A writes, B/C read)  1 halt: non-positive curvature (C writes, A reads)
//          2 iterations (C, workgroup 0 only)  3 converged (A)  4 breakdown (A)

override D: u32 = 3u;
override WG: u32 = 64u;
override PRECOND: u32 = 1u;   // 0 none, 1 Jacobi, 2 block-Jacobi
override HIST: u32 = 0u;      // Lanczos coefficients recorded per run (0: none)

// First slot of the coefficient history in `scal` (N_SCAL in src/gpu/solver/mod.rs).
const SCAL_HIST: u32 = 8u;

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

var<workgroup> sh: array<acc, WG_MAX>;
var<workgroup> sh2: array<acc, WG_MAX>;
var<workgroup> bcast: acc;
var<workgroup> wg_u: u32;

// Sum of partial slot `slot` in a fixed order, identical in every workgroup.
fn reduce_slot(slot: u32, lid: u32) -> acc {
    var s = acc(0.0);
    for (var t = lid; t < params.n_partials; t += WG) {
        s += partials[slot * params.n_partials + t];
    }
    sh[lid] = s;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            sh[lid] += sh[lid + h];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        bcast = sh[0];
    }
    return workgroupUniformLoad(&bcast);
}

// Workgroup tree sums of sh and sh2 into slots 1 and 2 of this workgroup's partials.
fn write_rz_rr(lid: u32, wg: u32, prz: acc, prr: acc) {
    sh[lid] = prz;
    sh2[lid] = prr;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h = h >> 1u) {
        if (lid < h) {
            sh[lid] += sh[lid + h];
            sh2[lid] += sh2[lid + h];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        partials[params.n_partials + wg] = sh[0];
        partials[2u * params.n_partials + wg] = sh2[0];
    }
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
fn update_p(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let rz = reduce_slot(1u, lid.x);
    let rr = reduce_slot(2u, lid.x);
    if (lid.x == 0u) {
        wg_u = state[1];
    }
    let halt = workgroupUniformLoad(&wg_u);
    let conv = rr <= scal[5];
    // NaN fails every comparison: a non-finite ρ or r·r is a breakdown, never convergence.
    let bad = !(rz >= acc(0.0)) || !(rr >= acc(0.0));
    let stop = halt != 0u || conv || bad;
    if (wid.x == 0u && lid.x == 0u) {
        scal[0] = rz;
        scal[4] = rr;
        if (stop) {
            state[0] = 1u;
            if (halt == 0u && !bad && conv) {
                state[3] = 1u;
            }
            if (halt == 0u && bad) {
                state[4] = 1u;
            }
        }
    }
    if (stop) {
        return;
    }
    let beta_acc = rz / scal[1];
    let beta = real(beta_acc);
    if (wid.x == 0u && lid.x == 0u) {
        let it = state[2];
        if (it == 0u) {
            scal[7] = beta_acc;
        } else if (it <= HIST) {
            scal[SCAL_HIST + 2u * (it - 1u) + 1u] = beta_acc;
        }
    }
    let n = params.n_nodes * D;
    for (var k = wid.x * WG + lid.x; k < n; k += params.n_partials * WG) {
        p[k] = z[k] + beta * p[k];
    }
}

@compute @workgroup_size(WG)
fn update_xrz(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    if (lid.x == 0u) {
        wg_u = state[0];
    }
    if (workgroupUniformLoad(&wg_u) != 0u) {
        return;
    }
    let pq = reduce_slot(0u, lid.x);
    if (!(pq > acc(0.0))) {
        if (wid.x == 0u && lid.x == 0u) {
            state[1] = 1u;
            scal[2] = pq;
        }
        return;
    }
    let alpha_acc = scal[0] / pq;
    let alpha = real(alpha_acc);
    var prz = acc(0.0);
    var prr = acc(0.0);
    let stride = params.n_partials * WG;
    if (PRECOND != 2u) {
        // Diagonal preconditioners: element-wise over the d·n components.
        let n = params.n_nodes * D;
        for (var k = wid.x * WG + lid.x; k < n; k += stride) {
            x[k] += alpha * p[k];
            let rk = r[k] - alpha * q[k];
            r[k] = rk;
            let zk = diag_z(k, rk);
            z[k] = zk;
            prz += acc(rk) * acc(zk);
            prr += acc(rk) * acc(rk);
        }
    } else if (D == 3u) {
        for (var i = wid.x * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 3u * i;
            let pv = vec3<real>(p[k], p[k + 1u], p[k + 2u]);
            let xv = vec3<real>(x[k], x[k + 1u], x[k + 2u]) + alpha * pv;
            let qv = vec3<real>(q[k], q[k + 1u], q[k + 2u]);
            let rv = vec3<real>(r[k], r[k + 1u], r[k + 2u]) - alpha * qv;
            let zv = block3(i, rv);
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
        for (var i = wid.x * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 2u * i;
            let pv = vec2<real>(p[k], p[k + 1u]);
            let xv = vec2<real>(x[k], x[k + 1u]) + alpha * pv;
            let qv = vec2<real>(q[k], q[k + 1u]);
            let rv = vec2<real>(r[k], r[k + 1u]) - alpha * qv;
            let zv = block2(i, rv);
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
    write_rz_rr(lid.x, wid.x, prz, prr);
    if (wid.x == 0u && lid.x == 0u) {
        scal[1] = scal[0];
        scal[2] = pq;
        scal[3] = alpha_acc;
        let it = state[2];
        if (it < HIST) {
            scal[SCAL_HIST + 2u * it] = alpha_acc;
        }
        state[2] = it + 1u;
    }
}

// (Re)start from the current x, with q = Ĥx already computed: r = b − q, z = M⁻¹r, the
// r·z, r·r partials, and p = scal[6]·p. A restart has scal[6] = 0, so p = 0 and the next
// update_p sets p = z. Mixed precision's reliable update keeps the search direction
// instead: b is the new, renormalized true residual, x and q are zero, and scal[6] rescales
// p (and the host rescales ρ_prev) to the new normalization, so CG goes on, not over.
@compute @workgroup_size(WG)
fn init(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    var prz = acc(0.0);
    var prr = acc(0.0);
    let stride = params.n_partials * WG;
    let n = params.n_nodes * D;
    let keep = real(scal[6]);
    for (var k = wid.x * WG + lid.x; k < n; k += stride) {
        let rk = b[k] - q[k];
        r[k] = rk;
        // select, not 0·p: p may hold non-finite values after a breakdown.
        p[k] = select(real(0.0), keep * p[k], keep != real(0.0));
    }
    if (PRECOND != 2u) {
        for (var k = wid.x * WG + lid.x; k < n; k += stride) {
            let rk = b[k] - q[k];
            let zk = diag_z(k, rk);
            z[k] = zk;
            prz += acc(rk) * acc(zk);
            prr += acc(rk) * acc(rk);
        }
    } else if (D == 3u) {
        for (var i = wid.x * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 3u * i;
            // Recomputed rather than read back: r[k] may come from another workgroup.
            let rv = vec3<real>(b[k], b[k + 1u], b[k + 2u]) - vec3<real>(q[k], q[k + 1u], q[k + 2u]);
            let zv = block3(i, rv);
            z[k] = zv.x;
            z[k + 1u] = zv.y;
            z[k + 2u] = zv.z;
            prz += acc(rv.x) * acc(zv.x) + acc(rv.y) * acc(zv.y) + acc(rv.z) * acc(zv.z);
            prr += acc(rv.x) * acc(rv.x) + acc(rv.y) * acc(rv.y) + acc(rv.z) * acc(rv.z);
        }
    } else {
        for (var i = wid.x * WG + lid.x; i < params.n_nodes; i += stride) {
            let k = 2u * i;
            let rv = vec2<real>(b[k], b[k + 1u]) - vec2<real>(q[k], q[k + 1u]);
            let zv = block2(i, rv);
            z[k] = zv.x;
            z[k + 1u] = zv.y;
            prz += acc(rv.x) * acc(zv.x) + acc(rv.y) * acc(zv.y);
            prr += acc(rv.x) * acc(rv.x) + acc(rv.y) * acc(rv.y);
        }
    }
    write_rz_rr(lid.x, wid.x, prz, prr);
}
