// Shared by every pass: the scene's GPU layout and the light, shadow and colour helpers.
// Concatenated in front of each pass file (WGSL has no includes); see engines/src/shaders.rs.
// Every pass binds its per-frame parameters as `var<storage, read> X_buffer` and copies them
// into `var<private> X` first thing in each entry point, never as a uniform buffer
// (`shaders::PARAMS_USAGE` says why).

const PI: f32 = 3.14159265358979;
const KIND_POINT: u32 = 0u;
const KIND_SPOT: u32 = 1u;
const KIND_DIRECTIONAL: u32 = 2u;
const FLAG_VIRTUAL: u32 = 1u;
// The vertex carries a measured albedo (engines/src/gpu_scene.rs `pack_measured_albedo`).
const FLAG_MEASURED_ALBEDO: u32 = 2u;

struct Camera {
    view_proj: mat4x4<f32>,
    // xyz: eye position in the world.
    position: vec4<f32>,
    // width, height, 1/width, 1/height.
    size: vec4<f32>,
}

struct Material {
    // rgb: diffuse albedo k_d; w: Phong exponent n.
    albedo: vec4<f32>,
    // rgb: specular reflectance k_s.
    specular: vec4<f32>,
}

struct Light {
    // xyz: position (point, spot); w: kind.
    position: vec4<f32>,
    // xyz: unit direction the light travels (spot axis, directional); w: cos of the outer angle.
    direction: vec4<f32>,
    // rgb: W/sr (point, spot) or W/m² (directional); w: cos of the inner angle.
    intensity: vec4<f32>,
    // x: first shadow-map layer, y: layer count (6 for a point light's cube, else 1).
    faces: vec4<u32>,
}

struct Face {
    view_proj: mat4x4<f32>,
    // xyz: the face's forward axis; w: tan of the half field of view (perspective) or the
    // cross-section's area in m² (orthographic), at every map size.
    axis: vec4<f32>,
    // x: light index; y: 1 when orthographic.
    light: vec4<u32>,
}

// The scene's vertex layout (engines/src/gpu_scene.rs `GpuVertex`), for the raster passes.
struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) material: u32,
    @location(3) flags: u32,
}

// A vertex's measured albedo (rgb) and weight (w: 1 where measured, else 0), for the vertex
// stage to interpolate: the fragment's albedo is then rgb + (1 − w) · the material's, which
// blends correctly across a triangle whose corners differ. The albedo is stored as its square
// root in the top three bytes of the flags (8 bits each), for precision on dark surfaces.
fn measured_albedo(flags: u32) -> vec4<f32> {
    if (flags & FLAG_MEASURED_ALBEDO) == 0u {
        return vec4<f32>(0.0);
    }
    let root = unpack4x8unorm(flags).yzw;
    return vec4<f32>(root * root, 1.0);
}

fn surface_albedo(measured: vec4<f32>, material: vec3<f32>) -> vec3<f32> {
    return measured.rgb + (1.0 - measured.w) * material;
}

// Unit shading normal from the interpolated vertex normal, or the facet's when the mesh has
// none (zero normals). Fragment stage only (it takes screen-space derivatives).
fn surface_normal(interpolated: vec3<f32>, world: vec3<f32>) -> vec3<f32> {
    if dot(interpolated, interpolated) < 1e-12 {
        return normalize(cross(dpdx(world), dpdy(world)));
    }
    return normalize(interpolated);
}

// Hermite smoothstep in cos θ between the outer and inner cone (core::light::spot_falloff).
fn spot_falloff(cos_angle: f32, cos_inner: f32, cos_outer: f32) -> f32 {
    if cos_angle >= cos_inner {
        return 1.0;
    }
    if cos_angle <= cos_outer || cos_inner <= cos_outer {
        return 0.0;
    }
    let t = (cos_angle - cos_outer) / (cos_inner - cos_outer);
    return t * t * (3.0 - 2.0 * t);
}

struct Incident {
    // Unit vector from the point towards the light.
    to_light: vec3<f32>,
    // Irradiance on a surface facing the light, W/m².
    irradiance: vec3<f32>,
}

// Light arriving at `p` from light `l` (core::light::Light::incident).
fn incident(l: Light, p: vec3<f32>) -> Incident {
    var out: Incident;
    let kind = u32(l.position.w);
    if kind == KIND_DIRECTIONAL {
        out.to_light = -l.direction.xyz;
        out.irradiance = l.intensity.rgb;
        return out;
    }
    let d = l.position.xyz - p;
    let d2 = max(dot(d, d), 1e-12);
    out.to_light = d * inverseSqrt(d2);
    var falloff = 1.0;
    if kind == KIND_SPOT {
        falloff = spot_falloff(dot(l.direction.xyz, -out.to_light), l.intensity.w, l.direction.w);
    }
    out.irradiance = l.intensity.rgb * falloff / d2;
    return out;
}

// Which layer of light `l`'s shadow maps sees `p`: the cube face of the major axis for a point
// light (+X, −X, +Y, −Y, +Z, −Z), the only face otherwise.
fn face_of(l: Light, p: vec3<f32>) -> u32 {
    if l.faces.y < 6u {
        return l.faces.x;
    }
    let d = p - l.position.xyz;
    let a = abs(d);
    if a.x >= a.y && a.x >= a.z {
        return l.faces.x + select(1u, 0u, d.x >= 0.0);
    }
    if a.y >= a.z {
        return l.faces.x + select(3u, 2u, d.y >= 0.0);
    }
    return l.faces.x + select(5u, 4u, d.z >= 0.0);
}

// What a shadow map stores as a texel's distance: from the light for point and spot lights,
// along the light's direction for directional ones.
fn light_distance(l: Light, p: vec3<f32>) -> f32 {
    if u32(l.position.w) == KIND_DIRECTIONAL {
        return dot(p, l.direction.xyz);
    }
    return distance(p, l.position.xyz);
}

// Texel coordinates of `p` in `face` (may fall outside the map).
fn face_texel(face: Face, p: vec3<f32>, size: f32) -> vec2<f32> {
    let clip = face.view_proj * vec4<f32>(p, 1.0);
    let ndc = clip.xy / clip.w;
    return vec2<f32>(ndc.x * 0.5 + 0.5, 0.5 - ndc.y * 0.5) * size;
}

