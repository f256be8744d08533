//! Every WGSL pass, each with `shaders/common.wgsl` in front (WGSL has no includes). The list
//! [`ALL`] is what the naga validation test walks, so a pass that is not listed here is a test
//! failure waiting to happen: add new passes to it.

macro_rules! pass {
    ($file:literal) => {
        concat!(
            include_str!("../../shaders/common.wgsl"),
            "\n",
            include_str!(concat!("../../shaders/", $file))
        )
    };
}

pub const GBUFFER: &str = pass!("gbuffer.wgsl");
pub const RSM: &str = pass!("rsm.wgsl");
pub const SHADE: &str = pass!("shade.wgsl");
pub const DLPV_INJECT: &str = pass!("dlpv_inject.wgsl");
pub const DLPV_RESOLVE: &str = pass!("dlpv_resolve.wgsl");
pub const DLPV_PROPAGATE: &str = pass!("dlpv_propagate.wgsl");
pub const DLPV_LOOKUP: &str = pass!("dlpv_lookup.wgsl");
pub const FAR_EMITTERS: &str = pass!("far_emitters.wgsl");
pub const DVCT_VOXELIZE: &str = pass!("dvct_voxelize.wgsl");
pub const DVCT_MIP: &str = pass!("dvct_mip.wgsl");
pub const DVCT_TRACE: &str = pass!("dvct_trace.wgsl");
pub const DIR_ROWS: &str = pass!("dir_rows.wgsl");
pub const ROOFLINE: &str = pass!("roofline.wgsl");
pub const DIR_ALLOC: &str = pass!("dir_alloc.wgsl");
pub const DIR_VPL: &str = pass!("dir_vpl.wgsl");
pub const DIR_ISM: &str = pass!("dir_ism.wgsl");
pub const DIR_GATHER: &str = pass!("dir_gather.wgsl");
pub const IBL_CONVOLVE: &str = pass!("ibl_convolve.wgsl");
pub const IBL_SHADE: &str = pass!("ibl_shade.wgsl");
pub const PT_TRACE: &str = pass!("pt_trace.wgsl");
pub const PT_RESOLVE: &str = pass!("pt_resolve.wgsl");
/// The depth-reconstruction passes (`recon_gpu`) share `recon_common.wgsl` after `common.wgsl`.
macro_rules! recon_pass {
    ($file:literal) => {
        concat!(
            include_str!("../../shaders/common.wgsl"),
            "\n",
            include_str!("../../shaders/recon_common.wgsl"),
            "\n",
            include_str!(concat!("../../shaders/", $file))
        )
    };
}
pub const RECON_GUIDE: &str = recon_pass!("recon_guide.wgsl");
pub const RECON_MOMENTS: &str = recon_pass!("recon_moments.wgsl");
pub const RECON_SOLVE: &str = recon_pass!("recon_solve.wgsl");
pub const RECON_SPREAD: &str = recon_pass!("recon_spread.wgsl");
pub const RECON_APPLY: &str = recon_pass!("recon_apply.wgsl");
pub const RECON_MERGE: &str = recon_pass!("recon_merge.wgsl");
pub const RECON_SELECT: &str = recon_pass!("recon_select.wgsl");
pub const RECON_NORMALS: &str = recon_pass!("recon_normals.wgsl");

