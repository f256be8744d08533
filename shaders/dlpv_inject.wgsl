// DLPV injection (Franke 2013, Sec. 4.2–4.3): every texel of R^ρ and R^μ is a VPL with intensity
// I_p(ω) = Φ_p/π ⟨n_p, ω⟩₊ (L1 SH: Φ_p/π · cosine lobe). V^Δ receives I^ρ − I^μ, so VPLs seen
// in both maps cancel exactly; V^ρ receives I^ρ alone (it shades the virtual object). Each VPL
// moves half a cell along its normal before its cell is chosen (no self-illumination). With
// direct injection on, each texel also injects the light's incident flux along the light's
// direction of travel, moved half a cell back towards the light, into V^Δ only: where the
// object blocks light, R^μ's floor texels inject it negatively (antiradiance, the shadow).
//
// Accumulation is fixed point: WGSL has no float atomics, and integer addition commutes, so the
// result does not depend on the order threads run in and identical VPLs of R^ρ and R^μ cancel
// to exactly zero. `volume.scale.x` (counts per unit) is chosen on the CPU from a bound on the
// total injected magnitude so no cell can overflow.

@group(0) @binding(0) var<uniform> volume: Volume;
@group(0) @binding(1) var<storage, read> lights: array<Light>;
@group(0) @binding(2) var<storage, read> faces: array<Face>;
@group(0) @binding(3) var rsm_rho_position: texture_2d_array<f32>;
@group(0) @binding(4) var rsm_rho_normal: texture_2d_array<f32>;
@group(0) @binding(5) var rsm_rho_albedo: texture_2d_array<f32>;
@group(0) @binding(6) var rsm_mu_position: texture_2d_array<f32>;
@group(0) @binding(7) var rsm_mu_normal: texture_2d_array<f32>;
@group(0) @binding(8) var rsm_mu_albedo: texture_2d_array<f32>;
// Two volumes of n³ cells × 12 values (4 SH coefficients × RGB): V^Δ, then V^ρ.
@group(0) @binding(9) var<storage, read_write> cells: array<atomic<i32>>;

fn cell_of(p: vec3<f32>) -> i32 {
    let n = i32(volume.dims.x);
    let c = vec3<i32>(floor((p - volume.origin.xyz) / volume.origin.w));
    if any(c < vec3<i32>(0)) || any(c >= vec3<i32>(n)) {
        return -1;
    }
    return (c.z * n + c.y) * n + c.x;
}

fn inject(which: u32, cell: i32, lobe: vec4<f32>, flux: vec3<f32>) {
    if cell < 0 {
        return;
    }
    let n3 = volume.dims.x * volume.dims.x * volume.dims.x;
    let base = (which * n3 + u32(cell)) * 12u;
    for (var ch = 0u; ch < 3u; ch++) {
        let v = lobe * (flux[ch] / PI) * volume.scale.x;
        for (var k = 0u; k < 4u; k++) {
            atomicAdd(&cells[base + ch * 4u + k], i32(round(v[k])));
        }
    }
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let size = volume.dims.y;
    let layer = id.z / 2u;
    let rho = (id.z % 2u) == 0u;
    if id.x >= size || id.y >= size || layer >= volume.dims.z {
        return;
    }
    let texel = vec2<i32>(id.xy);
    var position: vec4<f32>;
    var normal: vec4<f32>;
    var albedo: vec4<f32>;
    if rho {
        position = textureLoad(rsm_rho_position, texel, i32(layer), 0);
        normal = textureLoad(rsm_rho_normal, texel, i32(layer), 0);
        albedo = textureLoad(rsm_rho_albedo, texel, i32(layer), 0);
    } else {
        position = textureLoad(rsm_mu_position, texel, i32(layer), 0);
        normal = textureLoad(rsm_mu_normal, texel, i32(layer), 0);
        albedo = textureLoad(rsm_mu_albedo, texel, i32(layer), 0);
    }
    if albedo.w < 0.5 {
        return;
    }
    let face = faces[layer];
    let l = lights[face.light.x];
    let p = position.xyz;
    let n = normalize(normal.xyz);
    let sign = select(-1.0, 1.0, rho);
    let half_cell = 0.5 * volume.origin.w;
    // Indirect: the VPL's reflected flux.
    let flux = vpl_flux(l, face, p, albedo.rgb, size);
    let vpl_cell = cell_of(p + n * half_cell);
    inject(0u, vpl_cell, cosine_lobe(n), sign * flux);
    if rho {
        inject(1u, vpl_cell, cosine_lobe(n), flux);
    }
    // Direct: the incident flux along the light's direction of travel.
    if volume.scale.y > 0.5 {
        let incident_flux = vpl_flux(l, face, p, vec3<f32>(1.0), size);
        let travel = -incident(l, p).to_light;
        inject(0u, cell_of(p - travel * half_cell), cosine_lobe(travel), sign * incident_flux);
    }
}
