//! `dir`: Differential Instant Radiosity (Knecht et al., "Reciprocal shading for mixed reality",
//! C&G 2012).
//!
//! Every light, VPL and surface point carries a flag, real or virtual, and the engine computes
//! two solutions in one pass: L_rv (the scene with the object) and L_r (the real scene alone);
//! real pixels get the camera image + L_rv − L_r.
//! - **Direct**: st_rv from the shadow map of every mesh (R^ρ; the depth of the nearer of the
//!   real-only and the virtual-only maps, i.e. min(st_r, st_v)), st_r from the real-only map
//!   (R^μ); the shared shading pass computes both.
//! - **VPLs** (`dir_rows`, `dir_alloc`, `dir_vpl`): importance-sampled from the maps' flux in
//!   three groups: R^ρ texels on real surfaces (light both solutions), on the virtual object
//!   (L_rv only), and "VPL3", R^μ texels the object hides from the light (L_r only: the real
//!   bleeding the object now blocks). VPLs are split between groups by flux share, the object's
//!   groups getting at least a quarter each, with intensity compensation; positions follow a
//!   fixed stratification of the flux CDF, so a static scene gives the same VPLs every frame.
//! - **Visibility** (`dir_ism`): imperfect shadow maps, a paraboloid depth map per VPL
//!   splatted from a fixed point cloud of the surfaces ([`points::surface_points`]), real and
//!   virtual points in separate layers (st_r, and st_rv = min(st_r, st_v)).
//! - **Gather** (`dir_gather`): per pixel, every VPL into both solutions.
//!
//! - **Environment light** ([`environment::environment_lights`]): `env_lights` directional
//!   lights importance-sampled from the scene's environment map, shadowed and bounced like the
//!   others.
//!
//! - **Second bounce** (`bounce`): the first bounce's VPLs are read back and continued on
//!   the CPU, one ray each (`second_bounce` = 1), to VPLs where their light lands, classed by
//!   the path flag (where the ray lands with the object and without it); they join the first
//!   bounce's in the ISM and gather passes. The light the object changes is carried by rays
//!   aimed at it (`object_rays`), the rest by the cosine rays; the light landing on the object
//!   itself by a grid of its box's faces lit by every first-bounce VPL (`object_cells`). With
//!   `third_bounce`, the second bounce's VPLs are continued the same way once more.

mod bounce;
mod environment;
mod points;

use bounce::{BounceGeometry, GpuVpl, ObjectBounce, second_bounce};
pub use environment::{EnvironmentLights, environment_lights};
pub use points::surface_points;

use std::sync::Arc;
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use relight_core::scene::Scene;
use serde_json::{Map, Value};
use wgpu::util::DeviceExt;

use crate::deferred::{Deferred, ExtraLights, KeptInputs, MapSizes, ShadeOptions};
use crate::engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::gbuffer::Targets;
use crate::gpu::{GpuContext, GpuError};
use crate::params::{ParamSpec, ParamsSchema};
use crate::roofline::{PassWork, Work};
use crate::shaders;
use crate::timer::timed_pass;

/// `gather_stride` by default: chosen by measured error (`docs/ALGORITHMS.md`, `dir`).
const GATHER_STRIDE_DEFAULT: u32 = 2;

/// `Dir` in `shaders/common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct DirUniform {
    dims: [u32; 4],
    size: [u32; 4],
    params: [f32; 4],
    sampling: [f32; 4],
    object_lo: [f32; 4],
    object_hi: [f32; 4],
}

/// Where in its stratum of the flux each VPL sits (`dir_vpl.wgsl`) on the frame at `index` in
/// the running mean of still frames ([`Deferred::accumulation_index`]): ½ on a frame shown
/// alone, as always; then ½ plus the base-5 van der Corput sequence (bases 2 and 3 jitter the
/// camera), so that the mean of k frames averages k sets of VPLs, each stratified, and the VPL
/// placement's own error falls with the picture's edges.
fn vpl_stratum(index: u32) -> f32 {
    (0.5 + crate::deferred::radical_inverse(index, 5)).fract()
}

