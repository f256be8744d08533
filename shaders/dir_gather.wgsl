// DIR gather (Knecht et al. 2012, Sec. 4.3): every camera pixel sums every VPL's light with its
// imperfect-shadow-map visibility into the two solutions at once:
//   L_rv += L_o · (1 − ir(VPL)) · st_rv      (classes 0 and 1: the scene with the object)
//   L_r  += L_o · r(VPL) · r(p) · st_r       (classes 0 and 2: the real scene alone)
// with L_o = f_r(p) · Φ/π · cos θ_VPL · cos θ_p / max(d², clamp²). Real pixels get L_rv − L_r
// (the indirect part of Δ), virtual pixels L_rv. A group-0 VPL's term is computed once and
// added to both sums, so where the object changes nothing Δ is exactly 0.

@group(0) @binding(0) var<storage, read> dir_buffer: Dir;
var<private> dir: Dir;
@group(0) @binding(1) var<storage, read> camera_buffer: Camera;
var<private> camera: Camera;
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

fn receiver_at(xy: vec2<i32>) -> PixelSurface {
    return pixel_surface(textureLoad(gb_position, xy, 0), textureLoad(gb_normal, xy, 0));
}

// Whether the receiver's BRDF is its albedo/π alone, so that its light is its albedo times an
// irradiance its neighbours may share.
fn is_diffuse(r: PixelSurface) -> bool {
    let m = materials[u32(r.p.w) - 1u];
    return !(m.albedo.w > 0.0 && any(m.specular.rgb > vec3<f32>(0.0)));
}

// Every VPL's light at the receiver: L_rv on the object, L_rv − L_r on real surfaces. With
// `irradiance`, the BRDF is taken as 1/π: a diffuse receiver's light divided by its albedo.
fn gathered(xy: vec2<i32>, r: PixelSurface, irradiance: bool) -> vec3<f32> {
    let p = r.p;
    let n = r.n;
    let is_virtual = r.is_virtual;
    let albedo = textureLoad(gb_albedo, xy, 0).rgb;
    let m = materials[u32(p.w) - 1u];
    let wo = normalize(camera.position.xyz - p.xyz);
    let s = f32(dir.dims.w);
    let clamp2 = dir.params.x * dir.params.x;
    // The footprint (m) under which a real VPL lights the object as its square, and the least
    // cosine the object's slope-scaled ISM bias takes (both explained where they are used).
    let edge = dir.object_hi.xyz - dir.object_lo.xyz;
    let object_square_under = max(dir.params.x, 0.5 * min(edge.x, min(edge.y, edge.z)));
    let slope_cos = 1.0 / max(dir.object_lo.w, 1.0);
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
        var f = vec3<f32>(1.0 / PI);
        if !irradiance {
            f = brdf(m, albedo, n, -w, wo);
        }
        // A second-bounce VPL clamps within its footprint (normal.w, m), wider than the first's.
        var l_o = f * vpl.flux.rgb / PI * cos_vpl * cos_p
            / max(dist2, max(clamp2, vpl.normal.w * vpl.normal.w));
        // With `near_vpls = "patches"`, near a real surface the VPL is the square of surface its
        // clamp's disc stands for (of the disc's area, π r²): the floor beside a wall lights the
        // wall's foot as the floor does, where the clamped point gives it almost nothing. The
        // object takes a real VPL's square too where its footprint is under the clamp's disc or
        // half the object's thinnest extent, where the 5 cm clamp held their light back: a
        // spot's concentrated VPLs at its foot (the clamp's rule: spot_bleed's object 0.103 →
        // 0.096), a desk's or a wall's beside it (the object's rule: desk_box 0.081 → 0.048,
        // touching_wall 0.142 → 0.132). Wider ones stay points: the object's foot stands in its
        // own shadow, of the object's size, into which a wider square spreads the light of the
        // lit floor around it (window_env's sky, object 0.081 → 0.143). A VPL on the object is a
        // piece of one of its faces (`box_square_quad`), no smaller than `clamp_distance`'s
        // disc, as the point's clamp is: unfloored, the small squares of a brightly lit face put
        // one live frame of the bundled recording at Δ 1.78 (0.74 floored), where the point's
        // clamp held. Which VPLs take the square is still decided by their own footprint: by the
        // floored one, touching_wall's Δ went 0.309 → 0.423 (its converged Δ held), one VPL
        // set's squares moved inside the box lighting its contact shadow.
        let half = 0.886226925 * vpl.normal.w;
        let small = is_virtual && group != 1u && vpl.normal.w < object_square_under;
        if dir.sampling.z == 1.0 && (!is_virtual || small)
            && dist2 < PATCH_AS_POINT * PATCH_AS_POINT * half * half {
            var q: Quad;
            if group == 1u {
                q = box_square_quad(vpl.position.xyz, vpl.normal.xyz,
                                    0.886226925 * max(vpl.normal.w, dir.params.x),
                                    dir.object_lo.xyz, dir.object_hi.xyz, p.xyz);
            } else {
                q = square_quad(-d, vpl.normal.xyz, half);
            }
            l_o = f * vpl.flux.rgb / PI * quad_form_factor(q.a, q.b, q.c, q.d, n)
                / max(q.area, 1e-30);
        }
        let t = vec2<u32>(paraboloid_texel(vpl.normal.xyz, w, s));
        // The depth a texel holds can differ from the receiver's by the texel's footprint, and
        // on a surface seen at a grazing angle by its footprint over the cosine (the slope):
        // the object's own points in a texel shadowed its side faces from the floor's VPLs
        // (object L2 desk_box 0.048 → 0.035, touching_wall 0.132 → 0.124). Real pixels keep
        // the constant bias: there a larger one lets the object's contact shadow leak
        // (touching_wall's Δ 0.250 → 0.282, scaled on every pixel).
        let slope = select(1.0, 1.0 / max(cos_p, slope_cos), is_virtual);
        let bias = dir.params.y * dist * 4.0 / s * slope;
        let st_r = visible(k, 0u, t, dist, bias);
        let st_rv = min(st_r, visible(k, 1u, t, dist, bias));
        if group != 2u {
            l_rv += l_o * st_rv;
        }
        if group != 1u {
            l_r += l_o * st_r;
        }
    }
    if is_virtual {
        return l_rv;
    }
    return l_rv - l_r;
}

