// Progressive differential path tracing (engines/src/pt), the resolve: per pixel, Δ and the
// variance of its mean from the running means `pt_trace.wgsl` keeps, and the composite over
// this frame's background. Apart from the trace, so that a frame tracing a share of a sample
// dispatches the tracer only over the tiles it traces.

struct ResolveParams {
    // width, height (the trace's parameters; the rest is not read here).
    size: vec4<u32>,
}

// As `pt_trace.wgsl` keeps them: the overlay with the object's coverage in w; Δ's mean with the
// pixel's sample count in w; Δ's sum of squared deviations.
struct Accum {
    overlay: vec4<f32>,
    delta_mean: vec4<f32>,
    delta_m2: vec4<f32>,
}

@group(0) @binding(0) var<storage, read> params_buffer: ResolveParams;
var<private> params: ResolveParams;
@group(0) @binding(1) var<storage, read> accum: array<Accum>;
@group(0) @binding(2) var<storage, read> background: array<u32>;
// rgb: Δ; w: the variance of its mean, summed over the channels (−1 below two samples).
@group(0) @binding(3) var<storage, read_write> delta_out: array<vec4<f32>>;
// sRGB composite; alpha: the object's coverage.
@group(0) @binding(4) var<storage, read_write> composite_out: array<u32>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    params = params_buffer;
    if id.x >= params.size.x || id.y >= params.size.y {
        return;
    }
    let i = id.y * params.size.x + id.x;
    let acc = accum[i];
    let n = acc.delta_mean.w;
    var variance = -1.0;
    if n >= 2.0 {
        let v = acc.delta_m2.xyz / (n - 1.0) / n;
        variance = v.x + v.y + v.z;
    }
    delta_out[i] = vec4<f32>(acc.delta_mean.xyz, variance);
    var composite = srgb_to_linear(unpack4x8unorm(background[i]).rgb);
    var coverage = 0.0;
    if n >= 1.0 {
        coverage = acc.overlay.w;
        composite = acc.overlay.rgb + (1.0 - coverage) * composite;
    }
    // Alpha: the object's coverage of the pixel.
    composite_out[i] = pack4x8unorm(vec4<f32>(linear_to_srgb(composite), coverage));
}
