//! Irradiance gathered at a stride: the engines whose per-pixel gather dominates their frame
//! (`dvct`'s diffuse cones, `trace_stride`; `dir`'s VPL sum, `gather_stride`) gather at every
//! `stride`-th pixel per axis, and each pixel between takes the bilinear blend of the gathered
//! pixels around it whose surface is like its own (`stride_corner`, `stride_weight` and `alike`
//! in `shaders/common.wgsl`), or gathers its own where none is. What is shared is irradiance
//! (the light over the albedo), which is smooth across one surface; every pixel applies its
//! own albedo and whatever depends on its own view (a glossy lobe). This is the interleaved,
//! edge-aware upsampling real-time global illumination commonly uses for its gathers; at a
//! stride of 1 the engines gather every pixel, as the papers do.
//!
//! A shader has three entries over one indirect buffer: `main` gathers at the strided pixels
//! (and at a stride of 1 writes each pixel's light directly), `fill` gives every other pixel
//! its light, and `resolve` turns the gathered irradiance into light.

/// Run a strided gather's `[main, fill, resolve]` entries (or `[main, fill]` where the engine's
/// own pass resolves) with their bind groups, over a `width` × `height` picture (8 × 8
/// workgroups): `main` alone at a stride of 1.
pub fn dispatch(
    pass: &mut wgpu::ComputePass,
    entries: &[wgpu::ComputePipeline],
    groups: &[wgpu::BindGroup],
    (width, height): (u32, u32),
    stride: u32,
) {
    let gathered = (width.div_ceil(stride), height.div_ceil(stride));
    let passes = if stride > 1 { entries.len() } else { 1 };
    for (k, (pipeline, group)) in entries.iter().zip(groups).take(passes).enumerate() {
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        let (x, y) = if k == 1 { (width, height) } else { gathered };
        pass.dispatch_workgroups(x.div_ceil(8), y.div_ceil(8), 1);
    }
}
