// Gather assembly of the Newton system from the per-element arrays of elements.wgsl, and
// two products with it: the assembled block matrix's and a matrix-free one over the
// element Hessians. One invocation per output block or node, each summing its own
// contributions in a fixed order (src/sim/device/assembly.rs builds the gather lists on the
// host): no atomics, the same result on every run and in the CPU's order
// (src/sim/energy: inertia, then the element sets in order with their elements in order, then
// the node terms).
//
// H = M + s·(Σ_sets K_e + B), g = M(x − x̃) + s·(Σ_sets g_e + g_gravity + g_barrier),
// s = coef[1] (h²); the inertia terms enter with coef[0] = 1.
//
// An element set or node term too large for one storage binding comes as several chunk
// terms of consecutive items, each with its own arrays and gather lists (offsets local to
// the chunk). A chunk's pass reads `out` and adds its own list in element order, so an
// entry receives the unsplit additions in the unsplit order: the same bits.
//
// The block values come in chunks of consecutive block rows, each its own buffer (one
// storage binding caps its size); a block pass runs once per chunk with `out` that chunk
// and its items local to it (global block block_first + k at out[k·D² ..]), so every
// block still receives its additions in the unsplit order.
//
// Block values are row-major D×D at out[k·D² ..], k in the BlockCsr order; element
// Hessians hessian[e·nl² + (a·D + r)·nl + b·D + c], gradients gradient[e·nl + a·D + c].

override D: u32 = 3u;

// Mirrors `AssemblyParams` in src/sim/device/assembly.rs (eight u32, 32 bytes, size-asserted there).
struct AssemblyParams {
    // Output blocks or nodes of the dispatch.
    count: u32,
    // Entries per element gradient (nodes per element · D).
    nl: u32,
    // Nodes per element.
    arity: u32,
    // Index into `coef` of this term's factor.
    coef_slot: u32,
    // Node passes: the mesh node of the term's item 0. A node term too large for one
    // storage binding comes in chunks of consecutive nodes, each with its own `src` from
    // index 0; `out` and `x` are the whole mesh's.
    first: u32,
    // Block passes: the global block of the values chunk's block 0 (`out` holds that
    // chunk only; items are local to it).
    block_first: u32,
    // Node-block passes: the term chunk's item of the dispatch's item 0 (a term chunk's
    // nodes may lie in several values chunks).
    src_first: u32,
    _pad: u32,
}

const NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: AssemblyParams;
// Per output item, its range in `gather` (count + 1 entries); CSR row pointers for the
// assembled product.
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
// Element passes: offsets into `src` (block: e·nl² + a·D·nl + b·D; node: e·nl + a·D).
// Node passes: per block its node when diagonal, else NONE (block init), or per node its
// diagonal block (adding a node term). Assembled product: block column indices.
@group(0) @binding(2) var<storage, read> gather: array<u32>;
// The term's per-item Hessians or gradients; the block values for the assembled product.
@group(0) @binding(3) var<storage, read> src: array<real>;
// Term factors: [1, s].
@group(0) @binding(4) var<storage, read> coef: array<real>;
// The vector of a product, node-major.
@group(0) @binding(5) var<storage, read> x: array<real>;
// Element-to-node indices of the set (matrix-free product).
@group(0) @binding(6) var<storage, read> nodes: array<u32>;
// Block values, gradient or product.
@group(0) @binding(7) var<storage, read_write> out: array<real>;

// Block k := the inertia block gather[k] of the first inertia chunk (its diagonal blocks),
// else zero (NONE: off-diagonal, or a node of a later chunk, set by blocks_set_nodes).
// gather is indexed by global block.
@compute @workgroup_size(WG)
fn blocks_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let c = coef[params.coef_slot];
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        let i = gather[params.block_first + k];
        for (var t = 0u; t < dd; t++) {
            var v = real(0.0);
            if i != NONE {
                v = c * src[i * dd + t];
            }
            out[k * dd + t] = v;
        }
    }
}

// Block k += s·Σ (its element sub-blocks, in gather order).
@compute @workgroup_size(WG)
fn blocks_add_elements(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let nl = params.nl;
    let c = coef[params.coef_slot];
    for (var k = grid_index(gid, nwg); k < params.count; k += grid_stride(nwg)) {
        var sum: array<real, 9>;
        for (var t = 0u; t < dd; t++) {
            sum[t] = out[k * dd + t];
        }
        let kg = params.block_first + k;
        for (var j = offsets[kg]; j < offsets[kg + 1u]; j++) {
            let base = gather[j];
            for (var r = 0u; r < D; r++) {
                for (var q = 0u; q < D; q++) {
                    sum[r * D + q] += c * src[base + r * nl + q];
                }
            }
        }
        for (var t = 0u; t < dd; t++) {
            out[k * dd + t] = sum[t];
        }
    }
}

