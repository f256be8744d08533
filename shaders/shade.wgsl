// Final shading and differential compositing (Algorithm 1 of the DLPV paper) for every engine:
// direct light with shadow maps on the ρ G-buffer (every mesh, R^ρ) and the μ G-buffer (real
// meshes, R^μ), plus the engine's indirect term, then
//   virtual pixels: L^ρ = direct^ρ + indirect (the engine's V^ρ lookup);
//   real pixels:    B + Δ, Δ = (direct^ρ − direct^μ when `options.y` is 1) + indirect (V^Δ);
//   empty pixels:   B.
// Δ is written per pixel (linear, may be negative) as packed f16 (`pack_delta`); the composite
// as sRGB RGBA8.
//
// Accumulation (`Accumulation` in deferred.rs): while the picture holds still, frames drawn at
// sub-pixel offsets are averaged. The mean is kept as the overlay O (L^ρ on samples that hit
// the object, Δ on real ones) with the object's coverage c, and Δ; the composite is then
// O + (1 − c)·B with this frame's background B, the mean of the samples' composites, so the
// live video never lags behind the average.

struct ShadeParams {
    // width, height, light count, shadow-map size
    size: vec4<u32>,
    // x: shadow bias in texels; y: 1 to add the shadow-mapped direct Δ on real pixels;
    // z: this frame's weight in the running mean (1: alone, 0: keep the mean); w: 1 to write
    // the mean.
    options: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: ShadeParams;
@group(0) @binding(1) var<uniform> camera: Camera;
@group(0) @binding(2) var<storage, read> lights: array<Light>;
@group(0) @binding(3) var<storage, read> faces: array<Face>;
@group(0) @binding(4) var<storage, read> materials: array<Material>;
@group(0) @binding(5) var gb_rho_position: texture_2d<f32>;
@group(0) @binding(6) var gb_rho_normal: texture_2d<f32>;
@group(0) @binding(7) var gb_rho_albedo: texture_2d<f32>;
@group(0) @binding(8) var gb_mu_position: texture_2d<f32>;
@group(0) @binding(9) var gb_mu_normal: texture_2d<f32>;
@group(0) @binding(10) var gb_mu_albedo: texture_2d<f32>;
@group(0) @binding(11) var rsm_rho: texture_depth_2d_array;
@group(0) @binding(12) var rsm_mu: texture_depth_2d_array;
@group(0) @binding(13) var background: texture_2d<f32>;
@group(0) @binding(14) var<storage, read> indirect: array<vec4<f32>>;
@group(0) @binding(15) var<storage, read_write> delta: array<vec2<u32>>;
@group(0) @binding(16) var<storage, read_write> composite: array<u32>;
// Two vec4 a pixel: (O, c) and (Δ, 0).
@group(0) @binding(17) var<storage, read_write> history: array<vec4<f32>>;

// `on_virtual`: the point is on the virtual object, which LIGHT_SHADOW_ONLY lights do not shade.
fn direct(p: vec4<f32>, n: vec3<f32>, albedo: vec3<f32>, rho: bool, on_virtual: bool) -> vec3<f32> {
    let m = materials[u32(p.w) - 1u];
    let wo = normalize(camera.position.xyz - p.xyz);
    var sum = vec3<f32>(0.0);
    for (var i = 0u; i < params.size.z; i++) {
        let l = lights[i];
        if on_virtual && l.faces.z == LIGHT_SHADOW_ONLY {
            continue;
        }
        let inc = incident(l, p.xyz);
        let cos_theta = dot(n, inc.to_light);
        if cos_theta <= 0.0 || all(inc.irradiance <= vec3<f32>(0.0)) {
            continue;
        }
        let layer = face_of(l, p.xyz);
        var vis: f32;
        if rho {
            vis = lit(l, faces[layer], layer, p.xyz, n, inc.to_light, rsm_rho, params.size.w, params.options.x);
        } else {
            vis = lit(l, faces[layer], layer, p.xyz, n, inc.to_light, rsm_mu, params.size.w, params.options.x);
        }
        sum += brdf(m, albedo, n, inc.to_light, wo) * inc.irradiance * cos_theta * vis;
    }
    return sum;
}

// This frame's picture at pixel `xy` (index `i`): the overlay (L^ρ with coverage 1 on the
// object, Δ with 0 on real pixels) and Δ.
struct Shaded {
    overlay: vec4<f32>,
    d: vec3<f32>,
}

fn shade_pixel(xy: vec2<i32>, i: u32) -> Shaded {
    let p_rho = textureLoad(gb_rho_position, xy, 0);
    let n_rho = textureLoad(gb_rho_normal, xy, 0);
    let p_mu = textureLoad(gb_mu_position, xy, 0);
    var l_rho = vec3<f32>(0.0);
    var l_mu = vec3<f32>(0.0);
    if p_rho.w > 0.5 {
        l_rho = direct(p_rho, normalize(n_rho.xyz), textureLoad(gb_rho_albedo, xy, 0).rgb, true, n_rho.w > 0.5);
    }
    if p_mu.w > 0.5 {
        let n_mu = textureLoad(gb_mu_normal, xy, 0).xyz;
        l_mu = direct(p_mu, normalize(n_mu), textureLoad(gb_mu_albedo, xy, 0).rgb, false, false);
    }
    var d = vec3<f32>(0.0);
    var overlay = vec4<f32>(0.0);
    if p_rho.w > 0.5 && n_rho.w > 0.5 {
        l_rho += indirect[i].rgb;
        d = l_rho - l_mu;
        overlay = vec4<f32>(l_rho, 1.0);
    } else if p_rho.w > 0.5 {
        if params.options.y > 0.5 {
            d = l_rho - l_mu;
        }
        d += indirect[i].rgb;
        overlay = vec4<f32>(d, 0.0);
    }
    return Shaded(overlay, d);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.size.x || id.y >= params.size.y {
        return;
    }
    let i = id.y * params.size.x + id.x;
    let xy = vec2<i32>(id.xy);
    let background_linear = srgb_to_linear(textureLoad(background, xy, 0).rgb);
    let weight = params.options.z;
    // A frame that holds the complete mean (weight 0, `Deferred::prepare`) drew nothing: it keeps
    // the mean.
    var overlay = vec4<f32>(0.0);
    var d = vec3<f32>(0.0);
    if weight > 0.0 {
        let frame = shade_pixel(xy, i);
        overlay = frame.overlay;
        d = frame.d;
    }
    if weight < 1.0 {
        overlay = mix(history[2u * i], overlay, weight);
        d = mix(history[2u * i + 1u].rgb, d, weight);
    }
    if params.options.w > 0.5 {
        history[2u * i] = overlay;
        history[2u * i + 1u] = vec4<f32>(d, 0.0);
    }
    let out = overlay.rgb + (1.0 - overlay.w) * background_linear;
    delta[i] = pack_delta(d);
    composite[i] = pack4x8unorm(vec4<f32>(linear_to_srgb(out), 1.0));
}
