// Shared by the depth-reconstruction passes (recon_*.wgsl), after common.wgsl: the frame's
// settings, the validity test, the sensor's noise model and the guide colour. Every value is
// filled by engines/src/recon_gpu.rs; each pass mirrors a function of the CPU oracle
// (relight-recon: depth.rs, temporal.rs, normals.rs) operation for operation, in the same order,
// so the two agree to float rounding.
//
// Images are row-major, width × height, one invocation per pixel (8 × 8 workgroups).

struct Recon {
    // width, height, window radius r (px), guide channels (1: Mono8, 3: Rgb8).
    dims: vec4<u32>,
    // x: normal span k (px); y: 1 = the merge restarts from the current frame (the CPU decided:
    // first frame, camera change, pose jump); z: 1 = deviation guard on; w: 1 = normals' jump
    // test on.
    flags: vec4<u32>,
    // ε, ε_pos, deviation guard (σ), normals' jump (max_relative_jump · k).
    settings: vec4<f32>,
    // The filter's DepthNoise (for the deviation guard): σ_a (m), σ_b (1/m), z0 (m), disparity
    // step (px); then focal length (px), baseline (m).
    guard_noise: vec4<f32>,
    guard_optics: vec4<f32>,
    // The merge's DepthNoise (for the agreement test), the same way; merge_optics.zw: reject σ,
    // max weight.
    merge_noise: vec4<f32>,
    merge_optics: vec4<f32>,
    // Previous camera: fx, fy, cx, cy.
    previous_k: vec4<f32>,
    // Previous camera: k1, k2, p1, p2.
    previous_distortion: vec4<f32>,
    // Previous camera: k3, largest r² of its valid field, width, height.
    previous_field: vec4<f32>,
    // x: min_agreement.
    merge: vec4<f32>,
    previous_from_current: mat4x4<f32>,
    current_from_previous: mat4x4<f32>,
    // Guide value of each 8-bit code, code / 255 as the CPU rounds it.
    code_values: array<vec4<f32>, 64>,
}

// Binding 0 of every recon pass. Read-only storage rather than uniform: lavapipe specialises
// shaders on the UBO values their branches read, one cached variant per frame's pose.
@group(0) @binding(0) var<storage, read> recon: Recon;

const OUTCOME_MERGED: u32 = 0u;
const OUTCOME_REJECTED: u32 = 1u;
const OUTCOME_FRESH: u32 = 2u;
const OUTCOME_INVALID: u32 = 3u;

// Finite and positive (`is_valid_depth`), on the bits: a NaN test a compiler may fold away is
// never needed. Positive finite floats are exactly the bit patterns 1 ..< 0x7f800000.
fn is_valid_depth(z: f32) -> bool {
    let bits = bitcast<u32>(z);
    return bits != 0u && bits < 0x7f800000u;
}

fn is_finite(v: f32) -> bool {
    return (bitcast<u32>(v) & 0x7f800000u) != 0x7f800000u;
}

// DepthNoise::sigma_m: √(σ_z² + step²/12), σ_z = a + b (z − z0)², step = z² s / (f b), with
// noise = (a, b, z0, s) and optics.xy = (f, b).
fn sigma_m(z: f32, noise: vec4<f32>, optics: vec4<f32>) -> f32 {
    let dz = z - noise.z;
    let sigma_z = noise.x + noise.y * (dz * dz);
    let quantum = z * z * noise.w / (optics.x * optics.y);
    return sqrt(sigma_z * sigma_z + quantum * quantum / 12.0);
}

// Guide value of byte `byte` of the packed guide image (4 bytes per word, little-endian).
fn guide_value(word: u32, byte: u32) -> f32 {
    let code = (word >> ((byte & 3u) * 8u)) & 0xffu;
    return recon.code_values[code >> 2u][code & 3u];
}
