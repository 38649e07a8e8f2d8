// The eliminated PCG on the device-assembled Newton system (src/gpu/newton/cg.rs):
//
//   Ĥ y = b̂,  Ĥ = P VᵀHV P + (I − P),  b̂ = −P Vᵀ g,  Δx = V P y
//
// H is read where the assembly left it (assemble.wgsl: block CSR, both triangles,
// row-major D×D blocks), never copied; V_i is applied only at rotated nodes.
//
// Per CG iteration the host records five dispatches:
//   matvec       q = Ĥp, p·q partials (one invocation per block row)
//   scalar_alpha one workgroup: p·q, α = ρ / p·q, curvature check
//   update_yr    y += αp, r −= αq, z = M⁻¹r, r·z and r·r partials
//   scalar_beta  one workgroup: ρ' = r·z, r·r, stop flags, β = ρ'/ρ, iteration count
//   update_p     p = z + βp
// A (re)start is `init` (r = b̂ − q with q = Ĥy, z = M⁻¹r, p = z, partials) and
// `scalar_start` (then `update_p` with β = 0 under COARSE), whose r·r is the true residual.
// `prepare` adds `coarse_e` and `coarse_e_sum` (E = ZᵀĤZ, below) to `rhs` and `precond`. Reductions are deterministic: a fixed
// number of workgroups each writes one partial from a grid-stride loop in a fixed order,
// and the one-workgroup scalar kernels sum the partials in a fixed order too.
// Once a stop flag is set, every later CG dispatch of the submit is a no-op.
//
// H's values come in chunks of consecutive block rows, one buffer each (one storage
// binding caps its size). The kernels that read them (matvec, precond, coarse_e) run once
// per chunk, each over its rows with `hvals` that chunk's buffer. A thread visits its rows
// in the order of the unsplit grid-stride loop; the reductions carry each thread's running
// sum from one chunk's dispatch to the next (the CARRY slots of `partials`), and only the
// last chunk's dispatch sums the workgroup: the same additions in the same order, so the
// results are those of one chunk, bit for bit.

override D: u32 = 3u;
// 0: none, 1: Jacobi, 2: block Jacobi (the preconditioner applied by init and update_yr).
override PRECOND: u32 = 1u;
// The coarse correction on the rigid translations (src/coarse.rs, docs/coarse.md):
// M⁻¹r = M_J⁻¹r + Z E⁺ Zᵀr with Z_i = P_i V_iᵀ from the frames (no basis stored) and
// E⁺ (D×D, from the host) in `scal`. Why: a body that can translate or slide has Ĥ's
// smallest eigenvalues on its translations (the mass term), which M_J cannot see.
// update_yr and init sum Zᵀr in the tree of r·M_J⁻¹r and r·r; scalar_beta and
// scalar_start form c = E⁺Zᵀr and ρ = r·M_J⁻¹r + Zᵀr·c; update_p adds Z_i c to p.
// z holds M_J⁻¹r only, so the correction costs no dispatch in the iteration.
override COARSE: bool = false;

// Mirrors `NewtonCgParams` in src/gpu/newton/cg.rs (four u32, 16 bytes, size-asserted
// there).
struct NewtonCgParams {
    n_nodes: u32,
    // Partials per reduction (the workgroups of the grid-stride kernels).
    n_partials: u32,
    // Where the column indices and the diagonal block indices start in `pattern` (the
    // n + 1 row pointers start at 0).
    col_at: u32,
    diag_at: u32,
    // The values chunk bound as `hvals`: its rows, its first (global) block, and whether
    // it is the first (bit 0) and the last (bit 1) chunk.
    row_begin: u32,
    row_end: u32,
    block_first: u32,
    chunk: u32,
}

const H_FIRST_CHUNK: u32 = 1u;
const H_LAST_CHUNK: u32 = 2u;

