//! The volume around the virtual object that DLPV and DVCT both inject into: its placement, the
//! injection uniform (`Volume` in `shaders/common.wgsl`), the fixed-point scale that keeps the
//! integer atomics from overflowing, and timed compute passes.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crate::deferred::RealIndirect;
use crate::engine::SceneFrame;
use crate::gbuffer::Targets;
use crate::gpu::{GpuContext, GpuError};
use crate::gpu_scene::GpuLight;
use crate::params::ParamSpec;
use crate::roofline::Work;
use crate::shaders;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub(crate) struct VolumeUniform {
    pub origin: [f32; 4],
    pub dims: [u32; 4],
    pub scale: [f32; 4],
    pub options: [u32; 4],
}

/// A cube of `n`³ cells centred on the virtual object's bounds `(lo, hi)`, `scale` × their
/// largest edge on a side: (minimum corner, cell edge).
pub(crate) fn placement(lo: Vec3, hi: Vec3, n: u32, scale: f32) -> (Vec3, f32) {
    let edge = (hi - lo).max_element().max(1e-3) * scale;
    ((lo + hi) / 2.0 - Vec3::splat(edge / 2.0), edge / n as f32)
}

/// Where a volume engine's indirect term can be nonzero on real pixels of `frame`: within its
/// volume ([`placement`] of `n`³ cells, `scale` × the object) grown by `grow_cells` cells, and
/// `margin_px` pixels around where that is seen; anywhere without an object.
pub(crate) fn volume_reach(
    frame: &SceneFrame,
    (n, scale): (u32, f32),
    grow_cells: f32,
    margin_px: u32,
) -> RealIndirect {
    let object = frame.scene.as_ref().and_then(|s| s.virtual_bounds());
    object.map_or(RealIndirect::Anywhere, |(lo, hi)| {
        let (origin, cell) = placement(lo, hi, n, scale);
        let grow = Vec3::splat(grow_cells * cell);
        let far = origin + Vec3::splat(n as f32 * cell);
        RealIndirect::Within {
            bounds: (origin - grow, far + grow),
            margin_px,
        }
    })
}

/// Fixed-point counts per unit for injection: 2³⁰ over a bound on any single injected SH
/// coefficient's magnitude summed over a frame, which is every light's total flux (4π I for
/// point and spot lights, E · (2R)² for directional ones over the scene's bounding sphere of
/// radius `scene_radius`), twice (direct and indirect), twice (ρ and μ), times the cosine
/// lobe's largest coefficient over π.
pub(crate) fn fixed_point_scale(lights: &[GpuLight], scene_radius: f32) -> f32 {
    let total: f32 = lights
        .iter()
        .map(|l| {
            let peak = l.intensity[0]
                .max(l.intensity[1])
                .max(l.intensity[2])
                .max(0.0);
            if l.position[3] as u32 == 2 {
                peak * (2.0 * scene_radius).powi(2)
            } else {
                peak * 4.0 * std::f32::consts::PI
            }
        })
        .sum();
    let bound = total * 4.0 * 1.0234 / std::f32::consts::PI;
    if bound > 0.0 && bound.is_finite() {
        (1u64 << 30) as f32 / bound
    } else {
        1.0
    }
}

/// The `far_field` setting both volume engines have: `probe` (default) lights the object with
/// [`CellCounts::far_field`] as well as the volume, `none` with the volume alone (the papers).
pub(crate) fn far_field_param() -> ParamSpec {
    ParamSpec::choice(
        "far_field",
        "`probe`: the object also takes the light of real surfaces outside the volume, gathered at its centre as L2 SH (a volume reaches only `volume_scale` × the object); `none`: the volume's light alone, as in the paper",
        vec!["probe", "none"],
    )
}

/// The injection's fixed-point counts, n³ cells × 12 (4 SH × RGB) i32 each of V^Δ and V^ρ, in
/// one buffer whose halves are bound apart: each half need only fit the adapter's largest
/// storage binding (lavapipe's 128 MiB held both only up to 110³). After them, the far field's
/// 27 sums ([`CellCounts::far_field`]).
#[derive(Debug)]
pub(crate) struct CellCounts {
    pub buffer: wgpu::Buffer,
    /// One volume's bytes, what each binding holds (and what was checked against the limit).
    bytes: u64,
    /// Bytes from V^Δ's start to V^ρ's: one volume's, rounded up to the binding alignment.
    half: u64,
}

