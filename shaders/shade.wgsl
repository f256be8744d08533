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
    // The virtual object's bounds in the world (`virtual_hi.w`: 1 when there is an object).
    virtual_lo: vec4<f32>,
    virtual_hi: vec4<f32>,
    // x: shadow bias in texels; y: 1 to add the shadow-mapped direct Δ on real pixels;
    // z: this frame's weight in the running mean (1: alone, 0: keep the mean); w: 1 to write
    // the mean.
    options: vec4<f32>,
    // The pixels shaded, first (xy) to last + 1 (zw): the whole image, or where the virtual
    // object can change a real pixel (`deferred.rs`, `real_pixels`); the CPU shows the camera's
    // own picture outside.
    region: vec4<u32>,
    // x: 1 to add the engine's indirect term (its `indirect` parameter), 0 for its direct light
    // alone.
    terms: vec4<f32>,
}

@group(0) @binding(0) var<storage, read> params_buffer: ShadeParams;
var<private> params: ShadeParams;
@group(0) @binding(1) var<storage, read> camera_buffer: Camera;
var<private> camera: Camera;
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

// Light `l` arriving at `p` (normal `n`), and where its shadow maps are tested. `reaches` is
// false where `l` does not light the side `n` faces.
struct Arrival {
    inc: Incident,
    cos_theta: f32,
    probe: ShadowProbe,
    layer: u32,
    reaches: bool,
}

fn arrival(l: Light, p: vec3<f32>, n: vec3<f32>) -> Arrival {
    var a: Arrival;
    a.inc = incident(l, p);
    a.cos_theta = dot(n, a.inc.to_light);
    a.reaches = a.cos_theta > 0.0 && any(a.inc.irradiance > vec3<f32>(0.0));
    if a.reaches {
        a.layer = face_of(l, p);
        a.probe = shadow_probe(l, faces[a.layer], p, n, a.inc.to_light, params.size.w, params.options.x);
    }
    return a;
}

// 1 where the arrival's point is lit in `map`.
fn visible(a: Arrival, map: texture_depth_2d_array) -> f32 {
    if !a.probe.tested {
        return 1.0;
    }
    return select(0.0, 1.0, a.probe.depth <= textureLoad(map, a.probe.texel, i32(a.layer), 0));
}

// What the arriving light reflects towards `wo`, unshadowed. Evaluated only where some light
// gets through (or, for Δ, where the two maps differ): most pixels are outside the object's
// shadow, and the BRDF is the costly part.
fn reflected(a: Arrival, m: Material, albedo: vec3<f32>, n: vec3<f32>, wo: vec3<f32>) -> vec3<f32> {
    return brdf(m, albedo, n, a.inc.to_light, wo) * a.inc.irradiance * a.cos_theta;
}

// Direct light at `p` with the shadows of R^ρ (`rho`) or R^μ. `on_virtual`: the point is on the
// virtual object, which LIGHT_SHADOW_ONLY lights do not shade.
fn direct(p: vec4<f32>, n: vec3<f32>, albedo: vec3<f32>, rho: bool, on_virtual: bool) -> vec3<f32> {
    let m = materials[u32(p.w) - 1u];
    let wo = normalize(camera.position.xyz - p.xyz);
    var sum = vec3<f32>(0.0);
    for (var i = 0u; i < params.size.z; i++) {
        let l = lights[i];
        if on_virtual && l.faces.z == LIGHT_SHADOW_ONLY {
            continue;
        }
        let a = arrival(l, p.xyz, n);
        if !a.reaches {
            continue;
        }
        var vis: f32;
        if rho {
            vis = visible(a, rsm_rho);
        } else {
            vis = visible(a, rsm_mu);
        }
        if vis > 0.0 {
            sum += reflected(a, m, albedo, n, wo) * vis;
        }
    }
    return sum;
}

