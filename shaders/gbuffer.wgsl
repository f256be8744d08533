// Camera G-buffer: world position (w: material index + 1, 0 = nothing), normal facing the
// camera (w: 1 on the virtual object), diffuse albedo. Drawn twice per frame: every mesh (ρ) and
// the real meshes only (μ).

@group(0) @binding(0) var<storage, read> camera_buffer: Camera;
var<private> camera: Camera;
@group(0) @binding(1) var<storage, read> materials: array<Material>;

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) @interpolate(flat) material: u32,
    @location(3) @interpolate(flat) flags: u32,
    @location(5) measured: vec4<f32>,
}

struct GBufferOut {
    @location(0) position: vec4<f32>,
    @location(1) normal: vec4<f32>,
    @location(2) albedo: vec4<f32>,
}

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    camera = camera_buffer;
    var out: VertexOut;
    out.clip = camera.view_proj * vec4<f32>(v.position, 1.0);
    out.world = v.position;
    out.normal = v.normal;
    out.material = v.material;
    out.flags = v.flags;
    out.measured = measured_albedo(v.flags);
    return out;
}

@fragment
fn fs_main(in: VertexOut) -> GBufferOut {
    camera = camera_buffer;
    var n = surface_normal(in.normal, in.world);
    // Shade the side the camera sees, as the reference does.
    if dot(n, camera.position.xyz - in.world) < 0.0 {
        n = -n;
    }
    let m = materials[in.material];
    var out: GBufferOut;
    out.position = vec4<f32>(in.world, f32(in.material + 1u));
    out.normal = vec4<f32>(n, f32(in.flags & FLAG_VIRTUAL));
    out.albedo = vec4<f32>(surface_albedo(in.measured, m.albedo.rgb), 1.0);
    return out;
}