/// The far field's bytes: 9 L2 SH coefficients × RGB, i32 (`FAR_FIELD_VALUES` in common.wgsl).
const FAR_FIELD_BYTES: u64 = 27 * 4;

impl CellCounts {
    pub fn new(ctx: &GpuContext, label: &str, n: u32, setting: &str) -> Result<Self, GpuError> {
        let bytes = u64::from(n).pow(3) * 48;
        let half =
            bytes.next_multiple_of(u64::from(ctx.limits.min_storage_buffer_offset_alignment));
        ctx.require("max_storage_buffer_binding_size", bytes, setting)?;
        ctx.require("max_buffer_size", 2 * half + FAR_FIELD_BYTES, setting)?;
        Ok(Self {
            buffer: ctx.buffer(
                label,
                2 * half + FAR_FIELD_BYTES,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            ),
            bytes,
            half,
        })
    }

    /// V^Δ's counts (`which` 0) or V^ρ's (1).
    pub fn binding(&self, which: u64) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: which * self.half,
            size: wgpu::BufferSize::new(self.bytes),
        })
    }

    /// The far field: the light of R^ρ's VPLs that land outside the volume, gathered at its
    /// centre as L2 SH of incident radiance (`dlpv_inject.wgsl`). A volume only reaches
    /// `volume_scale` × the object's size, so without it the object sees none of the room's
    /// bounce light (on desk_box 30–40 % of its radiance); the object's pixels add it
    /// (`dlpv_lookup.wgsl`, `dvct_trace.wgsl`).
    pub fn far_field(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: 2 * self.half,
            size: wgpu::BufferSize::new(FAR_FIELD_BYTES),
        })
    }
}

/// The VPL injection pass (`dlpv_inject.wgsl`) both volume engines run: every R^ρ and R^μ
/// texel into fixed-point L1 SH cells (DLPV with direct injection on, DVCT's split injection
/// with it off).
#[derive(Debug)]
pub(crate) struct InjectPass {
    pipeline: wgpu::ComputePipeline,
}

impl InjectPass {
    pub fn new(device: &wgpu::Device, label: &str) -> Self {
        Self {
            pipeline: shaders::compute_pipeline(device, label, shaders::DLPV_INJECT),
        }
    }

    /// Bind the injection uniform, the light and face buffers, both maps and the cells.
    pub fn bind_group(
        &self,
        device: &wgpu::Device,
        uniform: &wgpu::Buffer,
        (lights, faces, rsm_rho, rsm_mu): (&wgpu::Buffer, &wgpu::Buffer, &Targets, &Targets),
        cells: &CellCounts,
    ) -> wgpu::BindGroup {
        let rsm_views = Targets::rsm_views(rsm_rho, rsm_mu);
        let mut resources = vec![
            uniform.as_entire_binding(),
            lights.as_entire_binding(),
            faces.as_entire_binding(),
        ];
        resources.extend(rsm_views.iter().map(wgpu::BindingResource::TextureView));
        resources.extend([cells.binding(0), cells.binding(1), cells.far_field()]);
        shaders::pipeline_bind_group(device, &self.pipeline, "inject", &resources)
    }

    /// What injecting `layers` faces of `rsm_size`² into `cells` cells must do: every texel of
    /// R^ρ read once (32 bytes; R^μ only where the object covers it, a share this neglects), at
    /// least R^ρ's VPL turned into 12 fixed-point SH values (about 36 operations, 60 more for
    /// the texel's VPL itself; the V^Δ pairs that cancel need none), and the cells written once
    /// (48 bytes).
    pub fn work(rsm_size: u32, layers: u32, cells: f64) -> Work {
        let pairs = f64::from(layers) * f64::from(rsm_size).powi(2);
        Work::new(32.0, 156.0).times(pairs) + Work::new(48.0, 0.0).times(cells)
    }

    /// Inject every texel of `layers` shadow-map layers of `rsm_size`², both maps.
    pub fn dispatch(
        &self,
        pass: &mut wgpu::ComputePass,
        group: &wgpu::BindGroup,
        rsm_size: u32,
        layers: u32,
    ) {
        if layers == 0 {
            return;
        }
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, group, &[]);
        // Each thread injects a 4 × 4 tile (`TILE` in the shader), 8 × 8 threads a group.
        let s = rsm_size.div_ceil(4 * 8);
        pass.dispatch_workgroups(s, s, layers);
    }
}
