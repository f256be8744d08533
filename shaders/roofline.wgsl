// Micro-kernels of `relightd bench --roofline` (engines/src/roofline.rs): the adapter's memory
// bandwidth (`copy`: one vec4 read and one written per invocation, nothing else) and its ALU
// rate (`fma`: eight independent vec4 fused multiply-add chains per invocation, so latency
// hides behind the other chains and only throughput counts).

struct Roofline {
    // x: elements (copy) or invocations (fma); y: fma iterations per invocation.
    size: vec4<u32>,
}

@group(0) @binding(0) var<storage, read> roofline_buffer: Roofline;
var<private> roofline: Roofline;
@group(0) @binding(1) var<storage, read> source: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> output: array<vec4<f32>>;

@compute @workgroup_size(64)
fn copy(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    roofline = roofline_buffer;
    let i = id.x + id.y * groups.x * 64u;
    if i < roofline.size.x {
        output[i] = source[i];
    }
}

@compute @workgroup_size(64)
fn fma_rate(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    roofline = roofline_buffer;
    let i = id.x + id.y * groups.x * 64u;
    if i >= roofline.size.x {
        return;
    }
    // Seeds the compiler cannot fold: the invocation index and a value read from memory.
    let seed = source[i % 64u];
    let m = vec4<f32>(0.999) + seed * 1e-9;
    let c = vec4<f32>(f32(i) * 1e-7);
    var a0 = seed;
    var a1 = seed + 1.0;
    var a2 = seed + 2.0;
    var a3 = seed + 3.0;
    var a4 = seed + 4.0;
    var a5 = seed + 5.0;
    var a6 = seed + 6.0;
    var a7 = seed + 7.0;
    for (var k = 0u; k < roofline.size.y; k++) {
        a0 = fma(a0, m, c);
        a1 = fma(a1, m, c);
        a2 = fma(a2, m, c);
        a3 = fma(a3, m, c);
        a4 = fma(a4, m, c);
        a5 = fma(a5, m, c);
        a6 = fma(a6, m, c);
        a7 = fma(a7, m, c);
    }
    output[i] = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7;
}
