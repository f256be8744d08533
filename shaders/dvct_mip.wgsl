// DVCT mip chain (Franke 2014, Sec. 3.1–3.2), one level per dispatch. Level 0 turns the
// voxelisation's bits into occlusion (x: any geometry, y: the virtual object) and the injected
// fixed-point VPL counts (V^Δ, V^ρ; the DLPV injection pass with direct injection off) into
// float L1 SH intensity. Every coarser cell is the mean of its (up to) eight children, so a
// level-L cell holds the mean occlusion and the mean intensity per level-0 cell of its block.
// Isotropic: one value per cell, not six directional ones (the SH radiance already carries
// direction; see the engine's doc for why).

struct Mip {
    // x: level; y: cells per axis at this level; z: at the level below.
    level: vec4<u32>,
}

@group(0) @binding(0) var<uniform> dvct: Dvct;
@group(0) @binding(1) var<uniform> mip: Mip;
// The injection's fixed-point counts: [V^Δ, V^ρ] × n³ cells × 12 (4 SH × RGB).
@group(0) @binding(2) var<storage, read> cells: array<i32>;
@group(0) @binding(3) var<storage, read> occupancy: array<u32>;
// [V^Δ, V^ρ] × every level's cells × 3 channels of L1 SH.
@group(0) @binding(4) var<storage, read_write> radiance: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> occlusion: array<vec2<f32>>;

fn radiance_index(which: u32, level: u32, cell: u32, ch: u32) -> u32 {
    let total = dvct_offset(dvct, dvct.dims.y);
    return (which * total + dvct_offset(dvct, level) + cell) * 3u + ch;
}

@compute @workgroup_size(4, 4, 4)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let level = mip.level.x;
    let m = mip.level.y;
    if any(id >= vec3<u32>(m)) {
        return;
    }
    let cell = (id.z * m + id.y) * m + id.x;
    if level == 0u {
        let bits = occupancy[cell];
        occlusion[cell] = vec2<f32>(select(0.0, 1.0, bits != 0u), select(0.0, 1.0, (bits & 2u) != 0u));
        let n3 = m * m * m;
        for (var which = 0u; which < 2u; which++) {
            for (var ch = 0u; ch < 3u; ch++) {
                let b = ((which * n3 + cell) * 3u + ch) * 4u;
                radiance[radiance_index(which, 0u, cell, ch)] =
                    vec4<f32>(f32(cells[b]), f32(cells[b + 1u]), f32(cells[b + 2u]), f32(cells[b + 3u]))
                    / dvct.options.w;
            }
        }
        return;
    }
    let below = mip.level.z;
    var occ = vec2<f32>(0.0);
    var sh: array<vec4<f32>, 6>;
    var count = 0.0;
    for (var k = 0u; k < 8u; k++) {
        let c = 2u * id + vec3<u32>(k & 1u, (k >> 1u) & 1u, (k >> 2u) & 1u);
        if any(c >= vec3<u32>(below)) {
            continue;
        }
        let child = (c.z * below + c.y) * below + c.x;
        occ += occlusion[dvct_offset(dvct, level - 1u) + child];
        for (var j = 0u; j < 6u; j++) {
            sh[j] += radiance[radiance_index(j / 3u, level - 1u, child, j % 3u)];
        }
        count += 1.0;
    }
    occlusion[dvct_offset(dvct, level) + cell] = occ / count;
    for (var j = 0u; j < 6u; j++) {
        radiance[radiance_index(j / 3u, level, cell, j % 3u)] = sh[j] / count;
    }
}
