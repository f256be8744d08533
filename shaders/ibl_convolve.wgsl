// Reflection-map convolution (Kan et al.): every output texel of the octahedral maps integrates
// the *whole* input environment, no mip-map approximation. Layer 0 is the diffuse irradiance map
// E_d(n) = 1/π Σ L ΔΩ ⟨n, ω⟩₊, layer 1 + k the specular map of Phong exponent n_k,
// E_s(r) = (n_k + 1)/(2π) Σ L ΔΩ ⟨r, ω⟩₊^n_k, all levels in one pass. The input texels
// (direction, solid angle, radiance; black ones left out) are staged through workgroup memory in
// tiles, each read once per workgroup instead of once per output texel.

struct InputTexel {
    // xyz: unit direction; w: solid angle (sr).
    direction: vec4<f32>,
    // rgb: radiance; w: 1 = left out of the diffuse map.
    radiance: vec4<f32>,
}

const TILE: u32 = 64u;
const MAX_LEVELS: u32 = 8u;

@group(0) @binding(0) var<storage, read> ibl_buffer: Ibl;
var<private> ibl: Ibl;
@group(0) @binding(1) var<storage, read> input: array<InputTexel>;
@group(0) @binding(2) var<storage, read_write> maps: array<vec4<f32>>;

var<workgroup> tile: array<InputTexel, TILE>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(local_invocation_index) local: u32) {
    ibl = ibl_buffer;
    let size = ibl.dims.x;
    let levels = min(ibl.dims.y, MAX_LEVELS);
    let count = ibl.dims.z;
    let texels = size * size;
    let inside = id.x < texels;
    let t = min(id.x, texels - 1u);
    let d = oct_decode((vec2<f32>(f32(t % size), f32(t / size)) + 0.5) / f32(size));
    var diffuse = vec3<f32>(0.0);
    var specular: array<vec3<f32>, MAX_LEVELS>;
    for (var base = 0u; base < count; base += TILE) {
        let j = base + local;
        if j < count {
            tile[local] = input[j];
        } else {
            tile[local] = InputTexel(vec4<f32>(0.0), vec4<f32>(0.0));
        }
        workgroupBarrier();
        for (var k = 0u; k < TILE; k++) {
            let c = dot(d, tile[k].direction.xyz);
            if c > 0.0 {
                let e = tile[k].radiance.rgb * tile[k].direction.w;
                // w = 1: a local picture's surface, whose diffuse light the shading takes from
                // its patch where the pixel stands (`ibl_shade.wgsl`, `near`).
                diffuse += e * c * (1.0 - tile[k].radiance.w);
                for (var l = 0u; l < levels; l++) {
                    specular[l] += e * pow(c, ibl_shininess(ibl, l));
                }
            }
        }
        workgroupBarrier();
    }
    if !inside {
        return;
    }
    maps[t] = vec4<f32>(diffuse / PI, 1.0);
    for (var l = 0u; l < levels; l++) {
        let n = ibl_shininess(ibl, l);
        maps[(l + 1u) * texels + t] = vec4<f32>(specular[l] * (n + 1.0) / (2.0 * PI), 1.0);
    }
}
