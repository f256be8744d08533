// Guided filter, step 1 of 4: the horizontal half of every window moment (depth.rs
// `guided_filter` → `box_sum_weighted`, first pass). Per pixel, over the row's offsets
// d = −r ..= r in ascending order, clipped at the border: Σ w(d) · v(x + d) of the masked
// values v (zero where the depth is invalid, so invalid neighbours add nothing; `guided` from
// step 0 holds the colour and disparity) with the x
// weight w ∈ {1, d/r, (d/r)²} of each moment. Moments whose x weight and value agree share a
// row sum (m_1, m_y and m_yy all start from Σ 1 · mask), so 20 row sums serve the 27 moments.
//
// rows[g · n + i], g = 0 ..< 5:
//   0: (Σ 1, Σ d, Σ d², Σ p)         mask and disparity p = 1/z
//   1: (Σ d p, Σ R, Σ G, Σ B)
//   2: (Σ d R, Σ d G, Σ d B, Σ R p)
//   3: (Σ G p, Σ B p, Σ RR, Σ RG)
//   4: (Σ RB, Σ GG, Σ GB, Σ BB)

@group(0) @binding(1) var<storage, read> kernel: array<f32>;
@group(0) @binding(2) var<storage, read> guided: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> rows: array<vec4<f32>>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if id.x >= w || id.y >= h {
        return;
    }
    let r = i32(recon.dims.z);
    let taps = u32(2 * r + 1);
    var s0 = vec4<f32>(0.0);
    var s1 = vec4<f32>(0.0);
    var s2 = vec4<f32>(0.0);
    var s3 = vec4<f32>(0.0);
    var s4 = vec4<f32>(0.0);
    for (var d = -r; d <= r; d++) {
        let x = i32(id.x) + d;
        if x < 0 || x >= i32(w) {
            continue;
        }
        let v = guided[id.y * w + u32(x)];
        let p = v.w;
        if p < 0.0 {
            continue;
        }
        let kd = kernel[u32(d + r)];
        let kd2 = kernel[taps + u32(d + r)];
        let c = v.xyz;
        let cp = c * p;
        s0 += vec4<f32>(1.0, kd, kd2, p);
        s1 += vec4<f32>(kd * p, c);
        s2 += vec4<f32>(kd * c, cp.x);
        s3 += vec4<f32>(cp.y, cp.z, c.x * c.x, c.x * c.y);
        s4 += vec4<f32>(c.x * c.z, c.y * c.y, c.y * c.z, c.z * c.z);
    }
    let n = w * h;
    let i = id.y * w + id.x;
    rows[i] = s0;
    rows[n + i] = s1;
    rows[2u * n + i] = s2;
    rows[3u * n + i] = s3;
    rows[4u * n + i] = s4;
}