// The gather runs at every `dir.sampling.y`-th pixel per axis. At 1 (every pixel) `main` alone
// writes each pixel's light. Above 1 (see `stride_corner` in common.wgsl), three dispatches over
// one buffer: `main` writes a traced diffuse pixel's irradiance (w = 1) or a glossy one's own
// light (w = 0); `fill` gives every other pixel its albedo times the blend of its alike traced
// diffuse neighbours' irradiance, or gathers its own where it is glossy or none is alike;
// `resolve` turns each traced irradiance into light (and reads only the uniform, the albedo and
// the buffer: its derived layout has those bindings alone).
fn gather_stride() -> u32 {
    return u32(dir.sampling.y);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    dir = dir_buffer;
    camera = camera_buffer;
    let stride = gather_stride();
    let at = id.xy * stride;
    if at.x >= dir.size.x || at.y >= dir.size.y {
        return;
    }
    let i = at.y * dir.size.x + at.x;
    let xy = vec2<i32>(at);
    let r = receiver_at(xy);
    if !r.found {
        indirect[i] = vec4<f32>(0.0);
        return;
    }
    let lent = stride > 1u && is_diffuse(r);
    indirect[i] = vec4<f32>(gathered(xy, r, lent), select(0.0, 1.0, lent));
}

@compute @workgroup_size(8, 8)
fn fill(@builtin(global_invocation_id) id: vec3<u32>) {
    dir = dir_buffer;
    camera = camera_buffer;
    let size = dir.size.xy;
    let stride = gather_stride();
    if id.x >= size.x || id.y >= size.y || is_gathered(id.xy, stride) {
        return;
    }
    let xy = vec2<i32>(id.xy);
    let i = id.y * size.x + id.x;
    let r = receiver_at(xy);
    if !r.found {
        indirect[i] = vec4<f32>(0.0);
        return;
    }
    var sum = vec3<f32>(0.0);
    var weight = 0.0;
    if is_diffuse(r) {
        for (var k = 0u; k < 4u; k++) {
            let at = stride_corner(id.xy, stride, k);
            let w = stride_weight(id.xy, stride, k, size);
            if w <= 0.0 {
                continue;
            }
            let traced = indirect[at.y * size.x + at.x];
            if traced.w > 0.5 && alike(r, receiver_at(vec2<i32>(at)), camera.position.xyz) {
                sum += w * traced.rgb;
                weight += w;
            }
        }
    }
    var out: vec3<f32>;
    if weight > 0.0 {
        out = textureLoad(gb_albedo, xy, 0).rgb * sum / weight;
    } else {
        out = gathered(xy, r, false);
    }
    indirect[i] = vec4<f32>(out, 0.0);
}

@compute @workgroup_size(8, 8)
fn resolve(@builtin(global_invocation_id) id: vec3<u32>) {
    dir = dir_buffer;
    let at = id.xy * gather_stride();
    if at.x >= dir.size.x || at.y >= dir.size.y {
        return;
    }
    let i = at.y * dir.size.x + at.x;
    let traced = indirect[i];
    if traced.w > 0.5 {
        indirect[i] = vec4<f32>(textureLoad(gb_albedo, vec2<i32>(at), 0).rgb * traced.rgb, 0.0);
    }
}
