// DLPV lookup (Algorithm 1): per camera pixel, trilinear L1 SH from V^Δ (real pixels) or V^ρ
// (virtual pixels) `lookup_offset` cells off the surface along its normal, irradiance by the cosine
// convolution of the light arriving against the normal, E = ⟨SH, cosine lobe(−n)⟩ / cell²
// (each cell's intensity spread over its face, Kaplanyan & Dachsbacher), and diffuse radiance
// albedo/π · E into the engine's indirect buffer, which the shading pass adds to Δ or L^ρ.
// With `object_light = "patches"` (`volume.options.z`) virtual pixels take V^ρ's injected light
// as patches of surface instead (`patches` and `fill`, before `main`).
// Virtual pixels add the far field's irradiance (the light of real surfaces outside the volume,
// `volume.options.x`).
// Real pixels, with the probe on (`volume.options.y`), add the Δ of the real light the object
// blocks on its way to them (`blocked_irradiance`).

struct LookupParams {
    // width, height, the object's patch stride (`patches`)
    size: vec4<u32>,
}

@group(0) @binding(0) var<storage, read> volume_buffer: Volume;
var<private> volume: Volume;
@group(0) @binding(1) var<storage, read> lookup_buffer: LookupParams;
var<private> lookup: LookupParams;
@group(0) @binding(2) var<storage, read> accumulated: array<vec2<u32>>;
@group(0) @binding(3) var gb_position: texture_2d<f32>;
@group(0) @binding(4) var gb_normal: texture_2d<f32>;
@group(0) @binding(5) var gb_albedo: texture_2d<f32>;
@group(0) @binding(6) var<storage, read_write> indirect: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> far_field: array<i32, FAR_FIELD_VALUES>;
@group(0) @binding(8) var<storage, read> probe: array<i32, FAR_FIELD_VALUES>;
@group(0) @binding(9) var<storage, read> rho_emitters: FarEmitters;
@group(0) @binding(10) var<storage, read> camera_buffer: Camera;
// The object's irradiance from the patches, per pixel (`patches`, then `fill`).
@group(0) @binding(11) var<storage, read_write> object_irradiance: array<vec4<f32>>;

fn cell_sh(which: u32, c: vec3<i32>, ch: u32) -> vec4<f32> {
    let n = i32(volume.dims.x);
    if any(c < vec3<i32>(0)) || any(c >= vec3<i32>(n)) {
        return vec4<f32>(0.0);
    }
    let n3 = u32(n * n * n);
    let index = which * n3 + u32((c.z * n + c.y) * n + c.x);
    return unpack_sh(accumulated[index * 3u + ch]);
}

// The irradiance V^Δ (`which` 0) or V^ρ (1) gives a surface at `p` (unit normal `n`): the
// trilinear cells `lookup_offset` cells off it.
fn volume_irradiance(which: u32, p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let cell = volume.origin.w;
    // Cell centres sit at origin + (c + ½) · cell.
    let g = (p + n * volume.scale.w * cell - volume.origin.xyz) / cell - vec3<f32>(0.5);
    let c0 = vec3<i32>(floor(g));
    let f = g - floor(g);
    let lobe = cosine_lobe(-n);
    var e = vec3<f32>(0.0);
    for (var k = 0u; k < 8u; k++) {
        let o = vec3<i32>(i32(k & 1u), i32((k >> 1u) & 1u), i32((k >> 2u) & 1u));
        let w = select(1.0 - f.x, f.x, o.x == 1) * select(1.0 - f.y, f.y, o.y == 1)
            * select(1.0 - f.z, f.z, o.z == 1);
        if w <= 0.0 {
            continue;
        }
        for (var ch = 0u; ch < 3u; ch++) {
            e[ch] += w * dot(cell_sh(which, c0 + o, ch), lobe);
        }
    }
    // The volume's units (`pack_sh`) back to intensity: counts, then the injection's scale.
    let units = 1.0 / (SH_UNITS_PER_COUNT * volume.scale.x);
    return e * (units / (cell * cell));
}

fn surface_at(xy: vec2<u32>) -> PixelSurface {
    let at = vec2<i32>(xy);
    return pixel_surface(textureLoad(gb_position, at, 0), textureLoad(gb_normal, at, 0));
}

