// Builds the Jacobi (PRECOND = 1) or block-Jacobi (PRECOND = 2) preconditioner on the
// device from the diagonal blocks of Ĥ = P VᵀHV P + (I − P) D (blocks already rotated).
// Block-Jacobi inverts each d×d block when it is SPD (all leading minors positive) and
// falls back to the inverse diagonal otherwise, like the CPU reference (cg.rs).

override D: u32 = 3u;
override MASKED: bool = true;
override PRECOND: u32 = 1u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> col: array<u32>;
// Block planes as in matvec.wgsl: blk_a[k] = e0..e3, blk_b[k] = e4..e7, blk_c[k] = e8,
// bound per row chunk with `col` (see `Chunk`).
@group(0) @binding(3) var<storage, read> blk_a: array<vec4<real>>;
@group(0) @binding(4) var<storage, read> mask: array<u32>;
@group(0) @binding(5) var<storage, read> dvals: array<real>;
@group(0) @binding(6) var<storage, read_write> minv: array<real>;
@group(0) @binding(7) var<storage, read> blk_b: array<vec4<real>>;
@group(0) @binding(8) var<storage, read> blk_c: array<real>;
@group(0) @binding(9) var<uniform> chunk: Chunk;

// Block k as row-major d×d values (the first D·D entries are meaningful).
fn load_block(k: u32) -> array<real, 9> {
    let a = blk_a[k];
    if (D == 3u) {
        let b = blk_b[k];
        return array<real, 9>(a.x, a.y, a.z, a.w, b.x, b.y, b.z, b.w, blk_c[k]);
    }
    let z = real(0.0);
    return array<real, 9>(a.x, a.y, a.z, a.w, z, z, z, z, z);
}

fn build_row(i: u32) {
    var b: array<real, 9>;
    for (var e = 0u; e < 9u; e++) {
        b[e] = real(0.0);
    }
    // Blocks of the row, as entries of this chunk's bound pieces.
    for (var k = row_ptr[i] - chunk.kbase; k < row_ptr[i + 1u] - chunk.kbase; k++) {
        if ((col[k] & COL_BITS) == i) {
            b = load_block(k);
        }
    }
    if (MASKED) {
        let m = mask[i];
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                if (((m >> r) & 1u) != 0u || ((m >> c) & 1u) != 0u) {
                    b[r * D + c] = real(0.0);
                }
            }
            if (((m >> r) & 1u) != 0u) {
                b[r * D + r] = dvals[i * D + r];
            }
        }
    }
    // The one block-Jacobi specification (common.wgsl).
    if (PRECOND == 1u) {
        for (var a = 0u; a < D; a++) {
            minv[i * D + a] = jacobi_inverse(b[a * D + a]);
        }
        return;
    }
    let out = block_jacobi_inverse(b, D);
    for (var e = 0u; e < D * D; e++) {
        minv[i * D * D + e] = out[e];
    }
}

// The rows of this dispatch's chunk (`Chunk`, common.wgsl), grid-stride.
@compute @workgroup_size(WG)
fn build(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = chunk.row0 + grid_index(gid, nwg); i < chunk.row1; i += grid_stride(nwg)) {
        build_row(i);
    }
}