// Slots of `scal`, `state` and the partial sums, mirrored by `slot` in
// src/gpu/newton/cg.rs (a unit test there checks every value).
// scal: ρ = r·z (scalar_start, scalar_beta), p·q (scalar_alpha), α (scalar_alpha),
// β (scalar_beta), r·r of the last reduction, tol² (host), ‖b̂‖² (scalar_start); then
// (COARSE) c = E⁺Zᵀr, D values (scalar_beta, scalar_start), E⁺, D² row-major (host), and
// E = ZᵀĤZ unsymmetrized, D² row-major, then per world axis a 2^-64 · Σ|entries| of the
// rows of component a of ZᵀĤ's blocks, D values (coarse_e_sum, read back by the host,
// which asks whether a translation is pinned by nothing).
const NCG_RHO: u32 = 0u;
const NCG_PQ: u32 = 1u;
const NCG_ALPHA: u32 = 2u;
const NCG_BETA: u32 = 3u;
const NCG_RR: u32 = 4u;
const NCG_TOL2: u32 = 5u;
const NCG_BB: u32 = 6u;
const NCG_C: u32 = 8u;
const NCG_EINV: u32 = 11u;
const NCG_E: u32 = 20u;
const NCG_EABS: u32 = 29u;
// state: stop (any reason), converged, non-positive curvature, non-finite value,
// iterations done (all u32; the host clears the four flags before a restart).
const NCG_DONE: u32 = 0u;
const NCG_CONVERGED: u32 = 1u;
const NCG_HALT: u32 = 2u;
const NCG_BREAKDOWN: u32 = 3u;
const NCG_ITERS: u32 = 4u;
// Partial-sum slots, each n_partials long: p·q, r·z, r·r, ‖b̂‖², then D slots of Zᵀr
// (COARSE), D² of E then D of its rows' absolute sums (coarse_e).
const NCG_PART_PQ: u32 = 0u;
const NCG_PART_RZ: u32 = 1u;
const NCG_PART_RR: u32 = 2u;
const NCG_PART_BB: u32 = 3u;
const NCG_PART_ZR: u32 = 4u;
const NCG_PART_E: u32 = 7u;
// After the partial-sum slots (NCG_CARRY · n_partials): per thread of the grid-stride
// kernels, NCG_CARRY_LEN running sums carried between the dispatches of H's chunks.
const NCG_CARRY: u32 = 19u;
const NCG_CARRY_LEN: u32 = 12u;
// 2^-64: the scale of the absolute row sums (src/solve/coarse.rs, ABS_SUM_SCALE).
const ABS_SUM_SCALE = 0x1p-64;

@group(0) @binding(0) var<uniform> params: NewtonCgParams;
// Row pointers, column indices and per node its diagonal block (see NewtonCgParams).
@group(0) @binding(1) var<storage, read> pattern: array<u32>;
// The assembly's blocks and gradient.
// (hvals: the values chunk of this dispatch, block block_first at 0.)
@group(0) @binding(2) var<storage, read> hvals: array<real>;
@group(0) @binding(3) var<storage, read> grad: array<real>;
// Per node: its constraint mask (bit a: component a of the frame is constrained) and its
// index into `rotations` or NO_ROTATION.
@group(0) @binding(4) var<storage, read> frame: array<u32>;
// D×D per rotated node, row-major V_i (its columns are the frame basis).
@group(0) @binding(5) var<storage, read> rotations: array<real>;
@group(0) @binding(6) var<storage, read_write> y: array<real>;
@group(0) @binding(7) var<storage, read_write> r: array<real>;
@group(0) @binding(8) var<storage, read_write> z: array<real>;
@group(0) @binding(9) var<storage, read_write> p: array<real>;
@group(0) @binding(10) var<storage, read_write> q: array<real>;
@group(0) @binding(11) var<storage, read_write> b: array<real>;
// The inverse diagonal blocks of Ĥ (n·D², block Jacobi), then 1/diag(Ĥ) (n·D, Jacobi).
@group(0) @binding(12) var<storage, read_write> minv: array<real>;
@group(0) @binding(13) var<storage, read_write> dx: array<real>;
@group(0) @binding(14) var<storage, read_write> partials: array<acc>;
@group(0) @binding(15) var<storage, read_write> scal: array<acc>;
@group(0) @binding(16) var<storage, read_write> state: array<u32>;

var<workgroup> wg_flag: u32;

// The stop flag as a workgroup-uniform value (later barriers may depend on it).
fn stopped(lid: u32) -> bool {
    if (lid == 0u) {
        wg_flag = state[NCG_DONE];
    }
    return workgroupUniformLoad(&wg_flag) != 0u;
}