/// (file name, full source) of every pass.
pub const ALL: &[(&str, &str)] = &[
    ("gbuffer.wgsl", GBUFFER),
    ("rsm.wgsl", RSM),
    ("shade.wgsl", SHADE),
    ("dlpv_inject.wgsl", DLPV_INJECT),
    ("dlpv_resolve.wgsl", DLPV_RESOLVE),
    ("dlpv_propagate.wgsl", DLPV_PROPAGATE),
    ("dlpv_lookup.wgsl", DLPV_LOOKUP),
    ("far_emitters.wgsl", FAR_EMITTERS),
    ("dvct_voxelize.wgsl", DVCT_VOXELIZE),
    ("dvct_mip.wgsl", DVCT_MIP),
    ("dvct_trace.wgsl", DVCT_TRACE),
    ("dir_rows.wgsl", DIR_ROWS),
    ("roofline.wgsl", ROOFLINE),
    ("dir_alloc.wgsl", DIR_ALLOC),
    ("dir_vpl.wgsl", DIR_VPL),
    ("dir_ism.wgsl", DIR_ISM),
    ("dir_gather.wgsl", DIR_GATHER),
    ("ibl_convolve.wgsl", IBL_CONVOLVE),
    ("ibl_shade.wgsl", IBL_SHADE),
    ("pt_trace.wgsl", PT_TRACE),
    ("pt_resolve.wgsl", PT_RESOLVE),
    ("recon_common.wgsl", pass!("recon_common.wgsl")),
    ("recon_guide.wgsl", RECON_GUIDE),
    ("recon_moments.wgsl", RECON_MOMENTS),
    ("recon_solve.wgsl", RECON_SOLVE),
    ("recon_spread.wgsl", RECON_SPREAD),
    ("recon_apply.wgsl", RECON_APPLY),
    ("recon_merge.wgsl", RECON_MERGE),
    ("recon_select.wgsl", RECON_SELECT),
    ("recon_normals.wgsl", RECON_NORMALS),
];

/// How a buffer of a pass's parameters is made: every pass reads them as a read-only storage
/// buffer (`var<storage, read>`), never as a uniform buffer.
///
/// Lavapipe (Mesa 22.3, Debian 12's) specialises a shader on the uniform-buffer values that its
/// branches and loops read ("inline uniforms") and compiles that variant on its queue thread
/// when the dispatch or draw runs, while its shader threads wait. The values change every frame
/// (a pose, a volume's placement), so every such pass paid a compile every frame: `dvct`'s
/// injection took 19–24 ms of wall time on desk_box for 9 ms of shader work. Storage buffers are
/// not inlined. Each entry point copies its parameters into a `var<private>` of the same name
/// first (`volume = volume_buffer;`): read in place, every use after an atomic or a storage
/// write was a fresh load, and `dlpv`'s injection took 25–32 ms instead of 18. On other drivers
/// a few hundred bytes read alike by every invocation cost the same either way. A pass now
/// binds up to 10 storage buffers (`pt_trace.wgsl`; `shade.wgsl` 9): over WebGPU's floor of 8
/// per stage, within what the Vulkan drivers we have met allow (lavapipe's and NVIDIA's are far
/// higher), and the device is opened with the adapter's own limits.
/// `shaders_validate.rs` fails on a `var<uniform>`.
pub const PARAMS_USAGE: wgpu::BufferUsages =
    wgpu::BufferUsages::STORAGE.union(wgpu::BufferUsages::COPY_DST);

/// A buffer of `size` bytes of a pass's parameters, which the CPU rewrites every frame (see
/// [`PARAMS_USAGE`]).
pub fn params_buffer(device: &wgpu::Device, label: &str, size: usize) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size as u64,
        usage: PARAMS_USAGE,
        mapped_at_creation: false,
    })
}

/// Compile a pass into a shader module.
pub fn module(device: &wgpu::Device, name: &str, source: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    })
}

/// A compute pipeline of a pass's `main` entry point, its bind-group layout derived from the
/// shader.
pub fn compute_pipeline(device: &wgpu::Device, label: &str, source: &str) -> wgpu::ComputePipeline {
    compute_pipeline_at(device, label, source, "main")
}