// World-space width of one shadow-map texel of `face` at distance `dist` from its light.
fn texel_footprint(face: Face, dist: f32, size: f32) -> f32 {
    if face.light.y == 1u {
        return sqrt(face.axis.w) / size;
    }
    return 2.0 * face.axis.w * dist / size;
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let low = c / 12.92;
    let high = pow((c + 0.055) / 1.055, vec3<f32>(2.4));
    return select(high, low, c <= vec3<f32>(0.04045));
}

fn linear_to_srgb(c: vec3<f32>) -> vec3<f32> {
    let x = clamp(c, vec3<f32>(0.0), vec3<f32>(1.0));
    let low = x * 12.92;
    let high = 1.055 * pow(x, vec3<f32>(1.0 / 2.4)) - 0.055;
    return select(high, low, x <= vec3<f32>(0.0031308));
}

// Δ as the frame's Rgba16F texel, packed into two words, so the frame is read back at half the
// bytes and copied, not converted, on the CPU. A channel that is not finite becomes 0 and one
// that rounds beyond f16's range (from 65520 on) its largest value; the alpha, otherwise 1, is
// 1 plus the number of channels so changed, which the reader counts and sets back to 1
// (`deferred::unpack_delta`), as `deferred::write_delta` does on the CPU.
const F16_MAX: f32 = 65504.0;
const F16_OVERFLOW: f32 = 65520.0;
fn pack_delta(d: vec3<f32>) -> vec2<u32> {
    var v = d;
    var changed = 0u;
    for (var c = 0; c < 3; c++) {
        if ((bitcast<u32>(v[c]) >> 23u) & 0xffu) == 0xffu {
            v[c] = 0.0;
            changed += 1u;
        } else if abs(v[c]) >= F16_OVERFLOW {
            v[c] = clamp(v[c], -F16_MAX, F16_MAX);
            changed += 1u;
        }
    }
    // 1 + changed is exact in f16: 0x3c00 is 1, 0x4000 2, 0x4200 3, 0x4400 4.
    let alpha = array<u32, 4>(0x3c00u, 0x4000u, 0x4200u, 0x4400u)[changed];
    return vec2<u32>(f16_bits(v.x) | (f16_bits(v.y) << 16u), f16_bits(v.z) | (alpha << 16u));
}

// The f16 nearest to a finite `x` within f16's range (ties to even, subnormals kept), by hand:
// WGSL's pack2x16float needs a capability not every adapter has.
fn f16_bits(x: f32) -> u32 {
    let b = bitcast<u32>(x);
    let sign = (b >> 16u) & 0x8000u;
    let e = i32((b >> 23u) & 0xffu) - 112;
    var m = b & 0x7fffffu;
    var shift = 13u;
    var h = 0u;
    if e <= 0 {
        if e < -10 {
            return sign;
        }
        m |= 0x800000u;
        shift = u32(14 - e);
    } else {
        h = u32(e) << 10u;
    }
    h |= m >> shift;
    let rest = m & ((1u << shift) - 1u);
    let half = 1u << (shift - 1u);
    if rest > half || (rest == half && (h & 1u) == 1u) {
        h += 1u;
    }
    return sign | h;
}

// Lambert plus normalised Phong (core::scene::Material), for light arriving along `wi` at a
// surface with normal `n` seen from direction `wo` (both unit, pointing away from the surface).
fn brdf(m: Material, albedo: vec3<f32>, n: vec3<f32>, wi: vec3<f32>, wo: vec3<f32>) -> vec3<f32> {
    var f = albedo / PI;
    let shininess = m.albedo.w;
    if shininess > 0.0 && any(m.specular.rgb > vec3<f32>(0.0)) {
        let mirror = reflect(-wo, n);
        let cos_alpha = max(dot(mirror, wi), 0.0);
        f += m.specular.rgb * (shininess + 1.0) / (2.0 * PI) * pow(cos_alpha, shininess);
    }
    return f;
}

// 1 where `p` (normal `n`) is lit by light `l` according to the shadow map `map` (layer `layer`:
// the depth of the surface nearest the light, as the face's projection gives it), 0 where
// something nearer the light covers it. The bias grows with the texel's footprint and the slope
// of the surface towards the light. Depth grows with the distance along every ray from a point
// light and along a directional light's direction, so moving `p` towards the light by the bias
// and comparing depths tests its distance less the bias against the stored surface's along the
// same ray.
fn lit(l: Light, face: Face, layer: u32, p: vec3<f32>, n: vec3<f32>, to_light: vec3<f32>,
       map: texture_depth_2d_array, size: u32, bias_texels: f32) -> f32 {
    let probe = shadow_probe(l, face, p, n, to_light, size, bias_texels);
    if !probe.tested {
        return 1.0;
    }
    return select(0.0, 1.0, probe.depth <= textureLoad(map, probe.texel, i32(layer), 0));
}

// Where `lit` looks in a shadow map, and the depth it compares there: the same for every map of
// one face, so two maps (R^ρ and R^μ) are tested for the cost of one. `tested` is false where
// no test is needed (outside the face, or behind a point light): the point is lit.
struct ShadowProbe {
    texel: vec2<i32>,
    depth: f32,
    tested: bool,
}

fn shadow_probe(l: Light, face: Face, p: vec3<f32>, n: vec3<f32>, to_light: vec3<f32>,
                size: u32, bias_texels: f32) -> ShadowProbe {
    let s = f32(size);
    let t = face_texel(face, p, s);
    if any(t < vec2<f32>(0.0)) || any(t >= vec2<f32>(s)) {
        return ShadowProbe(vec2<i32>(0), 0.0, false);
    }
    let cos_theta = clamp(dot(n, to_light), 0.05, 1.0);
    let tan_theta = sqrt(1.0 - cos_theta * cos_theta) / cos_theta;
    let bias = texel_footprint(face, light_distance(l, p), s) * bias_texels
        * (1.0 + min(tan_theta, 10.0));
    let clip = face.view_proj * vec4<f32>(p + to_light * bias, 1.0);
    // Behind a point light: p is within the bias of it.
    if clip.w <= 0.0 {
        return ShadowProbe(vec2<i32>(0), 0.0, false);
    }
    return ShadowProbe(vec2<i32>(floor(t)), clip.z / clip.w, true);
}

