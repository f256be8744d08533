// DIR VPL sampling, step 1 of 3: per shadow-map layer and row, the summed luminance of the
// texels' VPL flux in each VPL group (the density VPLs are importance-sampled from).

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
// [layer][group][row]
@group(0) @binding(9) var<storage, read_write> rows: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    dir = dir_buffer;
    let size = dir.dims.y;
    let layer = id.y;
    if id.x >= size || layer >= dir.dims.z {
        return;
    }
    let face = faces[layer];
    let l = lights[face.light.x];
    // Groups 0, 1, 2: each texel is read once for all three.
    var sums = vec3<f32>(0.0);
    for (var x = 0u; x < size; x++) {
        let v = vpl_texels(layer, vec2<i32>(i32(x), i32(id.x)), rsm_rho_position, rsm_rho_normal,
                           rsm_rho_albedo, rsm_mu_position, rsm_mu_normal, rsm_mu_albedo);
        if v.rho.valid {
            let flux = dot(vpl_flux(l, face, v.rho.position, v.rho.albedo, size), LUMINANCE);
            if v.on_virtual {
                sums.y += flux;
            } else {
                sums.x += flux;
            }
        }
        if v.vpl3.valid {
            sums.z += dot(vpl_flux(l, face, v.vpl3.position, v.vpl3.albedo, size), LUMINANCE);
        }
    }
    for (var group = 0u; group < 3u; group++) {
        rows[(layer * 3u + group) * size + id.x] = sums[group];
    }
}
