// Fixed-point injection counts → f16 SH in units of 2^23 counts (`pack_sh`): the start of
// propagation and of the accumulation.

@group(0) @binding(0) var<storage, read> volume_buffer: Volume;
var<private> volume: Volume;
// The injection's counts of V^Δ and of V^ρ (`dlpv_inject.wgsl`).
@group(0) @binding(1) var<storage, read> cells_delta: array<i32>;
@group(0) @binding(2) var<storage, read> cells_rho: array<i32>;
@group(0) @binding(3) var<storage, read_write> injected: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read_write> accumulated: array<vec2<u32>>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    volume = volume_buffer;
    let n = volume.dims.x;
    let count = 2u * n * n * n * 3u;
    if id.x >= count {
        return;
    }
    let per_volume = n * n * n * 3u;
    let b = (id.x % per_volume) * 4u;
    var c: vec4<i32>;
    if id.x < per_volume {
        c = vec4<i32>(cells_delta[b], cells_delta[b + 1u], cells_delta[b + 2u], cells_delta[b + 3u]);
    } else {
        c = vec4<i32>(cells_rho[b], cells_rho[b + 1u], cells_rho[b + 2u], cells_rho[b + 3u]);
    }
    let packed = pack_sh(vec4<f32>(c) * SH_UNITS_PER_COUNT);
    injected[id.x] = packed;
    accumulated[id.x] = packed;
}
