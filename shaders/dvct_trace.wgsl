// DVCT cone tracing (Franke 2014, Sec. 3.3), one thread per camera pixel, into the engine's
// indirect buffer (the shared shading pass adds it to Δ on real pixels and to L^ρ on virtual
// ones):
//   real pixels:    albedo/π · Σ 9 diffuse cones through V^Δ + k_s · 1 glossy cone through V^Δ
//                   − Σ_lights (occlusion of the virtual object along a shadow cone towards the
//                   light) · (the light's shadow-mapped direct radiance without the object);
//                   with directional occlusion, each cone through V^ρ (every surface occluding)
//                   minus through V^μ = V^ρ − V^Δ (the real surfaces occluding), so that the
//                   real light the object blocks is taken away too;
//   virtual pixels: the same diffuse and glossy cones through V^ρ; what a cone lets through
//                   out of the volume takes the far field's radiance in its direction (the
//                   light of real surfaces outside the volume, `dvct.modes.y`).
// Cones march front to back through the mip chain at the level whose cells match the cone's
// diameter (quadrilinear), accumulating premultiplied radiance and opacity
// (c += (1 − a) L Δt/d, a += (1 − a) α).

@group(0) @binding(0) var<storage, read> dvct_buffer: Dvct;
var<private> dvct: Dvct;
@group(0) @binding(1) var<storage, read> camera_buffer: Camera;
var<private> camera: Camera;
@group(0) @binding(2) var<storage, read> lights: array<Light>;
@group(0) @binding(3) var<storage, read> faces: array<Face>;
@group(0) @binding(4) var<storage, read> materials: array<Material>;
@group(0) @binding(5) var gb_position: texture_2d<f32>;
@group(0) @binding(6) var gb_normal: texture_2d<f32>;
@group(0) @binding(7) var gb_albedo: texture_2d<f32>;
@group(0) @binding(8) var rsm_mu: texture_depth_2d_array;
// The mip chains (`dvct_mip.wgsl`): L1 SH per colour channel of V^Δ and V^ρ, and occlusion;
// the sampler is quadrilinear with a zero border, so a cone reads nothing outside the volume.
@group(0) @binding(9) var delta_r: texture_3d<f32>;
@group(0) @binding(10) var delta_g: texture_3d<f32>;
@group(0) @binding(11) var delta_b: texture_3d<f32>;
@group(0) @binding(12) var rho_r: texture_3d<f32>;
@group(0) @binding(13) var rho_g: texture_3d<f32>;
@group(0) @binding(14) var rho_b: texture_3d<f32>;
@group(0) @binding(15) var occlusion: texture_3d<f32>;
@group(0) @binding(16) var volume_sampler: sampler;
@group(0) @binding(17) var<storage, read_write> indirect: array<vec4<f32>>;
// Read only, but declared read_write: it shares its buffer with the cells `bounce` writes
// (`CellCounts`), and one dispatch may not use a buffer both ways.
@group(0) @binding(18) var<storage, read_write> far_field: array<i32, FAR_FIELD_VALUES>;
@group(0) @binding(19) var<storage, read> far_emitters: FarEmitters;
// The real scene's first bounce where the object stands, as L2 SH of incident radiance (rgb):
// written by `probe`, read by the other entries (`blocked_irradiance`).
@group(0) @binding(20) var<storage, read_write> object_probe: array<vec4<f32>, 9>;
// The second bounce (`bounce`): the injection's fixed-point cells of V^Δ and V^ρ it adds to,
// and the voxelisation's surfaces (SURFACE_VALUES in common.wgsl).
@group(0) @binding(21) var<storage, read_write> cells_delta: array<atomic<i32>>;
@group(0) @binding(22) var<storage, read_write> cells_rho: array<atomic<i32>>;
@group(0) @binding(23) var<storage, read> surfaces: array<i32>;

// The hemisphere split into a central cone (half angle acos(8/9)) and eight around it, each
// holding an equal solid angle; weights are ∫ cos θ dω over each part (they sum to π), ring
// axes at sin θ = 7/9, the cosine-weighted middle of the ring.
const CENTRAL_WEIGHT: f32 = 0.659374; // π · 17/81
const RING_WEIGHT: f32 = 0.310282; // π · 8/81
const RING_SIN: f32 = 0.777778;
const RING_COS: f32 = 0.628539;

