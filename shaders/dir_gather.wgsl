// DIR gather (Knecht et al. 2012, Sec. 4.3): every camera pixel sums every VPL's light with its
// imperfect-shadow-map visibility into the two solutions at once:
//   L_rv += L_o · (1 − ir(VPL)) · st_rv      (classes 0 and 1: the scene with the object)
//   L_r  += L_o · r(VPL) · r(p) · st_r       (classes 0 and 2: the real scene alone)
// with L_o = f_r(p) · Φ/π · cos θ_VPL · cos θ_p / max(d², clamp²). Real pixels get L_rv − L_r
// (the indirect part of Δ), virtual pixels L_rv. A group-0 VPL's term is computed once and
// added to both sums, so where the object changes nothing Δ is exactly 0.

@group(0) @binding(0) var<uniform> dir: Dir;
@group(0) @binding(1) var<uniform> camera: Camera;
@group(0) @binding(2) var<storage, read> materials: array<Material>;
@group(0) @binding(3) var gb_position: texture_2d<f32>;
@group(0) @binding(4) var gb_normal: texture_2d<f32>;
@group(0) @binding(5) var gb_albedo: texture_2d<f32>;
@group(0) @binding(6) var<storage, read> vpls: array<Vpl>;
@group(0) @binding(7) var<storage, read> ism: array<u32>;
@group(0) @binding(8) var<storage, read_write> indirect: array<vec4<f32>>;

// 1 where VPL `k`'s map layer `layer` has nothing nearer than `dist` towards texel `t`.
fn visible(k: u32, layer: u32, t: vec2<u32>, dist: f32, bias: f32) -> f32 {
    let stored = ism[((k * 2u + layer) * dir.dims.w + t.y) * dir.dims.w + t.x];
    if stored == 0u {
        return 1.0;
    }
    return select(0.0, 1.0, dist <= bitcast<f32>(~stored) + bias);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= dir.size.x || id.y >= dir.size.y {
        return;
    }
    let i = id.y * dir.size.x + id.x;
    let xy = vec2<i32>(id.xy);
    let p = textureLoad(gb_position, xy, 0);
    if p.w < 0.5 {
        indirect[i] = vec4<f32>(0.0);
        return;
    }
    let normal = textureLoad(gb_normal, xy, 0);
    let n = normalize(normal.xyz);
    let is_virtual = normal.w > 0.5;
    let albedo = textureLoad(gb_albedo, xy, 0).rgb;
    let m = materials[u32(p.w) - 1u];
    let wo = normalize(camera.position.xyz - p.xyz);
    let s = f32(dir.dims.w);
    let clamp2 = dir.params.x * dir.params.x;
    var l_rv = vec3<f32>(0.0);
    var l_r = vec3<f32>(0.0);
    for (var k = 0u; k < dir.size.w; k++) {
        let vpl = vpls[k];
        let group = u32(vpl.position.w);
        if all(vpl.flux.rgb <= vec3<f32>(0.0)) || (is_virtual && group == 2u) {
            continue;
        }
        let d = p.xyz - vpl.position.xyz;
        let dist2 = dot(d, d);
        if dist2 <= 0.0 {
            continue;
        }
        let dist = sqrt(dist2);
        let w = d / dist;
        let cos_vpl = dot(vpl.normal.xyz, w);
        let cos_p = dot(n, -w);
        if cos_vpl <= 0.0 || cos_p <= 0.0 {
            continue;
        }
        // A second-bounce VPL clamps within its footprint (normal.w, m), wider than the first's.
        let l_o = brdf(m, albedo, n, -w, wo) * vpl.flux.rgb / PI * cos_vpl * cos_p
            / max(dist2, max(clamp2, vpl.normal.w * vpl.normal.w));
        let t = vec2<u32>(paraboloid_texel(vpl.normal.xyz, w, s));
        // The depth a texel holds can differ from the receiver's by the texel's footprint.
        let bias = dir.params.y * dist * 4.0 / s;
        let st_r = visible(k, 0u, t, dist, bias);
        let st_rv = min(st_r, visible(k, 1u, t, dist, bias));
        if group != 2u {
            l_rv += l_o * st_rv;
        }
        if group != 1u {
            l_r += l_o * st_r;
        }
    }
    var out = l_rv;
    if !is_virtual {
        out = l_rv - l_r;
    }
    indirect[i] = vec4<f32>(out, 0.0);
}
