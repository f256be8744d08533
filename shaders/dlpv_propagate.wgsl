// DLPV propagation, one step (Kaplanyan & Dachsbacher 2010, as DLPV uses it): every cell
// gathers from its six neighbours. The neighbour's intensity towards each of the five faces of
// this cell it can see (the face opposite it, solid angle 0.4006696846 sr, and the four side
// faces, 0.4234413544 sr each, seen at (d + s/2)/|d + s/2|) becomes flux through that face,
// re-emitted into this cell as a cosine lobe around the face's normal. Values are float here:
// each cell is written by exactly one thread. `accumulated` sums every step (and the
// injection). Negative light (antiradiance) is scaled by 1 − dampening per step (Sec. 4.4: it
// keeps shadows from bleeding far beyond the occluder; see the closing notes for how this
// differs from the paper's derivative-based rule).

@group(0) @binding(0) var<uniform> volume: Volume;
// n³ cells × 3 channels of L1 SH (one vec4 per channel), for V^Δ then V^ρ.
@group(0) @binding(1) var<storage, read> source: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> next: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> accumulated: array<vec4<f32>>;

const DIRECT_FACE: f32 = 0.4006696846 / PI;
const SIDE_FACE: f32 = 0.4234413544 / PI;

// Flux through a face of `solid_angle` for intensity `intensity` towards it.
fn flux(intensity: f32, solid_angle: f32) -> f32 {
    let f = solid_angle * intensity;
    // Light (positive) passes unchanged; antiradiance (negative) is dampened.
    return select(f * (1.0 - volume.scale.z), f, f >= 0.0);
}

// For each of the six propagation axes, the four axes perpendicular to it (side faces).
const AXES = array<vec3<i32>, 6>(
    vec3<i32>(1, 0, 0), vec3<i32>(-1, 0, 0), vec3<i32>(0, 1, 0),
    vec3<i32>(0, -1, 0), vec3<i32>(0, 0, 1), vec3<i32>(0, 0, -1),
);
const SIDES = array<vec4<u32>, 6>(
    vec4<u32>(2u, 3u, 4u, 5u), vec4<u32>(2u, 3u, 4u, 5u), vec4<u32>(0u, 1u, 4u, 5u),
    vec4<u32>(0u, 1u, 4u, 5u), vec4<u32>(0u, 1u, 2u, 3u), vec4<u32>(0u, 1u, 2u, 3u),
);

@compute @workgroup_size(4, 4, 4)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = volume.dims.x;
    let which = id.z / n;
    let z = id.z % n;
    if id.x >= n || id.y >= n || which >= 2u {
        return;
    }
    let c = vec3<i32>(i32(id.x), i32(id.y), i32(z));
    let ni = i32(n);
    let n3 = n * n * n;
    let index = which * n3 + u32((c.z * ni + c.y) * ni + c.x);
    var sum = array<vec4<f32>, 3>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    for (var a = 0u; a < 6u; a++) {
        // Light travelling along `d` arrives from the neighbour at c − d.
        let d = AXES[a];
        let s = c - d;
        if any(s < vec3<i32>(0)) || any(s >= vec3<i32>(ni)) {
            continue;
        }
        let src = (which * n3 + u32((s.z * ni + s.y) * ni + s.x)) * 3u;
        let sh = array<vec4<f32>, 3>(source[src], source[src + 1u], source[src + 2u]);
        let df = vec3<f32>(d);
        let main_basis = sh_basis(df);
        let main_lobe = cosine_lobe(df);
        for (var ch = 0u; ch < 3u; ch++) {
            sum[ch] += flux(dot(sh[ch], main_basis), DIRECT_FACE) * main_lobe;
        }
        for (var k = 0u; k < 4u; k++) {
            let side = vec3<f32>(AXES[SIDES[a][k]]);
            // Centre of the side face seen from the neighbour's centre: (d + s/2) / |d + s/2|.
            let basis = sh_basis(0.894427191 * df + 0.447213595 * side);
            let lobe = cosine_lobe(side);
            for (var ch = 0u; ch < 3u; ch++) {
                sum[ch] += flux(dot(sh[ch], basis), SIDE_FACE) * lobe;
            }
        }
    }
    for (var ch = 0u; ch < 3u; ch++) {
        next[index * 3u + ch] = sum[ch];
        accumulated[index * 3u + ch] += sum[ch];
    }
}