// What a cone gathers (`trace`).
// V^Δ through every surface: the paper's real pixels.
const CONE_DELTA: u32 = 0u;
// V^ρ through every surface: virtual pixels.
const CONE_RHO: u32 = 1u;
// V^ρ through every surface minus V^μ = V^ρ − V^Δ through the real ones alone: real pixels
// with directional occlusion, the real indirect light the object blocks as well as its own.
const CONE_OCCLUDED: u32 = 2u;
// Nothing but the virtual object's opacity: shadow cones.
const CONE_SHADOW: u32 = 3u;
// V^μ = V^ρ − V^Δ through the real surfaces alone: the real scene's light where the object
// stands, as if it were not there (`probe`).
const CONE_MU: u32 = 4u;
// V^ρ through every surface: a real surface's light with the object there (`bounce`).
const CONE_RHO_OCCLUDED: u32 = 5u;

// `dvct.modes.x`: how real pixels take the light the object blocks (`occlusion`).
const OCCLUSION_DIRECTIONAL: u32 = 1u;
const OCCLUSION_PROBE: u32 = 2u;

// Radiance (W/sr/m²) towards the cone's apex of V^Δ (`delta`) or V^ρ, quadrilinear at `uvw`
// and mip level `l` along the SH `basis`. A level-L cell's radiance is stored times 2^L (see
// `dvct_mip.wgsl`), so one division by the level-0 cell's area is left.
fn radiance(delta: bool, uvw: vec3<f32>, l: f32, basis: vec4<f32>) -> vec3<f32> {
    var sh: array<vec4<f32>, 3>;
    if delta {
        sh = array(textureSampleLevel(delta_r, volume_sampler, uvw, l),
                   textureSampleLevel(delta_g, volume_sampler, uvw, l),
                   textureSampleLevel(delta_b, volume_sampler, uvw, l));
    } else {
        sh = array(textureSampleLevel(rho_r, volume_sampler, uvw, l),
                   textureSampleLevel(rho_g, volume_sampler, uvw, l),
                   textureSampleLevel(rho_b, volume_sampler, uvw, l));
    }
    return vec3<f32>(dot(sh[0], basis), dot(sh[1], basis), dot(sh[2], basis))
        / (dvct.origin.w * dvct.origin.w);
}

// The opacity a step of `steps` level-0 cells through mean occlusion `occ` adds.
fn absorbed(occ: f32, steps: f32) -> f32 {
    return 1.0 - pow(max(1.0 - clamp(occ, 0.0, 1.0), 1e-6), steps);
}

struct Cone {
    light: vec3<f32>,
    alpha: f32,
}

// March a cone of `kind` from `apex` along unit `dir` (half angle with tangent `tan_half`) up
// to `max_t` or out of the volume, sampling the mip level whose cells match its diameter.
fn trace(kind: u32, apex: vec3<f32>, dir: vec3<f32>, tan_half: f32, max_t: f32) -> Cone {
    let s0 = dvct.origin.w;
    let lo = dvct.origin.xyz - vec3<f32>(s0);
    let hi = dvct.origin.xyz + vec3<f32>(s0 * f32(dvct.dims.x + 1u));
    let top = f32(dvct.dims.y - 1u);
    var basis = sh_basis(-dir);
    if kind == CONE_RHO || kind == CONE_MU {
        basis *= dvct.lobe.xyyy;
    }
    var out: Cone;
    // V^μ's light and its opacity through the real surfaces (CONE_OCCLUDED; opaque, so that
    // only `out` decides where the march ends, for the other kinds).
    var mu = Cone(vec3<f32>(0.0), select(1.0, 0.0, kind == CONE_OCCLUDED));
    var t = s0;
    for (var i = 0u; i < 2048u && t < max_t && min(out.alpha, mu.alpha) < 0.99; i++) {
        let d = max(2.0 * t * tan_half, s0);
        let p = apex + dir * t;
        if any(p < lo) || any(p > hi) {
            break;
        }
        let uvw = (p - dvct.origin.xyz) / (s0 * f32(dvct.dims.x));
        let l = clamp(log2(d / s0), 0.0, top);
        let occ = textureSampleLevel(occlusion, volume_sampler, uvw, l);
        let dt = max(d * dvct.cone.y, 0.25 * s0);
        if kind != CONE_SHADOW {
            var light = radiance(kind == CONE_DELTA, uvw, l, basis);
            if kind == CONE_MU {
                light -= radiance(true, uvw, l, basis);
            }
            out.light += (1.0 - out.alpha) * light * (dt / d);
            if kind == CONE_OCCLUDED {
                let mu_light = light - radiance(true, uvw, l, basis);
                mu.light += (1.0 - mu.alpha) * mu_light * (dt / d);
                mu.alpha += (1.0 - mu.alpha) * absorbed(occ.z, dt / s0);
            }
        }
        // A virtual pixel's cone is not stopped by the object's own voxels: within a few cells of
        // the apex the mip cell a wide cone samples holds the object's own surface, so a convex
        // object occluded its own light.
        var blocking = occ.x;
        if kind == CONE_SHADOW {
            blocking = occ.y;
        } else if kind == CONE_RHO || kind == CONE_MU {
            blocking = occ.z;
        }
        out.alpha += (1.0 - out.alpha) * absorbed(blocking, dt / s0);
        t += dt;
    }
    out.light -= mu.light;
    return out;
}

