// Reflective shadow maps: one layer per light face (six for a point light's cube). Each texel is
// a VPL: world position, normal facing the light
// (w: 1 on the virtual object), diffuse albedo (w: 1 where something was drawn). Its flux is
// computed where it is used (`vpl_flux`), so the maps stay within 32 bytes per texel. R^μ is
// drawn from the real meshes; R^ρ is R^μ copied (depth included) with the virtual object drawn
// over it (`RsmPass::render`). Engines that use the maps only for visibility (`differential`,
// `ibl`) draw the depth alone (`vs_depth`): a fifth of the position's bytes, a ninth of the full
// map's. Visibility is tested on the depth in every engine (`lit`).

@group(0) @binding(0) var<storage, read> lights: array<Light>;
@group(0) @binding(1) var<storage, read> faces: array<Face>;
@group(0) @binding(2) var<storage, read> materials: array<Material>;

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) @interpolate(flat) material: u32,
    @location(3) @interpolate(flat) flags: u32,
    @location(5) measured: vec4<f32>,
    @location(4) @interpolate(flat) face: u32,
}

struct RsmOut {
    @location(0) position: vec4<f32>,
    @location(1) normal: vec4<f32>,
    @location(2) albedo: vec4<f32>,
}

// The face is the draw's instance index (`first_instance` = face).
@vertex
fn vs_main(v: VertexIn, @builtin(instance_index) face: u32) -> VertexOut {
    var out: VertexOut;
    out.clip = faces[face].view_proj * vec4<f32>(v.position, 1.0);
    out.world = v.position;
    out.normal = v.normal;
    out.material = v.material;
    out.flags = v.flags;
    out.measured = measured_albedo(v.flags);
    out.face = face;
    return out;
}

@fragment
fn fs_main(in: VertexOut) -> RsmOut {
    let l = lights[faces[in.face].light.x];
    var n = surface_normal(in.normal, in.world);
    let to_light = incident(l, in.world).to_light;
    if dot(n, to_light) < 0.0 {
        n = -n;
    }
    var out: RsmOut;
    out.position = vec4<f32>(in.world, 1.0);
    out.normal = vec4<f32>(n, f32(in.flags & FLAG_VIRTUAL));
    out.albedo = vec4<f32>(surface_albedo(in.measured, materials[in.material].albedo.rgb), 1.0);
    return out;
}

// Shadow maps for visibility alone (`differential`, `ibl`): the depth, without a fragment stage.
@vertex
fn vs_depth(v: VertexIn, @builtin(instance_index) face: u32) -> @builtin(position) vec4<f32> {
    return faces[face].view_proj * vec4<f32>(v.position, 1.0);
}
