// The gate of conditional work (src/gpu/gate.rs): one workgroup writes the indirect
// dispatch arguments of the work that follows it, the launches the host tabled where a
// flag word of a state buffer is set, zero workgroups where it is not. So work recorded
// ahead of a decision the device makes (a solve that may or may not have converged in the
// chunk) costs nothing when it is not wanted.

// Mirrors `GateParams` in src/gpu/gate.rs (four u32, 16 bytes, size-asserted there).
struct GateParams {
    // Dispatches gated (three words each in `table` and `args`).
    count: u32,
    // The word of `state` that opens the gate.
    flag: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<uniform> params: GateParams;
@group(0) @binding(1) var<storage, read> state: array<u32>;
@group(0) @binding(2) var<storage, read> table: array<u32>;
@group(0) @binding(3) var<storage, read_write> args: array<u32>;

@compute @workgroup_size(WG)
fn gate(@builtin(local_invocation_id) lid: vec3<u32>) {
    let open = state[params.flag] != 0u;
    for (var k = lid.x; k < 3u * params.count; k += WG) {
        args[k] = select(0u, table[k], open);
    }
}