// The light a cone gathers, plus, where `far` is on, the far field's radiance from its
// direction times what the cone lets through.
fn gathered(kind: u32, apex: vec3<f32>, dir: vec3<f32>, tan_half: f32, far: bool,
            far_sh: array<vec3<f32>, 9>) -> vec3<f32> {
    let cone = trace(kind, apex, dir, tan_half, 1e30);
    if !far {
        return cone.light;
    }
    return cone.light + (1.0 - cone.alpha) * far_field_radiance(far_sh, dir);
}

// Irradiance from the nine diffuse cones around `n`.
fn diffuse(kind: u32, apex: vec3<f32>, n: vec3<f32>, far: bool, far_sh: array<vec3<f32>, 9>)
    -> vec3<f32> {
    let up = select(vec3<f32>(0.0, 0.0, 1.0), vec3<f32>(1.0, 0.0, 0.0), abs(n.z) > 0.9);
    let t1 = normalize(cross(up, n));
    let t2 = cross(n, t1);
    let tan_half = dvct.cone.x;
    var e = CENTRAL_WEIGHT * gathered(kind, apex, n, tan_half, far, far_sh);
    for (var k = 0u; k < 8u; k++) {
        let phi = f32(k) * PI / 4.0;
        let dir = n * RING_COS + (t1 * cos(phi) + t2 * sin(phi)) * RING_SIN;
        e += RING_WEIGHT * gathered(kind, apex, dir, tan_half, far, far_sh);
    }
    return e;
}

fn surface_at(xy: vec2<i32>) -> PixelSurface {
    return pixel_surface(textureLoad(gb_position, xy, 0), textureLoad(gb_normal, xy, 0));
}

fn cone_kind(s: PixelSurface) -> u32 {
    if s.is_virtual {
        return CONE_RHO;
    }
    return select(CONE_DELTA, CONE_OCCLUDED, dvct.modes.x == OCCLUSION_DIRECTIONAL);
}

fn cone_apex(s: PixelSurface) -> vec3<f32> {
    return s.p.xyz + s.n * dvct.cone.w * dvct.origin.w;
}

fn far_on(s: PixelSurface) -> bool {
    return s.is_virtual && dvct.modes.y == 1u;
}

// The far field's light as L2 SH of radiance arriving at the volume.
fn far_light() -> array<vec3<f32>, 9> {
    let half_edge = 0.5 * f32(dvct.dims.x) * dvct.origin.w;
    return far_field_sh(far_field, dvct.options.w * half_edge * half_edge);
}

fn far_sh_of(s: PixelSurface) -> array<vec3<f32>, 9> {
    var far_sh: array<vec3<f32>, 9>;
    if far_on(s) {
        far_sh = far_light();
    }
    return far_sh;
}

// The Δ irradiance the far emitters give a real surface at `p` of unit normal `n` outside the
// volume: the object's directly lit surfaces' light, less what it takes from the real ones.
fn emitted_irradiance(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    var e = vec3<f32>(0.0);
    for (var k = 0u; k < far_emitters.count.x; k++) {
        e += far_emitter_irradiance(far_emitters.emitters[k], p, n);
    }
    return e;
}

