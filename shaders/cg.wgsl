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
//          4 r·r (A)  5 threshold tol²‖b‖² (host)
//   state: 0 done (A writes, B/C read)  1 halt: non-positive curvature (C writes, A reads)
//          2 iterations (C, workgroup 0 only)  3 converged (A)  4 breakdown (A)

override D: u32 = 3u;
override WG: u32 = 64u;
override PRECOND: u32 = 1u;   // 0 none, 1 Jacobi, 2 block-Jacobi

struct Params {
    n_nodes: u32,
    n_rot: u32,
    n_partials: u32,
    n_blocks: u32,
}

const WG_MAX: u32 = 256u;

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

fn precondition(i: u32, rv: array<real, 3>) -> array<real, 3> {
    var zv = rv;
    if (PRECOND == 1u) {
        for (var a = 0u; a < D; a++) {
            zv[a] = minv[i * D + a] * rv[a];
        }
    } else if (PRECOND == 2u) {
        for (var a = 0u; a < D; a++) {
            var s = real(0.0);
            for (var c = 0u; c < D; c++) {
                s += minv[i * D * D + a * D + c] * rv[c];
            }
            zv[a] = s;
        }
    }
    return zv;
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
    let beta = real(rz / scal[1]);
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
    for (var i = wid.x * WG + lid.x; i < params.n_nodes; i += params.n_partials * WG) {
        var rv = array<real, 3>(real(0.0), real(0.0), real(0.0));
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            x[k] += alpha * p[k];
            let rk = r[k] - alpha * q[k];
            r[k] = rk;
            rv[a] = rk;
        }
        let zv = precondition(i, rv);
        for (var a = 0u; a < D; a++) {
            z[i * D + a] = zv[a];
            prz += acc(rv[a]) * acc(zv[a]);
            prr += acc(rv[a]) * acc(rv[a]);
        }
    }
    write_rz_rr(lid.x, wid.x, prz, prr);
    if (wid.x == 0u && lid.x == 0u) {
        scal[1] = scal[0];
        scal[2] = pq;
        scal[3] = alpha_acc;
        state[2] += 1u;
    }
}

// (Re)start from the current x, with q = Ĥx already computed: r = b − q, z = M⁻¹r, p = 0
// (so the next update_p sets p = z), and the r·z, r·r partials.
@compute @workgroup_size(WG)
fn init(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    var prz = acc(0.0);
    var prr = acc(0.0);
    for (var i = wid.x * WG + lid.x; i < params.n_nodes; i += params.n_partials * WG) {
        var rv = array<real, 3>(real(0.0), real(0.0), real(0.0));
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            let rk = b[k] - q[k];
            r[k] = rk;
            rv[a] = rk;
            p[k] = real(0.0);
        }
        let zv = precondition(i, rv);
        for (var a = 0u; a < D; a++) {
            z[i * D + a] = zv[a];
            prz += acc(rv[a]) * acc(zv[a]);
            prr += acc(rv[a]) * acc(rv[a]);
        }
    }
    write_rz_rr(lid.x, wid.x, prz, prr);
}
