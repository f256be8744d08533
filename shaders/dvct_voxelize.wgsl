// DVCT voxelisation (Franke 2014, Sec. 3.1): every triangle of the light-space geometry
// (`Dvct.voxelized`: the object and the real scene's shadow proxy, or every mesh) marks each
// level-0 cell it touches (conservative: the triangle–box overlap test of Akenine-Möller
// 2001, 13 separating axes), bit 0 for real geometry, bit 1 for the virtual object.
//
// A triangle's candidate cells are the columns of its bounding box along its normal's dominant
// axis, each only over the span its plane crosses there (plus a cell either side), so a tilted
// wall costs its area in cells, not its bounding box's volume (n³ for one across the volume).
// `Dvct.voxelized.z` threads share a triangle's columns (`voxelize_lanes` in dvct/mod.rs): on a
// GPU one thread walking a large triangle alone would hold the whole pass up.
//
// With the second bounce on (`Dvct.voxelized.w`), each column also sums a real triangle's
// surface into the cells it marks there (`surfaces`, see SURFACE_VALUES in common.wgsl): its
// area over the column's square (the square's share its projection covers, from 16 samples,
// over the normal's cosine to the column's axis), split evenly between those cells, with the
// normal, the albedo and the covered samples' centroid on the plane, clamped into each cell.
// A large triangle's area is so spread over every cell it crosses, and the sums over a surface
// keep its area to the samples' precision wherever its triangles' edges fall.

@group(0) @binding(0) var<storage, read> dvct_buffer: Dvct;
var<private> dvct: Dvct;
// The scene's vertex buffer (engines/src/gpu_scene.rs `GpuVertex`, 8 words each: position,
// normal, material, flags) and its triangles, three indices each.
@group(0) @binding(1) var<storage, read> vertices: array<u32>;
@group(0) @binding(2) var<storage, read_write> occupancy: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read> indices: array<u32>;
@group(0) @binding(4) var<storage, read_write> surfaces: array<atomic<i32>>;
@group(0) @binding(5) var<storage, read> materials: array<Material>;

fn vertex_position(i: u32) -> vec3<f32> {
    let b = i * 8u;
    return vec3<f32>(bitcast<f32>(vertices[b]), bitcast<f32>(vertices[b + 1u]),
                     bitcast<f32>(vertices[b + 2u]));
}

fn vertex_normal(i: u32) -> vec3<f32> {
    let b = i * 8u;
    return vec3<f32>(bitcast<f32>(vertices[b + 3u]), bitcast<f32>(vertices[b + 4u]),
                     bitcast<f32>(vertices[b + 5u]));
}

// The albedo the reflective shadow maps give a vertex's surface (rsm.wgsl): the rig's
// measurement where it has one, else the material's.
fn vertex_albedo(i: u32) -> vec3<f32> {
    let material = materials[vertices[8u * i + 6u]].albedo.rgb;
    return surface_albedo(measured_albedo(vertices[8u * i + 7u]), material);
}

// Whether the projections of the triangle (v0, v1, v2, relative to the box centre) and of the
// box (half extent h) onto `axis` are disjoint.
fn separated(axis: vec3<f32>, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>, h: f32) -> bool {
    let p = vec3<f32>(dot(axis, v0), dot(axis, v1), dot(axis, v2));
    let r = h * (abs(axis.x) + abs(axis.y) + abs(axis.z));
    return min(p.x, min(p.y, p.z)) > r || max(p.x, max(p.y, p.z)) < -r;
}

// Written out, without loops: lavapipe ends an invocation's loops after 65535 iterations of all
// its loops together (llvmpipe's LP_MAX_TGSI_LOOP_ITERATIONS), which a loop here per tested cell
// reached on a floor-sized triangle, leaving its far cells unmarked.
fn overlaps(centre: vec3<f32>, h: f32, a: vec3<f32>, b: vec3<f32>, c: vec3<f32>) -> bool {
    let v0 = a - centre;
    let v1 = b - centre;
    let v2 = c - centre;
    let e0 = v1 - v0;
    let e1 = v2 - v1;
    let e2 = v0 - v2;
    // The cross products of the box's axes x, y, z with each edge.
    return !(separated(vec3<f32>(0.0, -e0.z, e0.y), v0, v1, v2, h)
        || separated(vec3<f32>(0.0, -e1.z, e1.y), v0, v1, v2, h)
        || separated(vec3<f32>(0.0, -e2.z, e2.y), v0, v1, v2, h)
        || separated(vec3<f32>(e0.z, 0.0, -e0.x), v0, v1, v2, h)
        || separated(vec3<f32>(e1.z, 0.0, -e1.x), v0, v1, v2, h)
        || separated(vec3<f32>(e2.z, 0.0, -e2.x), v0, v1, v2, h)
        || separated(vec3<f32>(-e0.y, e0.x, 0.0), v0, v1, v2, h)
        || separated(vec3<f32>(-e1.y, e1.x, 0.0), v0, v1, v2, h)
        || separated(vec3<f32>(-e2.y, e2.x, 0.0), v0, v1, v2, h)
        // The box's own axes are covered by the bounding-box walk; the triangle's plane remains.
        || separated(cross(e0, e1), v0, v1, v2, h));
}

