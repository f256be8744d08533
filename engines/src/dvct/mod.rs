//! `dvct`: Delta Voxel Cone Tracing (Franke, ISMAR 2014).
//!
//! Per frame, after the shared G-buffers and reflective shadow maps (R^ρ, R^μ):
//! 1. **voxelise** (`dvct_voxelize.wgsl`) every triangle, real and virtual, into n³ cells around
//!    the virtual object, conservatively, one occupancy bit for real and one for virtual;
//! 2. **split injection**: R^ρ's VPLs into V^Δ and V^ρ, R^μ's VPLs negatively into V^Δ, as L1
//!    SH intensity (the DLPV injection pass with its direct injection off, so the same fixed-point
//!    atomics make VPLs seen in both maps cancel exactly);
//! 3. **mip chain** (`dvct_mip.wgsl`): level 0 resolves occlusion (any surface, virtual
//!    object, real scene) and radiance; each coarser level averages its children. The chains
//!    are mipmapped 3D textures (f32, filterable), as in the paper, so that a cone's
//!    quadrilinear sample is one filtered fetch per texture: with storage buffers and the
//!    eight-corner sum written out, the fetches held 90 % of a still frame on lavapipe;
//! 4. **cone tracing** (`dvct_trace.wgsl`) per pixel: 9 diffuse cones and 1 glossy cone whose
//!    aperture follows the Phong exponent, through V^Δ on real pixels and V^ρ on virtual ones
//!    (the diffuse cones at every `trace_stride`-th pixel per axis, 2 by default: the pixels
//!    between take the irradiance of their traced neighbours whose surface is like their own,
//!    or trace their own where none is);
//!    with directional occlusion (the default, by measurement), a real pixel's cones go
//!    through V^ρ with every surface occluding minus through V^μ = V^ρ − V^Δ with the real
//!    surfaces alone, so the real indirect light the object blocks is taken away as well;
//!    on real pixels, shadow cones towards each light take the virtual object's occlusion times
//!    the direct light as antiradiance;
//! 5. the shared shading pass composites.
//!
//! With `bounces` 2 (off by default: the gain is small for the time, see `docs/ALGORITHMS.md`),
//! voxelisation also sums each cell's real surfaces (area, normal, albedo, centroid), and after
//! step 3 those surfaces gather the first bounce as a pixel would and inject what they reflect
//! into the same cells (`bounce` in `dvct_trace.wgsl`); the far emitters, mip chain and probe
//! are built again from both bounces.
//!
//! The mip chain is **isotropic** (one occlusion value and one L1 SH radiance per cell) rather
//! than anisotropic (six directional values per cell, Crassin et al. 2011): the radiance is
//! already directional through its SH, and six occlusion and radiance copies would multiply the
//! memory by six, which at the paper's 256³ is the difference between fitting a GPU or not.
//! The cost is that a thin wall seen edge-on at a coarse level occludes as much as seen face-on.
//! With one bounce the voxels keep no normals: all radiance comes from the RSMs' VPLs, which
//! carry their own.

use std::sync::Arc;
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use serde_json::{Map, Value};

use crate::deferred::{Deferred, KeptInputs, MapSizes, RealIndirect, ShadeOptions};
use crate::engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::gbuffer::Targets;
use crate::gpu::{GpuContext, GpuError};
use crate::params::{ParamSpec, ParamsSchema};
use crate::roofline::{PassWork, Work};
use crate::shaders;
use crate::timer::timed_pass;
use crate::volume::{
    CellCounts, FarEmitters, InjectPass, ObjectBox, VolumeUniform, fixed_point_scale,
    frame_placement, volume_reach,
};

/// `env_lights` by default: chosen by measured error on window_env (`docs/ALGORITHMS.md`,
/// "Environment lights").
const ENV_LIGHTS_DEFAULT: u32 = 16;

/// `Dvct` in `shaders/common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct DvctUniform {
    origin: [f32; 4],
    dims: [u32; 4],
    cone: [f32; 4],
    options: [f32; 4],
    voxelized: [u32; 4],
    modes: [u32; 4],
    lobe: [f32; 4],
    object: [[f32; 4]; 3],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct MipUniform {
    level: [u32; 4],
}

/// The engine's settings (see [`Dvct::schema`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DvctSettings {
    pub rsm_size: u32,
    pub shadow_size: u32,
    pub volume_size: u32,
    pub volume_scale: f32,
    pub step: f32,
    pub cone_aperture_deg: f32,
    pub glossy_min_aperture_deg: f32,
    pub shadow_aperture_deg: f32,
    pub cone_offset: f32,
    pub shadow_cones: bool,
    pub shadow_bias: f32,
    /// How real pixels take the real indirect light the object blocks.
    pub occlusion: Occlusion,
    /// Virtual pixels' cones that leave the volume take the far field
    /// (`CellCounts::far_field`) beyond it.
    pub far_field: bool,
    /// The volume moved out of what lies beyond the scene's bounds (`volume::placement`).
    pub volume_in_scene: bool,
    /// Real pixels outside the volume take V^Δ's light as point emitters
    /// (`volume::FarEmitters`), and lose the light the object blocks, instead of nothing.
    pub far_receivers: bool,
    /// Diffuse cones at every `trace_stride`-th pixel per axis; the pixels between share their
    /// irradiance where their surfaces are alike (`dvct_trace.wgsl`, `fill`).
    pub trace_stride: u32,
    /// Along virtual pixels' cones, the share of each VPL read as the radiance its surface shows
    /// over its hemisphere rather than as the paper's cosine lobe of intensity
    /// (`radiance_lobe_gains`).
    pub radiance_lobe: f32,
    /// Bounces of indirect light: 1, the paper's, or 2, the first bounce gathered by each
    /// cell's surfaces and injected again (`bounce` in `dvct_trace.wgsl`).
    pub bounces: u32,
}

/// How real pixels take the real scene's indirect light that the object blocks (`occlusion`;
/// `Dvct.modes.x` in `shaders/common.wgsl`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Occlusion {
    /// Not at all: the cones through V^Δ alone, which holds only what the object changes in
    /// the maps (the paper).
    None = 0,
    /// Directional occlusion: the cones through V^ρ with every surface occluding, minus through
    /// V^μ = V^ρ − V^Δ with the real ones.
    Directional = 1,
    /// The cones through V^Δ, plus the light the probe finds where the object stands (the
    /// real scene's bounce, as if the object were not there), blocked over the solid angle the
    /// object covers from the pixel, less the object's own indirectly lit faces that the pixel
    /// sees instead (`blocked_irradiance` in `shaders/common.wgsl`).
    Probe = 2,
}

