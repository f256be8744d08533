// Progressive differential path tracing (engines/src/pt): one thread per pixel traces this
// dispatch's samples of L^ρ and, where the path touched the virtual object, L^μ from the same
// random numbers (correlated sampling), and folds them into the pixel's running means
// (`pt_resolve.wgsl` turns those into Δ and the composite). The estimator is the reference's (engines/reference/src/integrator.rs),
// step for step: next-event estimation of point, spot and directional lights, the environment
// by importance sampling combined with BSDF sampling by MIS (power heuristic, both halves at the
// last vertex), emission where a ray hits, Russian roulette from `rr_start`.
//
// Work comes in units: unit u is one sample for the pixels of the 8 × 8 tiles (this workgroup
// size; row-major tile index) ≡ u (mod phases), so a frame can trace a share of a sample per
// pixel where a whole one does not fit its budget. A dispatch traces units [first, first +
// count) over a grid of (tile slots, phases covered) workgroups, so its cost follows the tiles
// it traces (the whole image's invocations cost 9 ms a dispatch on lavapipe at 160 × 120 even
// when they trace nothing). Each pixel draws its samples in its own order: sample s of pixel i
// from stream (seed, i, s), s its own count so far, kept in `delta_mean.w`.

struct Params {
    // width, height, units this dispatch (≥ 1), the first unit's index.
    size: vec4<u32>,
    // x: max bounces; y: Russian roulette from this bounce; z: light count; w: root node
    // reference (an inner node's index, LEAF | triangle, or NONE without triangles).
    options: vec4<u32>,
    // x, y: seed (low, high word); z, w: environment map width, height (0: none).
    seed: vec4<u32>,
    // x: the tile phases a sample is split into.
    units: vec4<u32>,
}

// The camera, glTF convention (looks down −Z): its axes in the world.
struct PtCamera {
    // xyz: eye; w: tan of half the vertical field of view.
    position: vec4<f32>,
    // xyz: the camera's +X in the world; w: aspect (width / height).
    right: vec4<f32>,
    up: vec4<f32>,
    back: vec4<f32>,
}

// What the intersection tests read: the first corner and two edges. v0.w holds the material
// index, e1.w the flags (bit 0: virtual, bit 1: measured corner albedo), as bits.
struct Tri {
    v0: vec4<f32>,
    e1: vec4<f32>,
    e2: vec4<f32>,
}

// What shading reads: the unit geometric normal, the corners' normals and measured albedo.
struct TriShade {
    ng: vec4<f32>,
    n0: vec4<f32>,
    n1: vec4<f32>,
    n2: vec4<f32>,
    a0: vec4<f32>,
    a1: vec4<f32>,
    a2: vec4<f32>,
}

// An inner BVH node: both children's boxes; min.w holds a child reference as bits (an inner
// node's index, or LEAF | triangle).
struct Node {
    lmin: vec4<f32>,
    lmax: vec4<f32>,
    rmin: vec4<f32>,
    rmax: vec4<f32>,
}

struct PtMaterial {
    // rgb: k_d; w: Phong exponent n.
    albedo: vec4<f32>,
    // rgb: k_s.
    specular: vec4<f32>,
    // rgb: emitted radiance.
    emission: vec4<f32>,
}

// Per pixel, the running means: the overlay (L^ρ where the sample's camera ray met the object,
// Δ elsewhere) with the object's coverage in w; Δ's mean (the pixel's sample count in w) and
// its sum of squared deviations (Welford).
struct Accum {
    overlay: vec4<f32>,
    delta_mean: vec4<f32>,
    delta_m2: vec4<f32>,
}

@group(0) @binding(0) var<storage, read> params_buffer: Params;
var<private> params: Params;
@group(0) @binding(1) var<storage, read> camera_buffer: PtCamera;
var<private> camera: PtCamera;
@group(0) @binding(2) var<storage, read> tris: array<Tri>;
@group(0) @binding(3) var<storage, read> shades: array<TriShade>;
@group(0) @binding(4) var<storage, read> nodes: array<Node>;
@group(0) @binding(5) var<storage, read> materials: array<PtMaterial>;
@group(0) @binding(6) var<storage, read> lights: array<Light>;
// The environment map (rgb), then its sampling tables: the marginal CDF over rows (height + 1),
// the conditional CDF per row (height × (width + 1)) and each texel's probability.
@group(0) @binding(7) var<storage, read> env_radiance: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read> env_tables: array<f32>;
@group(0) @binding(9) var<storage, read_write> accum: array<Accum>;