fn fixed(i: u32, a: u32) -> bool {
    return ((frame[2u * i] >> a) & 1u) != 0u;
}

fn rot_of(i: u32) -> u32 {
    return frame[2u * i + 1u];
}

// V_i v: frame to world.
fn from_frame(i: u32, v: array<real, 3>) -> array<real, 3> {
    let ri = rot_of(i);
    if (ri == NO_ROTATION) {
        return v;
    }
    var o: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        var s = real(0.0);
        for (var c = 0u; c < D; c++) {
            s += rotations[ri * D * D + a * D + c] * v[c];
        }
        o[a] = s;
    }
    return o;
}

// V_iᵀ v: world to frame.
fn to_frame(i: u32, v: array<real, 3>) -> array<real, 3> {
    let ri = rot_of(i);
    if (ri == NO_ROTATION) {
        return v;
    }
    var o: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        var s = real(0.0);
        for (var c = 0u; c < D; c++) {
            s += rotations[ri * D * D + c * D + a] * v[c];
        }
        o[a] = s;
    }
    return o;
}

// z_i = M_i⁻¹ r_i.
fn apply_precond(i: u32, rv: array<real, 3>) -> array<real, 3> {
    var o = rv;
    if (PRECOND == 1u) {
        let base = params.n_nodes * D * D + i * D;
        for (var a = 0u; a < D; a++) {
            o[a] = minv[base + a] * rv[a];
        }
    } else if (PRECOND == 2u) {
        let base = i * D * D;
        for (var a = 0u; a < D; a++) {
            var s = real(0.0);
            for (var c = 0u; c < D; c++) {
                s += minv[base + a * D + c] * rv[c];
            }
            o[a] = s;
        }
    }
    return o;
}

// Z_iᵀ r_i = V_i P_i r_i: node i's share of Zᵀr.
fn zt(i: u32, rv: array<real, 3>) -> array<real, 3> {
    var w: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        w[a] = select(rv[a], real(0.0), fixed(i, a));
    }
    return from_frame(i, w);
}

// Z_i c = P_i V_iᵀ c.
fn zc(i: u32, c: array<real, 3>) -> array<real, 3> {
    var w = to_frame(i, c);
    for (var a = 0u; a < D; a++) {
        w[a] = select(w[a], real(0.0), fixed(i, a));
    }
    return w;
}

// c = E⁺ Zᵀr into scal (lane 0 of a one-workgroup kernel); returns Zᵀr·c, the coarse
// share of ρ = r·M⁻¹r.
fn coarse_c(zr: array<acc, 3>) -> acc {
    var wc = acc(0.0);
    for (var a = 0u; a < D; a++) {
        var s = acc(0.0);
        for (var b = 0u; b < D; b++) {
            s += scal[NCG_EINV + a * D + b] * zr[b];
        }
        scal[NCG_C + a] = s;
        wc += zr[a] * s;
    }
    return wc;
}

// Index of thread t's carried sum m (see NCG_CARRY).
fn carry(t: u32, m: u32) -> u32 {
    return NCG_CARRY * params.n_partials + t * NCG_CARRY_LEN + m;
}

// Thread t's first row of the chunk in the unsplit grid-stride order (t, t + stride, …).
fn chunk_start(t: u32, stride: u32) -> u32 {
    if (t >= params.row_begin) {
        return t;
    }
    return t + (params.row_begin - t + stride - 1u) / stride * stride;
}

// Sum of partial slot `slot`, in a fixed order, in one workgroup.
fn reduce_slot(slot: u32, lid: u32) -> acc {
    var s = acc(0.0);
    for (var t = lid; t < params.n_partials; t += WG) {
        s += partials[slot * params.n_partials + t];
    }
    return workgroup_sum_uniform1(lid, s);
}

// b̂ = −P Vᵀ g and the ‖b̂‖² partials.
@compute @workgroup_size(WG)
fn rhs(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    var bb = acc(0.0);
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
        var g: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            g[a] = grad[i * D + a];
        }
        let t = to_frame(i, g);
        for (var a = 0u; a < D; a++) {
            var v = -t[a];
            if (fixed(i, a)) {
                v = real(0.0);
            }
            b[i * D + a] = v;
            bb += acc(v) * acc(v);
        }
    }
    workgroup_sum(lid.x, sum1(bb), 1u);
    if (lid.x == 0u) {
        partials[NCG_PART_BB * params.n_partials + group_index(wid, nwg)] = summed(0u);
    }
}