impl Default for DvctSettings {
    fn default() -> Self {
        Self {
            rsm_size: 128,
            shadow_size: crate::deferred::SHADOW_SIZE_DEFAULT,
            volume_size: 32,
            volume_scale: 3.0,
            step: 1.0,
            cone_aperture_deg: 27.3,
            glossy_min_aperture_deg: 2.0,
            shadow_aperture_deg: 3.0,
            cone_offset: 1.0,
            shadow_cones: false,
            shadow_bias: 1.5,
            occlusion: Occlusion::Probe,
            far_field: true,
            volume_in_scene: true,
            far_receivers: true,
            trace_stride: 2,
            radiance_lobe: 0.5,
            bounces: 1,
        }
    }
}

/// The gains on V^ρ's L0 and L1 SH bands that read each VPL, injected as the paper's cosine
/// lobe of intensity I(ω) = Φ/π ⟨n, ω⟩₊ (`cosine_lobe`, `shaders/common.wgsl`), as a `share`
/// of the radiance its surface shows over its hemisphere instead: the non-negative L1 lobe
/// (2/3)(1 + ⟨n, ω⟩) per unit Φ/π, whose mean over the hemisphere is 1, projects to
/// (4√π/3, (2/3)√(4π/3) n) against the cosine lobe's (√π/2, √(π/3) n), so it is the cosine
/// lobe with L0 times 8/3 and L1 times 4/3 whatever the normal, and a cell's sum of either is
/// the other's by the same gains.
///
/// Why: a cone sees a voxel as a surface whose opacity does not depend on the direction it is
/// seen from, so the light it takes from an opaque cell should be the surface's radiance, which
/// for a Lambertian surface is the same towards every direction it faces; an intensity lobe
/// instead falls with the cosine, and a surface seen at a grazing angle, as an object's side
/// sees the floor it stands on, gives almost nothing. Measured (`dvct.rs`,
/// `an_object_on_a_lit_floor_takes_its_bounce`): the unlit sides of desk_box's object on a lit
/// floor took 0.63 of the reference's bounce with the intensity lobe, 1.17 with the radiance
/// lobe alone (the lobe sits half a cell off the surface, so a cone crossing that layer
/// obliquely gathers over a longer path, which already makes up part of the cosine), and
/// 0.90 at the default share of ½, 0.89–1.04 whether the floor is in the volume or beyond it.
/// Only the object's cones (V^ρ, `CONE_RHO`) read it: through real pixels' cones it deepened
/// the object's indirect shadow past the reference's (glossy_floor's shadow region 0.016 →
/// 0.039), so they keep the paper's lobe and are unchanged.
fn radiance_lobe_gains(share: f32) -> [f32; 4] {
    [1.0 + share * 5.0 / 3.0, 1.0 + share / 3.0, 0.0, 0.0]
}

/// Mip levels of an `n`³ chain down to one cell, and the cells of all of them.
fn mip_chain(n: u32) -> (u32, u64) {
    let levels = n.ilog2() + 1;
    let cells = (0..levels).map(|l| u64::from((n >> l).max(1)).pow(3)).sum();
    (levels, cells)
}

/// A cell's surface sums for the second bounce: two records of 10 `i32` (`SURFACE_PARTS` and
/// `SURFACE_VALUES` in `shaders/common.wgsl`).
const SURFACE_BYTES: u64 = 2 * 10 * 4;

/// The surface buffer of an `n`³ volume: every cell's sums when `summed` (the second bounce),
/// else one cell's, bound but unread.
fn surface_bytes(n: u32, summed: bool) -> u64 {
    SURFACE_BYTES * if summed { u64::from(n).pow(3) } else { 1 }
}

/// The mip chains' textures: V^Δ's three channels of L1 SH, V^ρ's, then occlusion.
const CHAINS: usize = 7;

/// The chains' filtering (`dvct_trace.wgsl`): f32 texels and the zero border need these.
const CHAIN_FEATURES: wgpu::Features =
    wgpu::Features::FLOAT32_FILTERABLE.union(wgpu::Features::ADDRESS_MODE_CLAMP_TO_BORDER);

#[derive(Debug)]
struct VolumeBuffers {
    n: u32,
    cells: CellCounts,
    occupancy: wgpu::Buffer,
    /// Each cell's real surfaces for the second bounce (`SURFACE_VALUES` in
    /// `shaders/common.wgsl`); one cell's worth, unread, with one bounce.
    surfaces: wgpu::Buffer,
    /// Whether `surfaces` holds every cell's.
    summed: bool,
    /// Every chain's whole mip chain, as the tracer samples it.
    chains: Vec<wgpu::TextureView>,
    /// Each level's dispatches, first V^Δ's (which writes occlusion too), then V^ρ's, with
    /// their cells per axis; built once with the textures.
    mip_groups: Vec<(bool, u32, wgpu::BindGroup)>,
}

#[derive(Debug)]
pub struct Dvct {
    deferred: Deferred,
    settings: DvctSettings,
    voxelize: wgpu::ComputePipeline,
    inject: InjectPass,
    far_emitters: FarEmitters,
    /// Level 0 of the mip chains, from the injected cells, and the coarser levels.
    mip: [wgpu::ComputePipeline; 2],
    /// The cone tracer's entries (`dvct_trace.wgsl`): `main`, and with a `trace_stride` above
    /// 1 `fill` and `resolve` after it.
    trace: [wgpu::ComputePipeline; 3],
    /// The real scene's first bounce where the object stands (`dvct_trace.wgsl`, `probe`),
    /// into `object_probe`: what the object blocks (`occlusion` "probe", the far receivers).
    probe: wgpu::ComputePipeline,
    object_probe: wgpu::Buffer,
    /// The second bounce (`dvct_trace.wgsl`, `bounce`).
    bounce: wgpu::ComputePipeline,
    sampler: wgpu::Sampler,
    inject_uniform: wgpu::Buffer,
    dvct_uniform: wgpu::Buffer,
    volume: Option<VolumeBuffers>,
    /// What `volume`'s voxels, radiance and mips were built from.
    voxelized: KeptInputs,
}

impl Dvct {
    pub const NAME: &'static str = "dvct";

