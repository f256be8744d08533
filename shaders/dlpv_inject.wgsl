// DLPV injection (Franke 2013, Sec. 4.2–4.3): every texel of R^ρ and R^μ is a VPL with intensity
// I_p(ω) = Φ_p/π ⟨n_p, ω⟩₊ (L1 SH: Φ_p/π · cosine lobe). V^Δ receives I^ρ − I^μ, so VPLs seen
// in both maps cancel exactly; V^ρ receives I^ρ alone (it shades the virtual object). Each VPL
// moves half a cell along its normal before its cell is chosen (no self-illumination). With
// direct injection on, each texel also injects the light's incident flux along the light's
// direction of travel, moved half a cell back towards the light, into V^Δ only: where the
// object blocks light, R^μ's floor texels inject it negatively (antiradiance, the shadow).
//
// The R^ρ VPLs that land outside the volume light the object from afar: each adds its intensity
// towards the volume's centre over the squared distance, as L2 SH of the direction it arrives
// from, to the far field (`far_field`, see common.wgsl), summed per thread, then per workgroup,
// then once per workgroup into the buffer.
//
// With the probe on (`volume.options.y`), every VPL of R^μ (the real scene's first bounce, as
// if the object were not there) likewise adds its intensity towards the object's centre to the
// probe (`probe_sh` in common.wgsl): the light the object blocks from the real surfaces around
// it (`blocked_irradiance`).
//
// Accumulation is fixed point: WGSL has no float atomics, and integer addition commutes, so the
// result does not depend on the order threads run in and identical VPLs of R^ρ and R^μ cancel
// to exactly zero. `volume.scale.x` (counts per unit) is chosen on the CPU from a bound on the
// total injected magnitude so no cell can overflow.

@group(0) @binding(0) var<storage, read> volume_buffer: Volume;
var<private> volume: Volume;
@group(0) @binding(1) var<storage, read> lights: array<Light>;
@group(0) @binding(2) var<storage, read> faces: array<Face>;
@group(0) @binding(3) var rsm_rho_position: texture_2d_array<f32>;
@group(0) @binding(4) var rsm_rho_normal: texture_2d_array<f32>;
@group(0) @binding(5) var rsm_rho_albedo: texture_2d_array<f32>;
@group(0) @binding(6) var rsm_mu_position: texture_2d_array<f32>;
@group(0) @binding(7) var rsm_mu_normal: texture_2d_array<f32>;
@group(0) @binding(8) var rsm_mu_albedo: texture_2d_array<f32>;
// Two volumes of n³ cells × 12 values (4 SH coefficients × RGB), V^Δ and V^ρ (two bindings,
// so that each stays within the adapter's largest storage binding).
@group(0) @binding(9) var<storage, read_write> cells_delta: array<atomic<i32>>;
@group(0) @binding(10) var<storage, read_write> cells_rho: array<atomic<i32>>;
@group(0) @binding(11) var<storage, read_write> far_field: array<atomic<i32>, FAR_FIELD_VALUES>;
@group(0) @binding(12) var<storage, read_write> probe: array<atomic<i32>, FAR_FIELD_VALUES>;

var<workgroup> far_group: array<atomic<i32>, FAR_FIELD_VALUES>;
var<workgroup> probe_group: array<atomic<i32>, FAR_FIELD_VALUES>;

fn cell_of(p: vec3<f32>) -> i32 {
    let n = i32(volume.dims.x);
    let c = vec3<i32>(floor((p - volume.origin.xyz) / volume.origin.w));
    if any(c < vec3<i32>(0)) || any(c >= vec3<i32>(n)) {
        return -1;
    }
    return (c.z * n + c.y) * n + c.x;
}

// Counts not yet added to a cell of one volume: consecutive texels of a tile mostly land in
// the same cell, so each thread sums them privately and adds them with one set of atomics per
// run of texels (integer sums: the same counts as adding each texel's, in any order).
struct Pending {
    cell: i32,
    r: vec4<i32>,
    g: vec4<i32>,
    b: vec4<i32>,
}

fn pending() -> Pending {
    return Pending(-1, vec4<i32>(0), vec4<i32>(0), vec4<i32>(0));
}

fn add_counts(which: u32, base: u32, v: vec4<i32>) {
    for (var k = 0u; k < 4u; k++) {
        if v[k] != 0 {
            if which == 0u {
                atomicAdd(&cells_delta[base + k], v[k]);
            } else {
                atomicAdd(&cells_rho[base + k], v[k]);
            }
        }
    }
}