/// The engine's settings (see [`Dir::schema`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DirSettings {
    pub rsm_size: u32,
    pub shadow_size: u32,
    pub vpl_count: u32,
    pub ism_size: u32,
    pub ism_points: u32,
    pub ism_bias: f32,
    /// At the object's pixels the ISM bias grows as 1/cos of a VPL's angle to the receiver, up
    /// to this factor (1: constant, as at real pixels).
    pub object_slope_bias: f32,
    pub clamp_distance: f32,
    pub shadow_bias: f32,
    pub env_lights: u32,
    /// Second-bounce rays as a share of `vpl_count` (`bounce`); 0: one bounce.
    pub second_bounce: f32,
    /// Third-bounce rays as a share of `vpl_count`, continuing the second bounce's VPLs as the
    /// second continues the first's (`bounce`); 0: two bounces.
    pub third_bounce: f32,
    /// Second-bounce rays into the object's cone, as a share of `vpl_count`, for the light the
    /// object changes (`bounce`); 0: the cosine rays carry it too.
    pub object_rays: f32,
    /// With object rays, the light landing on the object from this many cells per edge of
    /// each face of its box (`bounce`); 0: from where the rays land on it.
    pub object_cells: u32,
    /// A first-bounce VPL's 1/d² clamp as a share of the radius of the surface it stands for;
    /// 0: `clamp_distance` alone.
    pub footprint_clamp: f32,
    /// Each still frame averaged into the picture draws its VPLs anew (`vpl_stratum`); off,
    /// every frame has the same ones.
    pub vpls_per_frame: bool,
    /// The gather at every `gather_stride`-th pixel per axis (`crate::strided`).
    pub gather_stride: u32,
    /// A real surface takes a VPL within 6 half edges of it as the square of surface its clamp
    /// stands for (`quad_form_factor` in `shaders/common.wgsl`), a VPL on the object as a square
    /// of its box's face (`box_square_quad`), not as a clamped point.
    pub near_patches: bool,
}

impl DirSettings {
    /// Second-bounce rays a frame.
    fn bounce_rays(&self) -> u32 {
        (self.second_bounce * self.vpl_count as f32).round() as u32
    }

    /// Third-bounce rays a frame (none without a second bounce).
    fn third_bounce_rays(&self) -> u32 {
        if self.bounce_rays() == 0 {
            return 0;
        }
        (self.third_bounce * self.vpl_count as f32).round() as u32
    }

    /// Second-bounce rays into the object's cone a frame (none without a second bounce).
    fn object_rays(&self) -> u32 {
        if self.bounce_rays() == 0 {
            return 0;
        }
        (self.object_rays * self.vpl_count as f32).round() as u32
    }

    /// How the second bounce takes the light the object changes.
    fn object_bounce(&self) -> ObjectBounce {
        ObjectBounce {
            rays: self.object_rays() as usize,
            cells: self.object_cells,
            clamp_m: self.clamp_distance,
        }
    }

    /// Room for every VPL: the first bounce's, up to two per second- and third-bounce ray, and
    /// one per cell of the object's faces for each bounce past the first.
    fn vpl_capacity(&self) -> u32 {
        let object = 2 * self.object_rays() + self.object_bounce().face_cells() as u32;
        let third = self.third_bounce_rays();
        self.vpl_count
            + 2 * self.bounce_rays()
            + object
            + if third > 0 { 2 * third + object } else { 0 }
    }
}

impl Default for DirSettings {
    fn default() -> Self {
        Self {
            rsm_size: 512,
            shadow_size: crate::deferred::SHADOW_SIZE_DEFAULT,
            vpl_count: 256,
            ism_size: 96,
            ism_points: 16384,
            ism_bias: 6.0,
            object_slope_bias: 4.0,
            clamp_distance: 0.05,
            shadow_bias: 1.5,
            env_lights: 16,
            second_bounce: 1.0,
            third_bounce: 0.0,
            object_rays: 0.5,
            object_cells: 3,
            footprint_clamp: 1.0,
            near_patches: true,
            gather_stride: GATHER_STRIDE_DEFAULT,
            vpls_per_frame: true,
        }
    }
}

/// Buffers sized by the settings and the light count.
#[derive(Debug)]
struct VplBuffers {
    key: (u32, u32, u32, u32, u32),
    rows: wgpu::Buffer,
    summary: wgpu::Buffer,
    /// The first bounce's VPLs, then the second's.
    vpls: wgpu::Buffer,
    /// The first bounce's VPLs read back for the second.
    staging: wgpu::Buffer,
    ism: wgpu::Buffer,
}