// Entry distance of the ray into a box, or +∞ when it misses or enters beyond `t_max`.
fn box_entry(lo: vec3<f32>, hi: vec3<f32>, o: vec3<f32>, inv_d: vec3<f32>, t_max: f32) -> f32 {
    let t0 = (lo - o) * inv_d;
    let t1 = (hi - o) * inv_d;
    let near = min(t0, t1);
    let far = max(t0, t1);
    let enter = max(max(near.x, near.y), max(near.z, 0.0));
    let exit = min(min(far.x, far.y), min(far.z, t_max));
    return select(3.4e38, enter, enter <= exit);
}

// The ray direction the box tests divide by: a zero component becomes a tiny one of its sign
// (the reference's culling ray), so no 0 · ∞ reads as a miss.
fn inverse_direction(d: vec3<f32>) -> vec3<f32> {
    let tiny = select(vec3<f32>(1e-20), vec3<f32>(-1e-20), d < vec3<f32>(0.0));
    return 1.0 / select(d, tiny, abs(d) < vec3<f32>(1e-20));
}

// Flux Φ_p (W) a shadow-map texel reflects as a VPL: its albedo times the light's flux through
// the texel, I · Ω_texel for point and spot lights (Ω = (2 tan(fov/2) / size)² cos³ of the angle
// off the face axis), E · A_texel for directional ones.
fn vpl_flux(l: Light, face: Face, p: vec3<f32>, albedo: vec3<f32>, size: u32) -> vec3<f32> {
    if face.light.y == 1u {
        return albedo * l.intensity.rgb * orthographic_texel_area(face, size);
    }
    let d = p - l.position.xyz;
    let dir = d * inverseSqrt(max(dot(d, d), 1e-12));
    var intensity = l.intensity.rgb;
    if u32(l.position.w) == KIND_SPOT {
        intensity *= spot_falloff(dot(l.direction.xyz, dir), l.intensity.w, l.direction.w);
    }
    return albedo * intensity * texel_solid_angle(face, dir, size);
}

// The cross-section (m²) of one texel of an orthographic face `size` texels square.
fn orthographic_texel_area(face: Face, size: u32) -> f32 {
    let s = f32(size);
    return face.axis.w / (s * s);
}

// The solid angle of the perspective face's texel that unit `dir` passes through.
fn texel_solid_angle(face: Face, dir: vec3<f32>, size: u32) -> f32 {
    let c = max(dot(dir, face.axis.xyz), 0.0);
    let a = 2.0 * face.axis.w / f32(size);
    return a * a * c * c * c;
}

// The surface area (m²) the shadow-map texel at `p` (normal `n`) of `face` covers: its solid
// angle (perspective) or cross-section (orthographic), over the cosine it meets the surface at
// (at least 0.1, so a grazing texel does not stand for the whole floor).
fn texel_area(l: Light, face: Face, p: vec3<f32>, n: vec3<f32>, size: u32) -> f32 {
    if face.light.y == 1u {
        return orthographic_texel_area(face, size) / max(abs(dot(n, l.direction.xyz)), 0.1);
    }
    let d = p - l.position.xyz;
    let dist2 = max(dot(d, d), 1e-12);
    let dir = d * inverseSqrt(dist2);
    return texel_solid_angle(face, dir, size) * dist2 / max(abs(dot(n, dir)), 0.1);
}

// DLPV's volumes store their SH as f16 (two u32 words per channel's four coefficients), in
// units of 2^23 injection counts. The counts of one coefficient are bounded by 2^30
// (`volume::fixed_point_scale`), so an injected value is at most 128 units; a propagation step
// passes a uniform field's light on unchanged, so no step should exceed that, and the sum of
// the injection and 256 steps (the most `steps` allows) stays under f16's largest value,
// 65504; the clamp guards what that argument leaves open. The smallest normal f16 is then 512
// counts, 2^-21 of the bound. Each step's f32 sums are rounded to f16 once: a relative 2^-11
// of each value.
const SH_UNITS_PER_COUNT: f32 = 1.0 / 8388608.0;
const SH_F16_MAX: f32 = 65504.0;

// pack2x16float and unpack2x16float would do, but need a capability (f16 in f32) that
// llvmpipe grants only with native f16 and naga's default validation refuses: by hand, with
// `f16_bits`, on every adapter.
fn pack_sh(v: vec4<f32>) -> vec2<u32> {
    let c = clamp(v, vec4<f32>(-SH_F16_MAX), vec4<f32>(SH_F16_MAX));
    return vec2<u32>(f16_bits(c.x) | (f16_bits(c.y) << 16u), f16_bits(c.z) | (f16_bits(c.w) << 16u));
}

// The value of the f16 in the low 16 bits of `h`, finite (`pack_sh` stores no ∞ or NaN):
// normal halves by moving exponent and mantissa into place, subnormal ones as m · 2^-24.
fn f16_value(h: u32) -> f32 {
    let e = (h >> 10u) & 0x1fu;
    let m = h & 0x3ffu;
    let magnitude = select(bitcast<f32>(((e + 112u) << 23u) | (m << 13u)), f32(m) * 5.9604645e-8, e == 0u);
    return select(magnitude, -magnitude, (h & 0x8000u) != 0u);
}

fn unpack_sh(p: vec2<u32>) -> vec4<f32> {
    return vec4<f32>(f16_value(p.x), f16_value(p.x >> 16u), f16_value(p.y), f16_value(p.y >> 16u));
}

// The virtual object as the real surfaces around it see it (`ObjectBox` in
// engines/src/volume.rs; `blocked_irradiance`).
struct ObjectBox {
    // xyz: its bounding box's centre; w: its surface's area over the box's, at most 1 (the
    // box's mean projected area times w is the object's, if convex: Cauchy); 0 without one.
    centre: vec4<f32>,
    // xyz: the box's half extents.
    half: vec4<f32>,
    // rgb: the object's area-weighted diffuse albedo.
    albedo: vec4<f32>,
}

// The DLPV volume: n³ cells of L1 SH per colour channel, twice (V^Δ, then V^ρ).
struct Volume {
    // xyz: minimum corner; w: cell edge (m).
    origin: vec4<f32>,
    // x: cells per axis; y: shadow-map size; z: light faces; w: light count.
    dims: vec4<u32>,
    // x: fixed-point counts per unit; y: 1 = direct injection; z: dampening of negative light;
    // w: lookup offset along the normal, in cells.
    scale: vec4<f32>,
    // x: 1 = gather the far field (`dlpv_inject.wgsl`) and light the object with it; y: 1 =
    // gather the probe of the real scene's first bounce at the object (`gather_probe`).
    options: vec4<u32>,
    object: ObjectBox,
}

