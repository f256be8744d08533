// Temporal merge, the agreement test (temporal.rs `merge`): when fewer than min_agreement of
// the pixels that found history agreed with it, the pose is wrong even though it did not jump,
// and the whole history is dropped: every pixel restarts from the current depth (weight 1
// where valid). counters = (merged, rejected, fresh, valid depth, reset flag written here).

@group(0) @binding(1) var<storage, read> current: array<f32>;
@group(0) @binding(2) var<storage, read_write> counters: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> merged_depth: array<f32>;
@group(0) @binding(4) var<storage, read_write> merged_weight: array<f32>;

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if recon.flags.y != 0u || id.x >= w || id.y >= h {
        return;
    }
    let merged = atomicLoad(&counters[0]);
    let compared = merged + atomicLoad(&counters[1]);
    var agreement = 1.0;
    if compared != 0u {
        agreement = f32(merged) / f32(compared);
    }
    if !(agreement < recon.merge.x) {
        return;
    }
    if id.x == 0u && id.y == 0u {
        atomicStore(&counters[4], 1u);
    }
    let i = id.y * w + id.x;
    let z = current[i];
    let valid = is_valid_depth(z);
    merged_depth[i] = select(0.0, z, valid);
    merged_weight[i] = select(0.0, 1.0, valid);
}
