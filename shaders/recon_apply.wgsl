// Guided filter, step 4 of 4: the vertical half of the window sums (weight d/r for a_k.y, 1 for
// the rest), then each valid pixel's output (depth.rs `guided_filter`, last step):
//   q = (Σ n_k a_k.RGB · g.RGB − Σ n_k a_k.x d_x − Σ n_k a_k.y d_y + Σ n_k b_k) / Σ n_k,
//   z = 1/q, kept when it is valid depth within the deviation guard of the raw depth, else the
//   raw depth. Invalid pixels stay 0.

@group(0) @binding(1) var<storage, read> kernel: array<f32>;
@group(0) @binding(2) var<storage, read> sums: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> depth: array<f32>;
@group(0) @binding(4) var<storage, read> guided: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> filtered: array<f32>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if id.x >= w || id.y >= h {
        return;
    }
    let r = i32(recon.dims.z);
    let n = w * h;
    var weight_sum = 0.0;
    var sum_colour = vec3<f32>(0.0);
    var sum_x = 0.0;
    var sum_y = 0.0;
    var sum_b = 0.0;
    for (var d = -r; d <= r; d++) {
        let y = i32(id.y) + d;
        if y < 0 || y >= i32(h) {
            continue;
        }
        let i = u32(y) * w + id.x;
        let kd = kernel[u32(d + r)];
        let s0 = sums[i];
        let s1 = sums[n + i];
        weight_sum += s0.x;
        sum_colour += s0.yzw;
        sum_x += s1.x;
        sum_y += kd * s1.y;
        sum_b += s1.z;
    }
    let i = id.y * w + id.x;
    let raw = depth[i];
    if !is_valid_depth(raw) || !(weight_sum > 0.0) {
        filtered[i] = 0.0;
        return;
    }
    let c = guided[i].xyz;
    var colour_term = sum_colour.x * c.x;
    colour_term += sum_colour.y * c.y;
    colour_term += sum_colour.z * c.z;
    let q = (colour_term - sum_x - sum_y + sum_b) / weight_sum;
    let z = 1.0 / q;
    var keep = is_valid_depth(z);
    if keep && recon.flags.z != 0u {
        keep = abs(z - raw) <= recon.settings.z * sigma_m(raw, recon.guard_noise, recon.guard_optics);
    }
    filtered[i] = select(raw, z, keep);
}