// Whether the virtual object can shadow `p` from light `l` in R^ρ: the segment from `p` to a
// point or spot light, or the ray towards a directional one, meets the object's bounds grown by
// one shadow-map texel at the object's far side. R^ρ is R^μ with the object drawn over it, so
// they differ at p's texel only where the object covers that texel's centre nearer the light
// than p; that centre's ray passes within half a texel's diagonal of p's. Elsewhere both maps
// hold the same depth there, and Δ's direct term is exactly 0 without a lookup.
fn may_shadow(l: Light, p: vec3<f32>) -> bool {
    let lo = params.virtual_lo.xyz;
    let hi = params.virtual_hi.xyz;
    var towards = l.position.xyz - p;
    var reach = 1.0;
    var farthest = 0.0;
    if u32(l.position.w) == KIND_DIRECTIONAL {
        towards = -l.direction.xyz;
        reach = 3.0e38;
    } else {
        let from_light = max(abs(hi - l.position.xyz), abs(lo - l.position.xyz));
        farthest = length(from_light);
    }
    let grow = texel_footprint(faces[l.faces.x], farthest, f32(params.size.w));
    return box_entry(lo - grow, hi + grow, p, inverse_direction(towards), reach) < 3.4e38;
}

// direct^ρ − direct^μ at a real point, which both G-buffers hold alike (ρ is μ with the object
// drawn over it): the light and its shadow-map lookup are computed once, only the two maps'
// visibilities differ, and the light is reflected only where they do.
fn direct_delta(p: vec4<f32>, n: vec3<f32>, albedo: vec3<f32>) -> vec3<f32> {
    var sum = vec3<f32>(0.0);
    if params.virtual_hi.w < 0.5 {
        return sum;
    }
    for (var i = 0u; i < params.size.z; i++) {
        if !may_shadow(lights[i], p.xyz) {
            continue;
        }
        let a = arrival(lights[i], p.xyz, n);
        if !a.reaches || !a.probe.tested {
            continue;
        }
        let difference = visible(a, rsm_rho) - visible(a, rsm_mu);
        if difference != 0.0 {
            let m = materials[u32(p.w) - 1u];
            let wo = normalize(camera.position.xyz - p.xyz);
            sum += reflected(a, m, albedo, n, wo) * difference;
        }
    }
    return sum;
}

// This frame's picture at pixel `xy` (index `i`): the overlay (L^ρ with coverage 1 on the
// object, Δ with 0 on real pixels) and Δ.
struct Shaded {
    overlay: vec4<f32>,
    d: vec3<f32>,
}

fn indirect_term(i: u32) -> vec3<f32> {
    return select(vec3<f32>(0.0), indirect[i].rgb, params.terms.x > 0.5);
}

fn shade_pixel(xy: vec2<i32>, i: u32) -> Shaded {
    let p_rho = textureLoad(gb_rho_position, xy, 0);
    if p_rho.w < 0.5 {
        return Shaded(vec4<f32>(0.0), vec3<f32>(0.0));
    }
    let n_rho = textureLoad(gb_rho_normal, xy, 0);
    let albedo_rho = textureLoad(gb_rho_albedo, xy, 0).rgb;
    if n_rho.w > 0.5 {
        let l_rho = direct(p_rho, normalize(n_rho.xyz), albedo_rho, true, true) + indirect_term(i);
        let p_mu = textureLoad(gb_mu_position, xy, 0);
        var l_mu = vec3<f32>(0.0);
        if p_mu.w > 0.5 {
            let n_mu = textureLoad(gb_mu_normal, xy, 0).xyz;
            l_mu = direct(p_mu, normalize(n_mu), textureLoad(gb_mu_albedo, xy, 0).rgb, false, false);
        }
        return Shaded(vec4<f32>(l_rho, 1.0), l_rho - l_mu);
    }
    var d = indirect_term(i);
    if params.options.y > 0.5 {
        d += direct_delta(p_rho, normalize(n_rho.xyz), albedo_rho);
    }
    return Shaded(vec4<f32>(d, 0.0), d);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    params = params_buffer;
    camera = camera_buffer;
    let pixel = id.xy + params.region.xy;
    if pixel.x >= params.region.z || pixel.y >= params.region.w {
        return;
    }
    let i = pixel.y * params.size.x + pixel.x;
    let xy = vec2<i32>(pixel);
    let background_linear = textureLoad(background, xy, 0).rgb;
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
