// Fixed-point injection counts → float SH (the start of propagation and of the accumulation).

@group(0) @binding(0) var<uniform> volume: Volume;
@group(0) @binding(1) var<storage, read> cells: array<i32>;
@group(0) @binding(2) var<storage, read_write> injected: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> accumulated: array<vec4<f32>>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = volume.dims.x;
    let count = 2u * n * n * n * 3u;
    if id.x >= count {
        return;
    }
    let b = id.x * 4u;
    let v = vec4<f32>(f32(cells[b]), f32(cells[b + 1u]), f32(cells[b + 2u]), f32(cells[b + 3u]))
        / volume.scale.x;
    injected[id.x] = v;
    accumulated[id.x] = v;
}
