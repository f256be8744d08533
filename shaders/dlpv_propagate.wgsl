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

fn flux(sh: vec4<f32>, dir: vec3<f32>, solid_angle: f32) -> f32 {
    let f = solid_angle * sh_eval(sh, dir);
    // Light (positive) passes unchanged; antiradiance (negative) is dampened.
    return select(f * (1.0 - volume.scale.z), f, f >= 0.0);
}

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
    var sum: array<vec4<f32>, 3>;
    let axes = array<vec3<i32>, 6>(
        vec3<i32>(1, 0, 0), vec3<i32>(-1, 0, 0), vec3<i32>(0, 1, 0),
        vec3<i32>(0, -1, 0), vec3<i32>(0, 0, 1), vec3<i32>(0, 0, -1),
    );
    for (var a = 0u; a < 6u; a++) {
        // Light travelling along `d` arrives from the neighbour at c − d.
        let d = axes[a];
        let s = c - d;
        if any(s < vec3<i32>(0)) || any(s >= vec3<i32>(ni)) {
            continue;
        }
        let src = which * n3 + u32((s.z * ni + s.y) * ni + s.x);
        let df = vec3<f32>(d);
        for (var ch = 0u; ch < 3u; ch++) {
            let sh = source[src * 3u + ch];
            var gathered = flux(sh, df, DIRECT_FACE) * cosine_lobe(df);
            for (var k = 0u; k < 6u; k++) {
                let side = vec3<f32>(axes[k]);
                if abs(dot(side, df)) > 0.5 {
                    continue;
                }
                let towards = normalize(df + 0.5 * side);
                gathered += flux(sh, towards, SIDE_FACE) * cosine_lobe(side);
            }
            sum[ch] += gathered;
        }
    }
    for (var ch = 0u; ch < 3u; ch++) {
        next[index * 3u + ch] = sum[ch];
        accumulated[index * 3u + ch] += sum[ch];
    }
}