// L1 SH basis (Y00, Y1−1, Y10, Y11 = 0.2821, 0.4886 · (y, z, x)) at unit `d`: a function's
// value in direction d is ⟨sh, sh_basis(d)⟩.
fn sh_basis(d: vec3<f32>) -> vec4<f32> {
    return vec4<f32>(0.282094792, 0.488602512 * d.y, 0.488602512 * d.z, 0.488602512 * d.x);
}

// SH projection of the clamped cosine lobe around unit `d`: (√π/2, √(π/3) (d_y, d_z, d_x)).
// Also the kernel of the cosine convolution: ∫ f(ω) ⟨d, ω⟩₊ dω = ⟨f_SH, cosine_lobe(d)⟩.
fn cosine_lobe(d: vec3<f32>) -> vec4<f32> {
    return vec4<f32>(0.886226925, 1.023326708 * d.y, 1.023326708 * d.z, 1.023326708 * d.x);
}

// The far field of a volume (`CellCounts::far_field` in engines/src/volume.rs): the light
// arriving at the volume's centre from the VPLs of R^ρ that fall outside it, which the volume
// cannot carry, as L2 SH of incident radiance per colour channel (coefficient k of RGB),
// injected as 27 fixed-point sums in units of `volume scale × h²` (h: half the volume's edge).
// A VPL outside is at least h from the centre, so its share of a sum is at most 1.09 × its
// intensity (the largest L2 basis value): within the bound `fixed_point_scale` keeps for the
// four sums of its cell's coefficient, so the far field cannot overflow either.
const FAR_FIELD_VALUES: u32 = 27u;

// L2 SH basis (Ramamoorthi & Hanrahan 2001, eq. 3: Y00; Y1−1, Y10, Y11; Y2−2, Y2−1, Y20, Y21,
// Y22) at unit `d`; the first four are `sh_basis`.
fn sh9_basis(d: vec3<f32>) -> array<f32, 9> {
    return array<f32, 9>(
        0.282094792,
        0.488602512 * d.y, 0.488602512 * d.z, 0.488602512 * d.x,
        1.092548431 * d.x * d.y, 1.092548431 * d.y * d.z, 0.315391565 * (3.0 * d.z * d.z - 1.0),
        1.092548431 * d.x * d.z, 0.546274215 * (d.x * d.x - d.y * d.y),
    );
}

// The far field's sums as incident radiance SH (W/sr/m² per unit of the basis): counts over
// `units`, the fixed-point scale times h².
fn far_field_sh(counts: array<i32, 27>, units: f32) -> array<vec3<f32>, 9> {
    var sh: array<vec3<f32>, 9>;
    for (var k = 0u; k < 9u; k++) {
        sh[k] = vec3<f32>(f32(counts[3u * k]), f32(counts[3u * k + 1u]), f32(counts[3u * k + 2u]))
            / units;
    }
    return sh;
}

// Irradiance the far field gives a surface of normal `n`: the SH cosine convolution (Ramamoorthi
// & Hanrahan 2001, eq. 7; Â = π, 2π/3, π/4 per band), clamped where the truncation rings
// below zero.
fn far_field_irradiance(sh: array<vec3<f32>, 9>, n: vec3<f32>) -> vec3<f32> {
    let y = sh9_basis(n);
    var e = PI * sh[0] * y[0];
    for (var k = 1u; k < 4u; k++) {
        e += (2.0 * PI / 3.0) * sh[k] * y[k];
    }
    for (var k = 4u; k < 9u; k++) {
        e += (PI / 4.0) * sh[k] * y[k];
    }
    return max(e, vec3<f32>(0.0));
}

// Radiance arriving from unit direction `d` (towards the source), clamped at zero.
fn far_field_radiance(sh: array<vec3<f32>, 9>, d: vec3<f32>) -> vec3<f32> {
    let y = sh9_basis(d);
    var l = vec3<f32>(0.0);
    for (var k = 0u; k < 9u; k++) {
        l += sh[k] * y[k];
    }
    return max(l, vec3<f32>(0.0));
}

// The far emitters of a volume (`FarEmitters` in engines/src/volume.rs): a volume's injected
// light summed over blocks of cells (`FAR_EMITTER_BLOCKS` per axis), each a point (or a patch)
// that surfaces the volume's own lookup does not serve take their bounce from. The sum of a
// block's VPLs' Φ/π cosine lobes (`dlpv_inject.wgsl`; for V^Δ, ρ's less μ's) is read as one
// clamped cosine lobe about their mean normal (`far_emitters.wgsl`). `position`: xyz the block's cells' centre
// weighted by their |L0|, w the block's half edge (the nearest a receiver's 1/d² counts it; 0:
// the block is empty); `normal`: the lobe's unit normal; `intensity`: rgb its intensity along
// it (W/sr).
const FAR_EMITTER_BLOCKS: u32 = 8u;
const FAR_EMITTERS: u32 = 512u;

struct FarEmitter {
    position: vec4<f32>,
    normal: vec4<f32>,
    intensity: vec4<f32>,
}

// x: how many of `emitters` are listed (the non-empty blocks, in block order).
struct FarEmitters {
    count: vec4<u32>,
    emitters: array<FarEmitter, FAR_EMITTERS>,
}

// Irradiance one far emitter gives a surface at `p` of unit normal `n`: its intensity towards
// p, ⟨n_e, −ω⟩₊ along its lobe, with ω from the emitter to p, times ⟨n, −ω⟩₊ / d², d no nearer
// than the block's half edge. The point light of instant radiosity (Keller 1997), without
// visibility: what lies between a receiver and the object is not in the volume.
fn far_emitter_irradiance(e: FarEmitter, p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let to_emitter = e.position.xyz - p;
    let d2 = dot(to_emitter, to_emitter);
    let w = to_emitter * inverseSqrt(max(d2, 1e-12));
    let cos_p = dot(n, w);
    if cos_p <= 0.0 {
        return vec3<f32>(0.0);
    }
    let intensity = e.intensity.rgb * max(dot(e.normal.xyz, -w), 0.0);
    return intensity * cos_p / max(d2, e.position.w * e.position.w);
}

// Beyond this many half edges a patch's light is its centre's, as a point's: within 4 % of the
// irradiance it gives head on at that distance (worst case over directions and normals).
const PATCH_AS_POINT: f32 = 6.0;