fn flush(which: u32, p: ptr<function, Pending>) {
    if (*p).cell < 0 {
        return;
    }
    let base = u32((*p).cell) * 12u;
    add_counts(which, base, (*p).r);
    add_counts(which, base + 4u, (*p).g);
    add_counts(which, base + 8u, (*p).b);
    *p = pending();
}

// A VPL's L1 SH (`lobe` × flux / π) into `cell` of volume `which`, in fixed point.
fn inject(which: u32, p: ptr<function, Pending>, cell: i32, lobe: vec4<f32>, flux: vec3<f32>) {
    if cell < 0 {
        return;
    }
    if cell != (*p).cell {
        flush(which, p);
        (*p).cell = cell;
    }
    let s = lobe * volume.scale.x / PI;
    (*p).r += vec4<i32>(round(s * flux.r));
    (*p).g += vec4<i32>(round(s * flux.g));
    (*p).b += vec4<i32>(round(s * flux.b));
}

struct Texel {
    position: vec4<f32>,
    normal: vec4<f32>,
    albedo: vec4<f32>,
}

// A texel's VPL: its reflected flux as a cosine lobe around its normal, moved half a cell
// along the normal. False where that lands outside the volume (nothing injected).
fn inject_reflected(which: u32, p: ptr<function, Pending>, t: Texel, face: Face, l: Light,
                    sign: f32) -> bool {
    let n = normalize(t.normal.xyz);
    let cell = cell_of(t.position.xyz + n * (0.5 * volume.origin.w));
    if cell < 0 {
        return false;
    }
    let flux = vpl_flux(l, face, t.position.xyz, t.albedo.rgb, volume.dims.y);
    inject(which, p, cell, cosine_lobe(n), sign * flux);
    return true;
}

// A VPL into a thread's sums of the light arriving at `centre` (in units of the fixed-point
// scale × r², so that a VPL's share is at most its intensity, as in the volume): I_p(t) / d²
// along its direction t to the centre, d no less than `r`, as arriving from −t. The far field
// takes the R^ρ VPLs outside the volume towards its centre (r: half its edge); the probe every
// VPL of R^μ towards the object's centre (r: its half diagonal).
fn gather_towards(sums: ptr<function, array<vec3<f32>, 9>>, t: Texel, face: Face, l: Light,
                  centre: vec3<f32>, r: f32) {
    let to_centre = centre - t.position.xyz;
    let d2 = max(dot(to_centre, to_centre), r * r);
    let travel = to_centre * inverseSqrt(max(dot(to_centre, to_centre), 1e-12));
    let cos_out = dot(normalize(t.normal.xyz), travel);
    if cos_out <= 0.0 {
        return;
    }
    let flux = vpl_flux(l, face, t.position.xyz, t.albedo.rgb, volume.dims.y);
    let value = flux * (cos_out / PI * r * r / d2 * volume.scale.x);
    let y = sh9_basis(-travel);
    for (var k = 0u; k < 9u; k++) {
        (*sums)[k] += value * y[k];
    }
}

fn gather_far(far: ptr<function, array<vec3<f32>, 9>>, t: Texel, face: Face, l: Light) {
    let half_edge = 0.5 * f32(volume.dims.x) * volume.origin.w;
    gather_towards(far, t, face, l, volume.origin.xyz + vec3<f32>(half_edge), half_edge);
}

fn gather_probe(sums: ptr<function, array<vec3<f32>, 9>>, t: Texel, face: Face, l: Light) {
    gather_towards(sums, t, face, l, volume.object.centre.xyz, length(volume.object.half.xyz));
}

// Direct injection: the light's incident flux at the texel along its direction of travel,
// moved half a cell back towards the light.
fn inject_direct(p: ptr<function, Pending>, t: Texel, face: Face, l: Light, sign: f32) {
    let travel = -incident(l, t.position.xyz).to_light;
    let cell = cell_of(t.position.xyz - travel * (0.5 * volume.origin.w));
    let flux = vpl_flux(l, face, t.position.xyz, vec3<f32>(1.0), volume.dims.y);
    inject(0u, p, cell, cosine_lobe(travel), sign * flux);
}

// Texels per thread along each axis of its tile.
const TILE: u32 = 4u;

