// Image-based shading of the virtual object from the convolved maps (Kan et al.):
//   L_o = k_d (E_d(n) + (E_B(n) + E_N(p, n))/π) · AO + k_s E_s^n(r) · ⟨n, r⟩₊
// with E_B the irradiance of the local picture's later bounces (`ibl.bounce`, L2 SH) and E_N
// its surfaces' from where they are (`near_irradiance`); E_d then holds the rest of the picture.
// written to the indirect buffer, which the shared shading pass adds to virtual pixels' L^ρ.
// ⟨n, r⟩ is the cosine of the scene format's Phong BRDF (without the paper's division by
// |n·ω_i|) taken at the lobe's centre, exact as the lobe narrows. The ambient occlusion is the
// visibility of the environment's shadow lights (importance-sampled from the map, flagged
// LIGHT_SHADOW_ONLY) through R^ρ, weighted by the light each brings to the surface. Real
// pixels get nothing here but, with `occlusion` on, the light the object blocks (`real`); the
// rest of their Δ is the shadow those lights' maps give (shade.wgsl).

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
// The local picture's surfaces, one patch per texel that meets one (`LocalPicture::near`).
struct NearPatch {
    // xyz: position; w: area (m²).
    position: vec4<f32>,
    normal: vec4<f32>,
    radiance: vec4<f32>,
}
@group(0) @binding(11) var<storage, read> near: array<NearPatch>;

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

// The irradiance the local picture's surfaces send to `p` (normal `n`): Σ L A ⟨n_j, −ω⟩ ⟨n, ω⟩ / d²
// over their patches, each a small Lambertian emitter whose 1/d² is clamped within its own
// footprint (radius √(A/π)). The diffuse map holds the rest of the picture (where its rays
// escape); from the centre the patches give what their texels gave there, and elsewhere
// their light falls with distance: the foot of an object on a lit floor takes more of it
// than its top.
fn near_irradiance(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    var e = vec3<f32>(0.0);
    for (var j = 0u; j < ibl.dims.w; j++) {
        let piece = near[j];
        let d = piece.position.xyz - p;
        let d2 = dot(d, d);
        let w = d * inverseSqrt(max(d2, 1e-12));
        let cos_p = dot(n, w);
        let cos_j = -dot(piece.normal.xyz, w);
        if cos_p > 0.0 && cos_j > 0.0 {
            let area = piece.position.w;
            e += piece.radiance.rgb * (area * cos_j * cos_p / max(d2, area / PI));
        }
    }
    return e;
}

fn surface_at(xy: vec2<u32>) -> PixelSurface {
    let at = vec2<i32>(xy);
    return pixel_surface(textureLoad(gb_position, at, 0), textureLoad(gb_normal, at, 0));
}

// The object's light at pixel `xy` (surface `s`), given the near surfaces' irradiance there.
fn shaded(xy: vec2<u32>, s: PixelSurface, near_e: vec3<f32>) -> vec3<f32> {
    let m = materials[u32(s.p.w) - 1u];
    let n = s.n;
    let wo = normalize(camera.position.xyz - s.p.xyz);
    var bounce: array<vec3<f32>, 9>;
    for (var k = 0u; k < 9u; k++) {
        bounce[k] = ibl.bounce[k].rgb;
    }
    // The diffuse map holds E/π; the later bounces' irradiance and the near surfaces' join
    // it so.
    let diffuse = map_lookup(0u, n) + (far_field_irradiance(bounce, n) + near_e) / PI;
    var l_o = textureLoad(gb_albedo, vec2<i32>(xy), 0).rgb * diffuse * occlusion(s.p.xyz, n);
    if ibl.dims.y > 0u && m.albedo.w > 0.0 && any(m.specular.rgb > vec3<f32>(0.0)) {
        let r = reflect(-wo, n);
        l_o += m.specular.rgb * map_lookup(1u + level_of(m.albedo.w), r) * max(dot(n, r), 0.0);
    }
    return l_o;
}

// The near surfaces' irradiance is gathered at every `near_stride()`-th pixel per axis (see
// `stride_corner` in common.wgsl and `engines/src/strided.rs`). At 1, `main` alone shades every
// pixel of the object. Above 1: `main` writes the gathered irradiance at the strided pixels
// (w = 1); `fill` shades every other pixel with the blend of its alike strided neighbours'
// irradiance, or gathers its own where none is alike; `resolve` shades the strided pixels.
fn near_stride() -> u32 {
    return max(u32(ibl.params.y), 1u);
}