// A positive, finite value (NaN and ±∞ fail).
fn positive_finite(v: real) -> bool {
    return v > real(0.0) && real(1.0) / v > real(0.0);
}

// The preconditioners from the diagonal blocks of Ĥ: B = P V_iᵀ H_ii V_i P + (I − P).
// Jacobi: 1/B_aa (1 where B_aa is not positive and finite). Block Jacobi: B⁻¹ by
// Cholesky, or the Jacobi diagonal where B is not positive definite (as the CPU's CG).
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
        var dinv: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            let v = h[a * D + a];
            dinv[a] = select(real(1.0), real(1.0) / v, positive_finite(v));
            minv[params.n_nodes * dd + i * D + a] = dinv[a];
        }
        // Cholesky h = L Lᵀ, then the columns of h⁻¹ by two triangular solves.
        var l: array<real, 9>;
        var ok = true;
        for (var j = 0u; j < D; j++) {
            var s = h[j * D + j];
            for (var m = 0u; m < j; m++) {
                s -= l[j * D + m] * l[j * D + m];
            }
            if (!positive_finite(s)) {
                ok = false;
                break;
            }
            let ljj = sqrt(s);
            l[j * D + j] = ljj;
            for (var a = j + 1u; a < D; a++) {
                var t = h[a * D + j];
                for (var m = 0u; m < j; m++) {
                    t -= l[a * D + m] * l[j * D + m];
                }
                l[a * D + j] = t / ljj;
            }
        }
        for (var c = 0u; c < D; c++) {
            var u: array<real, 3>;
            for (var a = 0u; a < D; a++) {
                var s = select(real(0.0), real(1.0), a == c);
                for (var m = 0u; m < a; m++) {
                    s -= l[a * D + m] * u[m];
                }
                u[a] = s / l[a * D + a];
            }
            for (var aa = 0u; aa < D; aa++) {
                let a = D - 1u - aa;
                var s = u[a];
                for (var m = a + 1u; m < D; m++) {
                    s -= l[m * D + a] * u[m];
                }
                u[a] = s / l[a * D + a];
            }
            for (var a = 0u; a < D; a++) {
                var v = u[a];
                if (!ok) {
                    v = select(real(0.0), dinv[a], a == c);
                }
                minv[i * dd + a * D + c] = v;
            }
        }
    }
}

// q = Ĥp = P Vᵀ H V P p + (I − P) p, one invocation per block row, with the p·q partials.
@compute @workgroup_size(WG)
fn matvec(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let dd = D * D;
    let th = group_index(wid, nwg) * WG + lid.x;
    let stride = grid_stride(nwg);
    var pq = acc(0.0);
    if ((params.chunk & H_FIRST_CHUNK) == 0u) {
        pq = partials[carry(th, 0u)];
    }
    for (var i = chunk_start(th, stride); i < params.row_end; i += stride) {
        var s: array<real, 3>;
        for (var k = pattern[i]; k < pattern[i + 1u]; k++) {
            let j = pattern[params.col_at + k];
            let kl = k - params.block_first;
            var w: array<real, 3>;
            for (var c = 0u; c < D; c++) {
                w[c] = select(p[j * D + c], real(0.0), fixed(j, c));
            }
            w = from_frame(j, w);
            for (var a = 0u; a < D; a++) {
                var t = s[a];
                for (var c = 0u; c < D; c++) {
                    t += hvals[kl * dd + a * D + c] * w[c];
                }
                s[a] = t;
            }
        }
        let t = to_frame(i, s);
        for (var a = 0u; a < D; a++) {
            let pa = p[i * D + a];
            let qa = select(t[a], pa, fixed(i, a));
            q[i * D + a] = qa;
            pq += acc(pa) * acc(qa);
        }
    }
    if ((params.chunk & H_LAST_CHUNK) == 0u) {
        partials[carry(th, 0u)] = pq;
        return;
    }
    workgroup_sum(lid.x, sum1(pq), 1u);
    if (lid.x == 0u) {
        partials[NCG_PART_PQ * params.n_partials + group_index(wid, nwg)] = summed(0u);
    }
}

