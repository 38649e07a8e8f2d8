// Mixed precision: the f64 outer loop of iterative refinement around the f32 CG.
// residual:   r64 = b̂ − Ĥy (q64 = Ĥy from the f64 matvec) stored back into q64, and
//             per-workgroup partials of ‖r64‖² (deterministic, summed by the host).
// scale_rhs:  rhs32 = f32(r64 · factors[0]), factors[0] = 1/‖r64‖: the inner CG always
//             sees a unit right-hand side, so tiny or huge residuals neither underflow
//             nor overflow f32.
// accumulate: y64 += factors[1] · f64(x32), the correction found by the inner f32 CG,
//             scaled back (factors[1] = 2^s·‖r64‖ where the f32 operator is 2^s·Ĥ).
// Needs SHADER_F64; the scalar types are explicit here.

override D: u32 = 3u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> b64: array<f64>;
@group(0) @binding(2) var<storage, read_write> q64: array<f64>;
@group(0) @binding(3) var<storage, read_write> rhs32: array<f32>;
@group(0) @binding(4) var<storage, read_write> partials64: array<f64>;
@group(0) @binding(5) var<storage, read> x32: array<f32>;
@group(0) @binding(6) var<storage, read_write> y64: array<f64>;
@group(0) @binding(7) var<storage, read> factors: array<f64>;

@compute @workgroup_size(WG)
fn residual(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = params.n_nodes * D;
    var s = f64(0.0);
    for (var k = group_index(wid, nwg) * WG + lid.x; k < n; k += params.n_partials * WG) {
        let rk = b64[k] - q64[k];
        q64[k] = rk;
        s += rk * rk;
    }
    // acc is f64 wherever this kernel is built; the conversions keep the source valid
    // under every prelude.
    workgroup_sum(lid.x, sum1(acc(s)), 1u);
    if (lid.x == 0u) {
        partials64[group_index(wid, nwg)] = f64(summed(0u));
    }
}

@compute @workgroup_size(WG)
fn scale_rhs(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = params.n_nodes * D;
    for (var k = grid_index(gid, nwg); k < n; k += grid_stride(nwg)) {
        rhs32[k] = f32(q64[k] * factors[0]);
    }
}

@compute @workgroup_size(WG)
fn accumulate(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let n = params.n_nodes * D;
    for (var k = grid_index(gid, nwg); k < n; k += grid_stride(nwg)) {
        y64[k] += factors[1] * f64(x32[k]);
    }
}
