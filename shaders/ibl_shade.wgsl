// Image-based shading of the virtual object from the convolved maps (Kan et al.):
//   L_o = k_d (E_d(n) + E_B(n)/π) · AO + k_s E_s^n(r) · ⟨n, r⟩₊
// with E_B the irradiance of the local picture's second bounce (`ibl.bounce`, L2 SH).
// written to the indirect buffer, which the shared shading pass adds to virtual pixels' L^ρ.
// ⟨n, r⟩ is the cosine of the scene format's Phong BRDF (without the paper's division by
// |n·ω_i|) taken at the lobe's centre, exact as the lobe narrows. The ambient occlusion is the
// visibility of the environment's shadow lights (importance-sampled from the map, flagged
// LIGHT_SHADOW_ONLY) through R^ρ, weighted by the light each brings to the surface. Real
// pixels get nothing here: their Δ is the shadow those lights' maps give (shade.wgsl).

@group(0) @binding(0) var<storage, read> ibl_buffer: Ibl;
var<private> ibl: Ibl;
@group(0) @binding(1) var<storage, read> camera_buffer: Camera;
var<private> camera: Camera;
@group(0) @binding(2) var<storage, read> lights: array<Light>;
@group(0) @binding(3) var<storage, read> faces: array<Face>;
@group(0) @binding(4) var<storage, read> materials: array<Material>;
@group(0) @binding(5) var gb_position: texture_2d<f32>;
@group(0) @binding(6) var gb_normal: texture_2d<f32>;
@group(0) @binding(7) var gb_albedo: texture_2d<f32>;
@group(0) @binding(8) var rsm_rho: texture_depth_2d_array;
@group(0) @binding(9) var<storage, read> maps: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> indirect: array<vec4<f32>>;

// Bilinear lookup of map `layer` in direction `d`, clamped at the square's edges.
fn map_lookup(layer: u32, d: vec3<f32>) -> vec3<f32> {
    let size = ibl.dims.x;
    let s = f32(size);
    let t = clamp(oct_encode(d) * s - 0.5, vec2<f32>(0.0), vec2<f32>(s - 1.0));
    let t0 = vec2<u32>(floor(t));
    let t1 = min(t0 + 1u, vec2<u32>(size - 1u));
    let f = t - floor(t);
    let base = layer * size * size;
    let a = maps[base + t0.y * size + t0.x].rgb;
    let b = maps[base + t0.y * size + t1.x].rgb;
    let c = maps[base + t1.y * size + t0.x].rgb;
    let e = maps[base + t1.y * size + t1.x].rgb;
    return mix(mix(a, b, f.x), mix(c, e, f.x), f.y);
}

// The specular level whose exponent is nearest `n` in log scale.
fn level_of(n: f32) -> u32 {
    var best = 0u;
    var best_gap = 3.0e38;
    for (var l = 0u; l < ibl.dims.y; l++) {
        let gap = abs(log2(ibl_shininess(ibl, l)) - log2(n));
        if gap < best_gap {
            best_gap = gap;
            best = l;
        }
    }
    return best;
}

fn occlusion(p: vec3<f32>, n: vec3<f32>) -> f32 {
    var total = 0.0;
    var visible = 0.0;
    for (var i = 0u; i < ibl.frame.z; i++) {
        let l = lights[i];
        if l.faces.z != LIGHT_SHADOW_ONLY {
            continue;
        }
        let inc = incident(l, p);
        let c = dot(n, inc.to_light);
        if c <= 0.0 {
            continue;
        }
        let w = dot(inc.irradiance, LUMINANCE) * c;
        let layer = face_of(l, p);
        total += w;
        visible += w * lit(l, faces[layer], layer, p, n, inc.to_light, rsm_rho, ibl.frame.w, ibl.params.x);
    }
    return select(1.0, visible / total, total > 0.0);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    ibl = ibl_buffer;
    camera = camera_buffer;
    let pixel = id.xy + ibl.region.xy;
    if pixel.x >= ibl.region.z || pixel.y >= ibl.region.w {
        return;
    }
    let xy = vec2<i32>(pixel);
    let p = textureLoad(gb_position, xy, 0);
    let nv = textureLoad(gb_normal, xy, 0);
    if p.w < 0.5 || nv.w < 0.5 {
        return;
    }
    let m = materials[u32(p.w) - 1u];
    let n = normalize(nv.xyz);
    let wo = normalize(camera.position.xyz - p.xyz);
    var bounce: array<vec3<f32>, 9>;
    for (var k = 0u; k < 9u; k++) {
        bounce[k] = ibl.bounce[k].rgb;
    }
    // The diffuse map holds E/π; the second bounce's irradiance joins it so.
    let diffuse = map_lookup(0u, n) + far_field_irradiance(bounce, n) / PI;
    var l_o = textureLoad(gb_albedo, xy, 0).rgb * diffuse * occlusion(p.xyz, n);
    if ibl.dims.y > 0u && m.albedo.w > 0.0 && any(m.specular.rgb > vec3<f32>(0.0)) {
        let r = reflect(-wo, n);
        l_o += m.specular.rgb * map_lookup(1u + level_of(m.albedo.w), r) * max(dot(n, r), 0.0);
    }
    indirect[pixel.y * ibl.frame.x + pixel.x] = vec4<f32>(l_o, 0.0);
}