// One thread per TILE × TILE texels of both maps, walked row by row in alternating directions
// so that consecutive texels are neighbours. Where R^ρ and R^μ hold the same surface
// (everywhere but the object and what it hides), their V^Δ contributions are equal
// fixed-point counts of opposite sign and cancel exactly, so neither is added: only R^ρ's VPL
// goes into V^ρ, and R^μ is not read. The volumes hold the same counts as if every texel were
// injected alone.
@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>,
        @builtin(local_invocation_index) local: u32) {
    volume = volume_buffer;
    let size = volume.dims.y;
    let layer = id.z;
    // Every thread reaches the workgroup barrier below, so none returns early.
    let tiles = id.x * TILE < size && id.y * TILE < size && layer < volume.dims.z;
    var far: array<vec3<f32>, 9>;
    var probed: array<vec3<f32>, 9>;
    if tiles {
        inject_tile(id, &far, &probed);
    }
    for (var k = 0u; k < 9u; k++) {
        let counts = vec3<i32>(round(far[k]));
        let probe_counts = vec3<i32>(round(probed[k]));
        for (var c = 0u; c < 3u; c++) {
            if counts[c] != 0 {
                atomicAdd(&far_group[3u * k + c], counts[c]);
            }
            if probe_counts[c] != 0 {
                atomicAdd(&probe_group[3u * k + c], probe_counts[c]);
            }
        }
    }
    workgroupBarrier();
    if local < FAR_FIELD_VALUES {
        let sum = atomicLoad(&far_group[local]);
        if sum != 0 {
            atomicAdd(&far_field[local], sum);
        }
        let probe_sum = atomicLoad(&probe_group[local]);
        if probe_sum != 0 {
            atomicAdd(&probe[local], probe_sum);
        }
    }
}

fn inject_tile(id: vec3<u32>, far: ptr<function, array<vec3<f32>, 9>>,
               probed: ptr<function, array<vec3<f32>, 9>>) {
    let size = volume.dims.y;
    let layer = id.z;
    let face = faces[layer];
    let l = lights[face.light.x];
    // Pending counts: V^Δ indirect, V^ρ indirect, V^Δ direct (each its own run of cells).
    var delta = pending();
    var rho_only = pending();
    var direct = pending();
    let direct_on = volume.scale.y > 0.5;
    let probe_on = volume.options.y == 1u;
    for (var j = 0u; j < TILE; j++) {
        for (var i = 0u; i < TILE; i++) {
            let column = select(i, TILE - 1u - i, (j & 1u) == 1u);
            let texel = vec2<i32>(vec2<u32>(id.x * TILE + column, id.y * TILE + j));
            if u32(texel.x) >= size || u32(texel.y) >= size {
                continue;
            }
            let rho = Texel(
                textureLoad(rsm_rho_position, texel, i32(layer), 0),
                textureLoad(rsm_rho_normal, texel, i32(layer), 0),
                textureLoad(rsm_rho_albedo, texel, i32(layer), 0),
            );
            // R^ρ is R^μ copied with the object drawn over it (`RsmPass::render`): a texel
            // the object did not win is a bit copy of R^μ's, so R^μ is read only where it did.
            if rho.albedo.w >= 0.5 {
                let inside = inject_reflected(1u, &rho_only, rho, face, l, 1.0);
                if !inside && volume.options.x == 1u {
                    gather_far(far, rho, face, l);
                }
            }
            if rho.normal.w < 0.5 {
                // R^μ's VPL is R^ρ's.
                if probe_on && rho.albedo.w >= 0.5 {
                    gather_probe(probed, rho, face, l);
                }
                continue;
            }
            _ = inject_reflected(0u, &delta, rho, face, l, 1.0);
            if direct_on {
                inject_direct(&direct, rho, face, l, 1.0);
            }
            let mu = Texel(
                textureLoad(rsm_mu_position, texel, i32(layer), 0),
                textureLoad(rsm_mu_normal, texel, i32(layer), 0),
                textureLoad(rsm_mu_albedo, texel, i32(layer), 0),
            );
            if mu.albedo.w >= 0.5 {
                if probe_on {
                    gather_probe(probed, mu, face, l);
                }
                _ = inject_reflected(0u, &delta, mu, face, l, -1.0);
                if direct_on {
                    inject_direct(&direct, mu, face, l, -1.0);
                }
            }
        }
    }
    flush(0u, &delta);
    flush(1u, &rho_only);
    flush(0u, &direct);
}
