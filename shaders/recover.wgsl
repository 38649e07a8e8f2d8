// Recovery, masking part: dx_i = P_i y_i (the rotation V_i and the lift Δx_p follow:
// rotate_vectors on slip nodes only, and the lift is added in f64 on the host so that
// constrained components come out exactly as prescribed).

override D: u32 = 3u;
override WG: u32 = 64u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> mask: array<u32>;
@group(0) @binding(2) var<storage, read> y: array<real>;
@group(0) @binding(3) var<storage, read_write> dx: array<real>;

@compute @workgroup_size(WG)
fn recover(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n_nodes) {
        return;
    }
    let m = mask[i];
    for (var a = 0u; a < D; a++) {
        var v = y[i * D + a];
        if (((m >> a) & 1u) != 0u) {
            v = real(0.0);
        }
        dx[i * D + a] = v;
    }
}