/// A compute pipeline of `entry` in a source with several entry points.
pub fn compute_pipeline_at(
    device: &wgpu::Device,
    label: &str,
    source: &str,
    entry: &str,
) -> wgpu::ComputePipeline {
    let module = module(device, label, source);
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: None,
        module: &module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// A bind group of `layout` with `resources` at bindings 0, 1, 2, … in order (every pass
/// numbers its bindings that way).
pub fn bind_group(
    device: &wgpu::Device,
    label: &str,
    layout: &wgpu::BindGroupLayout,
    resources: &[wgpu::BindingResource],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = resources
        .iter()
        .enumerate()
        .map(|(i, resource)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: resource.clone(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &entries,
    })
}

/// A bind group for group 0 of `pipeline`'s derived layout with `resources[b]` at each binding
/// `b` of `bindings` alone: an entry point that reads only some of its shader's bindings derives
/// a layout of those.
pub fn pipeline_bind_group_of(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    label: &str,
    resources: &[wgpu::BindingResource],
    bindings: &[u32],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = bindings
        .iter()
        .map(|&binding| wgpu::BindGroupEntry {
            binding,
            resource: resources[binding as usize].clone(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

/// A bind group for group 0 of `pipeline`'s derived layout (see [`bind_group`]).
pub fn pipeline_bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    label: &str,
    resources: &[wgpu::BindingResource],
) -> wgpu::BindGroup {
    bind_group(device, label, &pipeline.get_bind_group_layout(0), resources)
}

/// Runs `main` (appended to `shaders/common.wgsl`) once per query on the adapter and reads back
/// one `f32` per query: the unit tests' way to check a WGSL function against its integral.
/// `main` binds `data` at 0 (read), `queries` at 1 (read) and an `array<f32>` result at 2.
#[cfg(test)]
pub(crate) fn evaluate(main: &str, data: &[f32], queries: &[f32], count: usize) -> Vec<f32> {
    use wgpu::BufferUsages as U;
    let ctx = crate::gpu::GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
    let source = format!("{}\n{main}", include_str!("../../shaders/common.wgsl"));
    let buffer = |label, contents: &[f32], usage| {
        ctx.buffer_with(label, bytemuck::cast_slice(contents), usage)
    };
    let data = buffer("data", data, U::STORAGE);
    let queries = buffer("queries", queries, U::STORAGE);
    let result = buffer("result", &vec![0.0; count], U::STORAGE | U::COPY_SRC);
    let pipeline = compute_pipeline(&ctx.device, "evaluate", &source);
    ctx.run_once(
        &pipeline,
        &[
            data.as_entire_binding(),
            queries.as_entire_binding(),
            result.as_entire_binding(),
        ],
        count as u32,
        &result,
        (count * 4) as u64,
        |bytes| bytemuck::cast_slice(bytes).to_vec(),
    )
    .expect("the results read back")
}

/// π × the form factor from a surface at `p` (unit normal `n`) to the rectangle `corner` +
/// u `t` + v `b` (u, v ∈ [0, 1]) emitting along unit `normal`, summed in f64 over `pieces`²
/// pieces with no horizon clip but the cosines': the integral the tests hold a WGSL contour
/// integral to.
#[cfg(test)]
pub(crate) fn rectangle_form_factor(
    (p, n): (glam::DVec3, glam::DVec3),
    (corner, t, b, normal): (glam::DVec3, glam::DVec3, glam::DVec3, glam::DVec3),
    pieces: u32,
) -> f64 {
    let piece = t.length() * b.length() / f64::from(pieces * pieces);
    let mut sum = 0.0;
    for i in 0..pieces {
        for j in 0..pieces {
            let (u, v) = (
                (f64::from(i) + 0.5) / f64::from(pieces),
                (f64::from(j) + 0.5) / f64::from(pieces),
            );
            let d = p - (corner + u * t + v * b);
            let r2 = d.length_squared();
            let (cos_e, cos_r) = (normal.dot(d), -n.dot(d));
            if cos_e > 0.0 && cos_r > 0.0 {
                sum += cos_e * cos_r / (r2 * r2) * piece;
            }
        }
    }
    sum
}