// The irradiance at `s`: the nine diffuse cones'; at a real surface outside the volume, where
// they gather nothing, with far receivers on (`dvct.modes.w`) the far emitters' instead. A real
// surface also takes the light the object blocks (`blocked_irradiance`) with `occlusion` "probe"
// (`dvct.modes.x`), and, with the far emitters, outside the volume whatever the occlusion.
fn irradiance_at(s: PixelSurface) -> vec3<f32> {
    let p = s.p.xyz;
    let far = !s.is_virtual && dvct.modes.w == 1u
        && outside_volume(p, dvct.origin.xyz, dvct.origin.w, dvct.dims.x);
    var e: vec3<f32>;
    if far {
        e = emitted_irradiance(p, s.n);
    } else {
        e = diffuse(cone_kind(s), cone_apex(s), s.n, far_on(s), far_sh_of(s));
    }
    if !s.is_virtual && (far || dvct.modes.x == OCCLUSION_PROBE) {
        var light: array<vec3<f32>, 9>;
        for (var k = 0u; k < 9u; k++) {
            light[k] = object_probe[k].rgb;
        }
        e += blocked_irradiance(dvct.object, light, array<vec4<f32>, 6>(), p, s.n);
    }
    return e;
}

// The pixel's indirect term given its diffuse irradiance `e`: albedo/π · e, the glossy cone,
// and with shadow cones their antiradiance.
fn indirect_from(xy: vec2<i32>, s: PixelSurface, e: vec3<f32>) -> vec3<f32> {
    let kind = cone_kind(s);
    let apex = cone_apex(s);
    let n = s.n;
    let p = s.p;
    let albedo = textureLoad(gb_albedo, xy, 0).rgb;
    let m = materials[u32(p.w) - 1u];
    let wo = normalize(camera.position.xyz - p.xyz);
    var out = albedo / PI * e;
    let shininess = m.albedo.w;
    if shininess > 0.0 && any(m.specular.rgb > vec3<f32>(0.0)) {
        // A normalised Phong lobe holds its energy within 2π/(n + 1) sr: a cone of
        // cos θ = n/(n + 1).
        let c = shininess / (shininess + 1.0);
        let tan_half = max(sqrt(1.0 - c * c) / c, dvct.options.z);
        let r = reflect(-wo, n);
        out += m.specular.rgb * gathered(kind, apex, r, tan_half, far_on(s), far_sh_of(s))
            * max(dot(n, r), 0.0);
    }
    if !s.is_virtual && dvct.options.x > 0.5 {
        for (var li = 0u; li < dvct.dims.z; li++) {
            let l = lights[li];
            let inc = incident(l, p.xyz);
            let cos_theta = dot(n, inc.to_light);
            if cos_theta <= 0.0 || all(inc.irradiance <= vec3<f32>(0.0)) {
                continue;
            }
            let layer = face_of(l, p.xyz);
            let vis = lit(l, faces[layer], layer, p.xyz, n, inc.to_light, rsm_mu, dvct.dims.w,
                          dvct.options.y);
            let direct = brdf(m, albedo, n, inc.to_light, wo) * inc.irradiance * cos_theta * vis;
            if all(direct <= vec3<f32>(0.0)) {
                continue;
            }
            var max_t = 1e30;
            if u32(l.position.w) != KIND_DIRECTIONAL {
                max_t = distance(l.position.xyz, p.xyz);
            }
            let shadow = trace(CONE_SHADOW, apex, inc.to_light, dvct.cone.z, max_t);
            out -= shadow.alpha * direct;
        }
    }
    return out;
}

// The diffuse cones are traced at every `dvct.modes.z`-th pixel per axis. At 1 (every pixel)
// `main` alone writes each pixel's indirect term. Above 1, three dispatches over one buffer:
//   `main`:    a traced pixel's diffuse irradiance into `indirect`;
//   `fill`:    every other pixel's indirect term, from its traced neighbours' irradiance
//              (bilinear, over the neighbours whose surface is like its own) or, where none is,
//              from its own cones;
//   `resolve`: each traced pixel's irradiance into its indirect term.
// Irradiance is smooth across a surface, so it is what is shared; each pixel applies its own
// albedo, glossy cone and shadow cones. (Every entry reads every binding, so that each
// pipeline's derived layout takes the same bind group's resources.)
// The traced pixel of invocation `id` (every `dvct.modes.z`-th per axis): its index and
// surface, or `inside` false beyond the image.
struct Traced {
    inside: bool,
    xy: vec2<i32>,
    i: u32,
    s: PixelSurface,
}