#[derive(Debug)]
pub struct Dir {
    deferred: Deferred,
    settings: DirSettings,
    rows: wgpu::ComputePipeline,
    alloc: wgpu::ComputePipeline,
    vpl: wgpu::ComputePipeline,
    ism: wgpu::ComputePipeline,
    /// The gather's entries (`dir_gather.wgsl`): `main`, and with a `gather_stride` above 1
    /// `fill` and `resolve` after it.
    gather: [wgpu::ComputePipeline; 3],
    uniform: wgpu::Buffer,
    /// The surface points, the light-space geometry they were sampled from (its
    /// [`GpuScene::light_space_fingerprint`](crate::gpu_scene::GpuScene::light_space_fingerprint)),
    /// how many were asked for and how many came.
    points: Option<(u64, u32, u32, wgpu::Buffer)>,
    /// The scene and light count the environment lights were sampled for.
    environment: EnvironmentLights,
    buffers: Option<VplBuffers>,
    /// The light-space geometry the second bounce is traced through, and its fingerprint.
    bounce: Option<(u64, BounceGeometry)>,
    /// VPLs of both bounces in `buffers`, as the gather reads them.
    vpls_made: u32,
    /// What the VPLs and their imperfect shadow maps in `buffers` were made from: kept while
    /// the shadow maps, the geometry and the settings hold (the gather alone runs).
    lit: KeptInputs,
}

impl Dir {
    pub const NAME: &'static str = "dir";

    pub fn schema() -> ParamsSchema {
        let d = DirSettings::default();
        let int = |name, doc, min, max, default: u32| {
            ParamSpec::int(name, doc, min, max, i64::from(default))
        };
        let float = ParamSpec::float;
        ParamsSchema::new(vec![
            int(
                "rsm_size",
                "reflective-shadow-map edge per light face (VPLs are sampled from it; the shadows \
                 have their own map, `shadow_size`)",
                32,
                2048,
                d.rsm_size,
            ),
            crate::deferred::shadow_size_param(),
            int(
                "vpl_count",
                "VPLs per frame (the paper: 256)",
                1,
                1024,
                d.vpl_count,
            ),
            int(
                "ism_size",
                "imperfect-shadow-map edge per VPL, texels (the paper: 128; 96 by measurement, with ism_bias 6 the same bias in metres as 4 at 64)",
                8,
                256,
                d.ism_size,
            ),
            int(
                "ism_points",
                "surface points splatted into every imperfect shadow map",
                256,
                262_144,
                d.ism_points,
            ),
            float(
                "ism_bias",
                "imperfect-shadow-map depth bias in texel footprints (6: as much as 4 at ism_size 64, chosen there by measurement)",
                0.0,
                8.0,
                d.ism_bias,
            ),
            float(
                "object_slope_bias",
                "at the object's pixels the imperfect-shadow-map bias grows as 1/cos of a VPL's angle to the receiver, up to this factor, so its faces seen from a VPL at a grazing angle do not shadow themselves (1: constant, as at real pixels, where a larger bias lets the contact shadows leak)",
                1.0,
                16.0,
                d.object_slope_bias,
            ),
            float(
                "clamp_distance",
                "VPL–receiver distance below which the 1/d² falloff is clamped (m)",
                0.0,
                1.0,
                d.clamp_distance,
            ),
            float(
                "shadow_bias",
                "shadow-map depth bias in texel footprints",
                0.0,
                8.0,
                d.shadow_bias,
            ),
            int(
                "env_lights",
                "directional lights sampled from the environment map (0: ignore it); each costs a shadow map",
                0,
                48,
                d.env_lights,
            ),
            float(
                "second_bounce",
                "second-bounce rays as a share of vpl_count, each making a VPL where the first bounce's light lands (0: one bounce, as the paper's single-bounce setting)",
                0.0,
                2.0,
                d.second_bounce,
            ),
            float(
                "third_bounce",
                "third-bounce rays as a share of vpl_count, continuing the second bounce's VPLs as the second continues the first's, with the same object rays and face cells (0: two bounces)",
                0.0,
                2.0,
                d.third_bounce,
            ),
            float(
                "object_rays",
                "second-bounce rays aimed into the object's bounding cone, as a share of vpl_count, for the light the object changes (the cosine rays then carry only the rest; 0: they carry it all, and which few meet the object is left to chance)",
                0.0,
                1.0,
                d.object_rays,
            ),
            int(
                "object_cells",
                "with object rays, the second bounce's light on the object from this many points per edge of each face of its bounding box, lit by every first-bounce VPL (0: from where the object rays land on it, left to chance)",
                0,
                16,
                d.object_cells,
            ),
            float(
                "footprint_clamp",
                "a first-bounce VPL's 1/d² clamp as a share of the radius of the surface it stands for (0: clamp_distance alone)",
                0.0,
                4.0,
                d.footprint_clamp,
            ),
            ParamSpec::choice(
                "near_vpls",
                "`patches` (default, the lower error measured on every bench scene and live): a real surface takes a VPL near it as the square of surface its clamp's disc stands for, by Lambert's contour integral, a VPL on the object as a square of its box's face; `points` (as the paper; the object's pixels always do): a VPL is a point whose 1/d² is clamped",
                vec!["patches", "points"],
            ),
            ParamSpec::choice(
                "vpl_placement",
                "`per_frame` (default, the lower converged error measured): each still frame averaged into the picture (`accumulate`) places its VPLs at another point of their strata of the flux, so the picture averages as many VPL sets; `fixed`: the same VPLs every frame",
                vec!["per_frame", "fixed"],
            ),
            int(
                "gather_stride",
                "the VPL gather at every n-th pixel per axis; the diffuse pixels between take their alike neighbours' irradiance (1: every pixel, as the paper)",
                1,
                4,
                d.gather_stride,
            ),
            crate::deferred::accumulate_param(),
            crate::deferred::indirect_param(),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let pipeline = |label, source| shaders::compute_pipeline(&ctx.device, label, source);
        Ok(Self {
            rows: pipeline("dir rows", shaders::DIR_ROWS),
            alloc: pipeline("dir alloc", shaders::DIR_ALLOC),
            vpl: pipeline("dir vpl", shaders::DIR_VPL),
            ism: pipeline("dir ism", shaders::DIR_ISM),
            gather: ["main", "fill", "resolve"].map(|entry| {
                shaders::compute_pipeline_at(&ctx.device, "dir gather", shaders::DIR_GATHER, entry)
            }),
            uniform: shaders::params_buffer(&ctx.device, "dir", size_of::<DirUniform>()),
            deferred: Deferred::sampling_the_environment(ctx),
            settings: DirSettings::default(),
            points: None,
            environment: EnvironmentLights::default(),
            buffers: None,
            bounce: None,
            vpls_made: 0,
            lit: KeptInputs::default(),
        })
    }

    /// The point cloud of `scene`'s light-space geometry, whose hash is `geometry` (sampled
    /// again when that or the count changes).
    fn points(&mut self, scene: &Scene, geometry: u64) -> u32 {
        let count = self.settings.ism_points;
        if !self
            .points
            .as_ref()
            .is_some_and(|(g, c, _, _)| *g == geometry && *c == count)
        {
            // The light-space geometry, as the shadow maps draw it: the real scene's proxy
            // where it has one.
            let mut points = match &scene.shadow_proxy {
                Some(proxy) => surface_points(
                    std::iter::once(&**proxy).chain(scene.meshes.iter().filter(|m| m.is_virtual)),
                    count,
                ),
                None => surface_points(scene.meshes.iter(), count),
            };
            let used = points.len() as u32;
            if points.is_empty() {
                points.push([0.0; 4]);
            }
            let buffer =
                self.deferred
                    .ctx()
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("dir points"),
                        contents: bytemuck::cast_slice(&points),
                        usage: wgpu::BufferUsages::STORAGE,
                    });
            self.points = Some((geometry, count, used, buffer));
        }
        self.points.as_ref().map_or(0, |(_, _, used, _)| *used)
    }