// Irradiance one emitter gives a surface at `p` of unit normal `n` as the patch of surface it
// stands for: a square of the block's edge about its normal, moved `back` along it (onto the
// surface its VPLs were lifted off), of uniform radiance (intensity over area, a Lambertian
// patch's). Lambert's contour integral (E = L/2 Σ θ_i ⟨n, γ_i⟩, Baum et al. 1989) over the
// square clipped to p's horizon. Far away it is the point's light (`far_emitter_irradiance`);
// near, it is what the patch gives, where a point's 1/d² under a grazing cosine gives almost
// nothing: the floor right beside an object's face lights it most.
fn patch_irradiance(e: FarEmitter, back: f32, p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let normal = e.normal.xyz;
    let centre = e.position.xyz - back * normal;
    let from_centre = p - centre;
    let d2 = dot(from_centre, from_centre);
    let cos_e = dot(from_centre, normal);
    if cos_e <= 0.0 {
        return vec3<f32>(0.0);
    }
    let half = e.position.w;
    if d2 > PATCH_AS_POINT * PATCH_AS_POINT * half * half {
        return e.intensity.rgb * cos_e * max(-dot(n, from_centre), 0.0) / (d2 * d2);
    }
    let radiance = e.intensity.rgb / (4.0 * half * half);
    return radiance * square_form_factor(centre - p, normal, half, n);
}

// A quadrilateral's corners as seen from a surface (counter-clockwise about the side it shows
// that surface), and its area. A pass that takes one of several quads builds the one it takes
// and calls `quad_form_factor` once: on llvmpipe a second inlined call in `dir`'s VPL loop made
// every pixel's gather 1.9 times slower, whether a VPL took it or not.
struct Quad {
    a: vec3<f32>,
    b: vec3<f32>,
    c: vec3<f32>,
    d: vec3<f32>,
    area: f32,
}

// A square of half edge `half` about unit `normal`, its centre at `centre` from the surface.
fn square_quad(centre: vec3<f32>, normal: vec3<f32>, half: f32) -> Quad {
    // An orthonormal basis about the normal (Duff et al. 2017), t × b = normal.
    let z = normal;
    let sz = select(-1.0, 1.0, z.z >= 0.0);
    let a = -1.0 / (sz + z.z);
    let c = z.x * z.y * a;
    let t = vec3<f32>(1.0 + sz * z.x * z.x * a, sz * c, -sz * z.x);
    let b = vec3<f32>(c, sz + z.y * z.y * a, -z.y);
    return Quad(centre + half * (-t - b), centre + half * (t - b), centre + half * (t + b),
                centre + half * (-t + b), 4.0 * half * half);
}

// `quad_form_factor` of `square_quad`.
fn square_form_factor(centre: vec3<f32>, normal: vec3<f32>, half: f32, n: vec3<f32>) -> f32 {
    let q = square_quad(centre, normal, half);
    return quad_form_factor(q.a, q.b, q.c, q.d, n);
}

// The span of edge 2 · `half` about `c`, moved inside `lo`..`hi` and cut to it.
fn span_within(c: f32, half: f32, lo: f32, hi: f32) -> vec2<f32> {
    let width = min(2.0 * half, max(hi - lo, 0.0));
    let start = clamp(c - half, lo, hi - width);
    return vec2<f32>(start, start + width);
}

// The square of edge 2 · `half` that a point on the surface of the box `lo`..`hi` stands for,
// from `p`: in the plane of the box face whose axis its `normal` is nearest, through
// `position`, moved inside the box's extent on that face and cut to it (area 0 where the box
// has none). A VPL on the virtual object is a piece of one of its faces: a square about its own
// normal reaches past the object's edges, below the floor it stands on, where a sensor's depth
// mesh a few millimetres off lets a receiver at its foot see it, and beside it into its own
// shadow. Its flux is kept where it is cut: its light per unit of area is over the area left.
fn box_square_quad(position: vec3<f32>, normal: vec3<f32>, half: f32, lo: vec3<f32>,
                   hi: vec3<f32>, p: vec3<f32>) -> Quad {
    let a = abs(normal);
    // The face's axis and the other two, t × b = axis.
    var axis = vec3<f32>(1.0, 0.0, 0.0);
    var t = vec3<f32>(0.0, 1.0, 0.0);
    var b = vec3<f32>(0.0, 0.0, 1.0);
    if a.y >= a.x && a.y >= a.z {
        axis = vec3<f32>(0.0, 1.0, 0.0);
        t = vec3<f32>(0.0, 0.0, 1.0);
        b = vec3<f32>(1.0, 0.0, 0.0);
    } else if a.z >= a.x && a.z >= a.y {
        axis = vec3<f32>(0.0, 0.0, 1.0);
        t = vec3<f32>(1.0, 0.0, 0.0);
        b = vec3<f32>(0.0, 1.0, 0.0);
    }
    let st = span_within(dot(position, t), half, dot(lo, t), dot(hi, t));
    let sb = span_within(dot(position, b), half, dot(lo, b), dot(hi, b));
    let base = dot(position, axis) * axis - p;
    let c0 = base + st.x * t + sb.x * b;
    let c1 = base + st.y * t + sb.x * b;
    let c2 = base + st.y * t + sb.y * b;
    let c3 = base + st.x * t + sb.y * b;
    let area = max(st.y - st.x, 0.0) * max(sb.y - sb.x, 0.0);
    // Counter-clockwise about the face's outward normal.
    if dot(normal, axis) >= 0.0 {
        return Quad(c0, c1, c2, c3, area);
    }
    return Quad(c0, c3, c2, c1, area);
}

// One edge's term of Lambert's contour integral: the angle `u` and `v` (from the surface)
// subtend, times the cosine of their plane's normal with `n`.
fn contour_edge(u: vec3<f32>, v: vec3<f32>, n: vec3<f32>) -> f32 {
    let un = normalize(u);
    let vn = normalize(v);
    let g = cross(vn, un);
    let length_g = length(g);
    if length_g <= 1e-7 {
        return 0.0;
    }
    return acos(clamp(dot(un, vn), -1.0, 1.0)) * dot(n, g) / length_g;
}

// A polygon's edge from `u` to `v` clipped to the horizon of a surface of normal `n` (h = ⟨n, ·⟩
// ≥ 0): its contour term, and where it leaves the horizon or comes back over it.
struct ClippedEdge {
    term: f32,
    exit: vec3<f32>,
    entry: vec3<f32>,
    exits: bool,
}

