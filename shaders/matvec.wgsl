// Masked block-sparse Hessian-vector product in rotated coordinates, fused with the
// per-workgroup partial sums of p·q:
//   q_i = P_i Σ_j Ĥ_ij P_j p_j + (I − P_i) D_i p_i,   partials[0·G + wg] = Σ p·q.
// The scalar types `real` and `acc` come from a one-line alias prelude (WGSL overrides
// cannot change types); everything else is specialized with override constants.
//
// Block storage ("planes", one thread per block row, vector loads): block k, row-major
// entries e0..e8, is split over three arrays so that a row reads with three loads:
//   D = 3: blk_a[k] = (e0, e1, e2, e3), blk_b[k] = (e4, e5, e6, e7), blk_c[k] = e8
//   D = 2: blk_a[k] = (e0, e1, e2, e3); blk_b, blk_c unused.
// Row chunks (`Chunk`, common.wgsl): the per-block arrays (planes and columns) are bound
// per chunk of rows whose blocks fit one storage binding, and the product is one dispatch
// per chunk. Each invocation keeps its p·q sum over its rows of every chunk in `carry`
// between dispatches and the last chunk reduces it: the same rows are summed in the same
// order whatever the chunking, so a chunked product equals the one-chunk product bit for
// bit. The row sums of the difference form are bound per chunk too, from its first row.

override D: u32 = 3u;          // block size (2 or 3)
override MASKED: bool = true;  // false: the scene has no constraints, no masking work
// Difference form (f32 operators): Σ_{j≠i} Ĥ_ij (p̄_j − p̄_i) + S_i p̄_i with p̄ = P p and
// S_i = Σ_j Ĥ_ij summed in f64 on the host (`rowsum`); the diagonal block stays in the
// loop without a branch: its term Ĥ_ii(p̄_i − p̄_i) is exactly zero.
// Equal to Σ_j Ĥ_ij p̄_j in exact arithmetic. Why: rounding Ĥ's blocks to f32 breaks
// K·(translation) = 0 by ε_f32·‖K‖, which moves the small eigenvalue of a nearly free body
// (its mass) by κ·ε_f32; in this form the rounded operator still maps a translation t to
// S t (to f32 accuracy), so the near-null modes keep their eigenvalues (STABILITY.md).
// A smooth mode v gives terms of size ‖Ĥ‖·|v_j − v_i| that cancel to its small eigenvalue;
// rounding each term's sum to f32 would put ε_f32‖Ĥ‖|v_j − v_i| noise back on every
// row, so the row is summed in `acc` (f64 where the device has it), which keeps the
// bending modes of a stiffness-dominated body too, not only its translations.
// Only on rows whose node and neighbours are unrotated: differences are taken in each
// node's frame, so next to a rotated slip node a translation's p̄_j − p̄_i is not zero and
// those rows keep the plain f32 error.
override DIFF: bool = false;

// Column indices carry the column node's mask from bit MASK_SHIFT up (`col & COL_BITS` is
// the column), so P_j costs no extra memory traffic.

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> col: array<u32>;
@group(0) @binding(3) var<storage, read> blk_a: array<blk4>;
@group(0) @binding(4) var<storage, read> mask: array<u32>;
@group(0) @binding(5) var<storage, read> dvals: array<real>;
@group(0) @binding(6) var<storage, read> p: array<real>;
@group(0) @binding(7) var<storage, read_write> q: array<real>;
@group(0) @binding(8) var<storage, read_write> partials: array<acc>;
@group(0) @binding(9) var<storage, read> state: array<u32>;
@group(0) @binding(10) var<storage, read> blk_b: array<blk4>;
@group(0) @binding(11) var<storage, read> blk_c: array<real>;
@group(0) @binding(12) var<storage, read> rowsum: array<real>;
@group(0) @binding(13) var<uniform> chunk: Chunk;
@group(0) @binding(14) var<storage, read_write> carry: array<acc>;

var<workgroup> wg_done: u32;

// Component a of a packed mask is set (constrained).
fn mbits3(m: u32) -> vec3<bool> {
    return ((vec3<u32>(m) >> vec3<u32>(0u, 1u, 2u)) & vec3<u32>(1u)) != vec3<u32>(0u);
}

fn mbits2(m: u32) -> vec2<bool> {
    return ((vec2<u32>(m) >> vec2<u32>(0u, 1u)) & vec2<u32>(1u)) != vec2<u32>(0u);
}

fn p3(j: u32) -> vec3<real> {
    return vec3<real>(p[3u * j], p[3u * j + 1u], p[3u * j + 2u]);
}

fn p2(j: u32) -> vec2<real> {
    return vec2<real>(p[2u * j], p[2u * j + 1u]);
}