// Diagonal block of the dispatch's node i := factor·(its node-term block): the inertia of
// the chunks after the first (the first's blocks_init zeroes every other block). gather:
// per node of the dispatch its diagonal block, local to the values chunk.
@compute @workgroup_size(WG)
fn blocks_set_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        let k = gather[i];
        let s = params.src_first + i;
        for (var t = 0u; t < dd; t++) {
            out[k * dd + t] = c * src[s * dd + t];
        }
    }
}

// Diagonal block of the dispatch's node i += factor·(its node-term block).
@compute @workgroup_size(WG)
fn blocks_add_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        let k = gather[i];
        let s = params.src_first + i;
        for (var t = 0u; t < dd; t++) {
            out[k * dd + t] += c * src[s * dd + t];
        }
    }
}

// g_{first+i} := factor·(node term)_i.
@compute @workgroup_size(WG)
fn grad_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        let g = params.first + i;
        for (var q = 0u; q < D; q++) {
            out[g * D + q] = c * src[i * D + q];
        }
    }
}

// g_i += s·Σ (the element gradients' entries of node i, in gather order).
@compute @workgroup_size(WG)
fn grad_add_elements(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        var sum: array<real, 3>;
        for (var q = 0u; q < D; q++) {
            sum[q] = out[i * D + q];
        }
        for (var j = offsets[i]; j < offsets[i + 1u]; j++) {
            let base = gather[j];
            for (var q = 0u; q < D; q++) {
                sum[q] += c * src[base + q];
            }
        }
        for (var q = 0u; q < D; q++) {
            out[i * D + q] = sum[q];
        }
    }
}

// g_{first+i} += factor·(node term)_i.
@compute @workgroup_size(WG)
fn grad_add_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        let g = params.first + i;
        for (var q = 0u; q < D; q++) {
            out[g * D + q] += c * src[i * D + q];
        }
    }
}

// y = H x with the assembled blocks (BlockCsr::matvec's order), over the values chunk's
// rows first .. first + count.
@compute @workgroup_size(WG)
fn matvec_blocks(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    for (var li = grid_index(gid, nwg); li < params.count; li += grid_stride(nwg)) {
        let i = params.first + li;
        var sum: array<real, 3>;
        for (var k = offsets[i]; k < offsets[i + 1u]; k++) {
            let j = gather[k];
            let kl = k - params.block_first;
            for (var r = 0u; r < D; r++) {
                var s = real(0.0);
                for (var q = 0u; q < D; q++) {
                    s += src[kl * dd + r * D + q] * x[j * D + q];
                }
                sum[r] += s;
            }
        }
        for (var r = 0u; r < D; r++) {
            out[i * D + r] = sum[r];
        }
    }
}

// y_{first+i} := factor·(node-term block)_i x_{first+i} (matrix-free product, first term).
@compute @workgroup_size(WG)
fn matfree_init(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        let g = params.first + i;
        for (var r = 0u; r < D; r++) {
            var s = real(0.0);
            for (var q = 0u; q < D; q++) {
                s += src[i * dd + r * D + q] * x[g * D + q];
            }
            out[g * D + r] = c * s;
        }
    }
}

// y_{first+i} += factor·(node-term block)_i x_{first+i}.
@compute @workgroup_size(WG)
fn matfree_add_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let dd = D * D;
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        let g = params.first + i;
        for (var r = 0u; r < D; r++) {
            var s = real(0.0);
            for (var q = 0u; q < D; q++) {
                s += src[i * dd + r * D + q] * x[g * D + q];
            }
            out[g * D + r] += c * s;
        }
    }
}

// y_i += s·Σ over the elements touching node i (as local node a) of
// Σ_b H_e[a, b] x_{node(e, b)}: the element Hessians' rows of node i, H never formed.
@compute @workgroup_size(WG)
fn matfree_add_elements(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let nl = params.nl;
    let arity = params.arity;
    let c = coef[params.coef_slot];
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        var sum: array<real, 3>;
        for (var q = 0u; q < D; q++) {
            sum[q] = out[i * D + q];
        }
        for (var j = offsets[i]; j < offsets[i + 1u]; j++) {
            let base = gather[j];
            let e = base / nl;
            let a = (base % nl) / D;
            let row0 = e * nl * nl + a * D * nl;
            for (var b = 0u; b < arity; b++) {
                let n = nodes[e * arity + b];
                for (var r = 0u; r < D; r++) {
                    var s = real(0.0);
                    for (var q = 0u; q < D; q++) {
                        s += src[row0 + r * nl + b * D + q] * x[n * D + q];
                    }
                    sum[r] += c * s;
                }
            }
        }
        for (var q = 0u; q < D; q++) {
            out[i * D + q] = sum[q];
        }
    }
}
