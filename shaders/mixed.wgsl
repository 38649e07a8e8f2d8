// Mixed precision's f64 outer loop on the device PCG (src/gpu/pcg/refine.rs), between its
// f64 level (r64: the true residual its start formed; y64: the f64 iterate, both scaled
// by the level's σ) and its f32 level (b32: the next segment's right-hand side; d32: the
// segment's solution):
//   scale_rhs:  b32 = f32(r64 · factors[0]), factors[0] = 1/‖r64‖ (a unit right-hand side,
//               so tiny or huge residuals neither under- nor overflow f32)
//   accumulate: y64 += factors[1] · f64(d32), factors[1] = 2^s·‖r64‖ (the f32 operator
//               holds 2^s·Ĥ)
// One invocation per unknown. Needs SHADER_F64; the scalar types are explicit here.

// Mirrors `MixedParams` in src/gpu/pcg/refine.rs (four u32, 16 bytes, size-asserted).
struct MixedParams {
    n_dofs: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> params: MixedParams;
@group(0) @binding(1) var<storage, read> r64: array<f64>;
@group(0) @binding(2) var<storage, read_write> b32: array<f32>;
@group(0) @binding(3) var<storage, read> d32: array<f32>;
@group(0) @binding(4) var<storage, read_write> y64: array<f64>;
@group(0) @binding(5) var<storage, read> factors: array<f64>;

@compute @workgroup_size(WG)
fn scale_rhs(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var k = grid_index(gid, nwg); k < params.n_dofs; k += grid_stride(nwg)) {
        b32[k] = f32(r64[k] * factors[0]);
    }
}

@compute @workgroup_size(WG)
fn accumulate(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var k = grid_index(gid, nwg); k < params.n_dofs; k += grid_stride(nwg)) {
        y64[k] += factors[1] * f64(d32[k]);
    }
}