// α = ρ / p·q (one workgroup); a non-positive p·q halts, a NaN one is a breakdown.
@compute @workgroup_size(WG)
fn scalar_alpha(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let pq = reduce_slot(NCG_PART_PQ, lid.x);
    if (lid.x == 0u) {
        scal[NCG_PQ] = pq;
        if (pq > acc(0.0)) {
            scal[NCG_ALPHA] = scal[NCG_RHO] / pq;
        } else {
            state[NCG_DONE] = 1u;
            if (pq <= acc(0.0)) {
                state[NCG_HALT] = 1u;
            } else {
                state[NCG_BREAKDOWN] = 1u;
            }
        }
    }
}

// The r·z and r·r partials of one workgroup and, with COARSE, those of Zᵀr (one tree).
fn write_rz_rr(lid: u32, wg: u32, rz: acc, rr: acc, zr: array<acc, 3>) {
    let n = select(2u, 2u + D, COARSE);
    workgroup_sum(lid, array<acc, 5>(rz, rr, zr[0], zr[1], zr[2]), n);
    if (lid == 0u) {
        let np = params.n_partials;
        partials[NCG_PART_RZ * np + wg] = summed(0u);
        partials[NCG_PART_RR * np + wg] = summed(1u);
        for (var a = 0u; a + 2u < n; a++) {
            partials[(NCG_PART_ZR + a) * np + wg] = summed(2u + a);
        }
    }
}

// y += αp, r −= αq, z = M⁻¹r, with the r·z and r·r partials.
@compute @workgroup_size(WG)
fn update_yr(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let alpha = real(scal[NCG_ALPHA]);
    var rz = acc(0.0);
    var rr = acc(0.0);
    var zr: array<acc, 3>;
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
        var rv: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            y[k] += alpha * p[k];
            rv[a] = r[k] - alpha * q[k];
            r[k] = rv[a];
        }
        let zv = apply_precond(i, rv);
        for (var a = 0u; a < D; a++) {
            z[i * D + a] = zv[a];
            rz += acc(rv[a]) * acc(zv[a]);
            rr += acc(rv[a]) * acc(rv[a]);
        }
        if (COARSE) {
            let w = zt(i, rv);
            for (var a = 0u; a < D; a++) {
                zr[a] += acc(w[a]);
            }
        }
    }
    write_rz_rr(lid.x, group_index(wid, nwg), rz, rr, zr);
}

// ρ' = r·z (with COARSE r·M_J⁻¹r + Zᵀr·c, and c = E⁺Zᵀr) and r·r (one workgroup); stops
// on r·r ≤ tol²‖b̂‖² (the recurrence residual) or a non-finite value, else β = ρ'/ρ.
// Counts the iteration.
@compute @workgroup_size(WG)
fn scalar_beta(@builtin(local_invocation_id) lid: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    var v = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    let np = params.n_partials;
    let n = select(2u, 2u + D, COARSE);
    for (var t = lid.x; t < np; t += WG) {
        v[0] += partials[NCG_PART_RZ * np + t];
        v[1] += partials[NCG_PART_RR * np + t];
        for (var a = 0u; a + 2u < n; a++) {
            v[2u + a] += partials[(NCG_PART_ZR + a) * np + t];
        }
    }
    let s = workgroup_sum_uniform(lid.x, v, n);
    if (lid.x == 0u) {
        var rz = s[0];
        let rr = s[1];
        if (COARSE) {
            rz += coarse_c(array<acc, 3>(s[2], s[3], s[4]));
        }
        state[NCG_ITERS] += 1u;
        scal[NCG_RR] = rr;
        // NaN fails every comparison: a non-finite ρ or r·r is a breakdown.
        if (!(rz >= acc(0.0)) || !(rr >= acc(0.0))) {
            state[NCG_DONE] = 1u;
            state[NCG_BREAKDOWN] = 1u;
        } else if (rr <= scal[NCG_TOL2] * scal[NCG_BB]) {
            state[NCG_DONE] = 1u;
            state[NCG_CONVERGED] = 1u;
        } else {
            scal[NCG_BETA] = rz / scal[NCG_RHO];
            scal[NCG_RHO] = rz;
        }
    }
}