// Row i, D = 3, accumulated as columns of the block: Σ_k B_k p_j (DIFF: see above).
fn row3(i: u32) -> vec3<real> {
    var s = vec3<real>(real(0.0));
    // DIFF: the row is summed in `acc` (products of two f32 are exact in f64), so the
    // form's small terms are not rounded to f32 one by one (see DIFF above).
    var sa = vec3<acc>(acc(0.0));
    var pi = vec3<real>(real(0.0));
    if (DIFF) {
        pi = p3(i);
        if (MASKED) {
            pi = select(pi, vec3<real>(real(0.0)), mbits3(mask[i]));
        }
    }
    // Blocks of the row, as entries of this chunk's bound pieces.
    let k1 = row_ptr[i + 1u] - chunk.kbase;
    for (var k = row_ptr[i] - chunk.kbase; k < k1; k++) {
        let cj = col[k];
        var pj = p3(cj & COL_BITS);
        if (MASKED) {
            pj = select(pj, vec3<real>(real(0.0)), mbits3(cj >> MASK_SHIFT));
        }
        if (DIFF) {
            pj -= pi;
        }
        let a = unpack4(blk_a[k]);
        let b = unpack4(blk_b[k]);
        let c = blk_c[k];
        if (DIFF) {
            sa += vec3<acc>(vec3<real>(a.x, a.w, b.z)) * acc(pj.x) + vec3<acc>(vec3<real>(a.y, b.x, b.w)) * acc(pj.y)
                + vec3<acc>(vec3<real>(a.z, b.y, c)) * acc(pj.z);
        } else {
            s += vec3<real>(a.x, a.w, b.z) * pj.x + vec3<real>(a.y, b.x, b.w) * pj.y
                + vec3<real>(a.z, b.y, c) * pj.z;
        }
    }
    if (DIFF) {
        // Row sums are bound per chunk from its first row.
        let m = 9u * (i - chunk.row0);
        let pa = vec3<acc>(pi);
        sa += vec3<acc>(
            acc(rowsum[m]) * pa.x + acc(rowsum[m + 1u]) * pa.y + acc(rowsum[m + 2u]) * pa.z,
            acc(rowsum[m + 3u]) * pa.x + acc(rowsum[m + 4u]) * pa.y + acc(rowsum[m + 5u]) * pa.z,
            acc(rowsum[m + 6u]) * pa.x + acc(rowsum[m + 7u]) * pa.y + acc(rowsum[m + 8u]) * pa.z,
        );
        s = vec3<real>(sa);
    }
    return s;
}

fn row2(i: u32) -> vec2<real> {
    var s = vec2<real>(real(0.0));
    var sa = vec2<acc>(acc(0.0));
    var pi = vec2<real>(real(0.0));
    if (DIFF) {
        pi = p2(i);
        if (MASKED) {
            pi = select(pi, vec2<real>(real(0.0)), mbits2(mask[i]));
        }
    }
    // Blocks of the row, as entries of this chunk's bound pieces.
    let k1 = row_ptr[i + 1u] - chunk.kbase;
    for (var k = row_ptr[i] - chunk.kbase; k < k1; k++) {
        let cj = col[k];
        var pj = p2(cj & COL_BITS);
        if (MASKED) {
            pj = select(pj, vec2<real>(real(0.0)), mbits2(cj >> MASK_SHIFT));
        }
        if (DIFF) {
            pj -= pi;
        }
        let a = unpack4(blk_a[k]);
        if (DIFF) {
            sa += vec2<acc>(a.xz) * acc(pj.x) + vec2<acc>(a.yw) * acc(pj.y);
        } else {
            s += a.xz * pj.x + a.yw * pj.y;
        }
    }
    if (DIFF) {
        // Row sums are bound per chunk from its first row.
        let m = 4u * (i - chunk.row0);
        let pa = vec2<acc>(pi);
        sa += vec2<acc>(
            acc(rowsum[m]) * pa.x + acc(rowsum[m + 1u]) * pa.y,
            acc(rowsum[m + 2u]) * pa.x + acc(rowsum[m + 3u]) * pa.y,
        );
        s = vec2<real>(sa);
    }
    return s;
}

@compute @workgroup_size(WG)
fn matvec(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    if (lid.x == 0u) {
        wg_done = state[STATE_DONE];
    }
    // A converged (or halted) CG makes every later dispatch of its chunk a no-op.
    if (workgroupUniformLoad(&wg_done) != 0u) {
        return;
    }
    let stride = params.n_partials * WG;
    let t = group_index(wid, nwg) * WG + lid.x;
    var part = acc(0.0);
    if ((chunk.flags & CHUNK_FIRST) == 0u) {
        part = carry[t];
    }
    // This invocation's rows are t, t + stride, ...: the first of them in this chunk.
    var i0 = t;
    if (chunk.row0 > t) {
        i0 = t + (chunk.row0 - t + stride - 1u) / stride * stride;
    }
    for (var i = i0; i < chunk.row1; i += stride) {
        // Explicit 3- and 2-component paths: the override D removes the dead one, and
        // the straight-line vector code avoids dynamically indexed private arrays.
        if (D == 3u) {
            var v = row3(i);
            let pi = p3(i);
            if (MASKED) {
                let dv = vec3<real>(dvals[3u * i], dvals[3u * i + 1u], dvals[3u * i + 2u]);
                v = select(v, dv * pi, mbits3(mask[i]));
            }
            q[3u * i] = v.x;
            q[3u * i + 1u] = v.y;
            q[3u * i + 2u] = v.z;
            part += acc(pi.x) * acc(v.x) + acc(pi.y) * acc(v.y) + acc(pi.z) * acc(v.z);
        } else {
            var v = row2(i);
            let pi = p2(i);
            if (MASKED) {
                let dv = vec2<real>(dvals[2u * i], dvals[2u * i + 1u]);
                v = select(v, dv * pi, mbits2(mask[i]));
            }
            q[2u * i] = v.x;
            q[2u * i + 1u] = v.y;
            part += acc(pi.x) * acc(v.x) + acc(pi.y) * acc(v.y);
        }
    }
    if ((chunk.flags & CHUNK_LAST) == 0u) {
        carry[t] = part;
        return;
    }
    workgroup_sum(lid.x, sum1(part), 1u);
    if (lid.x == 0u) {
        partials[PART_PQ * params.n_partials + group_index(wid, nwg)] = summed(0u);
    }
}
