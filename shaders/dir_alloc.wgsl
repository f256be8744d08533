// DIR VPL sampling, step 2 of 3, one thread: row sums → inclusive CDFs per layer and group,
// each group's total flux, and how many of the VPLs each group gets (Knecht et al. 2012,
// Sec. 4.2: split by share, here by flux share, with at least a quarter of the VPLs for the
// virtual object's group and for VPL3 when they exist: they carry the whole of Δ's indirect
// light, and the object usually covers a small part of the maps).

struct Summary {
    // VPLs per group (x: real, y: virtual, z: VPL3).
    counts: vec4<u32>,
    // Total flux luminance per group.
    totals: vec4<f32>,
    // Per layer: total flux luminance per group.
    layers: array<vec4<f32>>,
}

@group(0) @binding(0) var<storage, read> dir_buffer: Dir;
var<private> dir: Dir;
@group(0) @binding(1) var<storage, read_write> rows: array<f32>;
@group(0) @binding(2) var<storage, read_write> summary: Summary;

@compute @workgroup_size(1)
fn main() {
    dir = dir_buffer;
    let size = dir.dims.y;
    var totals = vec3<f32>(0.0);
    for (var layer = 0u; layer < dir.dims.z; layer++) {
        var layer_totals = vec4<f32>(0.0);
        for (var group = 0u; group < 3u; group++) {
            var sum = 0.0;
            let base = (layer * 3u + group) * size;
            for (var y = 0u; y < size; y++) {
                sum += rows[base + y];
                rows[base + y] = sum;
            }
            layer_totals[group] = sum;
        }
        summary.layers[layer] = layer_totals;
        totals += layer_totals.xyz;
    }
    let n = dir.dims.x;
    let all = totals.x + totals.y + totals.z;
    var counts = vec3<u32>(0u);
    if all > 0.0 {
        for (var group = 1u; group < 3u; group++) {
            if totals[group] > 0.0 {
                counts[group] = max(u32(f32(n) * totals[group] / all), n / 4u);
            }
        }
        if totals.x > 0.0 {
            counts.x = n - counts.y - counts.z;
        }
    }
    summary.counts = vec4<u32>(counts, 0u);
    summary.totals = vec4<f32>(totals, 0.0);
}