// Whether `q` lies in the triangle (a, b, c) of signed doubled area `d`, as a count (0 or 1).
fn inside(q: vec2<f32>, a: vec2<f32>, b: vec2<f32>, c: vec2<f32>, d: f32) -> f32 {
    let cross2 = vec3<f32>(
        (b.x - a.x) * (q.y - a.y) - (b.y - a.y) * (q.x - a.x),
        (c.x - b.x) * (q.y - b.y) - (c.y - b.y) * (q.x - b.x),
        (a.x - c.x) * (q.y - c.y) - (a.y - c.y) * (q.x - c.x),
    ) * d;
    return select(0.0, 1.0, all(cross2 >= vec3<f32>(0.0)));
}

// The samples of one row of a column's square covered by the triangle: (count, Σu, Σv). The
// offsets are a little off the square's quarters, so that the diagonal shared by a grid-aligned
// quad's two triangles passes between samples rather than through them.
fn covered_row(corner: vec2<f32>, row: f32, a: vec2<f32>, b: vec2<f32>, c: vec2<f32>, d: f32)
    -> vec3<f32> {
    let v = corner.y + (row + 0.5) * 0.25 - 0.0071;
    let q0 = vec2<f32>(corner.x + 0.1359, v);
    let q1 = vec2<f32>(corner.x + 0.3859, v);
    let q2 = vec2<f32>(corner.x + 0.6359, v);
    let q3 = vec2<f32>(corner.x + 0.8859, v);
    let k = vec4<f32>(inside(q0, a, b, c, d), inside(q1, a, b, c, d), inside(q2, a, b, c, d),
                      inside(q3, a, b, c, d));
    let count = k.x + k.y + k.z + k.w;
    return vec3<f32>(count, dot(k, vec4<f32>(q0.x, q1.x, q2.x, q3.x)), count * v);
}

// Written out, without loops, as `overlaps` is.
fn covered(corner: vec2<f32>, a: vec2<f32>, b: vec2<f32>, c: vec2<f32>) -> vec3<f32> {
    let d = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
    return covered_row(corner, 0.0, a, b, c, d) + covered_row(corner, 1.0, a, b, c, d)
        + covered_row(corner, 2.0, a, b, c, d) + covered_row(corner, 3.0, a, b, c, d);
}