// p = z + βp; with COARSE p = (z + Zc) + βp, the preconditioned residual completed.
@compute @workgroup_size(WG)
fn update_p(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (stopped(lid.x)) {
        return;
    }
    let beta = real(scal[NCG_BETA]);
    if (!COARSE) {
        for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
            for (var a = 0u; a < D; a++) {
                let k = i * D + a;
                p[k] = z[k] + beta * p[k];
            }
        }
        return;
    }
    var c: array<real, 3>;
    for (var a = 0u; a < D; a++) {
        c[a] = real(scal[NCG_C + a]);
    }
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
        let w = zc(i, c);
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            p[k] = (z[k] + w[a]) + beta * p[k];
        }
    }
}

// A (re)start from y, with q = Ĥy already in q: r = b̂ − q, z = M⁻¹r, p = z, and the r·z
// and r·r partials (r·r of the true residual); with COARSE z = M_J⁻¹r and the Zᵀr
// partials too, and update_p (β = 0) then adds Zc to p.
@compute @workgroup_size(WG)
fn init(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    var rz = acc(0.0);
    var rr = acc(0.0);
    var zr: array<acc, 3>;
    for (var i = group_index(wid, nwg) * WG + lid.x; i < params.n_nodes; i += grid_stride(nwg)) {
        var rv: array<real, 3>;
        for (var a = 0u; a < D; a++) {
            let k = i * D + a;
            rv[a] = b[k] - q[k];
            r[k] = rv[a];
        }
        let zv = apply_precond(i, rv);
        for (var a = 0u; a < D; a++) {
            z[i * D + a] = zv[a];
            p[i * D + a] = zv[a];
            rz += acc(rv[a]) * acc(zv[a]);
            rr += acc(rv[a]) * acc(rv[a]);
        }
        if (COARSE) {
            let w = zt(i, rv);
            for (var a = 0u; a < D; a++) {
                zr[a] += acc(w[a]);
            }
        }
    }
    write_rz_rr(lid.x, group_index(wid, nwg), rz, rr, zr);
}

// After init (one workgroup): ρ, the true r·r and ‖b̂‖²; stops when the true residual
// meets the tolerance (always when b̂ = 0 and y = 0). With COARSE also c = E⁺Zᵀr (Zᵀr in
// a second tree), ρ += Zᵀr·c, and β = 0 for the update_p that completes p = z + Zc.
@compute @workgroup_size(WG)
fn scalar_start(@builtin(local_invocation_id) lid: vec3<u32>) {
    var v = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    var w = array<acc, 5>(acc(0.0), acc(0.0), acc(0.0), acc(0.0), acc(0.0));
    let np = params.n_partials;
    for (var t = lid.x; t < np; t += WG) {
        v[0] += partials[NCG_PART_RZ * np + t];
        v[1] += partials[NCG_PART_RR * np + t];
        v[2] += partials[NCG_PART_BB * np + t];
        if (COARSE) {
            for (var a = 0u; a < D; a++) {
                w[a] += partials[(NCG_PART_ZR + a) * np + t];
            }
        }
    }
    let s = workgroup_sum_uniform(lid.x, v, 3u);
    var zr: array<acc, 3>;
    if (COARSE) {
        let sw = workgroup_sum_uniform(lid.x, w, D);
        zr = array<acc, 3>(sw[0], sw[1], sw[2]);
    }
    if (lid.x == 0u) {
        var rz = s[0];
        let rr = s[1];
        let bb = s[2];
        if (COARSE) {
            rz += coarse_c(zr);
            scal[NCG_BETA] = acc(0.0);
        }
        scal[NCG_RHO] = rz;
        scal[NCG_RR] = rr;
        scal[NCG_BB] = bb;
        if (!(rz >= acc(0.0)) || !(rr >= acc(0.0)) || !(bb >= acc(0.0))) {
            state[NCG_DONE] = 1u;
            state[NCG_BREAKDOWN] = 1u;
        } else if (rr <= scal[NCG_TOL2] * bb) {
            state[NCG_DONE] = 1u;
            state[NCG_CONVERGED] = 1u;
        }
    }
}

