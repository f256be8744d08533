// Imperfect shadow maps (Ritschel et al. 2008, as Knecht et al. 2012 use them): every VPL gets
// a small paraboloid depth map of its hemisphere, splatted from a fixed point sampling of the
// scene's surfaces instead of rasterised. Two layers per VPL, real points and virtual points, so
// the gather can take st_r from the first and st_rv = min(st_r, st_v) from both. Depths are
// f32 bit patterns, complemented so that the zero a cleared buffer holds means "nothing" and
// atomicMax keeps the nearest.

@group(0) @binding(0) var<storage, read> dir_buffer: Dir;
var<private> dir: Dir;
@group(0) @binding(1) var<storage, read> vpls: array<Vpl>;
// xyz: position; w: the radius of the disc the point stands for (m), negative on the virtual
// object.
@group(0) @binding(2) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> ism: array<atomic<u32>>;

// VPLs one invocation splats its point into. With one (point, VPL) pair an invocation,
// llvmpipe's cost per invocation (its point and parameters loaded, its lanes set up) was about
// a ninth of this pass (desk_box 74 → 66 ms); the rest is the splats' atomics.
const VPLS_PER_INVOCATION: u32 = 8u;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    dir = dir_buffer;
    if id.x >= dir.size.z {
        return;
    }
    let point = points[id.x];
    let first = id.y * VPLS_PER_INVOCATION;
    for (var k = first; k < min(first + VPLS_PER_INVOCATION, dir.size.w); k++) {
        splat(point, k);
    }
}

// The point into VPL k's map of its layer, as a disc of up to 5 × 5 texels.
fn splat(point: vec4<f32>, k: u32) {
    let vpl = vpls[k];
    if all(vpl.flux.rgb <= vec3<f32>(0.0)) {
        return;
    }
    let d = point.xyz - vpl.position.xyz;
    let dist = length(d);
    if dist <= 0.0 {
        return;
    }
    let s = f32(dir.dims.w);
    let t = paraboloid_texel(vpl.normal.xyz, d / dist, s);
    if t.x < 0.0 {
        return;
    }
    // The point's disc covers about radius/dist radians, half a map per radian near the pole.
    let r = min(i32(abs(point.w) / dist * 0.5 * s), 2);
    let layer = select(0u, 1u, point.w < 0.0);
    let depth = ~bitcast<u32>(dist);
    let c = vec2<i32>(t);
    let m = i32(dir.dims.w);
    for (var y = max(c.y - r, 0); y <= min(c.y + r, m - 1); y++) {
        for (var x = max(c.x - r, 0); x <= min(c.x + r, m - 1); x++) {
            atomicMax(&ism[((k * 2u + layer) * dir.dims.w + u32(y)) * dir.dims.w + u32(x)], depth);
        }
    }
}