fn add_surface(cell: u32, part: u32, area: f32, normal: vec3<f32>, albedo: vec3<f32>,
               centroid: vec3<f32>) {
    let base = (cell * SURFACE_PARTS + part) * SURFACE_VALUES;
    let a = area * SURFACE_SCALE;
    // Written out: a loop here would count against lavapipe's iterations (see `overlaps`).
    atomicAdd(&surfaces[base], i32(round(a)));
    atomicAdd(&surfaces[base + 1u], i32(round(normal.x * a)));
    atomicAdd(&surfaces[base + 2u], i32(round(normal.y * a)));
    atomicAdd(&surfaces[base + 3u], i32(round(normal.z * a)));
    atomicAdd(&surfaces[base + 4u], i32(round(albedo.r * a)));
    atomicAdd(&surfaces[base + 5u], i32(round(albedo.g * a)));
    atomicAdd(&surfaces[base + 6u], i32(round(albedo.b * a)));
    atomicAdd(&surfaces[base + 7u], i32(round(centroid.x * a)));
    atomicAdd(&surfaces[base + 8u], i32(round(centroid.y * a)));
    atomicAdd(&surfaces[base + 9u], i32(round(centroid.z * a)));
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    dvct = dvct_buffer;
    // Dispatched as (min(groups, 65535), ⌈groups / 65535⌉) workgroups of 64.
    let thread = id.x + id.y * 65535u * 64u;
    let lanes = max(dvct.voxelized.z, 1u);
    let k = thread / lanes;
    let lane = thread % lanes;
    if k >= dvct.voxelized.y {
        return;
    }
    let corner = dvct.voxelized.x + 3u * k;
    let first_vertex = indices[corner];
    let a = vertex_position(first_vertex);
    let b = vertex_position(indices[corner + 1u]);
    let c = vertex_position(indices[corner + 2u]);
    let bit = select(1u, 2u, (vertices[8u * first_vertex + 7u] & FLAG_VIRTUAL) != 0u);
    let n = i32(dvct.dims.x);
    let s = dvct.origin.w;
    // Positions in cells from the volume's corner.
    let pa = (a - dvct.origin.xyz) / s;
    let pb = (b - dvct.origin.xyz) / s;
    let pc = (c - dvct.origin.xyz) / s;
    let lo = vec3<i32>(floor(min(pa, min(pb, pc))));
    let hi = vec3<i32>(floor(max(pa, max(pb, pc))));
    if any(hi < vec3<i32>(0)) || any(lo >= vec3<i32>(n)) {
        return;
    }
    let first = max(lo, vec3<i32>(0));
    let last = min(hi, vec3<i32>(n - 1));
    let normal = cross(pb - pa, pc - pa);
    let m = abs(normal);
    var w = 2;
    if m.x >= m.y && m.x >= m.z {
        w = 0;
    } else if m.y >= m.z {
        w = 1;
    }
    let u = (w + 1) % 3;
    let v = (w + 2) % 3;
    let summed = dvct.voxelized.w == 1u && bit == 1u && m[w] > 0.0;
    // What the surface sums take, read only for them.
    var unit_normal = vec3<f32>(0.0);
    var part = 0u;
    var albedo = vec3<f32>(0.0);
    if summed {
        // The face's normal, the winding's turned to the side its vertex normals face (where
        // the mesh has them).
        let facing = vertex_normal(first_vertex) + vertex_normal(indices[corner + 1u])
            + vertex_normal(indices[corner + 2u]);
        unit_normal = normal / length(normal) * select(1.0, -1.0, dot(facing, normal) < 0.0);
        part = select(0u, 1u, unit_normal[w] < 0.0);
        albedo = (vertex_albedo(first_vertex) + vertex_albedo(indices[corner + 1u])
            + vertex_albedo(indices[corner + 2u])) / 3.0;
    }
    // The plane's area over one column's square, in cell faces.
    let area_over_square = length(normal) / m[w];
    let ta = vec2<f32>(pa[u], pa[v]);
    let tb = vec2<f32>(pb[u], pb[v]);
    let tc = vec2<f32>(pc[u], pc[v]);
    for (var cv = first[v]; cv <= last[v]; cv++) {
        for (var cu = first[u] + i32(lane); cu <= last[u]; cu += i32(lanes)) {
            var cell = vec3<i32>(0);
            cell[u] = cu;
            cell[v] = cv;
            var w_first = first[w];
            var w_last = last[w];
            if m[w] > 0.0 {
                // The plane along w over the column's square, from its corner (cu, cv): linear,
                // so its extremes are at the square's corners.
                let at_corner = (dot(normal, pa) - normal[u] * f32(cu) - normal[v] * f32(cv))
                    / normal[w];
                let du = -normal[u] / normal[w];
                let dv = -normal[v] / normal[w];
                let low = at_corner + min(du, 0.0) + min(dv, 0.0);
                let high = at_corner + max(du, 0.0) + max(dv, 0.0);
                let bounds = vec2<f32>(f32(first[w]) - 1.0, f32(last[w]) + 1.0);
                w_first = max(w_first, i32(clamp(floor(low), bounds.x, bounds.y)) - 1);
                w_last = min(w_last, i32(clamp(floor(high), bounds.x, bounds.y)) + 1);
            }
            var marked = 0u;
            for (var along = w_first; along <= w_last; along++) {
                cell[w] = along;
                let centre = dvct.origin.xyz + (vec3<f32>(cell) + 0.5) * s;
                if overlaps(centre, 0.5 * s, a, b, c) {
                    atomicOr(&occupancy[(cell.z * n + cell.y) * n + cell.x], bit);
                    marked |= 1u << u32(along - w_first);
                }
            }
            if !summed || marked == 0u {
                continue;
            }
            let samples = covered(vec2<f32>(f32(cu), f32(cv)), ta, tb, tc);
            if samples.x == 0.0 {
                continue;
            }
            // The covered samples' centroid on the triangle's plane, in cells.
            var centroid = vec3<f32>(0.0);
            centroid[u] = samples.y / samples.x;
            centroid[v] = samples.z / samples.x;
            centroid[w] = (dot(normal, pa) - normal[u] * centroid[u] - normal[v] * centroid[v])
                / normal[w];
            let area = area_over_square * samples.x / 16.0 / f32(countOneBits(marked));
            for (var along = w_first; along <= w_last; along++) {
                if (marked & (1u << u32(along - w_first))) == 0u {
                    continue;
                }
                cell[w] = along;
                let inside_cell = clamp(centroid - vec3<f32>(cell), vec3<f32>(0.0), vec3<f32>(1.0));
                add_surface(u32((cell.z * n + cell.y) * n + cell.x), part, area, unit_normal,
                            albedo, inside_cell);
            }
        }
    }
}