// Node i has no constrained component and no rotation: Z_i = Q_i = I.
fn plain(i: u32) -> bool {
    return frame[2u * i] == 0u && rot_of(i) == NO_ROTATION;
}

// Every component of node i is constrained: Z_i = 0.
fn all_fixed(i: u32) -> bool {
    let full = (1u << D) - 1u;
    return (frame[2u * i] & full) == full;
}

// Q_i = Z_iᵀZ_i = V_i P_i V_iᵀ, row-major: Q_ab = Σ_c over the free frame components of
// V_ac V_bc (V = I at unrotated nodes), in the order src/coarse.rs sums it.
fn proj(i: u32) -> array<real, 9> {
    let ri = rot_of(i);
    var o: array<real, 9>;
    for (var a = 0u; a < D; a++) {
        for (var b = 0u; b < D; b++) {
            var s = real(0.0);
            for (var c = 0u; c < D; c++) {
                if (!fixed(i, c)) {
                    var va = select(real(0.0), real(1.0), a == c);
                    var vb = select(real(0.0), real(1.0), b == c);
                    if (ri != NO_ROTATION) {
                        va = rotations[ri * D * D + a * D + c];
                        vb = rotations[ri * D * D + b * D + c];
                    }
                    s += va * vb;
                }
            }
            o[a * D + b] = s;
        }
    }
    return o;
}

// x y for row-major D×D x and y.
fn mat_mul(x: array<real, 9>, y: array<real, 9>) -> array<real, 9> {
    var o: array<real, 9>;
    for (var a = 0u; a < D; a++) {
        for (var c = 0u; c < D; c++) {
            var s = real(0.0);
            for (var m = 0u; m < D; m++) {
                s += x[a * D + m] * y[m * D + c];
            }
            o[a * D + c] = s;
        }
    }
    return o;
}

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
    let th = group_index(wid, nwg) * WG + lid.x;
    let stride = grid_stride(nwg);
    // E's D² entries, then the D absolute row sums.
    var e: array<acc, 12>;
    if ((params.chunk & H_FIRST_CHUNK) == 0u) {
        for (var m = 0u; m < n_sums; m++) {
            e[m] = partials[carry(th, m)];
        }
    }
    for (var i = chunk_start(th, stride); i < params.row_end; i += stride) {
        if (all_fixed(i)) {
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
                var s = real(0.0);
                for (var c = 0u; c < D; c++) {
                    s += abs(b[a * D + c]) * ABS_SUM_SCALE;
                }
                e[dd + a] += acc(s);
            }
        }
        if (!plain(i)) {
            part = mat_mul(proj(i), part);
        }
        for (var m = 0u; m < dd; m++) {
            e[m] += acc(part[m]);
        }
    }
    if ((params.chunk & H_LAST_CHUNK) == 0u) {
        for (var m = 0u; m < n_sums; m++) {
            partials[carry(th, m)] = e[m];
        }
        return;
    }
    // The sums in trees of at most five.
    let np = params.n_partials;
    for (var base = 0u; base < n_sums; base += 5u) {
        let n = min(n_sums - base, 5u);
        var v: array<acc, 5>;
        for (var m = 0u; m < n; m++) {
            v[m] = e[base + m];
        }
        workgroup_sum(lid.x, v, n);
        if (lid.x == 0u) {
            for (var m = 0u; m < n; m++) {
                partials[(NCG_PART_E + base + m) * np + group_index(wid, nwg)] = summed(m);
            }
        }
        workgroupBarrier();
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
                v[m] += partials[(NCG_PART_E + base + m) * np + t];
            }
        }
        let s = workgroup_sum_uniform(lid.x, v, n);
        if (lid.x == 0u) {
            for (var m = 0u; m < n; m++) {
                let at = base + m;
                if (at < dd) {
                    scal[NCG_E + at] = s[m];
                } else {
                    scal[NCG_EABS + at - dd] = s[m];
                }
            }
        }
    }
}

// Δx = V P y (the prescribed part is zero in a Newton step).
@compute @workgroup_size(WG)
fn recover(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
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