fn clipped_edge(u: vec3<f32>, v: vec3<f32>, n: vec3<f32>, edge: ClippedEdge) -> ClippedEdge {
    var out = edge;
    let hu = dot(n, u);
    let hv = dot(n, v);
    if hu >= 0.0 && hv >= 0.0 {
        out.term += contour_edge(u, v, n);
    } else if hu >= 0.0 {
        let x = u + (v - u) * (hu / (hu - hv));
        out.term += contour_edge(u, x, n);
        out.exit = x;
        out.exits = true;
    } else if hv >= 0.0 {
        let x = u + (v - u) * (hu / (hu - hv));
        out.term += contour_edge(x, v, n);
        out.entry = x;
    }
    return out;
}

// π × the form factor from a surface of unit normal `n` to the quadrilateral `a b c d` (from
// the surface, counter-clockwise about the quad's normal, the side the surface sees): the
// irradiance a unit radiance over it gives. Lambert's contour integral, E/L = ½ Σ θ_i ⟨n, γ_i⟩
// (Baum et al. 1989), over the quad clipped to the surface's horizon, whose part of the
// clipped contour runs from where the quad leaves the horizon to where it comes back. Written
// out without arrays: llvmpipe keeps a dynamically indexed array in memory, which slowed every
// pixel of a pass that held one (`dir`'s gather 2–5 times), whether it took this path or not.
fn quad_form_factor(a: vec3<f32>, b: vec3<f32>, c: vec3<f32>, d: vec3<f32>,
                    n: vec3<f32>) -> f32 {
    var edge = ClippedEdge(0.0, vec3<f32>(0.0), vec3<f32>(0.0), false);
    edge = clipped_edge(a, b, n, edge);
    edge = clipped_edge(b, c, n, edge);
    edge = clipped_edge(c, d, n, edge);
    edge = clipped_edge(d, a, n, edge);
    var sum = edge.term;
    if edge.exits {
        sum += contour_edge(edge.exit, edge.entry, n);
    }
    return max(0.5 * sum, 0.0);
}

// Whether `p` lies outside a volume of `n`³ cells of edge `cell` from `origin`.
fn outside_volume(p: vec3<f32>, origin: vec3<f32>, cell: f32, n: u32) -> bool {
    return any(p < origin) || any(p > origin + vec3<f32>(cell * f32(n)));
}

// The probe (`CellCounts::probe` in engines/src/volume.rs): the real scene's first bounce
// arriving at the object's centre, as if the object were not there: every VPL of R^μ, its
// intensity towards the centre over the squared distance (no nearer than the object's half
// diagonal r), as L2 SH of incident radiance (`gather_towards` in dlpv_inject.wgsl), in units of
// the fixed-point scale × r².
fn probe_sh(counts: array<i32, 27>, object: ObjectBox, scale: f32) -> array<vec3<f32>, 9> {
    return far_field_sh(counts, scale * dot(object.half.xyz, object.half.xyz));
}

// The Δ irradiance at a real surface (`p`, unit `n`) from the real scene's bounce light that
// the object now blocks on its way there, and from its own surfaces that p sees instead: their
// indirect light, and `faces`' radiance (±x, ±y, ±z: the direct light on each face, for an
// engine whose real pixels do not already take the object's own bounce; zeros otherwise)
// (`occlusion = "probe"` of the volume engines, and `dvct`'s far receivers). Both come from
// the probe's light `light` where the object stands: what arrives there from behind the
// object is the radiance p no longer sees; its cosine convolution on each box face that faces
// p, times the object's albedo / π, the radiance p sees instead. The object is a point
// occluder of its box's projected area (times its surface's share) at its centre, over d² no
// less than the box's half diagonal squared: a disc model that took the distance to the box's
// surface blocked more near it and read worse on every scene of the bench (`dvct`).
fn blocked_irradiance(object: ObjectBox, light: array<vec3<f32>, 9>,
                      faces_lit: array<vec4<f32>, 6>, p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let to_object = object.centre.xyz - p;
    let d2 = dot(to_object, to_object);
    let w = to_object * inverseSqrt(max(d2, 1e-12));
    let cos_p = dot(n, w);
    if cos_p <= 0.0 || object.centre.w <= 0.0 {
        return vec3<f32>(0.0);
    }
    let h = object.half.xyz;
    // Each axis's face that p sees, by its projected area.
    let faces = abs(w) * vec3<f32>(h.y * h.z, h.z * h.x, h.x * h.y);
    let area = 4.0 * (faces.x + faces.y + faces.z) * object.centre.w;
    let solid_angle = min(area / max(d2, dot(h, h)), 2.0 * PI);
    let facing = -sign(w);
    let lit = faces.x * far_field_irradiance(light, vec3<f32>(facing.x, 0.0, 0.0))
        + faces.y * far_field_irradiance(light, vec3<f32>(0.0, facing.y, 0.0))
        + faces.z * far_field_irradiance(light, vec3<f32>(0.0, 0.0, facing.z));
    let direct = faces.x * faces_lit[select(1u, 0u, facing.x > 0.0)].rgb
        + faces.y * faces_lit[select(3u, 2u, facing.y > 0.0)].rgb
        + faces.z * faces_lit[select(5u, 4u, facing.z > 0.0)].rgb;
    let shown = (object.albedo.rgb / PI * lit + direct) / max(faces.x + faces.y + faces.z, 1e-12);
    return (shown - far_field_radiance(light, w)) * solid_angle * cos_p;
}

// The DVCT volumes (engines/src/dvct): occlusion (x: any surface, y: the virtual object, z: the
// real scene) and L1 SH radiance mip chains over n³ cells.
// A level-0 cell's real surfaces for `dvct`'s second bounce (`dvct_voxelize.wgsl` writes them,
// `bounce` in dvct_trace.wgsl reads them): SURFACE_PARTS records, split by the sign of the
// normal's largest component (so that the two faces of a wall or floor thinner than a cell keep
// their own normals rather than cancelling), each of SURFACE_VALUES fixed-point sums
// (SURFACE_SCALE per unit) over the triangles' area within the cell: the area in level-0 cell
// faces (s²), the area-weighted unit normal, albedo (rgb) and centroid (in cells from the
// cell's minimum corner).
const SURFACE_PARTS: u32 = 2u;
const SURFACE_VALUES: u32 = 10u;
const SURFACE_SCALE: f32 = 65536.0;

