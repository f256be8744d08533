// Normals from the position map (Knecht et al. 2012, Sec. 4.2; normals.rs `normals`):
// V = z · (x_n, −y_n, −1) per pixel, N = t_u × t_v with tangents from the points k pixels either
// side (central difference where both neighbours are on the pixel's surface, one-sided where one
// is), flipped to face the camera. Two points are on the same surface when their depths differ
// by at most jump · min(z). out[i] = (unit normal or 0 where none, depth or 0 where none), glTF
// camera frame.

@group(0) @binding(1) var<storage, read> rays: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> depth: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<vec4<f32>>;

struct Point {
    position: vec3<f32>,
    found: bool,
}

fn point_at(x: i32, y: i32) -> Point {
    var p: Point;
    p.found = false;
    if x < 0 || y < 0 || x >= i32(recon.dims.x) || y >= i32(recon.dims.y) {
        return p;
    }
    let i = u32(y) * recon.dims.x + u32(x);
    let z = depth[i];
    let ray = rays[i];
    if !is_valid_depth(z) || ray.z == 0.0 {
        return p;
    }
    p.position = vec3<f32>(ray.x * z, -ray.y * z, -z);
    p.found = true;
    return p;
}

struct Tangent {
    direction: vec3<f32>,
    found: bool,
}

// normals.rs `tangent`.
fn tangent(centre: vec3<f32>, before: Point, after: Point) -> Tangent {
    var t: Tangent;
    let joined_before = before.found && joined(centre, before.position);
    let joined_after = after.found && joined(centre, after.position);
    t.found = joined_before || joined_after;
    if joined_before && joined_after {
        t.direction = after.position - before.position;
    } else if joined_after {
        t.direction = after.position - centre;
    } else {
        t.direction = centre - before.position;
    }
    return t;
}

fn joined(centre: vec3<f32>, p: vec3<f32>) -> bool {
    if recon.flags.w == 0u {
        return true;
    }
    let za = -centre.z;
    let zb = -p.z;
    return abs(za - zb) <= recon.settings.w * min(za, zb);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if id.x >= w || id.y >= h {
        return;
    }
    let i = id.y * w + id.x;
    let z = depth[i];
    let depth_out = select(0.0, z, is_valid_depth(z));
    let x = i32(id.x);
    let y = i32(id.y);
    let k = i32(recon.flags.x);
    let centre = point_at(x, y);
    if !centre.found {
        out[i] = vec4<f32>(0.0, 0.0, 0.0, depth_out);
        return;
    }
    let along_u = tangent(centre.position, point_at(x - k, y), point_at(x + k, y));
    let along_v = tangent(centre.position, point_at(x, y - k), point_at(x, y + k));
    if !(along_u.found && along_v.found) {
        out[i] = vec4<f32>(0.0, 0.0, 0.0, depth_out);
        return;
    }
    let a = along_u.direction;
    let b = along_v.direction;
    var normal = vec3<f32>(a.y * b.z - b.y * a.z, a.z * b.x - b.z * a.x, a.x * b.y - b.x * a.y);
    let c = -centre.position;
    if normal.x * c.x + normal.y * c.y + normal.z * c.z < 0.0 {
        normal = -normal;
    }
    // glam's normalize_or_zero: n · (1 / |n|) when that reciprocal is finite and positive.
    let length_sq = normal.x * normal.x + normal.y * normal.y + normal.z * normal.z;
    let recip = 1.0 / sqrt(length_sq);
    var unit = vec3<f32>(0.0);
    if is_finite(recip) && recip > 0.0 {
        unit = normal * recip;
    }
    if !(is_finite(unit.x) && is_finite(unit.y) && is_finite(unit.z)) {
        unit = vec3<f32>(0.0);
    }
    out[i] = vec4<f32>(unit, depth_out);
}
