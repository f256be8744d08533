// Guided filter, step 3 of 4: the horizontal half of the sums over the windows containing each
// pixel (depth.rs `guided_filter`, after the per-window solve): Σ n_k, Σ n_k a_k.RGB, Σ n_k b_k
// and Σ n_k a_k.y with weight 1, Σ n_k a_k.x with weight d/r (the pixel's offset from window
// k's centre is minus k's offset from the pixel's, which the apply pass accounts for).
// Offsets d = −r ..= r in ascending order, clipped at the border. Same layout as
// `coefficients`: sums[i] = (n, a.R, a.G, a.B), sums[n + i] = (d · a.x, a.y, b, 0).

@group(0) @binding(1) var<storage, read> kernel: array<f32>;
@group(0) @binding(2) var<storage, read> coefficients: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> sums: array<vec4<f32>>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if id.x >= w || id.y >= h {
        return;
    }
    let r = i32(recon.dims.z);
    let n = w * h;
    var s0 = vec4<f32>(0.0);
    var s1 = vec4<f32>(0.0);
    for (var d = -r; d <= r; d++) {
        let x = i32(id.x) + d;
        if x < 0 || x >= i32(w) {
            continue;
        }
        let i = id.y * w + u32(x);
        let kd = kernel[u32(d + r)];
        let c1 = coefficients[n + i];
        s0 += coefficients[i];
        s1 += vec4<f32>(kd * c1.x, c1.y, c1.z, 0.0);
    }
    let i = id.y * w + id.x;
    sums[i] = s0;
    sums[n + i] = s1;
}