// The irradiance V^ρ's injected light gives an object's surface at `p` (unit normal `n`), as
// the patches of surface its blocks of cells stand for.
fn patches_irradiance(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    var e = vec3<f32>(0.0);
    for (var k = 0u; k < rho_emitters.count.x; k++) {
        e += patch_irradiance(rho_emitters.emitters[k], 0.5 * volume.origin.w, p, n);
    }
    return e;
}

// The patches' irradiance at the object's pixels at every `stride`-th pixel per axis (see
// `stride_corner` in common.wgsl and `engines/src/strided.rs`), dispatched over those pixels.
@compute @workgroup_size(8, 8)
fn patches(@builtin(global_invocation_id) id: vec3<u32>) {
    volume = volume_buffer;
    lookup = lookup_buffer;
    let xy = id.xy * lookup.size.z;
    if any(xy >= lookup.size.xy) {
        return;
    }
    let s = surface_at(xy);
    var e = vec3<f32>(0.0);
    if s.found && s.is_virtual {
        e = patches_irradiance(s.p.xyz, s.n);
    }
    object_irradiance[xy.y * lookup.size.x + xy.x] = vec4<f32>(e, 0.0);
}

// Every other object pixel's patches' irradiance: the bilinear blend of its alike strided
// neighbours' (`patches`), or its own where none is alike. Dispatched over every pixel, after
// `patches` and before `main`, which then reads one value per object pixel: the sums stay out
// of `main`, whose every pixel llvmpipe would otherwise run beside them.
@compute @workgroup_size(8, 8)
fn fill(@builtin(global_invocation_id) id: vec3<u32>) {
    volume = volume_buffer;
    lookup = lookup_buffer;
    let stride = lookup.size.z;
    if any(id.xy >= lookup.size.xy) || is_gathered(id.xy, stride) {
        return;
    }
    let s = surface_at(id.xy);
    if !(s.found && s.is_virtual) {
        return;
    }
    var sum = vec3<f32>(0.0);
    var weight = 0.0;
    for (var k = 0u; k < 4u; k++) {
        let at = stride_corner(id.xy, stride, k);
        let w = stride_weight(id.xy, stride, k, lookup.size.xy);
        if w > 0.0 && alike(s, surface_at(at), camera_buffer.position.xyz) {
            sum += w * object_irradiance[at.y * lookup.size.x + at.x].rgb;
            weight += w;
        }
    }
    var e: vec3<f32>;
    if weight > 0.0 {
        e = sum / weight;
    } else {
        e = patches_irradiance(s.p.xyz, s.n);
    }
    object_irradiance[id.y * lookup.size.x + id.x] = vec4<f32>(e, 0.0);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    volume = volume_buffer;
    lookup = lookup_buffer;
    if id.x >= lookup.size.x || id.y >= lookup.size.y {
        return;
    }
    let i = id.y * lookup.size.x + id.x;
    let xy = vec2<i32>(id.xy);
    let p = textureLoad(gb_position, xy, 0);
    if p.w < 0.5 {
        indirect[i] = vec4<f32>(0.0);
        return;
    }
    let normal = textureLoad(gb_normal, xy, 0);
    let n = normalize(normal.xyz);
    let which = select(0u, 1u, normal.w > 0.5);
    let cell = volume.origin.w;
    var e: vec3<f32>;
    if which == 1u && volume.options.z == 1u {
        e = object_irradiance[i].rgb;
    } else {
        e = volume_irradiance(which, p.xyz, n);
    }
    if which == 0u && volume.options.y == 1u {
        // The object's directly lit faces are V^Δ's VPLs already.
        e += blocked_irradiance(volume.object, probe_sh(probe, volume.object, volume.scale.x),
                                array<vec4<f32>, 6>(), p.xyz, n);
    }
    if which == 1u && volume.options.x == 1u {
        let half_edge = 0.5 * f32(volume.dims.x) * cell;
        e += far_field_irradiance(far_field_sh(far_field, volume.scale.x * half_edge * half_edge), n);
    }
    let albedo = textureLoad(gb_albedo, xy, 0).rgb;
    indirect[i] = vec4<f32>(albedo / PI * e, 0.0);
}