    fn buffers(&mut self, layers: u32) -> Result<&VplBuffers, EngineError> {
        let s = self.settings;
        let capacity = s.vpl_capacity();
        let key = (s.rsm_size, s.vpl_count, s.ism_size, layers, capacity);
        let ctx = self.deferred.ctx().clone();
        let ism = u64::from(capacity) * 2 * u64::from(s.ism_size).pow(2) * 4;
        ctx.require(
            "max_storage_buffer_binding_size",
            ism,
            "vpl_count, second_bounce, third_bounce or ism_size",
        )?;
        ctx.require(
            "max_compute_workgroups_per_dimension",
            u64::from(capacity),
            "vpl_count, second_bounce or third_bounce",
        )?;
        if self.buffers.as_ref().is_none_or(|b| b.key != key) {
            let buffer = |label, size: u64, usage| {
                ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: size.max(16),
                    usage,
                    mapped_at_creation: false,
                })
            };
            use wgpu::BufferUsages as U;
            self.lit.forget();
            self.buffers = Some(VplBuffers {
                key,
                rows: buffer(
                    "dir rows",
                    u64::from(layers * 3 * s.rsm_size) * 4,
                    U::STORAGE,
                ),
                summary: buffer("dir summary", 32 + u64::from(layers) * 16, U::STORAGE),
                vpls: buffer(
                    "dir vpls",
                    u64::from(capacity) * VPL_BYTES,
                    U::STORAGE | U::COPY_SRC | U::COPY_DST,
                ),
                staging: buffer(
                    "dir vpls read back",
                    u64::from(s.vpl_count) * VPL_BYTES,
                    U::MAP_READ | U::COPY_DST,
                ),
                ism: buffer("dir ism", ism, U::STORAGE | U::COPY_DST),
            });
        }
        self.buffers.as_ref().ok_or(EngineError::NotPrepared)
    }
}