    pub fn schema() -> ParamsSchema {
        let d = DvctSettings::default();
        let int = |name, doc, min, max, default: u32| {
            ParamSpec::int(name, doc, min, max, i64::from(default))
        };
        let float = ParamSpec::float;
        ParamsSchema::new(vec![
            int(
                "rsm_size",
                "reflective-shadow-map edge per light face; every texel is a VPL (the shadows \
                 have their own map, `shadow_size`). Scaled by √(6/n) where the faces are n > 6 \
                 directional lights alone, e.g. an environment's",
                32,
                2048,
                d.rsm_size,
            ),
            crate::deferred::shadow_size_param(),
            int(
                "volume_size",
                "cells per axis of the voxel volume (the paper: 256); memory grows as its cube",
                16,
                256,
                d.volume_size,
            ),
            float(
                "volume_scale",
                "volume edge as a multiple of the virtual object's largest bounding-box edge",
                1.0,
                16.0,
                d.volume_scale,
            ),
            float(
                "step",
                "cone-marching step as a fraction of the cone's diameter",
                0.1,
                2.0,
                d.step,
            ),
            float(
                "cone_aperture",
                "half angle of the 9 diffuse cones, degrees",
                5.0,
                45.0,
                d.cone_aperture_deg,
            ),
            float(
                "glossy_min_aperture",
                "smallest half angle of the glossy cone (a mirror-like Phong exponent), degrees",
                0.5,
                30.0,
                d.glossy_min_aperture_deg,
            ),
            float(
                "shadow_aperture",
                "half angle of the shadow cones towards each light, degrees (soft shadow size)",
                0.5,
                30.0,
                d.shadow_aperture_deg,
            ),
            float(
                "cone_offset",
                "cone apex moved off the surface along its normal, in cells (self-occlusion)",
                0.0,
                4.0,
                d.cone_offset,
            ),
            ParamSpec::choice(
                "shadows",
                "`shadow_map`: the differential engine's shadows; `cones`: shadow cones, the object's occlusion as antiradiance (the paper; the voxels' conservative footprint darkens ~1.5 cells around the object's contact)",
                vec!["shadow_map", "cones"],
            ),
            float(
                "shadow_bias",
                "shadow-map depth bias in texel footprints",
                0.0,
                8.0,
                d.shadow_bias,
            ),
            ParamSpec::choice(
                "occlusion",
                "`probe`: real pixels also lose the real bounce light crossing the object's place (a probe of 64 cones there), over the solid angle the object covers from them; `directional`: their cones take it away (through V^ρ minus V^μ, each with its occluders); `none`: the paper's cones through V^Δ",
                vec!["probe", "directional", "none"],
            ),
            crate::volume::far_field_param(),
            crate::volume::volume_placement_param(),
            crate::volume::far_receivers_param(),
            float(
                "radiance_lobe",
                "along the object's cones, the share of each VPL seen as the radiance its surface shows over its hemisphere rather than the paper's cosine lobe of intensity (0: the paper)",
                0.0,
                1.0,
                d.radiance_lobe,
            ),
            int(
                "bounces",
                "bounces of indirect light: 1 (the paper), or 2, each voxel's surfaces gathering the first bounce by cones and injecting what they reflect",
                1,
                2,
                d.bounces,
            ),
            int(
                "trace_stride",
                "diffuse cones at every n-th pixel per axis; the pixels between take their alike neighbours' irradiance (1: every pixel, as the paper)",
                1,
                4,
                d.trace_stride,
            ),
            crate::deferred::env_lights_param(ENV_LIGHTS_DEFAULT),
            crate::deferred::accumulate_param(),
            crate::deferred::indirect_param(),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let pipeline = |label, source| shaders::compute_pipeline(&ctx.device, label, source);
        Ok(Self {
            voxelize: pipeline("dvct voxelize", shaders::DVCT_VOXELIZE),
            inject: InjectPass::new(&ctx.device, "dvct inject"),
            far_emitters: FarEmitters::new(&ctx),
            mip: ["first", "coarser"].map(|entry| {
                shaders::compute_pipeline_at(&ctx.device, "dvct mip", shaders::DVCT_MIP, entry)
            }),
            trace: ["main", "fill", "resolve"].map(|entry| {
                shaders::compute_pipeline_at(&ctx.device, "dvct trace", shaders::DVCT_TRACE, entry)
            }),
            probe: shaders::compute_pipeline_at(
                &ctx.device,
                "dvct probe",
                shaders::DVCT_TRACE,
                "probe",
            ),
            object_probe: ctx.buffer("dvct probe", 9 * 16, wgpu::BufferUsages::STORAGE),
            bounce: shaders::compute_pipeline_at(
                &ctx.device,
                "dvct bounce",
                shaders::DVCT_TRACE,
                "bounce",
            ),
            sampler: ctx.device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("dvct volume"),
                address_mode_u: wgpu::AddressMode::ClampToBorder,
                address_mode_v: wgpu::AddressMode::ClampToBorder,
                address_mode_w: wgpu::AddressMode::ClampToBorder,
                border_color: Some(wgpu::SamplerBorderColor::TransparentBlack),
                mag_filter: wgpu::FilterMode::Linear,
                min_filter: wgpu::FilterMode::Linear,
                mipmap_filter: wgpu::MipmapFilterMode::Linear,
                ..Default::default()
            }),
            inject_uniform: shaders::params_buffer(
                &ctx.device,
                "dvct inject",
                size_of::<VolumeUniform>(),
            ),
            dvct_uniform: shaders::params_buffer(&ctx.device, "dvct", size_of::<DvctUniform>()),
            deferred: Deferred::new(ctx),
            settings: DvctSettings::default(),
            volume: None,
            voxelized: KeptInputs::default(),
        })
    }