// The strided pixel `id` of the region (its first is aligned to the stride, at or before the
// region's).
fn strided_pixel(id: vec2<u32>) -> vec2<u32> {
    let stride = near_stride();
    return (ibl.region.xy / stride + id) * stride;
}

fn on_object(s: PixelSurface) -> bool {
    return s.found && s.is_virtual;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    ibl = ibl_buffer;
    camera = camera_buffer;
    let pixel = strided_pixel(id.xy);
    if any(pixel >= ibl.region.zw) {
        return;
    }
    let i = pixel.y * ibl.frame.x + pixel.x;
    let s = surface_at(pixel);
    if !on_object(s) {
        if near_stride() > 1u {
            indirect[i] = vec4<f32>(0.0);
        }
        return;
    }
    let near_e = near_irradiance(s.p.xyz, s.n);
    if near_stride() > 1u {
        indirect[i] = vec4<f32>(near_e, 1.0);
    } else {
        indirect[i] = vec4<f32>(shaded(pixel, s, near_e), 0.0);
    }
}

@compute @workgroup_size(8, 8)
fn fill(@builtin(global_invocation_id) id: vec3<u32>) {
    ibl = ibl_buffer;
    camera = camera_buffer;
    let stride = near_stride();
    let pixel = ibl.region.xy + id.xy;
    if any(pixel >= ibl.region.zw) || all(pixel % stride == vec2<u32>(0u)) {
        return;
    }
    let s = surface_at(pixel);
    if !on_object(s) {
        return;
    }
    var sum = vec3<f32>(0.0);
    var weight = 0.0;
    for (var k = 0u; k < 4u; k++) {
        let at = stride_corner(pixel, stride, k);
        let w = stride_weight(pixel, stride, k, ibl.frame.xy);
        if w <= 0.0 || any(at >= ibl.region.zw) {
            continue;
        }
        let traced = indirect[at.y * ibl.frame.x + at.x];
        if traced.w > 0.5 && alike(s, surface_at(at), camera.position.xyz) {
            sum += w * traced.rgb;
            weight += w;
        }
    }
    var near_e: vec3<f32>;
    if weight > 0.0 {
        near_e = sum / weight;
    } else {
        near_e = near_irradiance(s.p.xyz, s.n);
    }
    indirect[pixel.y * ibl.frame.x + pixel.x] = vec4<f32>(shaded(pixel, s, near_e), 0.0);
}

@compute @workgroup_size(8, 8)
fn resolve(@builtin(global_invocation_id) id: vec3<u32>) {
    ibl = ibl_buffer;
    camera = camera_buffer;
    let pixel = strided_pixel(id.xy);
    if any(pixel >= ibl.region.zw) {
        return;
    }
    let i = pixel.y * ibl.frame.x + pixel.x;
    let traced = indirect[i];
    let s = surface_at(pixel);
    if traced.w > 0.5 && on_object(s) {
        indirect[i] = vec4<f32>(shaded(pixel, s, traced.rgb), 0.0);
    }
}

// With `occlusion` on (a nonzero `ibl.probe`), after the others over the region: each real
// pixel's Δ irradiance from the local picture's light that the object blocks on its way there
// (`blocked_irradiance`), as its indirect term; the object's pixels keep theirs.
@compute @workgroup_size(8, 8)
fn real(@builtin(global_invocation_id) id: vec3<u32>) {
    ibl = ibl_buffer;
    let pixel = ibl.region.xy + id.xy;
    if any(pixel >= ibl.region.zw) {
        return;
    }
    let s = surface_at(pixel);
    if on_object(s) {
        return;
    }
    var e = vec3<f32>(0.0);
    if s.found {
        var light: array<vec3<f32>, 9>;
        for (var k = 0u; k < 9u; k++) {
            light[k] = ibl.probe[k].rgb;
        }
        let albedo = textureLoad(gb_albedo, vec2<i32>(pixel), 0).rgb;
        e = albedo / PI * blocked_irradiance(ibl.object, light, ibl.object_faces, s.p.xyz, s.n);
    }
    indirect[pixel.y * ibl.frame.x + pixel.x] = vec4<f32>(e, 0.0);
}
