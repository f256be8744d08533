// DVCT mip chain (Franke 2014, Sec. 3.1–3.2), one level of one radiance volume per dispatch,
// into 3D textures the cone tracer samples with the sampler's quadrilinear filtering. Level 0
// (`first`) turns the voxelisation's bits into occlusion (x: any geometry, y: the virtual
// object, z: the real scene) and the injected fixed-point VPL counts (V^Δ or V^ρ; the DLPV injection pass with
// direct injection off) into float L1 SH intensity. Every coarser cell (`coarser`) is the mean
// of its (up to) eight children, so a level-L cell holds the mean occlusion, and the mean
// intensity per level-0 cell of its block times 2^L: seen from outside, a block's radiance is
// its total intensity over its projected area, mean · 8^L / (2^L s)², and storing the 2^L here
// lets the filtering blend two levels' radiance directly (the tracer divides by s² once).
// Isotropic: one value per cell, not six directional ones (the SH radiance already carries
// direction; see the engine's doc for why).

struct Mip {
    // x: level; y: cells per axis at this level; z: at the level below; w: which volume
    // (0: V^Δ, whose dispatch also writes occlusion; 1: V^ρ).
    level: vec4<u32>,
}

@group(0) @binding(0) var<storage, read> dvct_buffer: Dvct;
var<private> dvct: Dvct;
@group(0) @binding(1) var<storage, read> mip_buffer: Mip;
var<private> mip: Mip;
// The injection's fixed-point counts of this volume: n³ cells × 12 (4 SH × RGB).
@group(0) @binding(2) var<storage, read> cells: array<i32>;
@group(0) @binding(3) var<storage, read> occupancy: array<u32>;
// The level below, of this volume's three channels and of occlusion.
@group(0) @binding(4) var below_r: texture_3d<f32>;
@group(0) @binding(5) var below_g: texture_3d<f32>;
@group(0) @binding(6) var below_b: texture_3d<f32>;
@group(0) @binding(7) var below_occlusion: texture_3d<f32>;
@group(0) @binding(8) var out_r: texture_storage_3d<rgba32float, write>;
@group(0) @binding(9) var out_g: texture_storage_3d<rgba32float, write>;
@group(0) @binding(10) var out_b: texture_storage_3d<rgba32float, write>;
@group(0) @binding(11) var out_occlusion: texture_storage_3d<rgba32float, write>;

fn store(c: vec3<u32>, sh: array<vec4<f32>, 3>, occ: vec4<f32>) {
    textureStore(out_r, c, sh[0]);
    textureStore(out_g, c, sh[1]);
    textureStore(out_b, c, sh[2]);
    if mip.level.w == 0u {
        textureStore(out_occlusion, c, occ);
    }
}

@compute @workgroup_size(4, 4, 4)
fn first(@builtin(global_invocation_id) id: vec3<u32>) {
    dvct = dvct_buffer;
    mip = mip_buffer;
    let m = mip.level.y;
    if any(id >= vec3<u32>(m)) {
        return;
    }
    let cell = (id.z * m + id.y) * m + id.x;
    let bits = occupancy[cell];
    let occ = vec4<f32>(select(0.0, 1.0, bits != 0u), select(0.0, 1.0, (bits & 2u) != 0u),
                        select(0.0, 1.0, (bits & 1u) != 0u), 0.0);
    var sh: array<vec4<f32>, 3>;
    for (var ch = 0u; ch < 3u; ch++) {
        let b = (cell * 3u + ch) * 4u;
        sh[ch] = vec4<f32>(f32(cells[b]), f32(cells[b + 1u]), f32(cells[b + 2u]), f32(cells[b + 3u]))
            / dvct.options.w;
    }
    store(id, sh, occ);
}

@compute @workgroup_size(4, 4, 4)
fn coarser(@builtin(global_invocation_id) id: vec3<u32>) {
    mip = mip_buffer;
    let m = mip.level.y;
    if any(id >= vec3<u32>(m)) {
        return;
    }
    let below = mip.level.z;
    var occ = vec4<f32>(0.0);
    var sh: array<vec4<f32>, 3>;
    var count = 0.0;
    for (var k = 0u; k < 8u; k++) {
        let c = 2u * id + vec3<u32>(k & 1u, (k >> 1u) & 1u, (k >> 2u) & 1u);
        if any(c >= vec3<u32>(below)) {
            continue;
        }
        occ += textureLoad(below_occlusion, c, 0);
        sh[0] += textureLoad(below_r, c, 0);
        sh[1] += textureLoad(below_g, c, 0);
        sh[2] += textureLoad(below_b, c, 0);
        count += 1.0;
    }
    for (var ch = 0u; ch < 3u; ch++) {
        sh[ch] *= 2.0 / count;
    }
    store(id, sh, occ / count);
}