    fn volume_buffers(&mut self) -> Result<&VolumeBuffers, EngineError> {
        let n = self.settings.volume_size;
        let ctx = self.deferred.ctx().clone();
        let (levels, _) = mip_chain(n);
        ctx.require_features(CHAIN_FEATURES, "dvct's filtered voxel mips")?;
        ctx.require("max_texture_dimension_3d", u64::from(n), "volume_size")?;
        ctx.require(
            "max_compute_workgroups_per_dimension",
            u64::from(n).div_ceil(4),
            "volume_size",
        )?;
        let summed = self.settings.bounces > 1;
        if self
            .volume
            .as_ref()
            .is_none_or(|v| v.n != n || v.summed != summed)
        {
            use wgpu::BufferUsages as U;
            let cells = CellCounts::new(&ctx, "dvct cells", n, "volume_size")?;
            let occupancy = ctx.buffer(
                "dvct occupancy",
                u64::from(n).pow(3) * 4,
                U::STORAGE | U::COPY_DST,
            );
            let surface_bytes = surface_bytes(n, summed);
            ctx.require("max_storage_buffer_binding_size", surface_bytes, "bounces")?;
            let surfaces = ctx.buffer("dvct surfaces", surface_bytes, U::STORAGE | U::COPY_DST);
            let textures: Vec<wgpu::Texture> = (0..CHAINS)
                .map(|_| {
                    ctx.device.create_texture(&wgpu::TextureDescriptor {
                        label: Some("dvct chain"),
                        size: wgpu::Extent3d {
                            width: n,
                            height: n,
                            depth_or_array_layers: n,
                        },
                        mip_level_count: levels,
                        sample_count: 1,
                        dimension: wgpu::TextureDimension::D3,
                        format: wgpu::TextureFormat::Rgba32Float,
                        usage: wgpu::TextureUsages::TEXTURE_BINDING
                            | wgpu::TextureUsages::STORAGE_BINDING,
                        view_formats: &[],
                    })
                })
                .collect();
            let level_view = |chain: usize, level: u32| {
                textures[chain].create_view(&wgpu::TextureViewDescriptor {
                    base_mip_level: level,
                    mip_level_count: Some(1),
                    ..Default::default()
                })
            };
            let mut mip_groups = Vec::new();
            for level in 0..levels {
                let m = (n >> level).max(1);
                let below = (n >> level.saturating_sub(1)).max(1);
                for which in 0..2 {
                    let uniform = ctx.buffer_with(
                        "dvct mip",
                        bytemuck::bytes_of(&MipUniform {
                            level: [level, m, below, which],
                        }),
                        shaders::PARAMS_USAGE,
                    );
                    // This volume's three channels, then occlusion.
                    let chains: Vec<usize> = (0..3)
                        .map(|ch| 3 * which as usize + ch)
                        .chain([CHAINS - 1])
                        .collect();
                    let outputs: Vec<_> = chains.iter().map(|&c| level_view(c, level)).collect();
                    // Level 0 reads the injected cells, a coarser level the level below.
                    let inputs: Vec<_> = match level {
                        0 => Vec::new(),
                        _ => chains.iter().map(|&c| level_view(c, level - 1)).collect(),
                    };
                    let mut entries = vec![(1, uniform.as_entire_binding())];
                    if level == 0 {
                        entries.extend([
                            (0, self.dvct_uniform.as_entire_binding()),
                            (2, cells.binding(u64::from(which))),
                            (3, occupancy.as_entire_binding()),
                        ]);
                    }
                    entries
                        .extend((4..).zip(inputs.iter().map(wgpu::BindingResource::TextureView)));
                    entries
                        .extend((8..).zip(outputs.iter().map(wgpu::BindingResource::TextureView)));
                    let pipeline = &self.mip[usize::from(level > 0)];
                    let entries: Vec<wgpu::BindGroupEntry> = entries
                        .into_iter()
                        .map(|(binding, resource)| wgpu::BindGroupEntry { binding, resource })
                        .collect();
                    let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("dvct mip"),
                        layout: &pipeline.get_bind_group_layout(0),
                        entries: &entries,
                    });
                    mip_groups.push((level > 0, m, group));
                }
            }
            self.voxelized.forget();
            self.volume = Some(VolumeBuffers {
                n,
                cells,
                occupancy,
                surfaces,
                summed,
                chains: textures
                    .iter()
                    .map(|t| t.create_view(&Default::default()))
                    .collect(),
                mip_groups,
            });
        }
        self.volume.as_ref().ok_or(EngineError::NotPrepared)
    }
}

/// What the cone tracing must do over `pixels`: the G-buffer read and the result written per
/// pixel, the mip chains (`mip_cells`) read once; per cone, the samples a cone of its aperture
/// takes across the volume (its diameter grows by `2 tan(aperture/2) · step` a sample, from one
/// cell to the volume's diagonal), each a quadrilinear lookup of two levels (16 cells of 14
/// values: one volume's SH and two occlusions; 26 with directional occlusion, both volumes).
/// Nine diffuse cones, one glossy, and with shadow cones one per light.
fn trace_work(settings: &DvctSettings, n: u32, pixels: u32, lights: u32, mip_cells: f64) -> Work {
    let samples = |aperture_deg: f32| {
        let growth = 1.0 + 2.0 * f64::from(aperture_deg.to_radians().tan() * settings.step);
        ((1.7 * f64::from(n)).ln() / growth.ln()).max(1.0)
    };
    let values = if settings.occlusion == Occlusion::Directional {
        26.0
    } else {
        14.0
    };
    let cones = 10.0 * samples(settings.cone_aperture_deg) * values
        + if settings.shadow_cones {
            f64::from(lights) * samples(settings.shadow_aperture_deg) * 2.0
        } else {
            0.0
        };
    // The light the object blocks (`blocked_irradiance`): 9 SH coefficients read, about 200
    // operations to evaluate them for the pixel and three box faces.
    let blocked = if settings.occlusion == Occlusion::Probe || settings.far_receivers {
        200.0
    } else {
        0.0
    };
    Work::new(32.0 + 16.0, cones * 16.0 * 2.0 + blocked).times(f64::from(pixels))
        + Work::new(96.0 + 16.0, 0.0).times(mip_cells)
}

/// What one mip chain must do: every level's cells read as eight children and written once, two
/// radiance volumes (96 bytes) and the occlusion texel (16).
fn mip_work(mip_cells: f64) -> Work {
    Work::new(2.0 * (96.0 + 16.0), 8.0 * 27.0).times(mip_cells)
}

/// What the second bounce (`dvct_trace.wgsl`, `bounce`) must do: every cell's surfaces read
/// (80 bytes); at the cells a surface crosses, about 3 n² of them (a floor and two walls), the
/// nine diffuse cones twice (Δ and ρ) and the injection's 24 atomics.
fn bounce_work(settings: &DvctSettings, n: u32) -> Work {
    let growth =
        1.0 + 2.0 * f64::from(settings.cone_aperture_deg.to_radians().tan() * settings.step);
    let samples = ((1.7 * f64::from(n)).ln() / growth.ln()).max(1.0);
    Work::new(80.0, 4.0).times(f64::from(n).powi(3))
        + Work::new(96.0, 2.0 * 9.0 * samples * 14.0 * 16.0 * 2.0 + 24.0 * 4.0)
            .times(3.0 * f64::from(n).powi(2))
}

/// What the probe (`dvct_trace.wgsl`, `probe`) must do: 64 cones of half angle 14.4° from the
/// object's centre, each sample a quadrilinear lookup of both volumes' SH and the occlusion
/// (26 values of 16 cells), then the projection onto L2 SH.
fn probe_work(settings: &DvctSettings, n: u32) -> Work {
    let growth = 1.0 + 2.0 * 0.2567 * f64::from(settings.step);
    let samples = ((1.7 * f64::from(n)).ln() / growth.ln()).max(1.0);
    Work::new(
        64.0 * 16.0,
        64.0 * samples * 26.0 * 16.0 * 2.0 + 64.0 * 9.0 * 30.0,
    )
}

/// Dispatches `threads` threads of the 64-thread workgroups of `dvct_voxelize.wgsl` and of
/// `bounce`, in rows of 65535 workgroups (a dimension's limit); the shaders number a thread
/// `id.x + id.y * 65535 * 64`.
fn dispatch_threads(pass: &mut wgpu::ComputePass, threads: u32) {
    let groups = threads.div_ceil(64);
    if groups > 0 {
        pass.dispatch_workgroups(groups.min(65535), groups.div_ceil(65535), 1);
    }
}