struct Dvct {
    // xyz: minimum corner; w: level-0 cell edge (m).
    origin: vec4<f32>,
    // x: cells per axis at level 0; y: mip levels; z: light count; w: shadow-map size.
    dims: vec4<u32>,
    // x: tan of the diffuse cones' half angle; y: step as a fraction of the cone's diameter;
    // z: tan of the shadow cones' half angle; w: cone start offset along the normal, in cells.
    cone: vec4<f32>,
    // x: 1 = shadow cones (antiradiance), 0 = shadow maps; y: shadow bias in texels;
    // z: tan of the glossy cone's smallest half angle; w: fixed-point counts per unit.
    options: vec4<f32>,
    // x: first vertex of the triangles voxelised, y: how many triangles (the light-space
    // geometry: the virtual object and the real scene's shadow proxy, or every mesh); z: threads
    // per triangle; w: 1 = each cell's surfaces are summed too (`surfaces`, the second bounce).
    voxelized: vec4<u32>,
    // x: how real pixels take the light the object blocks: 0 not at all (the paper), 1
    // directional occlusion (`CONE_OCCLUDED` in dvct_trace.wgsl), 2 the probe's light blocked
    // over the object's solid angle (`blocked_irradiance`); y: 1 = virtual pixels' cones take
    // the far field beyond the volume; z: the diffuse cones' pixel stride; w: 1 = real pixels
    // outside the volume take the far emitters' light (`far_receivers`).
    modes: vec4<u32>,
    // The gains on V^ρ's SH bands (x: L0, y: L1) along virtual pixels' cones: each VPL read as
    // a share of the radiance its surface shows over its hemisphere rather than of its cosine
    // lobe of intensity (`radiance_lobe` in engines/src/dvct/mod.rs).
    lobe: vec4<f32>,
    object: ObjectBox,
}

// Differential Instant Radiosity (engines/src/dir): one VPL, `position.w` its group (0: on a
// real surface, lights L_rv and L_r; 1: on the virtual object, L_rv only; 2: "VPL3", on a real
// surface the virtual object hides from the light, L_r only).
struct Vpl {
    position: vec4<f32>,
    // w: the distance (m) within which its 1/d² is clamped, where wider than the engine's: the
    // radius of the disc of surface it stands for (its footprint).
    normal: vec4<f32>,
    // rgb: flux Φ (W) with the importance-sampling compensation applied.
    flux: vec4<f32>,
}

struct Dir {
    // x: first-bounce VPL count; y: shadow-map size; z: light faces; w: ISM edge in texels.
    dims: vec4<u32>,
    // x: width; y: height; z: ISM points; w: VPLs of both bounces (the ISMs and the gather).
    size: vec4<u32>,
    // x: distance clamp (m); y: ISM depth bias in texel footprints; z: second-bounce rays as a
    // share of dims.x (the CPU's; here only so a change relights); w: a first-bounce VPL's clamp
    // as a share of its footprint's radius (0: `x` alone).
    params: vec4<f32>,
    // x: where in its stratum of the flux each VPL sits, in (0, 1) (`dir::vpl_stratum`); y: the
    // gather's pixel stride; z: 1 = real surfaces take near VPLs as patches (`near_vpls`); w:
    // second-bounce rays into the object's cone as a share of dims.x (the CPU's, as params.z).
    sampling: vec4<f32>,
    // xyz: the virtual object's bounding box, its minimum and maximum corners (world).
    // object_lo.w: the most the ISM bias grows at the object's pixels, as 1/cos of a VPL's angle
    // to the receiver (`object_slope_bias`).
    object_lo: vec4<f32>,
    object_hi: vec4<f32>,
}

const LUMINANCE: vec3<f32> = vec3<f32>(0.2126, 0.7152, 0.0722);

struct VplTexel {
    valid: bool,
    position: vec3<f32>,
    normal: vec3<f32>,
    albedo: vec3<f32>,
}

// Texel `t` of shadow-map layer `layer` as VPLs: R^ρ's texel (`rho`: group 0 on a real
// surface, group 1 on the virtual object, `on_virtual`), and R^μ's texel where R^ρ sees the
// virtual object in front (`vpl3`: group 2). Read once for all three groups.
struct VplTexels {
    rho: VplTexel,
    on_virtual: bool,
    vpl3: VplTexel,
}

fn vpl_texels(layer: u32, t: vec2<i32>,
              rho_position: texture_2d_array<f32>, rho_normal: texture_2d_array<f32>,
              rho_albedo: texture_2d_array<f32>, mu_position: texture_2d_array<f32>,
              mu_normal: texture_2d_array<f32>, mu_albedo: texture_2d_array<f32>) -> VplTexels {
    var out: VplTexels;
    let albedo = textureLoad(rho_albedo, t, i32(layer), 0);
    if albedo.w < 0.5 {
        return out;
    }
    let normal = textureLoad(rho_normal, t, i32(layer), 0);
    out.on_virtual = normal.w > 0.5;
    out.rho.valid = true;
    out.rho.position = textureLoad(rho_position, t, i32(layer), 0).xyz;
    out.rho.normal = normal.xyz;
    out.rho.albedo = albedo.rgb;
    if out.on_virtual {
        let mu = textureLoad(mu_albedo, t, i32(layer), 0);
        out.vpl3.valid = mu.w > 0.5;
        out.vpl3.position = textureLoad(mu_position, t, i32(layer), 0).xyz;
        out.vpl3.normal = textureLoad(mu_normal, t, i32(layer), 0).xyz;
        out.vpl3.albedo = mu.rgb;
    }
    return out;
}

// Texel `t` of shadow-map layer `layer` as a VPL of `group` ([`vpl_texels`]).
fn vpl_texel(group: u32, layer: u32, t: vec2<i32>,
             rho_position: texture_2d_array<f32>, rho_normal: texture_2d_array<f32>,
             rho_albedo: texture_2d_array<f32>, mu_position: texture_2d_array<f32>,
             mu_normal: texture_2d_array<f32>, mu_albedo: texture_2d_array<f32>) -> VplTexel {
    let texels = vpl_texels(layer, t, rho_position, rho_normal, rho_albedo, mu_position,
                            mu_normal, mu_albedo);
    if group == 2u {
        return texels.vpl3;
    }
    var out = texels.rho;
    out.valid = out.valid && texels.on_virtual == (group == 1u);
    return out;
}

