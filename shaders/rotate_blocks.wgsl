// Setup, run only for scenes with slip nodes: Ĥ_ij = V_iᵀ H_ij V_j for every block that
// touches a rotated node, in place on the block planes of matvec.wgsl
// (blk_a[k] = e0..e3, blk_b[k] = e4..e7, blk_c[k] = e8; D = 2 uses blk_a only).

override D: u32 = 3u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> rot_index: array<u32>;
@group(0) @binding(2) var<storage, read> rot_nodes: array<u32>;
@group(0) @binding(3) var<storage, read> rotations: array<real>;
@group(0) @binding(4) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(5) var<storage, read> col: array<u32>;
@group(0) @binding(6) var<storage, read_write> blk_a: array<vec4<real>>;
@group(0) @binding(7) var<storage, read_write> blk_b: array<vec4<real>>;
@group(0) @binding(8) var<storage, read_write> blk_c: array<real>;
// The planes and `col` are bound per row chunk (see `Chunk`).
@group(0) @binding(9) var<uniform> chunk: Chunk;

// V_r[a][b], row-major: its columns are the frame basis.
fn v(r: u32, a: u32, b: u32) -> real {
    return rotations[r * D * D + a * D + b];
}

fn rotate_blocks_row(i: u32) {
    let ri = rot_index[i];
    // Blocks of the row, as entries of this chunk's bound pieces.
    for (var k = row_ptr[i] - chunk.kbase; k < row_ptr[i + 1u] - chunk.kbase; k++) {
        let rj = rot_index[col[k] & COL_BITS];
        if (ri == NO_ROTATION && rj == NO_ROTATION) {
            continue;
        }
        var b: array<real, 9>;
        let a4 = blk_a[k];
        b[0] = a4.x;
        b[1] = a4.y;
        b[2] = a4.z;
        b[3] = a4.w;
        if (D == 3u) {
            let b4 = blk_b[k];
            b[4] = b4.x;
            b[5] = b4.y;
            b[6] = b4.z;
            b[7] = b4.w;
            b[8] = blk_c[k];
        }
        // t = B V_j
        var t: array<real, 9>;
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                if (rj == NO_ROTATION) {
                    t[r * D + c] = b[r * D + c];
                } else {
                    var s = real(0.0);
                    for (var m = 0u; m < D; m++) {
                        s += b[r * D + m] * v(rj, m, c);
                    }
                    t[r * D + c] = s;
                }
            }
        }
        // out = V_iᵀ t
        var o: array<real, 9>;
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                if (ri == NO_ROTATION) {
                    o[r * D + c] = t[r * D + c];
                } else {
                    var s = real(0.0);
                    for (var m = 0u; m < D; m++) {
                        s += v(ri, m, r) * t[m * D + c];
                    }
                    o[r * D + c] = s;
                }
            }
        }
        blk_a[k] = vec4<real>(o[0], o[1], o[2], o[3]);
        if (D == 3u) {
            blk_b[k] = vec4<real>(o[4], o[5], o[6], o[7]);
            blk_c[k] = o[8];
        }
    }
}

// The rows of this dispatch's chunk (`Chunk`, common.wgsl), grid-stride.
@compute @workgroup_size(WG)
fn rotate_blocks(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = chunk.row0 + grid_index(gid, nwg); i < chunk.row1; i += grid_stride(nwg)) {
        rotate_blocks_row(i);
    }
}