/// Threads that share one triangle's cells in the voxelisation (`dvct_voxelize.wgsl`) of an
/// `n`³ volume. On a GPU, 32: one thread walking a floor-sized triangle alone held the pass at
/// 5 to 11 ms at 64³ (H200). On a CPU adapter threads are SIMD lanes of one core, so as few as
/// keep each under lavapipe's 65535 loop iterations an invocation (about 7 a column of n², 10
/// with the surfaces summed for the second bounce).
fn voxelize_lanes(ctx: &GpuContext, n: u32) -> u32 {
    let needed = (12 * n * n).div_ceil(65535).max(1);
    match ctx.info.device_type {
        wgpu::DeviceType::Cpu => needed,
        _ => needed.max(32),
    }
}

impl Engine for Dvct {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, frame: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let settings = self.settings;
        // A cone's first sample is a cell from its apex (`cone_offset` cells off the surface),
        // and its march ends at the first sample beyond the volume grown by a cell: a real
        // pixel farther out gathers nothing, and takes its direct Δ alone, as does every pixel
        // farther than the stride from one that gathers something.
        let n = settings.volume_size;
        let volume = frame_placement(frame, n, settings.volume_scale, settings.volume_in_scene);
        let object = ObjectBox::of_frame(frame);
        let probe = settings.far_receivers || settings.occlusion == Occlusion::Probe;
        // The far emitters and the light the object blocks reach real surfaces anywhere.
        self.deferred.set_real_indirect(if probe {
            RealIndirect::Anywhere
        } else {
            volume_reach(
                volume,
                n,
                2.01 + settings.cone_offset.abs(),
                2 * settings.trace_stride + 2,
            )
        });
        let Some((width, height)) = self.deferred.prepare(
            Self::NAME,
            frame,
            out,
            MapSizes::with_injected_rsm(settings.shadow_size, settings.rsm_size),
        )?
        else {
            return Ok(());
        };
        let started = Instant::now();
        let ctx = self.deferred.ctx().clone();
        let Some(scene) = self.deferred.scene() else {
            return Err(EngineError::NotPrepared);
        };
        let (bounds, voxelized, scene_geometry) = (
            scene.bounds,
            scene.light_space_indices(),
            scene.light_space_fingerprint(),
        );
        let triangles = voxelized.len() as u32 / 3;
        let faces = self.deferred.faces().len() as u32;
        let rsm_size = self.deferred.rsm_size().ok_or(EngineError::NotPrepared)?;
        if let Some((origin, cell)) = volume {
            let scale =
                fixed_point_scale(self.deferred.lights(), (bounds.1 - bounds.0).length() / 2.0);
            let (levels, mip_cells) = mip_chain(n);
            let tan = |deg: f32| deg.to_radians().tan();
            let inject_volume = VolumeUniform {
                origin: origin.extend(cell).to_array(),
                dims: [n, rsm_size, faces, self.deferred.lights().len() as u32],
                scale: [scale, 0.0, 0.0, 0.0],
                options: [u32::from(settings.far_field), 0, 0, 0],
                object: object.uniform(),
            };
            ctx.queue
                .write_buffer(&self.inject_uniform, 0, bytemuck::bytes_of(&inject_volume));
            ctx.queue.write_buffer(
                &self.dvct_uniform,
                0,
                bytemuck::bytes_of(&DvctUniform {
                    origin: origin.extend(cell).to_array(),
                    dims: [
                        n,
                        levels,
                        self.deferred.lights().len() as u32,
                        settings.shadow_size,
                    ],
                    cone: [
                        tan(settings.cone_aperture_deg),
                        settings.step,
                        tan(settings.shadow_aperture_deg),
                        settings.cone_offset,
                    ],
                    options: [
                        if settings.shadow_cones { 1.0 } else { 0.0 },
                        settings.shadow_bias,
                        tan(settings.glossy_min_aperture_deg),
                        scale,
                    ],
                    voxelized: [
                        voxelized.start,
                        triangles,
                        voxelize_lanes(&ctx, n),
                        u32::from(settings.bounces > 1),
                    ],
                    modes: [
                        settings.occlusion as u32,
                        u32::from(settings.far_field),
                        settings.trace_stride,
                        u32::from(settings.far_receivers),
                    ],
                    lobe: radiance_lobe_gains(settings.radiance_lobe),
                    object: object.uniform(),
                }),
            );
            self.volume_buffers()?;
            // Voxels and their radiance depend on the light-space geometry, the shadow maps and
            // the volume's placement, not on the camera: the trace alone runs while they hold.
            let inputs = KeptInputs::hash_of(&[
                bytemuck::bytes_of(&inject_volume),
                &scene_geometry.to_le_bytes(),
                &self.deferred.light_inputs().to_le_bytes(),
                &[
                    u8::from(settings.far_receivers),
                    settings.occlusion as u8,
                    settings.bounces as u8,
                ],
            ]);
            let revoxelize = !self.voxelized.holds(inputs);
            let mut timer = self.deferred.lend_timer();
            let (
                Some(v),
                Some((lights, faces_buf, rsm_rho, rsm_mu)),
                Some(shadows),
                Some((gb_rho, _, indirect)),
                Some(scene),
            ) = (
                self.volume.as_ref(),
                self.deferred.light_buffers(),
                self.deferred.shadow_maps(),
                self.deferred.frame_buffers(),
                self.deferred.scene(),
            )
            else {
                return Err(EngineError::NotPrepared);
            };
            let group = |pipeline, label, resources: &[wgpu::BindingResource]| {
                shaders::pipeline_bind_group(&ctx.device, pipeline, label, resources)
            };
            let voxelize_group = group(
                &self.voxelize,
                "dvct voxelize",
                &[
                    self.dvct_uniform.as_entire_binding(),
                    scene.vertices.as_entire_binding(),
                    v.occupancy.as_entire_binding(),
                    scene.indices.as_entire_binding(),
                    v.surfaces.as_entire_binding(),
                    scene.materials.as_entire_binding(),
                ],
            );
            let inject_group = self.inject.bind_group(
                &ctx.device,
                &self.inject_uniform,
                (lights, faces_buf, rsm_rho, rsm_mu),
                &v.cells,
            );
            let gb_views = [
                Targets::view(&gb_rho.position),
                Targets::view(&gb_rho.normal),
                Targets::view(&gb_rho.albedo),
                shadows.mu.depth_array_view(),
            ];
            let mut trace_resources = vec![
                self.dvct_uniform.as_entire_binding(),
                self.deferred.camera_buffer().as_entire_binding(),
                lights.as_entire_binding(),
                faces_buf.as_entire_binding(),
                scene.materials.as_entire_binding(),
            ];
            trace_resources.extend(gb_views.iter().map(wgpu::BindingResource::TextureView));
            trace_resources.extend(v.chains.iter().map(wgpu::BindingResource::TextureView));
            trace_resources.extend([
                wgpu::BindingResource::Sampler(&self.sampler),
                indirect.as_entire_binding(),
                v.cells.far_field(),
                self.far_emitters.buffer.as_entire_binding(),
                self.object_probe.as_entire_binding(),
                v.cells.binding(0),
                v.cells.binding(1),
                v.surfaces.as_entire_binding(),
            ]);
            let group_of = |pipeline, label, bindings: &[u32]| {
                shaders::pipeline_bind_group_of(
                    &ctx.device,
                    pipeline,
                    label,
                    &trace_resources,
                    bindings,
                )
            };
            // The pixels' entries read through the probe (20); `resolve` reads the traced
            // irradiance, not the far emitters or the probe it came from.
            let pixels: Vec<u32> = (0..21).collect();
            let [main, fill, resolve] = self.trace.each_ref();
            let trace_groups = [
                group_of(main, "dvct trace", &pixels),
                group_of(fill, "dvct trace", &pixels),
                group_of(resolve, "dvct trace", &pixels[..19]),
            ];

            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("dvct"),
                });
            if revoxelize {
                let cells = 2.0 * f64::from(n).powi(3);
                let mip_cells = mip_cells as f64;
                out.work.extend([
                    PassWork {
                        pass: "voxelize",
                        // Each triangle's vertices read, about 300 operations to find the
                        // cells it covers; the occupancy written once.
                        work: Work::new(96.0, 300.0).times(f64::from(triangles))
                            + Work::new(4.0, 0.0).times(cells),
                    },
                    PassWork {
                        pass: "inject",
                        work: InjectPass::work(rsm_size, faces, cells),
                    },
                ]);
                encoder.clear_buffer(&v.cells.buffer, 0, None);
                encoder.clear_buffer(&v.occupancy, 0, None);
                if settings.bounces > 1 {
                    encoder.clear_buffer(&v.surfaces, 0, None);
                }
                {
                    let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.voxelize");
                    pass.set_pipeline(&self.voxelize);
                    pass.set_bind_group(0, &voxelize_group, &[]);
                    dispatch_threads(&mut pass, triangles * voxelize_lanes(&ctx, n));
                }
                {
                    let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.inject");
                    self.inject
                        .dispatch(&mut pass, &inject_group, rsm_size, faces);
                }
                // Built only when the voxels are: a frame that keeps them traces alone.
                let probe_group = probe.then(|| {
                    group_of(
                        &self.probe,
                        "dvct probe",
                        &(0..1).chain(9..17).chain([18, 20]).collect::<Vec<_>>(),
                    )
                });
                let bounce_group = (settings.bounces > 1).then(|| {
                    group_of(
                        &self.bounce,
                        "dvct bounce",
                        &(0..1).chain(9..17).chain(18..24).collect::<Vec<_>>(),
                    )
                });
                // The far emitters, the mip chain and the probe, from the cells; with a second
                // bounce, which the cells gather from the first's chains and probe, once more.
                for bounce in 1..=settings.bounces {
                    if let Some(bounce_group) = bounce_group.as_ref().filter(|_| bounce > 1) {
                        out.work.push(PassWork {
                            pass: "bounce",
                            work: bounce_work(&settings, n),
                        });
                        let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.bounce");
                        pass.set_pipeline(&self.bounce);
                        pass.set_bind_group(0, bounce_group, &[]);
                        dispatch_threads(&mut pass, n.pow(3));
                    }
                    if settings.far_receivers {
                        out.work.push(PassWork {
                            pass: "far_emitters",
                            work: FarEmitters::work(n),
                        });
                        let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.far_emitters");
                        self.far_emitters.dispatch(
                            &ctx.device,
                            &mut pass,
                            &self.inject_uniform,
                            &v.cells,
                            0,
                        );
                    }
                    {
                        out.work.push(PassWork {
                            pass: "mip",
                            work: mip_work(mip_cells),
                        });
                        let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.mip");
                        for (coarser, m, mip_group) in &v.mip_groups {
                            let m = m.div_ceil(4);
                            pass.set_pipeline(&self.mip[usize::from(*coarser)]);
                            pass.set_bind_group(0, mip_group, &[]);
                            pass.dispatch_workgroups(m, m, m);
                        }
                    }
                    if let Some(probe_group) = &probe_group {
                        out.work.push(PassWork {
                            pass: "probe",
                            work: probe_work(&settings, n),
                        });
                        let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.probe");
                        pass.set_pipeline(&self.probe);
                        pass.set_bind_group(0, probe_group, &[]);
                        pass.dispatch_workgroups(1, 1, 1);
                    }
                }
            }
            out.work.push(PassWork {
                pass: "trace",
                work: trace_work(
                    &settings,
                    n,
                    width.div_ceil(settings.trace_stride) * height.div_ceil(settings.trace_stride),
                    self.deferred.lights().len() as u32,
                    mip_cells as f64,
                ),
            });
            {
                let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.trace");
                crate::strided::dispatch(
                    &mut pass,
                    &self.trace,
                    &trace_groups,
                    (width, height),
                    settings.trace_stride,
                );
            }
            ctx.queue.submit([encoder.finish()]);
            ctx.check()?;
            self.voxelized.record(inputs);
            self.deferred.return_timer(timer);
        }
        out.timings.push(PassTiming {
            pass: "volume",
            ms: started.elapsed().as_secs_f64() * 1e3,
        });
        self.deferred.finish(
            ShadeOptions {
                shadow_bias_texels: settings.shadow_bias,
                direct_delta: !settings.shadow_cones,
            },
            out,
        )
    }

    fn set_params(&mut self, params: &Map<String, Value>) {
        let schema = Self::schema();
        let (int, float) = (
            |name| schema.int(params, name) as u32,
            |name| schema.float(params, name) as f32,
        );
        self.settings = DvctSettings {
            rsm_size: int("rsm_size"),
            shadow_size: int("shadow_size"),
            volume_size: int("volume_size"),
            volume_scale: float("volume_scale"),
            step: float("step"),
            cone_aperture_deg: float("cone_aperture"),
            glossy_min_aperture_deg: float("glossy_min_aperture"),
            shadow_aperture_deg: float("shadow_aperture"),
            cone_offset: float("cone_offset"),
            shadow_cones: schema.choice(params, "shadows") == "cones",
            shadow_bias: float("shadow_bias"),
            occlusion: match schema.choice(params, "occlusion") {
                "directional" => Occlusion::Directional,
                "none" => Occlusion::None,
                _ => Occlusion::Probe,
            },
            radiance_lobe: float("radiance_lobe"),
            far_field: schema.choice(params, "far_field") == "probe",
            volume_in_scene: schema.choice(params, "volume_placement") == "scene",
            far_receivers: schema.choice(params, "far_receivers") == "emitters",
            trace_stride: int("trace_stride"),
            bounces: int("bounces"),
        };
        self.deferred
            .set_environment_light_count(schema.int(params, "env_lights") as u32);
        self.deferred.set_shared_params(&schema, params);
    }
}