const LEAF: u32 = 0x80000000u;
const NONE: u32 = 0xffffffffu;
const FLAG_TRI_VIRTUAL: u32 = 1u;
const FLAG_TRI_ALBEDO: u32 = 2u;
const TAU: f32 = 6.28318530717959;
const STACK: u32 = 64u;

// PCG (O'Neill 2014) as a hash and a stream: each sample's numbers come from its own seed, so
// the image after n samples is the same however they are split between frames.
struct Rng {
    state: u32,
}

fn pcg(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

fn rng_new(pixel: u32, sample: u32) -> Rng {
    return Rng(pcg(params.seed.x ^ pcg(pixel ^ pcg(sample ^ pcg(params.seed.y)))));
}

// Uniform in [0, 1).
fn rng_next(rng: ptr<function, Rng>) -> f32 {
    (*rng).state = (*rng).state * 747796405u + 2891336453u;
    let word = pcg((*rng).state);
    return f32(word >> 8u) * (1.0 / 16777216.0);
}

struct Hit {
    t: f32,
    tri: u32,
    u: f32,
    v: f32,
}

fn tri_flags(i: u32) -> u32 {
    return bitcast<u32>(tris[i].e1.w);
}

// Möller–Trumbore, two-sided, as the reference's accel.rs: (t, u, v), t < 0 on a miss.
fn moller_trumbore(i: u32, o: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    let tri = tris[i];
    let e1 = tri.e1.xyz;
    let e2 = tri.e2.xyz;
    let p = cross(d, e2);
    let det = dot(e1, p);
    if abs(det) < 1e-12 {
        return vec3<f32>(-1.0);
    }
    let inv = 1.0 / det;
    let s = o - tri.v0.xyz;
    let u = dot(s, p) * inv;
    if u < 0.0 || u > 1.0 {
        return vec3<f32>(-1.0);
    }
    let q = cross(s, e1);
    let v = dot(d, q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return vec3<f32>(-1.0);
    }
    return vec3<f32>(dot(e2, q) * inv, u, v);
}

// The closest hit with t in (0, t_max), or with `any_hit` the first one found (near child
// first either way). Ties go to the lower triangle index, so the closest hit depends only on the
// set of triangles met. `real_only` skips the virtual triangles (L^μ): on a ray the object does
// not meet, both answers are bitwise equal.
fn trace_ray(o: vec3<f32>, d: vec3<f32>, t_max: f32, real_only: bool, any_hit: bool) -> Hit {
    var best = Hit(t_max, NONE, 0.0, 0.0);
    if params.options.w == NONE {
        return best;
    }
    let inv_d = inverse_direction(d);
    var stack: array<u32, STACK>;
    var sp = 0u;
    var node = params.options.w;
    loop {
        if (node & LEAF) != 0u {
            let i = node & ~LEAF;
            if !(real_only && (tri_flags(i) & FLAG_TRI_VIRTUAL) != 0u) {
                let h = moller_trumbore(i, o, d);
                if h.x > 0.0 && (h.x < best.t || (h.x == best.t && i < best.tri)) {
                    best = Hit(h.x, i, h.y, h.z);
                    if any_hit {
                        return best;
                    }
                }
            }
        } else {
            let n = nodes[node];
            let tl = box_entry(n.lmin.xyz, n.lmax.xyz, o, inv_d, best.t);
            let tr = box_entry(n.rmin.xyz, n.rmax.xyz, o, inv_d, best.t);
            let l = bitcast<u32>(n.lmin.w);
            let r = bitcast<u32>(n.rmin.w);
            if tl < 3.0e38 && tr < 3.0e38 {
                let near_first = tl <= tr;
                if sp < STACK {
                    stack[sp] = select(l, r, near_first);
                    sp += 1u;
                }
                node = select(r, l, near_first);
                continue;
            }
            if tl < 3.0e38 {
                node = l;
                continue;
            }
            if tr < 3.0e38 {
                node = r;
                continue;
            }
        }
        if sp == 0u {
            break;
        }
        sp -= 1u;
        node = stack[sp];
    }
    return best;
}

fn intersect(o: vec3<f32>, d: vec3<f32>, t_max: f32, real_only: bool) -> Hit {
    return trace_ray(o, d, t_max, real_only, false);
}

// A triangle on the segment (0, t_max), NONE when it is clear.
fn occluder(o: vec3<f32>, d: vec3<f32>, t_max: f32, real_only: bool) -> u32 {
    return trace_ray(o, d, t_max, real_only, true).tri;
}

fn luminance(c: vec3<f32>) -> f32 {
    return dot(c, LUMINANCE);
}

// Power heuristic, β = 2, written with a ratio so huge densities cannot overflow (integrator.rs).
fn mis(a: f32, b: f32) -> f32 {
    if !(a > 0.0) {
        return 0.0;
    }
    if a >= b {
        let r = b / a;
        return 1.0 / (1.0 + r * r);
    }
    let r = a / b;
    return r * r / (1.0 + r * r);
}

// An orthonormal basis (t, b) around unit `n` (Duff et al. 2017), as sampling.rs.
fn basis_t(n: vec3<f32>) -> vec3<f32> {
    let sign = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
}

fn basis_b(n: vec3<f32>) -> vec3<f32> {
    let sign = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(b, sign + n.y * n.y * a, -n.y);
}

fn cosine_hemisphere(n: vec3<f32>, u1: f32, u2: f32) -> vec3<f32> {
    let r = sqrt(u1);
    let phi = TAU * u2;
    return normalize(basis_t(n) * (r * cos(phi)) + basis_b(n) * (r * sin(phi)) + n * sqrt(max(1.0 - u1, 0.0)));
}

fn phong_lobe(axis: vec3<f32>, shininess: f32, u1: f32, u2: f32) -> vec3<f32> {
    let cos_alpha = pow(u1, 1.0 / (shininess + 1.0));
    let sin_alpha = sqrt(max(1.0 - cos_alpha * cos_alpha, 0.0));
    let phi = TAU * u2;
    return normalize(basis_t(axis) * (sin_alpha * cos(phi)) + basis_b(axis) * (sin_alpha * sin(phi)) + axis * cos_alpha);
}

// Lambert plus normalised Phong at one shading point (brdf.rs `Bsdf`).
struct Bsdf {
    albedo: vec3<f32>,
    specular: vec3<f32>,
    shininess: f32,
    normal: vec3<f32>,
    wo: vec3<f32>,
    specular_weight: f32,
}

fn bsdf_new(m: PtMaterial, albedo: vec3<f32>, n: vec3<f32>, wo: vec3<f32>) -> Bsdf {
    let kd = max(luminance(albedo), 0.0);
    var ks = 0.0;
    if m.albedo.w > 0.0 {
        ks = max(luminance(m.specular.rgb), 0.0);
    }
    var weight = 0.0;
    if kd + ks > 0.0 {
        weight = ks / (kd + ks);
    }
    return Bsdf(albedo, m.specular.rgb, m.albedo.w, n, wo, weight);
}

fn bsdf_is_black(b: Bsdf) -> bool {
    return max(max(b.albedo.x, b.albedo.y), b.albedo.z) <= 0.0
        && (max(max(b.specular.x, b.specular.y), b.specular.z) <= 0.0 || b.shininess <= 0.0);
}

fn bsdf_mirror(b: Bsdf) -> vec3<f32> {
    return 2.0 * dot(b.wo, b.normal) * b.normal - b.wo;
}

fn bsdf_phong(b: Bsdf, wi: vec3<f32>) -> f32 {
    let cos_alpha = max(dot(bsdf_mirror(b), wi), 0.0);
    return (b.shininess + 1.0) / (2.0 * PI) * pow(cos_alpha, b.shininess);
}

fn bsdf_eval(b: Bsdf, wi: vec3<f32>) -> vec3<f32> {
    if dot(wi, b.normal) <= 0.0 {
        return vec3<f32>(0.0);
    }
    var f = b.albedo / PI;
    if b.shininess > 0.0 {
        f += b.specular * bsdf_phong(b, wi);
    }
    return f;
}

fn bsdf_pdf(b: Bsdf, wi: vec3<f32>) -> f32 {
    let c = dot(wi, b.normal);
    if c <= 0.0 {
        return 0.0;
    }
    let diffuse = c / PI;
    if b.specular_weight > 0.0 {
        return (1.0 - b.specular_weight) * diffuse + b.specular_weight * bsdf_phong(b, wi);
    }
    return diffuse;
}

// A direction by the lobes' weights (three numbers, always); w = 0 when it falls below.
fn bsdf_sample(b: Bsdf, rng: ptr<function, Rng>) -> vec4<f32> {
    let choice = rng_next(rng);
    let u1 = rng_next(rng);
    let u2 = rng_next(rng);
    var wi: vec3<f32>;
    if choice < b.specular_weight {
        wi = phong_lobe(bsdf_mirror(b), b.shininess, u1, u2);
    } else {
        wi = cosine_hemisphere(b.normal, u1, u2);
    }
    let ok = dot(wi, b.normal) > 0.0 && all(abs(wi) <= vec3<f32>(1.0));
    return vec4<f32>(wi, select(0.0, 1.0, ok));
}

fn env_width() -> u32 {
    return params.seed.z;
}

fn env_height() -> u32 {
    return params.seed.w;
}

// Offsets of the tables in `env_tables`.
fn row_cdf(i: u32) -> f32 {
    return env_tables[i];
}

fn col_cdf(y: u32, x: u32) -> f32 {
    return env_tables[env_height() + 1u + y * (env_width() + 1u) + x];
}

fn texel_p(y: u32, x: u32) -> f32 {
    return env_tables[env_height() + 1u + env_height() * (env_width() + 1u) + y * env_width() + x];
}

// Texel of the equirectangular map in direction `d` (u from −Z towards +X, v = 0 up).
fn env_texel(d: vec3<f32>) -> vec2<u32> {
    var phi = atan2(d.x, -d.z);
    if phi < 0.0 {
        phi += TAU;
    }
    let theta = acos(clamp(d.y, -1.0, 1.0));
    let x = min(u32(phi / TAU * f32(env_width())), env_width() - 1u);
    let y = min(u32(theta / PI * f32(env_height())), env_height() - 1u);
    return vec2<u32>(x, y);
}

fn env_lookup(d: vec3<f32>) -> vec3<f32> {
    let t = env_texel(d);
    return env_radiance[t.y * env_width() + t.x].rgb;
}

// Solid-angle density of sampling `d`: p(texel) · w·h / (2π² sin θ).
fn env_pdf(d: vec3<f32>) -> f32 {
    let t = env_texel(d);
    let sin_theta = sin(acos(clamp(d.y, -1.0, 1.0)));
    if sin_theta <= 1e-6 {
        return 0.0;
    }
    return texel_p(t.y, t.x) * f32(env_width() * env_height()) / (2.0 * PI * PI * sin_theta);
}

// Largest i < n with cdf(i) ≤ value (a non-decreasing table starting at 0).
fn find_row(value: f32) -> u32 {
    var lo = 0u;
    var hi = env_height();
    while lo < hi {
        let mid = (lo + hi + 1u) / 2u;
        if row_cdf(mid) <= value {
            lo = mid;
        } else {
            hi = mid - 1u;
        }
    }
    return lo;
}

fn find_col(y: u32, value: f32) -> u32 {
    var lo = 0u;
    var hi = env_width();
    while lo < hi {
        let mid = (lo + hi + 1u) / 2u;
        if col_cdf(y, mid) <= value {
            lo = mid;
        } else {
            hi = mid - 1u;
        }
    }
    return lo;
}

// A direction by luminance × sin θ (sampling.rs `EnvSampler::sample`); w: its density.
fn env_sample(u1: f32, u2: f32) -> vec4<f32> {
    let w = env_width();
    let h = env_height();
    let total = row_cdf(h);
    let y = min(find_row(u1 * total), h - 1u);
    let row_total = col_cdf(y, w);
    let x = min(find_col(y, u2 * row_total), w - 1u);
    let fu = clamp((u2 * row_total - col_cdf(y, x)) / max(col_cdf(y, x + 1u) - col_cdf(y, x), 1e-12), 0.0, 1.0);
    let fv = clamp((u1 * total - row_cdf(y)) / max(row_cdf(y + 1u) - row_cdf(y), 1e-12), 0.0, 1.0);
    let phi = TAU * (f32(x) + fu) / f32(w);
    let theta = PI * (f32(y) + fv) / f32(h);
    let d = vec3<f32>(sin(theta) * sin(phi), cos(theta), -sin(theta) * cos(phi));
    return vec4<f32>(d, env_pdf(d));
}

fn offset_from(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let a = abs(p);
    return p + n * (1e-4 * (1.0 + max(max(a.x, a.y), a.z)));
}

fn max3(v: vec3<f32>) -> f32 {
    return max(max(v.x, v.y), v.z);
}

struct Path {
    radiance: vec3<f32>,
    // A virtual triangle was the closest hit of one of the path's rays, or the first blocker of
    // one of its shadow rays: only then can L^μ differ.
    touched_virtual: bool,
    // The camera ray's first hit is virtual.
    first_virtual: bool,
}

fn is_virtual(i: u32) -> bool {
    return (tri_flags(i) & FLAG_TRI_VIRTUAL) != 0u;
}

// Radiance along one path from `origin` in `dir` (integrator.rs `radiance`).
fn radiance(origin_in: vec3<f32>, dir_in: vec3<f32>, real_only: bool, rng: ptr<function, Rng>) -> Path {
    var out = Path(vec3<f32>(0.0), false, false);
    var origin = origin_in;
    var dir = dir_in;
    var throughput = vec3<f32>(1.0);
    var bsdf_pdf_last = -1.0;
    let has_env = env_width() > 0u;
    let max_bounces = params.options.x;
    for (var depth = 0u; depth <= max_bounces + 1u; depth++) {
        let finishing = depth > max_bounces;
        let hit = intersect(origin, dir, 3.4e38, real_only);
        if hit.tri == NONE {
            if has_env {
                var weight = 1.0;
                if bsdf_pdf_last >= 0.0 {
                    weight = mis(bsdf_pdf_last, env_pdf(dir));
                }
                out.radiance += throughput * env_lookup(dir) * weight;
            }
            break;
        }
        let virtual_hit = is_virtual(hit.tri);
        out.touched_virtual = out.touched_virtual || virtual_hit;
        if depth == 0u {
            out.first_virtual = virtual_hit;
        }
        if finishing {
            break;
        }
        let tri = tris[hit.tri];
        let shade = shades[hit.tri];
        let material = materials[bitcast<u32>(tri.v0.w)];
        let p = origin + dir * hit.t;
        let wo = -dir;
        var ng = shade.ng.xyz;
        if dot(ng, wo) < 0.0 {
            ng = -ng;
        }
        let w = 1.0 - hit.u - hit.v;
        let interpolated = shade.n0.xyz * w + shade.n1.xyz * hit.u + shade.n2.xyz * hit.v;
        var ns = ng;
        let len2 = dot(interpolated, interpolated);
        if len2 > 0.0 {
            let unit = interpolated * inverseSqrt(len2);
            if all(abs(unit) <= vec3<f32>(2.0)) {
                ns = unit;
            }
        }
        if dot(ns, ng) < 0.0 {
            ns = -ns;
        }
        out.radiance += throughput * material.emission.rgb;
        var albedo = material.albedo.rgb;
        if (bitcast<u32>(tri.e1.w) & FLAG_TRI_ALBEDO) != 0u {
            albedo = shade.a0.rgb * w + shade.a1.rgb * hit.u + shade.a2.rgb * hit.v;
        }
        let bsdf = bsdf_new(material, albedo, ns, wo);
        if bsdf_is_black(bsdf) {
            break;
        }
        let start = offset_from(p, ng);
        for (var i = 0u; i < params.options.z; i++) {
            let l = lights[i];
            let inc = incident(l, p);
            let wi = inc.to_light;
            let c = dot(wi, ns);
            if c <= 0.0 || dot(wi, ng) <= 0.0 || max3(inc.irradiance) <= 0.0 {
                continue;
            }
            var t_max = 3.4e38;
            if u32(l.position.w) != KIND_DIRECTIONAL {
                t_max = distance(l.position.xyz, p) * (1.0 - 1e-4);
            }
            let blocker = occluder(start, wi, t_max, real_only);
            if blocker == NONE {
                out.radiance += throughput * bsdf_eval(bsdf, wi) * inc.irradiance * c;
            } else {
                out.touched_virtual = out.touched_virtual || is_virtual(blocker);
            }
        }
        if has_env {
            // Always two numbers, whatever follows, so correlated paths stay in step.
            let u1 = rng_next(rng);
            let u2 = rng_next(rng);
            let s = env_sample(u1, u2);
            let wi = s.xyz;
            let c = dot(wi, ns);
            if s.w > 0.0 && c > 0.0 && dot(wi, ng) > 0.0 {
                let blocker = occluder(start, wi, 3.4e38, real_only);
                if blocker == NONE {
                    let weight = mis(s.w, bsdf_pdf(bsdf, wi));
                    out.radiance += throughput * bsdf_eval(bsdf, wi) * env_lookup(wi) * (c * weight / s.w);
                } else {
                    out.touched_virtual = out.touched_virtual || is_virtual(blocker);
                }
            }
        }
        if depth == max_bounces && !has_env {
            break;
        }
        let sampled = bsdf_sample(bsdf, rng);
        if sampled.w == 0.0 {
            break;
        }
        let wi = sampled.xyz;
        let pdf = bsdf_pdf(bsdf, wi);
        let c = dot(wi, ns);
        if !(pdf > 0.0) || dot(wi, ng) <= 0.0 {
            break;
        }
        throughput *= bsdf_eval(bsdf, wi) * (c / pdf);
        bsdf_pdf_last = pdf;
        if depth >= params.options.y {
            let survive = min(max3(throughput), 0.95);
            if rng_next(rng) >= survive {
                break;
            }
            throughput /= survive;
        }
        if !all(abs(throughput) <= vec3<f32>(3.0e38)) {
            break;
        }
        origin = start;
        dir = wi;
    }
    if !all(abs(out.radiance) <= vec3<f32>(3.0e38)) {
        out.radiance = vec3<f32>(0.0);
    }
    return out;
}

fn camera_ray(x: u32, y: u32, jx: f32, jy: f32) -> vec3<f32> {
    let width = f32(params.size.x);
    let height = f32(params.size.y);
    let tan_half = camera.position.w;
    let ndc_x = (2.0 * (f32(x) + jx) / width - 1.0) * tan_half * camera.right.w;
    let ndc_y = (1.0 - 2.0 * (f32(y) + jy) / height) * tan_half;
    let d = normalize(vec3<f32>(ndc_x, ndc_y, -1.0));
    return normalize(camera.right.xyz * d.x + camera.up.xyz * d.y + camera.back.xyz * d.z);
}

@compute @workgroup_size(8, 8)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_id) local: vec3<u32>,
) {
    params = params_buffer;
    camera = camera_buffer;
    // Workgroup (slot, j) traces the slot-th tile of phase (first + j) mod phases.
    let phases = params.units.x;
    let first = params.size.w;
    let phase = (first + group.y) % phases;
    let tiles_x = (params.size.x + 7u) / 8u;
    let tile = group.x * phases + phase;
    let x = (tile % tiles_x) * 8u + local.x;
    let y = (tile / tiles_x) * 8u + local.y;
    if x >= params.size.x || y >= params.size.y {
        return;
    }
    let i = y * params.size.x + x;
    var acc = accum[i];
    // The units of this dispatch that fall on this phase.
    let end = first + params.size.z;
    let samples = (end + phases - 1u - phase) / phases - (first + phases - 1u - phase) / phases;
    let before = u32(acc.delta_mean.w);
    for (var s = 0u; s < samples; s++) {
        let sample = before + s;
        var rng = rng_new(i, sample);
        let jx = rng_next(&rng);
        let jy = rng_next(&rng);
        let dir = camera_ray(x, y, jx, jy);
        var rng_mu = rng;
        let rho = radiance(camera.position.xyz, dir, false, &rng);
        var l_mu = rho.radiance;
        if rho.touched_virtual {
            l_mu = radiance(camera.position.xyz, dir, true, &rng_mu).radiance;
        }
        let delta = rho.radiance - l_mu;
        let n = f32(sample + 1u);
        let overlay = select(vec4<f32>(delta, 0.0), vec4<f32>(rho.radiance, 1.0), rho.first_virtual);
        acc.overlay += (overlay - acc.overlay) / n;
        let dev = delta - acc.delta_mean.xyz;
        acc.delta_mean = vec4<f32>(acc.delta_mean.xyz + dev / n, n);
        acc.delta_m2 = vec4<f32>(acc.delta_m2.xyz + dev * (delta - acc.delta_mean.xyz), 0.0);
    }
    accum[i] = acc;
}