fn traced(id: vec3<u32>) -> Traced {
    let size = vec2<u32>(camera.size.xy);
    let xy = id.xy * dvct.modes.z;
    var t: Traced;
    t.inside = xy.x < size.x && xy.y < size.y;
    if t.inside {
        t.xy = vec2<i32>(xy);
        t.i = xy.y * size.x + xy.x;
        t.s = surface_at(t.xy);
    }
    return t;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    dvct = dvct_buffer;
    camera = camera_buffer;
    let t = traced(id);
    if !t.inside {
        return;
    }
    if !t.s.found {
        indirect[t.i] = vec4<f32>(0.0);
        return;
    }
    let e = irradiance_at(t.s);
    if dvct.modes.z == 1u {
        indirect[t.i] = vec4<f32>(indirect_from(t.xy, t.s, e), 0.0);
    } else {
        indirect[t.i] = vec4<f32>(e, 0.0);
    }
}

@compute @workgroup_size(8, 8)
fn fill(@builtin(global_invocation_id) id: vec3<u32>) {
    dvct = dvct_buffer;
    camera = camera_buffer;
    let size = vec2<u32>(camera.size.xy);
    let stride = dvct.modes.z;
    if id.x >= size.x || id.y >= size.y || is_gathered(id.xy, stride) {
        return;
    }
    let xy = vec2<i32>(id.xy);
    let i = id.y * size.x + id.x;
    let s = surface_at(xy);
    if !s.found {
        indirect[i] = vec4<f32>(0.0);
        return;
    }
    var sum = vec3<f32>(0.0);
    var weight = 0.0;
    for (var k = 0u; k < 4u; k++) {
        let at = stride_corner(id.xy, stride, k);
        let w = stride_weight(id.xy, stride, k, size);
        if w <= 0.0 {
            continue;
        }
        if alike(s, surface_at(vec2<i32>(at)), camera.position.xyz) {
            sum += w * indirect[at.y * size.x + at.x].rgb;
            weight += w;
        }
    }
    var e: vec3<f32>;
    if weight > 0.0 {
        e = sum / weight;
    } else {
        e = irradiance_at(s);
    }
    indirect[i] = vec4<f32>(indirect_from(xy, s, e), 0.0);
}

@compute @workgroup_size(8, 8)
fn resolve(@builtin(global_invocation_id) id: vec3<u32>) {
    dvct = dvct_buffer;
    camera = camera_buffer;
    let t = traced(id);
    if t.inside && t.s.found {
        indirect[t.i] = vec4<f32>(indirect_from(t.xy, t.s, indirect[t.i].rgb), 0.0);
    }
}

// The real scene's first bounce where the object stands, as if it were not there
// (`blocked_irradiance`): 64 cones (half angle 14.4°, 4π/64 sr each, about Fibonacci sphere
// directions) from the object's centre through V^μ with the real surfaces occluding, and the
// far field beyond them, projected onto L2 SH. `dlpv`, which has no cones, gathers its VPLs at
// the centre instead (`gather_probe` in dlpv_inject.wgsl); here that read Δ L2 0.158 / 0.316 on
// desk_box / touching_wall against the cones' 0.140 / 0.296 (the cones see the real surfaces'
// occlusion and the volume's averaged light rather than each VPL as a point).
const PROBE_DIRECTIONS: u32 = 64u;
const PROBE_TAN_HALF: f32 = 0.2567;
var<workgroup> probe_light: array<vec3<f32>, PROBE_DIRECTIONS>;

fn probe_direction(k: u32) -> vec3<f32> {
    let z = 1.0 - (2.0 * f32(k) + 1.0) / f32(PROBE_DIRECTIONS);
    let r = sqrt(max(1.0 - z * z, 0.0));
    let phi = f32(k) * 2.39996323;
    return vec3<f32>(r * cos(phi), r * sin(phi), z);
}

