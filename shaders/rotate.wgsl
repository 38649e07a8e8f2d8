// Per-node changes of basis V_i, run only for scenes with slip nodes.
// (rotate_blocks, Ĥ_ij = V_iᵀ H_ij V_j on the block planes, is in rotate_blocks.wgsl.)
// rotate_vectors: x_i ← V_i x_i (TRANSPOSE = false) or V_iᵀ x_i, over the rotated nodes.

override D: u32 = 3u;
override WG: u32 = 64u;
override TRANSPOSE: bool = false;

const NO_ROTATION: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> rot_index: array<u32>;
@group(0) @binding(2) var<storage, read> rot_nodes: array<u32>;
@group(0) @binding(3) var<storage, read> rotations: array<real>;
@group(0) @binding(4) var<storage, read_write> data: array<real>;

// V_r[a][b], row-major: its columns are the frame basis.
fn v(r: u32, a: u32, b: u32) -> real {
    return rotations[r * D * D + a * D + b];
}

@compute @workgroup_size(WG)
fn rotate_vectors(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = gid.x;
    if (r >= params.n_rot) {
        return;
    }
    let i = rot_nodes[r];
    var x = array<real, 3>(real(0.0), real(0.0), real(0.0));
    for (var a = 0u; a < D; a++) {
        x[a] = data[i * D + a];
    }
    for (var a = 0u; a < D; a++) {
        var s = real(0.0);
        for (var b = 0u; b < D; b++) {
            if (TRANSPOSE) {
                s += v(r, b, a) * x[b];
            } else {
                s += v(r, a, b) * x[b];
            }
        }
        data[i * D + a] = s;
    }
}