#[cfg(test)]
impl crate::shadow_reach::tests::WithDeferred for Dvct {
    fn deferred_mut(&mut self) -> &mut Deferred {
        &mut self.deferred
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// Akenine-Möller's triangle–box test, as `dvct_voxelize.wgsl` has it.
    fn overlaps(centre: Vec3, h: f32, [a, b, c]: [Vec3; 3]) -> bool {
        let (v0, v1, v2) = (a - centre, b - centre, c - centre);
        let separated = |axis: Vec3| {
            let p = [axis.dot(v0), axis.dot(v1), axis.dot(v2)];
            let r = h * axis.abs().element_sum();
            p.iter().copied().fold(f32::INFINITY, f32::min) > r
                || p.iter().copied().fold(f32::NEG_INFINITY, f32::max) < -r
        };
        let edges = [v1 - v0, v2 - v1, v0 - v2];
        !(Vec3::AXES
            .iter()
            .any(|u| edges.iter().any(|e| separated(u.cross(*e))))
            || separated(edges[0].cross(edges[1])))
    }

    /// The cells each triangle touches, by testing every cell of its bounding box.
    fn voxelize_on_cpu(triangles: &[([Vec3; 3], bool)], origin: Vec3, s: f32, n: i32) -> Vec<u32> {
        let mut occupancy = vec![0; (n * n * n) as usize];
        for (t, virtual_object) in triangles {
            let lo = ((t[0].min(t[1]).min(t[2]) - origin) / s).floor().as_ivec3();
            let hi = ((t[0].max(t[1]).max(t[2]) - origin) / s).floor().as_ivec3();
            let (lo, hi) = (lo.max(glam::IVec3::ZERO), hi.min(glam::IVec3::splat(n - 1)));
            for z in lo.z..=hi.z {
                for y in lo.y..=hi.y {
                    for x in lo.x..=hi.x {
                        let centre = origin + (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * s;
                        if overlaps(centre, 0.5 * s, *t) {
                            occupancy[((z * n + y) * n + x) as usize] |=
                                if *virtual_object { 2 } else { 1 };
                        }
                    }
                }
            }
        }
        occupancy
    }

    /// Runs `dvct_voxelize.wgsl` once over the vertices `words` (as `GpuVertex`, three a
    /// triangle) into a fresh `n`³ volume of cell edge `s` from `origin`, `lanes` threads a
    /// triangle, and reads back the occupancy, or with `summed` the surfaces' sums.
    fn voxelize_on_gpu(
        ctx: &GpuContext,
        words: &[u32],
        materials: &wgpu::Buffer,
        (n, s, origin): (u32, f32, Vec3),
        lanes: u32,
        summed: bool,
    ) -> Vec<u32> {
        use wgpu::BufferUsages as U;
        let triangles = words.len() as u32 / 24;
        let vertices = ctx.buffer_with("vertices", bytemuck::cast_slice(words), U::STORAGE);
        let corners: Vec<u32> = (0..3 * triangles).collect();
        let indices = ctx.buffer_with("indices", bytemuck::cast_slice(&corners), U::STORAGE);
        let cells = u64::from(n).pow(3);
        // New buffers start zeroed: nothing marked, nothing summed.
        let occupancy = ctx.buffer("occupancy", 4 * cells, U::STORAGE | U::COPY_SRC);
        let surface_bytes = surface_bytes(n, summed);
        let surfaces = ctx.buffer("surfaces", surface_bytes, U::STORAGE | U::COPY_SRC);
        let uniform = DvctUniform {
            origin: origin.extend(s).to_array(),
            dims: [n, 1, 0, 0],
            voxelized: [0, triangles, lanes, u32::from(summed)],
            ..DvctUniform::zeroed()
        };
        let uniform = ctx.buffer_with("dvct", bytemuck::bytes_of(&uniform), shaders::PARAMS_USAGE);
        let pipeline = shaders::compute_pipeline(&ctx.device, "voxelize", shaders::DVCT_VOXELIZE);
        let (read, bytes) = if summed {
            (&surfaces, surface_bytes)
        } else {
            (&occupancy, 4 * cells)
        };
        ctx.run_once(
            &pipeline,
            &[
                uniform.as_entire_binding(),
                vertices.as_entire_binding(),
                occupancy.as_entire_binding(),
                indices.as_entire_binding(),
                surfaces.as_entire_binding(),
                materials.as_entire_binding(),
            ],
            (triangles * lanes).div_ceil(64),
            read,
            bytes,
            |b| bytemuck::cast_slice(b).to_vec(),
        )
        .unwrap()
    }

    /// The column walk along each triangle's dominant axis marks exactly the cells the whole
    /// bounding-box walk marks, with one thread a triangle (CPU adapters) and with 32.
    #[test]
    fn voxelization_marks_every_touched_cell_and_no_other() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
        // 64³: a floor-sized triangle walks 4096 columns, past lavapipe's loop limit had the
        // overlap test loops of its own.
        let (n, s, origin) = (64, 2.0 / 64.0, Vec3::new(-1.01, -0.98, -1.03));
        let v = Vec3::new;
        let triangles = [
            // Tilted across the whole volume (its bounding box is all n³ cells).
            (
                [v(-1.2, -1.1, -0.9), v(1.1, 0.2, 1.2), v(-0.3, 1.15, 0.95)],
                false,
            ),
            // A floor quad, partly outside the volume.
            (
                [
                    v(-1.5, -0.61, -1.5),
                    v(1.5, -0.61, -1.5),
                    v(1.5, -0.61, 1.5),
                ],
                false,
            ),
            (
                [
                    v(-1.5, -0.61, -1.5),
                    v(1.5, -0.61, 1.5),
                    v(-1.5, -0.61, 1.5),
                ],
                false,
            ),
            // A steep wall and a small object triangle.
            (
                [v(0.31, -0.9, -0.8), v(0.37, 0.9, -0.7), v(0.43, 0.1, 0.9)],
                false,
            ),
            (
                [v(0.05, 0.02, 0.07), v(0.21, 0.09, 0.04), v(0.1, 0.23, 0.17)],
                true,
            ),
            // A sliver (nearly degenerate) and one wholly outside.
            (
                [v(-0.7, 0.3, 0.2), v(0.7, 0.3001, 0.2), v(0.0, 0.3, 0.2002)],
                false,
            ),
            (
                [v(2.0, 2.0, 2.0), v(2.5, 2.0, 2.0), v(2.0, 2.5, 2.0)],
                false,
            ),
            // On cell faces: a floor and a wall exactly between two layers of cells.
            (
                [
                    v(-1.5, origin.y + 3.0 * s, -1.5),
                    v(1.5, origin.y + 3.0 * s, -1.5),
                    v(0.3, origin.y + 3.0 * s, 1.5),
                ],
                false,
            ),
            (
                [
                    v(origin.x + 5.0 * s, -1.5, -1.5),
                    v(origin.x + 5.0 * s, 1.5, -1.5),
                    v(origin.x + 5.0 * s, 0.3, 1.5),
                ],
                false,
            ),
            (
                [
                    v(-1.5, -1.5, origin.z + 9.0 * s),
                    v(1.5, -1.5, origin.z + 9.0 * s),
                    v(0.3, 1.5, origin.z + 9.0 * s),
                ],
                false,
            ),
        ];
        let expected = voxelize_on_cpu(&triangles, origin, s, n);
        assert!(expected.iter().filter(|c| **c != 0).count() > 10_000);
        let mut words = Vec::new();
        for (t, virtual_object) in &triangles {
            for p in t {
                let flags = if *virtual_object { 1u32 } else { 0 };
                words.extend(p.to_array().map(f32::to_bits));
                words.extend([0, 0, 0, 0, flags]);
            }
        }
        // Not read: the surfaces are not summed.
        let materials = ctx.buffer("materials", 32, wgpu::BufferUsages::STORAGE);
        for lanes in [1, 32] {
            let got = voxelize_on_gpu(
                &ctx,
                &words,
                &materials,
                (n as u32, s, origin),
                lanes,
                false,
            );
            let differing: Vec<usize> =
                (0..got.len()).filter(|i| got[*i] != expected[*i]).collect();
            assert!(
                differing.is_empty(),
                "{lanes} lanes: {} cells differ, e.g. {:?}",
                differing.len(),
                &differing[..differing.len().min(5)]
            );
        }
    }

    /// The surfaces summed for the second bounce (`Dvct.voxelized.w`): over the cells, each
    /// side's area is its triangles' to the coverage samples' precision (16 a column), with
    /// their normal, turned to the side their vertex normals face, their material's albedo and
    /// a centroid within each cell. A slab thinner than a cell keeps its top and its underside
    /// apart, and the object's triangles add nothing.
    #[test]
    fn the_second_bounce_sums_each_sides_area_normal_and_albedo() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
        let (n, s, origin) = (16u32, 1.0 / 16.0, Vec3::splat(-0.5));
        let v = Vec3::new;
        let (top, under) = (-0.101, -0.118);
        let quad = |y: f32| {
            [
                [v(-0.31, y, -0.27), v(0.22, y, -0.27), v(0.22, y, 0.26)],
                [v(-0.31, y, -0.27), v(0.22, y, 0.26), v(-0.31, y, 0.26)],
            ]
        };
        // Facing +x mostly, of the second material.
        let tilted = [v(0.3, -0.4, -0.3), v(0.35, 0.4, -0.2), v(0.4, 0.0, 0.35)];
        let area = |t: &[Vec3; 3]| 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length();
        // (corners, vertex normal, material, virtual)
        let mut triangles = Vec::new();
        for t in quad(top) {
            triangles.push((t, Vec3::Y, 0u32, false));
        }
        for t in quad(under) {
            // The underside wound as the top is: its vertex normals turn it down.
            triangles.push((t, Vec3::NEG_Y, 0, false));
        }
        let tilted_normal = (tilted[1] - tilted[0])
            .cross(tilted[2] - tilted[0])
            .normalize();
        let tilted_normal = tilted_normal * tilted_normal.x.signum();
        triangles.push((tilted, tilted_normal, 1, false));
        triangles.push((
            [v(0.0, 0.1, 0.0), v(0.2, 0.1, 0.0), v(0.0, 0.3, 0.1)],
            Vec3::Z,
            1,
            true,
        ));
        let mut words = Vec::new();
        for (t, normal, material, virtual_object) in &triangles {
            for p in t {
                words.extend(p.to_array().map(f32::to_bits));
                words.extend(normal.to_array().map(f32::to_bits));
                words.extend([*material, u32::from(*virtual_object)]);
            }
        }
        let albedos = [[0.5f32, 0.6, 0.7, 0.0], [0.2, 0.3, 0.1, 0.0]];
        let material_words: Vec<f32> = albedos
            .iter()
            .flat_map(|a| [*a, [0.0; 4]])
            .flatten()
            .collect();
        let materials = ctx.buffer_with(
            "materials",
            bytemuck::cast_slice(&material_words),
            wgpu::BufferUsages::STORAGE,
        );
        let sums = voxelize_on_gpu(&ctx, &words, &materials, (n, s, origin), 1, true);
        // Per side: the area (m²) and the area-weighted normal and albedo.
        let mut totals = [[0.0f64; 7]; 2];
        for cell in sums.chunks(20) {
            for (side, record) in cell.chunks(10).enumerate() {
                let record: Vec<f64> = record.iter().map(|v| f64::from(*v as i32)).collect();
                for (total, value) in totals[side].iter_mut().zip(&record[..7]) {
                    *total += value / 65536.0 * f64::from(s * s);
                }
                for centroid in &record[7..] {
                    let inside = centroid / record[0].max(1.0);
                    assert!((-1e-3..=1.0 + 1e-3).contains(&inside), "centroid {inside}");
                }
            }
        }
        let quad_area = f64::from(area(&quad(top)[0]) * 2.0);
        let tilted_area = f64::from(area(&tilted));
        let [up, down] = totals;
        eprintln!("up {up:?}\ndown {down:?}\nquad {quad_area}, tilted {tilted_area}");
        assert!(
            (down[0] / quad_area - 1.0).abs() < 0.01,
            "underside {}",
            down[0]
        );
        assert!(
            (up[0] / (quad_area + tilted_area) - 1.0).abs() < 0.02,
            "up {}",
            up[0]
        );
        let expected_up = |quad_value: f32, tilted_value: f32| {
            (quad_area * f64::from(quad_value) + tilted_area * f64::from(tilted_value))
                / (quad_area + tilted_area)
        };
        for k in 0..3 {
            assert!((down[1 + k] / down[0] - f64::from(Vec3::NEG_Y[k])).abs() < 1e-3);
            assert!((down[4 + k] / down[0] - f64::from(albedos[0][k])).abs() < 1e-3);
            let normal = expected_up(Vec3::Y[k], tilted_normal[k]);
            assert!((up[1 + k] / up[0] - normal).abs() < 0.01, "normal {k}");
            let albedo = expected_up(albedos[0][k], albedos[1][k]);
            assert!((up[4 + k] / up[0] - albedo).abs() < 0.01, "albedo {k}");
        }
    }
}
