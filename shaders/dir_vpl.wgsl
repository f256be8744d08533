// DIR VPL sampling, step 3 of 3, one thread per VPL: the j-th of group c's n_c VPLs sits where
// the group's flux CDF (over layers, then rows, then texels of the row) reaches (j + u)/n_c of
// its total. The positions are a fixed stratification of the flux, not random: the same scene
// gives the same VPLs every frame (no flicker), and a small change moves them a little. u is ½
// but on the still frames the picture's mean is averaged over (`dir::vpl_stratum`), where each
// frame draws its VPLs at another point of every stratum.
// Flux is compensated so each VPL carries total/n_c of luminance: Φ = Φ_texel · (W_c / n_c) /
// lum(Φ_texel).

struct Summary {
    counts: vec4<u32>,
    totals: vec4<f32>,
    layers: array<vec4<f32>>,
}

@group(0) @binding(0) var<storage, read> dir_buffer: Dir;
var<private> dir: Dir;
@group(0) @binding(1) var<storage, read> lights: array<Light>;
@group(0) @binding(2) var<storage, read> faces: array<Face>;
@group(0) @binding(3) var rsm_rho_position: texture_2d_array<f32>;
@group(0) @binding(4) var rsm_rho_normal: texture_2d_array<f32>;
@group(0) @binding(5) var rsm_rho_albedo: texture_2d_array<f32>;
@group(0) @binding(6) var rsm_mu_position: texture_2d_array<f32>;
@group(0) @binding(7) var rsm_mu_normal: texture_2d_array<f32>;
@group(0) @binding(8) var rsm_mu_albedo: texture_2d_array<f32>;
@group(0) @binding(9) var<storage, read> rows: array<f32>;
@group(0) @binding(10) var<storage, read> summary: Summary;
@group(0) @binding(11) var<storage, read_write> vpls: array<Vpl>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    dir = dir_buffer;
    let k = id.x;
    if k >= dir.dims.x {
        return;
    }
    var vpl: Vpl;
    let counts = summary.counts.xyz;
    var group = 0u;
    var j = k;
    if j >= counts.x {
        j -= counts.x;
        group = 1u;
        if j >= counts.y {
            j -= counts.y;
            group = 2u;
        }
    }
    let n_c = counts[group];
    let total = summary.totals[group];
    if j >= n_c || total <= 0.0 {
        vpls[k] = vpl;
        return;
    }
    var target_flux = (f32(j) + dir.sampling.x) / f32(n_c) * total;
    // The layer.
    var layer = 0u;
    for (; layer + 1u < dir.dims.z; layer++) {
        let t = summary.layers[layer][group];
        if target_flux <= t {
            break;
        }
        target_flux -= t;
    }
    // The row: first whose inclusive CDF reaches the target.
    let size = dir.dims.y;
    let base = (layer * 3u + group) * size;
    var lo = 0u;
    var hi = size - 1u;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if rows[base + mid] >= target_flux {
            hi = mid;
        } else {
            lo = mid + 1u;
        }
    }
    let row = lo;
    if row > 0u {
        target_flux -= rows[base + row - 1u];
    }
    // The texel within the row (the last one with flux, should rounding leave the target
    // beyond the row's sum).
    let face = faces[layer];
    let l = lights[face.light.x];
    var chosen: VplTexel;
    var chosen_flux = vec3<f32>(0.0);
    var sum = 0.0;
    for (var x = 0u; x < size; x++) {
        let v = vpl_texel(group, layer, vec2<i32>(i32(x), i32(row)), rsm_rho_position,
                          rsm_rho_normal, rsm_rho_albedo, rsm_mu_position, rsm_mu_normal,
                          rsm_mu_albedo);
        if !v.valid {
            continue;
        }
        let flux = vpl_flux(l, face, v.position, v.albedo, size);
        let w = dot(flux, LUMINANCE);
        if w <= 0.0 {
            continue;
        }
        chosen = v;
        chosen_flux = flux;
        sum += w;
        if sum >= target_flux {
            break;
        }
    }
    let w = dot(chosen_flux, LUMINANCE);
    if !chosen.valid || w <= 0.0 {
        vpls[k] = vpl;
        return;
    }
    // The VPL stands for the texels that carry its share of the flux, (total / n_c) / w of
    // this one's area: a disc of radius √(A/π), within which a point's 1/d² overstates the
    // disc's light (at d² = A/π both give Φ/A).
    let normal = normalize(chosen.normal);
    let area = texel_area(l, face, chosen.position, normal, size) * (total / f32(n_c)) / w;
    vpl.position = vec4<f32>(chosen.position, f32(group));
    vpl.normal = vec4<f32>(normal, dir.params.w * sqrt(area / PI));
    vpl.flux = vec4<f32>(chosen_flux * (total / f32(n_c)) / w, 0.0);
    vpls[k] = vpl;
}
