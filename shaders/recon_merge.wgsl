// Temporal merge (Knecht et al. 2012, Sec. 4.2; temporal.rs `warp_and_merge`), as a gather per
// current pixel: its point P is moved into the previous camera by T_warp = previous_from_current,
// projected with the previous intrinsics, and the previous merged depth is read there
// (bilinear over valid neighbours). If it is within `reject σ` of P's depth in the previous
// camera, the history point is moved back and averaged with the current depth, weighted by
// the frames it holds (at most max_weight − 1); otherwise the pixel restarts from the current
// depth. With flags.y set (the CPU dropped the history) every pixel restarts.
// Outcomes are counted per workgroup, then added to `counters` (merged, rejected, fresh,
// valid depth); the select pass compares the agreement with the threshold.

@group(0) @binding(1) var<storage, read> current: array<f32>;
@group(0) @binding(2) var<storage, read> rays: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> history_depth: array<f32>;
@group(0) @binding(4) var<storage, read> history_weight: array<f32>;
@group(0) @binding(5) var<storage, read_write> merged_depth: array<f32>;
@group(0) @binding(6) var<storage, read_write> merged_weight: array<f32>;
@group(0) @binding(7) var<storage, read_write> counters: array<atomic<u32>>;

var<workgroup> workgroup_counts: array<atomic<u32>, 4>;

struct Landing {
    pixel: vec2<f32>,
    point_in_previous: vec3<f32>,
    found: bool,
}

// temporal.rs `Warp::land` with `Pinhole::project` (Brown–Conrady) of the previous camera.
fn land(point_in_current: vec3<f32>) -> Landing {
    var out: Landing;
    out.found = false;
    let p = (recon.previous_from_current * vec4<f32>(point_in_current, 1.0)).xyz;
    out.point_in_previous = p;
    // The OpenCV optical frame of the glTF camera frame.
    let optical = vec3<f32>(p.x, -p.y, -p.z);
    if !(optical.z > 0.0) {
        return out;
    }
    let u = vec2<f32>(optical.x / optical.z, optical.y / optical.z);
    let r2 = u.x * u.x + u.y * u.y;
    if !(r2 < recon.previous_field.y) {
        return out;
    }
    let k1 = recon.previous_distortion.x;
    let k2 = recon.previous_distortion.y;
    let p1 = recon.previous_distortion.z;
    let p2 = recon.previous_distortion.w;
    let k3 = recon.previous_field.x;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    let distorted = vec2<f32>(
        u.x * radial + 2.0 * p1 * u.x * u.y + p2 * (r2 + 2.0 * u.x * u.x),
        u.y * radial + p1 * (r2 + 2.0 * u.y * u.y) + 2.0 * p2 * u.x * u.y,
    );
    let pixel = vec2<f32>(
        recon.previous_k.x * distorted.x + recon.previous_k.z,
        recon.previous_k.y * distorted.y + recon.previous_k.w,
    );
    let size = recon.previous_field.zw;
    if !(pixel.x >= -0.5 && pixel.x <= size.x - 0.5 && pixel.y >= -0.5 && pixel.y <= size.y - 0.5) {
        return out;
    }
    out.pixel = pixel;
    out.found = true;
    return out;
}

struct HistorySample {
    depth: f32,
    weight: f32,
    found: bool,
}

// temporal.rs `bilinear_valid`: bilinear weights over the valid neighbours, renormalised.
fn bilinear_valid(pixel: vec2<f32>) -> HistorySample {
    let w = i32(recon.dims.x);
    let h = i32(recon.dims.y);
    let corner = floor(pixel);
    let f = pixel - corner;
    let x0 = i32(corner.x);
    let y0 = i32(corner.y);
    let offsets = array<vec2<i32>, 4>(vec2(0, 0), vec2(1, 0), vec2(0, 1), vec2(1, 1));
    let weights = array<f32, 4>(
        (1.0 - f.x) * (1.0 - f.y),
        f.x * (1.0 - f.y),
        (1.0 - f.x) * f.y,
        f.x * f.y,
    );
    var weight_sum = 0.0;
    var depth_sum = 0.0;
    var value_sum = 0.0;
    for (var k = 0u; k < 4u; k++) {
        let x = x0 + offsets[k].x;
        let y = y0 + offsets[k].y;
        let weight = weights[k];
        if !(weight > 0.0) || x < 0 || y < 0 || x >= w || y >= h {
            continue;
        }
        let i = u32(y * w + x);
        let z = history_depth[i];
        if is_valid_depth(z) {
            weight_sum += weight;
            depth_sum += weight * z;
            value_sum += weight * history_weight[i];
        }
    }
    var out: HistorySample;
    out.found = weight_sum > 0.0;
    out.depth = depth_sum / weight_sum;
    out.weight = value_sum / weight_sum;
    return out;
}

// Merge pixel i: writes its depth and weight, returns its outcome.
fn merge_pixel(i: u32) -> u32 {
    let z = current[i];
    if recon.flags.y != 0u {
        // temporal.rs `restart`: the current depth alone, weight 1 where valid.
        let valid = is_valid_depth(z);
        merged_depth[i] = select(0.0, z, valid);
        merged_weight[i] = select(0.0, 1.0, valid);
        return select(OUTCOME_INVALID, OUTCOME_FRESH, valid);
    }
    let ray = rays[i];
    if !is_valid_depth(z) || ray.z == 0.0 {
        merged_depth[i] = 0.0;
        merged_weight[i] = 0.0;
        return OUTCOME_INVALID;
    }
    merged_depth[i] = z;
    merged_weight[i] = 1.0;
    let point = vec3<f32>(ray.x * z, -ray.y * z, -z);
    let landing = land(point);
    if !landing.found {
        return OUTCOME_FRESH;
    }
    let history = bilinear_valid(landing.pixel);
    if !history.found {
        return OUTCOME_FRESH;
    }
    let predicted_z = -landing.point_in_previous.z;
    let limit = recon.merge_optics.z * sigma_m(predicted_z, recon.merge_noise, recon.merge_optics);
    if abs(history.depth - predicted_z) > limit || predicted_z <= 0.0 {
        return OUTCOME_REJECTED;
    }
    // The previous surface point on the previous camera's ray through P.
    let history_point = landing.point_in_previous * (history.depth / predicted_z);
    let history_in_current = -(recon.current_from_previous * vec4<f32>(history_point, 1.0)).z;
    if !is_valid_depth(history_in_current) {
        return OUTCOME_REJECTED;
    }
    let w = clamp(history.weight, 0.0, recon.merge_optics.w - 1.0);
    merged_depth[i] = (w * history_in_current + z) / (w + 1.0);
    merged_weight[i] = w + 1.0;
    return OUTCOME_MERGED;
}

@compute @workgroup_size(8, 8)
fn main(
    @builtin(global_invocation_id) id: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if id.x < w && id.y < h {
        let i = id.y * w + id.x;
        let outcome = merge_pixel(i);
        if outcome != OUTCOME_INVALID {
            atomicAdd(&workgroup_counts[outcome], 1u);
        }
        if is_valid_depth(current[i]) {
            atomicAdd(&workgroup_counts[3], 1u);
        }
    }
    workgroupBarrier();
    if local < 4u {
        let count = atomicLoad(&workgroup_counts[local]);
        if count > 0u {
            atomicAdd(&counters[local], count);
        }
    }
}
