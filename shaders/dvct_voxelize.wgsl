// DVCT voxelisation (Franke 2014, Sec. 3.1): every triangle of the light-space geometry
// (`Dvct.voxelized`: the object and the real scene's shadow proxy, or every mesh) marks each
// level-0 cell it touches (conservative: the triangle–box overlap test of Akenine-Möller
// 2001, 13 separating axes), bit 0 for real geometry, bit 1 for the virtual object. One thread per
// triangle walks the cells of its bounding box, so a depth-derived mesh of many small
// triangles costs a few tests each and a large floor quad costs its footprint.

@group(0) @binding(0) var<uniform> dvct: Dvct;
// The scene's vertex buffer (engines/src/gpu_scene.rs `GpuVertex`, 8 words each: position,
// normal, material, flags), three vertices per triangle.
@group(0) @binding(1) var<storage, read> vertices: array<u32>;
@group(0) @binding(2) var<storage, read_write> occupancy: array<atomic<u32>>;

fn vertex_position(i: u32) -> vec3<f32> {
    let b = i * 8u;
    return vec3<f32>(bitcast<f32>(vertices[b]), bitcast<f32>(vertices[b + 1u]),
                     bitcast<f32>(vertices[b + 2u]));
}

// Whether the projections of the triangle (v0, v1, v2, relative to the box centre) and of the
// box (half extent h) onto `axis` are disjoint.
fn separated(axis: vec3<f32>, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>, h: f32) -> bool {
    let p = vec3<f32>(dot(axis, v0), dot(axis, v1), dot(axis, v2));
    let r = h * (abs(axis.x) + abs(axis.y) + abs(axis.z));
    return min(p.x, min(p.y, p.z)) > r || max(p.x, max(p.y, p.z)) < -r;
}

fn overlaps(centre: vec3<f32>, h: f32, a: vec3<f32>, b: vec3<f32>, c: vec3<f32>) -> bool {
    let v0 = a - centre;
    let v1 = b - centre;
    let v2 = c - centre;
    let edges = array<vec3<f32>, 3>(v1 - v0, v2 - v1, v0 - v2);
    let units = array<vec3<f32>, 3>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0),
                                    vec3<f32>(0.0, 0.0, 1.0));
    for (var i = 0u; i < 3u; i++) {
        for (var j = 0u; j < 3u; j++) {
            if separated(cross(units[i], edges[j]), v0, v1, v2, h) {
                return false;
            }
        }
    }
    // The box's own axes are covered by the bounding-box walk; the triangle's plane remains.
    return !separated(cross(edges[0], edges[1]), v0, v1, v2, h);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    // Dispatched as (min(groups, 65535), ⌈groups / 65535⌉) workgroups of 64.
    let k = id.x + id.y * 65535u * 64u;
    if k >= dvct.voxelized.y {
        return;
    }
    let corner = dvct.voxelized.x + 3u * k;
    let a = vertex_position(corner);
    let b = vertex_position(corner + 1u);
    let c = vertex_position(corner + 2u);
    let bit = select(1u, 2u, (vertices[8u * corner + 7u] & FLAG_VIRTUAL) != 0u);
    let n = i32(dvct.dims.x);
    let s = dvct.origin.w;
    let lo = vec3<i32>(floor((min(a, min(b, c)) - dvct.origin.xyz) / s));
    let hi = vec3<i32>(floor((max(a, max(b, c)) - dvct.origin.xyz) / s));
    if any(hi < vec3<i32>(0)) || any(lo >= vec3<i32>(n)) {
        return;
    }
    let first = max(lo, vec3<i32>(0));
    let last = min(hi, vec3<i32>(n - 1));
    for (var z = first.z; z <= last.z; z++) {
        for (var y = first.y; y <= last.y; y++) {
            for (var x = first.x; x <= last.x; x++) {
                let centre = dvct.origin.xyz + (vec3<f32>(f32(x), f32(y), f32(z)) + 0.5) * s;
                if overlaps(centre, 0.5 * s, a, b, c) {
                    atomicOr(&occupancy[(z * n + y) * n + x], bit);
                }
            }
        }
    }
}