// Where unit direction `d` falls in the paraboloid map (Brabec et al. 2002) of the hemisphere
// around unit `n`, in texels of an `size`² map; x < 0 when `d` is behind.
fn paraboloid_texel(n: vec3<f32>, d: vec3<f32>, size: f32) -> vec2<f32> {
    let z = dot(d, n);
    if z <= 0.0 {
        return vec2<f32>(-1.0);
    }
    let up = select(vec3<f32>(0.0, 0.0, 1.0), vec3<f32>(1.0, 0.0, 0.0), abs(n.z) > 0.9);
    let t1 = normalize(cross(up, n));
    let t2 = cross(n, t1);
    let uv = vec2<f32>(dot(d, t1), dot(d, t2)) / (1.0 + z);
    return clamp((uv * 0.5 + 0.5) * size, vec2<f32>(0.0), vec2<f32>(size - 1.0));
}

// `Light.faces.z`: a light that stands for part of the environment whose unshadowed light an
// engine adds itself (IBL): it shades real surfaces in both solutions, so it shows in Δ only
// where the virtual object shadows it, and is left out of virtual pixels' direct light.
const LIGHT_SHADOW_ONLY: u32 = 1u;

// The reflection-map engine's settings (engines/src/ibl).
struct Ibl {
    // x: map edge (texels); y: shininess levels; z: input texels; w: the local picture's
    // surface patches (`ibl_shade.wgsl`, `near`; 0 without them).
    dims: vec4<u32>,
    // x, y: frame size; z: light count; w: shadow-map size.
    frame: vec4<u32>,
    // x: shadow bias in texels; y: the near surfaces' gather stride (`ibl_shade.wgsl`).
    params: vec4<f32>,
    // Phong exponents of the specular levels (8 at most), in order.
    shininess: array<vec4<f32>, 2>,
    // The pixels the shading pass covers, first (xy) to last + 1 (zw): the image, or the
    // pixels the object can change (`Deferred::real_pixels`), which hold its own.
    region: vec4<u32>,
    // The local picture's second bounce, L2 SH of radiance (rgb; `LocalPicture::bounce`).
    bounce: array<vec4<f32>, 9>,
    // The local picture's real surfaces, every bounce, L2 SH of radiance (rgb;
    // `LocalPicture::probe`): what the object blocks from real pixels (`occlusion`; zero: off).
    probe: array<vec4<f32>, 9>,
    object: ObjectBox,
    // The direct light on each face of the object's box (±x, ±y, ±z), radiance (rgb;
    // `LocalPicture::object_faces`): the object's own bounce, which `ibl`'s real pixels take
    // nowhere else.
    object_faces: array<vec4<f32>, 6>,
}

// Octahedral map (Engelhardt & Dachsbacher 2008): the unit sphere folded onto [0, 1]², +Z at
// the centre, −Z at the corners.
fn oct_decode(uv: vec2<f32>) -> vec3<f32> {
    let f = uv * 2.0 - 1.0;
    var n = vec3<f32>(f.x, f.y, 1.0 - abs(f.x) - abs(f.y));
    let t = max(-n.z, 0.0);
    n.x += select(t, -t, n.x >= 0.0);
    n.y += select(t, -t, n.y >= 0.0);
    return normalize(n);
}

fn oct_encode(d: vec3<f32>) -> vec2<f32> {
    let n = d / (abs(d.x) + abs(d.y) + abs(d.z));
    var f = n.xy;
    if n.z < 0.0 {
        f = (vec2<f32>(1.0) - abs(n.yx)) * select(vec2<f32>(-1.0), vec2<f32>(1.0), n.xy >= vec2<f32>(0.0));
    }
    return f * 0.5 + 0.5;
}

fn ibl_shininess(ibl: Ibl, level: u32) -> f32 {
    return ibl.shininess[level / 4u][level % 4u];
}

// Irradiance traced at a stride (`dvct` `trace_stride`, `dir` `gather_stride`): the engine
// gathers at every `stride`-th pixel per axis, and each pixel between takes the bilinear blend
// of the four traced pixels around it, over those whose surface is like its own (irradiance is
// smooth across one surface, not across a silhouette or a depth edge). Each pixel then applies
// its own albedo.

// The traced pixel at corner `k` (0–3: x then y) of the stride cell holding pixel `xy`.
fn stride_corner(xy: vec2<u32>, stride: u32, k: u32) -> vec2<u32> {
    return (xy / stride) * stride + vec2<u32>(k & 1u, k >> 1u) * stride;
}

// Pixel `xy`'s bilinear weight on corner `k` of its stride cell: 0 where that corner lies
// outside a picture of `size`.
fn stride_weight(xy: vec2<u32>, stride: u32, k: u32, size: vec2<u32>) -> f32 {
    if any(stride_corner(xy, stride, k) >= size) {
        return 0.0;
    }
    let f = vec2<f32>(xy % vec2<u32>(stride)) / f32(stride);
    return select(1.0 - f.x, f.x, (k & 1u) == 1u) * select(1.0 - f.y, f.y, (k >> 1u) == 1u);
}

// Whether pixel `xy` is one the engine gathers at (a stride cell's first corner).
fn is_gathered(xy: vec2<u32>, stride: u32) -> bool {
    return all(xy % vec2<u32>(stride) == vec2<u32>(0u));
}

// What a pixel of the camera's G-buffer holds (`position`: world position, material index + 1
// in w; `normal`: the virtual flag in w): `found` is false where nothing was drawn.
struct PixelSurface {
    p: vec4<f32>,
    n: vec3<f32>,
    is_virtual: bool,
    found: bool,
}

fn pixel_surface(position: vec4<f32>, normal: vec4<f32>) -> PixelSurface {
    var s: PixelSurface;
    s.p = position;
    s.found = position.w >= 0.5;
    if s.found {
        s.n = normalize(normal.xyz);
        s.is_virtual = normal.w > 0.5;
    }
    return s;
}

// Whether a traced surface `t` may lend its irradiance to `s`, seen from `eye`: both drawn, the
// same side of the object's silhouette, normals within about 25°, and `t` within 1 % of the
// camera distance of `s`'s plane.
fn alike(s: PixelSurface, t: PixelSurface, eye: vec3<f32>) -> bool {
    return s.found && t.found && s.is_virtual == t.is_virtual && dot(s.n, t.n) > 0.9
        && abs(dot(t.p.xyz - s.p.xyz, s.n)) < 0.01 * distance(eye, s.p.xyz);
}
