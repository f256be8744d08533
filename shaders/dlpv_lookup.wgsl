// DLPV lookup (Algorithm 1): per camera pixel, trilinear L1 SH from V^Δ (real pixels) or V^ρ
// (virtual pixels) `lookup_offset` cells off the surface along its normal, irradiance by the cosine
// convolution of the light arriving against the normal, E = ⟨SH, cosine lobe(−n)⟩ / cell²
// (each cell's intensity spread over its face, Kaplanyan & Dachsbacher), and diffuse radiance
// albedo/π · E into the engine's indirect buffer, which the shading pass adds to Δ or L^ρ.
// Virtual pixels add the far field's irradiance (the light of real surfaces outside the volume,
// `volume.options.x`).
// Real pixels, with the probe on (`volume.options.y`), add the Δ of the real light the object
// blocks on its way to them (`blocked_irradiance`).

struct LookupParams {
    // width, height
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

fn cell_sh(which: u32, c: vec3<i32>, ch: u32) -> vec4<f32> {
    let n = i32(volume.dims.x);
    if any(c < vec3<i32>(0)) || any(c >= vec3<i32>(n)) {
        return vec4<f32>(0.0);
    }
    let n3 = u32(n * n * n);
    let index = which * n3 + u32((c.z * n + c.y) * n + c.x);
    return unpack_sh(accumulated[index * 3u + ch]);
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
    // Cell centres sit at origin + (c + ½) · cell.
    let g = (p.xyz + n * volume.scale.w * cell - volume.origin.xyz) / cell - vec3<f32>(0.5);
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
    let albedo = textureLoad(gb_albedo, xy, 0).rgb;
    // The volume's units (`pack_sh`) back to intensity: counts, then the injection's scale.
    let units = 1.0 / (SH_UNITS_PER_COUNT * volume.scale.x);
    e *= units / (cell * cell);
    if which == 0u && volume.options.y == 1u {
        // The object's directly lit faces are V^Δ's VPLs already.
        e += blocked_irradiance(volume.object, probe_sh(probe, volume.object, volume.scale.x),
                                array<vec4<f32>, 6>(), p.xyz, n);
    }
    if which == 1u && volume.options.x == 1u {
        let half_edge = 0.5 * f32(volume.dims.x) * cell;
        e += far_field_irradiance(far_field_sh(far_field, volume.scale.x * half_edge * half_edge), n);
    }
    indirect[i] = vec4<f32>(albedo / PI * e, 0.0);
}