/// Bytes of one VPL (`Vpl` in `shaders/common.wgsl`).
const VPL_BYTES: u64 = size_of::<GpuVpl>() as u64;

/// `VPLS_PER_INVOCATION` in `dir_ism.wgsl`.
const ISM_VPLS_PER_INVOCATION: u32 = 8;

/// Bytes of `vpls` VPLs' imperfect shadow maps (one f32 depth a texel).
fn ism_size_bytes(s: &DirSettings, vpls: u32) -> f64 {
    f64::from(vpls) * f64::from(s.ism_size).powi(2) * 4.0
}

impl Engine for Dir {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, frame: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let s = self.settings;
        if let Some(scene) = &frame.scene
            && self
                .environment
                .update(scene.environment.as_ref(), s.env_lights)
        {
            self.deferred
                .set_extra_lights(self.environment.lights().to_vec(), ExtraLights::Full);
        }
        let sizes = MapSizes::with_rsm(s.shadow_size, s.rsm_size);
        let Some((width, height)) = self.deferred.prepare(Self::NAME, frame, out, sizes)? else {
            return Ok(());
        };
        let started = Instant::now();
        let ctx = self.deferred.ctx().clone();
        let layers = self.deferred.faces().len() as u32;
        let scene = frame.scene.clone().ok_or(EngineError::NotPrepared)?;
        let geometry = self
            .deferred
            .scene()
            .ok_or(EngineError::NotPrepared)?
            .light_space_fingerprint();
        let point_count = self.points(&scene, geometry);
        let mut bounce_ms = 0.0;
        if s.bounce_rays() > 0 && self.bounce.as_ref().is_none_or(|(g, _)| *g != geometry) {
            let built = Instant::now();
            self.bounce = Some((geometry, BounceGeometry::new(&scene)));
            bounce_ms += built.elapsed().as_secs_f64() * 1e3;
        }
        if layers > 0 {
            self.buffers(layers)?;
            let (object_lo, object_hi) = scene.virtual_bounds().unwrap_or_default();
            let mut uniform = DirUniform {
                dims: [s.vpl_count, s.rsm_size, layers, s.ism_size],
                size: [width, height, point_count, self.vpls_made],
                params: [
                    s.clamp_distance,
                    s.ism_bias,
                    s.second_bounce,
                    s.footprint_clamp,
                ],
                sampling: [
                    vpl_stratum(if s.vpls_per_frame {
                        self.deferred.accumulation_index()
                    } else {
                        0
                    }),
                    s.gather_stride as f32,
                    if s.near_patches { 1.0 } else { 0.0 },
                    s.object_rays,
                ],
                object_lo: object_lo.extend(s.object_slope_bias).to_array(),
                object_hi: object_hi.extend(0.0).to_array(),
            };
            ctx.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
            let inputs = KeptInputs::hash_of(&[
                bytemuck::bytes_of(&uniform.dims),
                bytemuck::bytes_of(&uniform.params),
                bytemuck::bytes_of(&uniform.sampling),
                bytemuck::bytes_of(&uniform.object_lo),
                bytemuck::bytes_of(&uniform.object_hi),
                &point_count.to_le_bytes(),
                &s.object_cells.to_le_bytes(),
                &s.third_bounce.to_le_bytes(),
                &geometry.to_le_bytes(),
                &self.deferred.light_inputs().to_le_bytes(),
            ]);
            let relight = !self.lit.holds(inputs);
            let mut timer = self.deferred.lend_timer();
            let (
                Some(b),
                Some((lights, faces, rsm_rho, rsm_mu)),
                Some((gb_rho, _, indirect)),
                Some(gpu_scene),
                Some((_, _, _, points)),
            ) = (
                self.buffers.as_ref(),
                self.deferred.light_buffers(),
                self.deferred.frame_buffers(),
                self.deferred.scene(),
                self.points.as_ref(),
            )
            else {
                return Err(EngineError::NotPrepared);
            };
            let group = |pipeline, label, resources: &[wgpu::BindingResource]| {
                shaders::pipeline_bind_group(&ctx.device, pipeline, label, resources)
            };
            let rsm_views = Targets::rsm_views(rsm_rho, rsm_mu);
            let mut sampling = vec![
                self.uniform.as_entire_binding(),
                lights.as_entire_binding(),
                faces.as_entire_binding(),
            ];
            sampling.extend(rsm_views.iter().map(wgpu::BindingResource::TextureView));
            let mut rows_resources = sampling.clone();
            rows_resources.push(b.rows.as_entire_binding());
            let rows_group = group(&self.rows, "dir rows", &rows_resources);
            let alloc_group = group(
                &self.alloc,
                "dir alloc",
                &[
                    self.uniform.as_entire_binding(),
                    b.rows.as_entire_binding(),
                    b.summary.as_entire_binding(),
                ],
            );
            let mut vpl_resources = sampling;
            vpl_resources.extend([&b.rows, &b.summary, &b.vpls].map(|b| b.as_entire_binding()));
            let vpl_group = group(&self.vpl, "dir vpl", &vpl_resources);
            let ism_group = group(
                &self.ism,
                "dir ism",
                &[
                    self.uniform.as_entire_binding(),
                    b.vpls.as_entire_binding(),
                    points.as_entire_binding(),
                    b.ism.as_entire_binding(),
                ],
            );
            let gb_views = [
                Targets::view(&gb_rho.position),
                Targets::view(&gb_rho.normal),
                Targets::view(&gb_rho.albedo),
            ];
            let mut gather_resources = vec![
                self.uniform.as_entire_binding(),
                self.deferred.camera_buffer().as_entire_binding(),
                gpu_scene.materials.as_entire_binding(),
            ];
            gather_resources.extend(gb_views.iter().map(wgpu::BindingResource::TextureView));
            gather_resources.extend([&b.vpls, &b.ism, indirect].map(|b| b.as_entire_binding()));
            let [gather, fill, resolve] = &self.gather;
            let gather_groups = [
                group(gather, "dir gather", &gather_resources),
                group(fill, "dir gather fill", &gather_resources),
                // `resolve` reads the uniform, the albedo and the light alone.
                shaders::pipeline_bind_group_of(
                    &ctx.device,
                    resolve,
                    "dir gather resolve",
                    &gather_resources,
                    &[0, 5, 8],
                ),
            ];

            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("dir") });
            if relight {
                out.work.push(PassWork {
                    pass: "vpls",
                    // Both maps' texels read for the importance rows (32 bytes, about 30
                    // operations each); each VPL written (64 bytes).
                    work: Work::new(2.0 * 32.0, 60.0)
                        .times(f64::from(layers) * f64::from(s.rsm_size).powi(2))
                        + Work::new(64.0, 100.0).times(f64::from(s.vpl_count)),
                });
                encoder.clear_buffer(&b.ism, 0, None);
                {
                    let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.vpls");
                    pass.set_pipeline(&self.rows);
                    pass.set_bind_group(0, &rows_group, &[]);
                    pass.dispatch_workgroups(s.rsm_size.div_ceil(64), layers, 1);
                    pass.set_pipeline(&self.alloc);
                    pass.set_bind_group(0, &alloc_group, &[]);
                    pass.dispatch_workgroups(1, 1, 1);
                    pass.set_pipeline(&self.vpl);
                    pass.set_bind_group(0, &vpl_group, &[]);
                    pass.dispatch_workgroups(s.vpl_count.div_ceil(64), 1, 1);
                }
                self.vpls_made = s.vpl_count;
                if let Some((_, bounce_geometry)) = &self.bounce
                    && s.bounce_rays() > 0
                {
                    // The first bounce's VPLs are read back and continued on the CPU.
                    ctx.queue.submit([encoder.finish()]);
                    encoder = ctx
                        .device
                        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                            label: Some("dir"),
                        });
                    let first: Vec<GpuVpl> = ctx.read_back(
                        &b.vpls,
                        &b.staging,
                        u64::from(s.vpl_count) * VPL_BYTES,
                        bytemuck::pod_collect_to_vec,
                    )?;
                    let traced = Instant::now();
                    let mut second = second_bounce(
                        bounce_geometry,
                        &first,
                        s.bounce_rays() as usize,
                        s.object_bounce(),
                    );
                    if s.third_bounce_rays() > 0 {
                        let third = second_bounce(
                            bounce_geometry,
                            &second,
                            s.third_bounce_rays() as usize,
                            s.object_bounce(),
                        );
                        second.extend(third);
                    }
                    ctx.queue.write_buffer(
                        &b.vpls,
                        u64::from(s.vpl_count) * VPL_BYTES,
                        bytemuck::cast_slice(&second),
                    );
                    self.vpls_made = s.vpl_count + second.len() as u32;
                    bounce_ms += traced.elapsed().as_secs_f64() * 1e3;
                }
                uniform.size[3] = self.vpls_made;
                ctx.queue
                    .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
                out.work.push(PassWork {
                    pass: "ism",
                    // Every surface point into every VPL's paraboloid (about 40
                    // operations); the points read once, the maps written once.
                    work: Work::new(0.0, 40.0)
                        .times(f64::from(point_count) * f64::from(self.vpls_made))
                        + Work::new(16.0, 0.0).times(f64::from(point_count))
                        + Work::new(ism_size_bytes(&s, self.vpls_made), 0.0),
                });
                let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.ism");
                if point_count > 0 && self.vpls_made > 0 {
                    pass.set_pipeline(&self.ism);
                    pass.set_bind_group(0, &ism_group, &[]);
                    pass.dispatch_workgroups(
                        point_count.div_ceil(64),
                        self.vpls_made.div_ceil(ISM_VPLS_PER_INVOCATION),
                        1,
                    );
                }
            }
            out.work.push(PassWork {
                pass: "gather",
                // Per pixel the G-buffer read and the result written, and per gathered pixel
                // (every `gather_stride`-th per axis) and VPL about 80 operations (its geometry
                // term, BRDF and one ISM lookup); the VPLs and their maps read once.
                work: Work::new(32.0 + 16.0, 0.0).times(f64::from(width) * f64::from(height))
                    + Work::new(0.0, 80.0).times(
                        f64::from(width.div_ceil(s.gather_stride))
                            * f64::from(height.div_ceil(s.gather_stride))
                            * f64::from(self.vpls_made),
                    )
                    + Work::new(
                        64.0 * f64::from(self.vpls_made) + ism_size_bytes(&s, self.vpls_made),
                        0.0,
                    ),
            });
            {
                let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.gather");
                crate::strided::dispatch(
                    &mut pass,
                    &self.gather,
                    &gather_groups,
                    (width, height),
                    s.gather_stride,
                );
            }
            ctx.queue.submit([encoder.finish()]);
            ctx.check()?;
            self.lit.record(inputs);
            self.deferred.return_timer(timer);
        }
        out.timings.push(PassTiming {
            pass: "vpls",
            ms: started.elapsed().as_secs_f64() * 1e3,
        });
        if bounce_ms > 0.0 {
            // The CPU's part of the second bounce: the geometry (when it changed) and the rays.
            out.timings.push(PassTiming {
                pass: "bounce",
                ms: bounce_ms,
            });
        }
        self.deferred.finish(
            ShadeOptions {
                shadow_bias_texels: s.shadow_bias,
                direct_delta: true,
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
        self.settings = DirSettings {
            rsm_size: int("rsm_size"),
            shadow_size: int("shadow_size"),
            vpl_count: int("vpl_count"),
            ism_size: int("ism_size"),
            ism_points: int("ism_points"),
            ism_bias: float("ism_bias"),
            object_slope_bias: float("object_slope_bias"),
            clamp_distance: float("clamp_distance"),
            shadow_bias: float("shadow_bias"),
            env_lights: int("env_lights"),
            second_bounce: float("second_bounce"),
            third_bounce: float("third_bounce"),
            object_rays: float("object_rays"),
            object_cells: int("object_cells"),
            footprint_clamp: float("footprint_clamp"),
            gather_stride: int("gather_stride"),
            vpls_per_frame: schema.choice(params, "vpl_placement") == "per_frame",
            near_patches: schema.choice(params, "near_vpls") == "patches",
        };
        self.deferred.set_shared_params(&schema, params);
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use crate::shaders;

    /// `box_square_quad`'s contour integral per unit of its area (`shaders/common.wgsl`)
    /// against the integral over the rectangle it should become, in f64 over 400² pieces: on
    /// desk_box's box, a square at the foot of its front face moved up onto the face and seen
    /// from the floor in front, head on, and from inside the box (nothing); one wider than the
    /// face cut to it; one on a side face, moved in from the back edge, cut by its receiver's
    /// horizon; one on the top with a tilted normal.
    #[test]
    fn an_object_s_square_stays_on_its_box() {
        let (lo, hi) = (DVec3::new(-0.15, 0.0, -0.25), DVec3::new(0.15, 0.3, 0.05));
        struct Case {
            position: DVec3,
            normal: DVec3,
            half: f64,
            p: DVec3,
            n: DVec3,
            /// The rectangle's corner, its two edges and the face's outward normal.
            rectangle: (DVec3, DVec3, DVec3, DVec3),
        }
        let front = |p, n| Case {
            position: DVec3::new(0.0, 0.02, 0.05),
            normal: DVec3::Z,
            half: 0.05,
            p,
            n,
            rectangle: (
                DVec3::new(-0.05, 0.0, 0.05),
                DVec3::new(0.1, 0.0, 0.0),
                DVec3::new(0.0, 0.1, 0.0),
                DVec3::Z,
            ),
        };
        let cases = [
            front(DVec3::new(0.0, 0.0, 0.06), DVec3::Y),
            front(DVec3::new(0.02, 0.05, 0.2), DVec3::NEG_Z),
            front(DVec3::new(0.0, 0.05, 0.0), DVec3::Z),
            Case {
                position: DVec3::new(0.14, 0.15, 0.05),
                normal: DVec3::Z,
                half: 0.2,
                p: DVec3::new(0.3, 0.1, 0.3),
                n: DVec3::new(-1.0, 0.0, -1.0),
                rectangle: (
                    DVec3::new(-0.15, 0.0, 0.05),
                    DVec3::new(0.3, 0.0, 0.0),
                    DVec3::new(0.0, 0.3, 0.0),
                    DVec3::Z,
                ),
            },
            Case {
                position: DVec3::new(-0.15, 0.1, -0.2),
                normal: DVec3::NEG_X,
                half: 0.06,
                p: DVec3::new(-0.25, 0.1, -0.2),
                n: DVec3::new(0.3, -1.0, 0.0),
                rectangle: (
                    DVec3::new(-0.15, 0.04, -0.25),
                    DVec3::new(0.0, 0.12, 0.0),
                    DVec3::new(0.0, 0.0, 0.12),
                    DVec3::NEG_X,
                ),
            },
            Case {
                position: DVec3::new(0.1, 0.3, 0.0),
                normal: DVec3::new(0.1, 1.0, 0.0),
                half: 0.05,
                p: DVec3::new(0.2, 0.5, 0.1),
                n: DVec3::new(-0.5, -1.0, -0.5),
                rectangle: (
                    DVec3::new(0.05, 0.3, -0.05),
                    DVec3::new(0.1, 0.0, 0.0),
                    DVec3::new(0.0, 0.0, 0.1),
                    DVec3::Y,
                ),
            },
        ];
        let data: Vec<f32> = [lo.extend(0.0), hi.extend(0.0)]
            .iter()
            .flat_map(|v| v.to_array().map(|x| x as f32))
            .collect();
        let queries: Vec<f32> = cases
            .iter()
            .flat_map(|c| {
                let (normal, n) = (c.normal.normalize(), c.n.normalize());
                [
                    [c.position.x, c.position.y, c.position.z, c.half],
                    [normal.x, normal.y, normal.z, 0.0],
                    [c.p.x, c.p.y, c.p.z, 0.0],
                    [n.x, n.y, n.z, 0.0],
                ]
                .concat()
                .into_iter()
                .map(|v| v as f32)
            })
            .collect();
        let gpu = shaders::evaluate(
            "@group(0) @binding(0) var<storage, read> bounds: array<vec4<f32>, 2>;
            @group(0) @binding(1) var<storage, read> queries: array<vec4<f32>>;
            @group(0) @binding(2) var<storage, read_write> result: array<f32>;
            @compute @workgroup_size(1)
            fn main(@builtin(global_invocation_id) id: vec3<u32>) {
                let at = queries[4u * id.x];
                let q = box_square_quad(at.xyz, queries[4u * id.x + 1u].xyz, at.w,
                    bounds[0].xyz, bounds[1].xyz, queries[4u * id.x + 2u].xyz);
                result[id.x] = quad_form_factor(q.a, q.b, q.c, q.d, queries[4u * id.x + 3u].xyz)
                    / q.area;
            }",
            &data,
            &queries,
            cases.len(),
        );
        for (c, gpu) in cases.iter().zip(&gpu) {
            let n = c.n.normalize();
            let (_, t, b, _) = c.rectangle;
            let expected = shaders::rectangle_form_factor((c.p, n), c.rectangle, 400)
                / (t.length() * b.length());
            eprintln!(
                "at {} facing {n}: {gpu:.4}, the integral {expected:.4}",
                c.p
            );
            assert!(
                (f64::from(*gpu) - expected).abs() <= 0.01 * expected + 1e-3,
                "at {} facing {n}: {gpu} against {expected}",
                c.p
            );
        }
        assert!(gpu[0] > 1.0 && gpu[2] == 0.0, "{gpu:?}");
    }
}
