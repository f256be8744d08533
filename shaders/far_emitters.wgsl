// Far emitters (engines/src/volume.rs, `FarEmitters`): a volume's injected counts summed over
// blocks of cells into point emitters (`FarEmitter`, common.wgsl). `main` sums one block per
// invocation; `list` then moves the non-empty blocks to the front, in block order, so that a
// receiver loops over those alone and the sums it adds come in the same order on every frame.

@group(0) @binding(0) var<storage, read> volume_buffer: Volume;
var<private> volume: Volume;
@group(0) @binding(1) var<storage, read> cells_delta: array<i32>;
@group(0) @binding(2) var<storage, read_write> far: FarEmitters;

fn counts(base: u32) -> vec4<f32> {
    return vec4<f32>(f32(cells_delta[base]), f32(cells_delta[base + 1u]),
                     f32(cells_delta[base + 2u]), f32(cells_delta[base + 3u]));
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    volume = volume_buffer;
    if id.x >= FAR_EMITTERS {
        return;
    }
    let n = volume.dims.x;
    let edge = (n + FAR_EMITTER_BLOCKS - 1u) / FAR_EMITTER_BLOCKS;
    let block = vec3<u32>(id.x % FAR_EMITTER_BLOCKS, (id.x / FAR_EMITTER_BLOCKS) % FAR_EMITTER_BLOCKS,
                          id.x / (FAR_EMITTER_BLOCKS * FAR_EMITTER_BLOCKS));
    let lo = block * edge;
    let hi = min(lo + vec3<u32>(edge), vec3<u32>(n));
    var r = vec4<f32>(0.0);
    var g = vec4<f32>(0.0);
    var b = vec4<f32>(0.0);
    var weight = 0.0;
    var centre = vec3<f32>(0.0);
    for (var z = lo.z; z < hi.z; z++) {
        for (var y = lo.y; y < hi.y; y++) {
            for (var x = lo.x; x < hi.x; x++) {
                let base = ((z * n + y) * n + x) * 12u;
                let cr = counts(base);
                let cg = counts(base + 4u);
                let cb = counts(base + 8u);
                r += cr;
                g += cg;
                b += cb;
                let w = abs(cr.x) + abs(cg.x) + abs(cb.x);
                weight += w;
                centre += w * (vec3<f32>(f32(x), f32(y), f32(z)) + vec3<f32>(0.5));
            }
        }
    }
    var e = FarEmitter(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    let cell = volume.origin.w;
    if weight > 0.0 && all(hi > lo) {
        r /= volume.scale.x;
        g /= volume.scale.x;
        b /= volume.scale.x;
        // The summed lobes as one clamped cosine lobe about their mean normal: the L1
        // projection itself is positive down to 120° off its normal, which lit the floor in
        // front of a box from the box's top. A block whose lobes cancel is left empty.
        let l0 = vec3<f32>(r.x, g.x, b.x);
        let l1 = LUMINANCE.r * r.wyz + LUMINANCE.g * g.wyz + LUMINANCE.b * b.wyz;
        let net = dot(LUMINANCE, l0);
        if dot(l1, l1) > 0.0 && net != 0.0 {
            e.position = vec4<f32>(volume.origin.xyz + centre / weight * cell,
                                   0.5 * f32(edge) * cell);
            e.normal = vec4<f32>(normalize(l1 * sign(net)), 0.0);
            e.intensity = vec4<f32>(l0 / 0.886226925, 0.0);
        }
    }
    far.emitters[id.x] = e;
}

@compute @workgroup_size(1)
fn list() {
    var count = 0u;
    for (var k = 0u; k < FAR_EMITTERS; k++) {
        let e = far.emitters[k];
        if e.position.w > 0.0 {
            far.emitters[count] = e;
            count++;
        }
    }
    far.count = vec4<u32>(count, 0u, 0u, 0u);
}