@compute @workgroup_size(64)
fn probe(@builtin(local_invocation_index) k: u32) {
    dvct = dvct_buffer;
    let d = probe_direction(k);
    probe_light[k] = gathered(CONE_MU, dvct.object.centre.xyz, d, PROBE_TAN_HALF,
                              dvct.modes.y == 1u, far_light());
    workgroupBarrier();
    if k < 9u {
        var sum = vec3<f32>(0.0);
        for (var j = 0u; j < PROBE_DIRECTIONS; j++) {
            let y = sh9_basis(probe_direction(j));
            sum += probe_light[j] * y[k];
        }
        object_probe[k] = vec4<f32>(sum * (4.0 * PI / f32(PROBE_DIRECTIONS)), 0.0);
    }
}

// The second bounce (`bounces` 2; the paper traces one): each level-0 cell's real surfaces
// (`surfaces`, summed at voxelisation) gather the first bounce as a pixel of theirs would
// (`irradiance_at`: its Δ irradiance), and through V^ρ with every surface occluding (its
// irradiance with the object there), and reflect each as a VPL of flux ρ E A, a cosine lobe
// around their normal, injected half a cell off their centroid as the reflective shadow maps'
// VPLs are (`inject_reflected` in dlpv_inject.wgsl), into V^Δ and V^ρ's fixed-point cells.
// V^μ = V^ρ − V^Δ so takes the real scene's second bounce without the object, which the probe
// then finds where the object stands. The mip chain, the probe and the far emitters are built
// again from the cells, which now hold both bounces, and the pixels' cones read them as before.
// The object's surfaces inject nothing: what they reflect of the first bounce reaches real
// surfaces as `blocked_irradiance`'s light shown in place of what the object blocks, as it
// does at the pixels (injected as well, it was counted twice: see docs/ALGORITHMS.md).
// One thread per cell.
@compute @workgroup_size(64)
fn bounce(@builtin(global_invocation_id) id: vec3<u32>) {
    dvct = dvct_buffer;
    let n = dvct.dims.x;
    let c = id.x + id.y * 65535u * 64u;
    if c >= n * n * n {
        return;
    }
    let s0 = dvct.origin.w;
    let corner = dvct.origin.xyz
        + vec3<f32>(vec3<u32>(c % n, (c / n) % n, c / (n * n))) * s0;
    for (var part = 0u; part < SURFACE_PARTS; part++) {
        let base = (c * SURFACE_PARTS + part) * SURFACE_VALUES;
        let area = f32(surfaces[base]);
        let normal = vec3<f32>(f32(surfaces[base + 1u]), f32(surfaces[base + 2u]),
                               f32(surfaces[base + 3u]));
        // Faces within one cell that turn away from each other (a box's edge) cancel in part;
        // where they leave little of a direction, no lobe holds them.
        if area <= 0.0 || length(normal) < 0.25 * area {
            continue;
        }
        var surface: PixelSurface;
        surface.found = true;
        surface.n = normalize(normal);
        surface.p = vec4<f32>(corner + vec3<f32>(f32(surfaces[base + 7u]),
            f32(surfaces[base + 8u]), f32(surfaces[base + 9u])) / area * s0, 1.0);
        let at = surface.p.xyz + surface.n * (0.5 * s0);
        if outside_volume(at, dvct.origin.xyz, s0, n) {
            continue;
        }
        let albedo = vec3<f32>(f32(surfaces[base + 4u]), f32(surfaces[base + 5u]),
                               f32(surfaces[base + 6u])) / area;
        let reflected = albedo * (area / SURFACE_SCALE * s0 * s0);
        let delta = reflected * irradiance_at(surface);
        let rho = reflected * diffuse(CONE_RHO_OCCLUDED, cone_apex(surface), surface.n,
                                      dvct.modes.y == 1u, far_light());
        let cell = vec3<u32>((at - dvct.origin.xyz) / s0);
        let first = ((cell.z * n + cell.y) * n + cell.x) * 12u;
        let lobe = cosine_lobe(surface.n) * dvct.options.w / PI;
        for (var ch = 0u; ch < 3u; ch++) {
            for (var k = 0u; k < 4u; k++) {
                atomicAdd(&cells_delta[first + 4u * ch + k], i32(round(lobe[k] * delta[ch])));
                atomicAdd(&cells_rho[first + 4u * ch + k], i32(round(lobe[k] * rho[ch])));
            }
        }
    }
}
