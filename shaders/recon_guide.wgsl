// Guided filter, step 0 of 4: each pixel's guide colour and disparity, unpacked once for the
// passes that read them at every tap of a window (llvmpipe pays per load: the moments pass read
// three guide words and three code values per tap and spent as long as the rest of the filter).
// guided[i] = (R, G, B, p): the colour (code / 255 per channel; a grey guide repeats its one
// channel) and p = 1/z where the depth is valid, −1 where it is not.

@group(0) @binding(1) var<storage, read> depth: array<f32>;
@group(0) @binding(2) var<storage, read> guide: array<u32>;
@group(0) @binding(3) var<storage, read_write> guided: array<vec4<f32>>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    if id.x >= w || id.y >= recon.dims.y {
        return;
    }
    let i = id.y * w + id.x;
    let channels = recon.dims.w;
    var c: vec3<f32>;
    for (var k = 0u; k < 3u; k++) {
        let byte = i * channels + min(k, channels - 1u);
        c[k] = guide_value(guide[byte >> 2u], byte);
    }
    let z = depth[i];
    guided[i] = vec4<f32>(c, select(-1.0, 1.0 / z, is_valid_depth(z)));
}
