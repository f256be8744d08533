//! The passes every GPU engine shares, per frame: upload the scene (when it changed), the camera,
//! the lights and the background; rasterise the ρ and μ G-buffers and the R^ρ and R^μ reflective
//! shadow maps; and, after the engine's own passes have written its indirect term, shade and
//! composite (`shaders/shade.wgsl`) and read Δ and the composite back into the [`RelitFrame`].

use std::hash::{BuildHasher, DefaultHasher, Hash, Hasher};
use std::sync::Arc;
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec2, Vec3, Vec4};
use relight_core::light::Light;
use relight_core::scene::{Scene, SceneCamera};
use relight_core::{Image, PixelFormat, PixelRect};
use serde_json::{Map, Value};
use wgpu::util::DeviceExt;

use crate::change::{self, camera_still};
use crate::engine::{EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::gbuffer::{GBufferPass, LayerRedraw, RealWithin, RsmPass, Targets};
use crate::gpu::GpuContext;
use crate::gpu_scene::{
    FACE_ORTHOGRAPHIC, GpuCamera, GpuFace, GpuLight, GpuScene, camera_uniform, is_shadowed,
    light_faces,
};
use crate::params::{ParamSpec, ParamsSchema};
use crate::roofline::{PassWork, Work};
use crate::shaders;
use crate::shadow_reach;
use crate::timer::{GpuTimer, timed_pass};

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ShadeParams {
    size: [u32; 4],
    virtual_lo: [f32; 4],
    virtual_hi: [f32; 4],
    options: [f32; 4],
    region: [u32; 4],
    terms: [f32; 4],
}

/// What an engine's result derived from the scene and its lights alone was computed from, so
/// that it is kept, not recomputed, while that holds (a still scene: the camera may move).
#[derive(Debug, Default)]
pub struct KeptInputs(Option<u64>);

impl KeptInputs {
    /// The inputs as one hash: `parts` in order. foldhash with a fixed seed, not SipHash: a
    /// live depth mesh's vertex buffer (3.6 MB at 320 × 240) is hashed every frame, 1.1 ms
    /// with SipHash against 0.25 ms on the 2-core machine; nothing here is adversarial.
    pub fn hash_of(parts: &[&[u8]]) -> u64 {
        let mut hasher = foldhash::fast::FixedState::with_seed(0).build_hasher();
        for part in parts {
            part.hash(&mut hasher);
        }
        hasher.finish()
    }

    /// Whether the result held was computed from `inputs`.
    pub fn holds(&self, inputs: u64) -> bool {
        self.0 == Some(inputs)
    }

    /// The result now held was computed from `inputs` (once its work is submitted).
    pub fn record(&mut self, inputs: u64) {
        self.0 = Some(inputs);
    }

    /// The result is gone (its buffers were made anew).
    pub fn forget(&mut self) {
        self.0 = None;
    }
}

/// The shadow maps' edge by default ([`shadow_size_param`]).
pub const SHADOW_SIZE_DEFAULT: u32 = 512;

/// The `shadow_size` parameter of the VPL engines, whose reflective shadow maps (`rsm_size`)
/// are drawn apart from the shadow maps: VPLs need far fewer texels than a shadow's edge does.
pub fn shadow_size_param() -> ParamSpec {
    ParamSpec::int(
        "shadow_size",
        "shadow-map edge in texels, per light face (depth alone: the direct light's shadows)",
        64,
        4096,
        i64::from(SHADOW_SIZE_DEFAULT),
    )
}

/// Frames averaged over sub-pixel offsets by default ([`accumulate_param`]).
const ACCUMULATE_DEFAULT: i64 = 32;

/// The `accumulate` parameter every GPU engine takes: how many frames, each drawn at another
/// sub-pixel offset, are averaged while the picture's inputs hold still.
pub fn accumulate_param() -> ParamSpec {
    ParamSpec::int(
        "accumulate",
        "frames averaged over sub-pixel offsets while the scene, camera and lights hold still, \
         so edges converge to the pixel's area (1: off)",
        1,
        256,
        ACCUMULATE_DEFAULT,
    )
}

/// Edges converged over frames (issue 18's pixel-area truth): every engine samples a pixel at
/// one point, where a camera integrates the pixel's area, and at a shadow or silhouette edge
/// the two differ by up to the whole step. While the inputs of the picture hold, frame k is
/// drawn at the k-th point of the Halton (2, 3) sequence within the pixel and averaged into a
/// running mean; the first frame after a change is drawn at the centre and shown alone, exactly
/// as without accumulation, and after `frames` frames the mean is kept as it is and nothing
/// more is drawn ([`Deferred::prepare`] finishes such a frame itself). The inputs are what
/// `pt` keeps its means by ([`change`]): the scene's geometry (a live depth surface by its
/// revision, which the temporal merge advances only when it resets, so sensor noise on a held
/// surface is averaged, not a change), materials, lights and environment; the camera while
/// [`change::camera_still`] (the held pose is drawn, so a tracked camera's jitter is no change
/// either); the image and map sizes. Not the background, which the composite takes fresh
/// every frame.
#[derive(Debug)]
struct Accumulation {
    frames: u32,
    /// The inputs the running mean was drawn from.
    key: Option<u64>,
    /// Frames since those inputs last changed.
    still: u32,
}

/// This frame's part in the running mean.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sample {
    /// Where in the pixel the frame samples, from its centre.
    offset_px: Vec2,
    /// The frame's weight in the mean: 1 shows it alone, 0 keeps the mean.
    weight: f32,
    /// Whether the mean is written (off without accumulation and once it is complete).
    write: bool,
    /// The frame's place in the mean (0: the first, or shown alone; once the mean is complete,
    /// the last frame's, so that what an engine drew for it is kept).
    index: u32,
}

impl Sample {
    /// The mean is complete and this frame keeps it: nothing need be drawn.
    fn holds(&self) -> bool {
        self.weight == 0.0
    }

    /// A frame shown alone: at the centre, no mean read or written.
    const ALONE: Self = Self {
        offset_px: Vec2::ZERO,
        weight: 1.0,
        write: false,
        index: 0,
    };
}

impl Accumulation {
    fn new() -> Self {
        Self {
            frames: ACCUMULATE_DEFAULT as u32,
            key: None,
            still: 0,
        }
    }

    fn set_frames(&mut self, frames: u32) {
        self.frames = frames.max(1);
        self.key = None;
    }

    /// The sample of a frame drawn from `key`'s inputs.
    fn advance(&mut self, key: u64) -> Sample {
        if self.key == Some(key) {
            self.still = self.still.saturating_add(1);
        } else {
            self.key = Some(key);
            self.still = 0;
        }
        match self.still {
            _ if self.frames <= 1 => Sample::ALONE,
            still if still >= self.frames => Sample {
                offset_px: Vec2::ZERO,
                weight: 0.0,
                write: false,
                index: self.frames - 1,
            },
            still => Sample {
                offset_px: halton_offset(still),
                weight: 1.0 / (still + 1) as f32,
                write: true,
                index: still,
            },
        }
    }
}

/// Point `index` of the Halton (2, 3) sequence as an offset from the pixel's centre; point 0
/// is the centre itself.
fn halton_offset(index: u32) -> Vec2 {
    if index == 0 {
        return Vec2::ZERO;
    }
    Vec2::new(radical_inverse(index, 2), radical_inverse(index, 3)) - 0.5
}

/// `index`'s digits in `base` mirrored about the point: the van der Corput sequence, whose
/// first n points spread evenly over [0, 1).
pub(crate) fn radical_inverse(index: u32, base: u32) -> f32 {
    let (mut i, mut f, mut r) = (index, 1.0f32, 0.0f32);
    while i > 0 {
        f /= base as f32;
        r += f * (i % base) as f32;
        i /= base;
    }
    r
}

/// How the final pass treats the direct light on real pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadeOptions {
    /// Shadow-map bias in texels.
    pub shadow_bias_texels: f32,
    /// Add the shadow-mapped direct Δ on real pixels (the differential baseline); engines that
    /// carry shadows as antiradiance in their indirect term turn it off.
    pub direct_delta: bool,
}

/// What the lights an engine adds to the scene's own do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExtraLights {
    /// Shaded, shadowed and given reflective shadow maps like the scene's own.
    Full,
    /// Stand-ins for part of the environment whose unshadowed light the engine adds itself:
    /// they light real surfaces in both solutions (so Δ holds only the shadows the virtual
    /// object casts in them) and leave virtual pixels' direct light alone
    /// (`LIGHT_SHADOW_ONLY` in `shaders/common.wgsl`).
    ShadowOnly,
}

/// Per-size resources: G-buffers, background, outputs and their staging copies.
#[derive(Debug)]
struct FrameResources {
    width: u32,
    height: u32,
    gb_rho: Targets,
    gb_mu: Targets,
    background: wgpu::Texture,
    indirect: wgpu::Buffer,
    delta: wgpu::Buffer,
    composite: wgpu::Buffer,
    /// Δ's packed f16 texels, then the composite: both read back in one copy.
    staging: wgpu::Buffer,
    /// The running mean ([`Accumulation`]), two vec4 a pixel: the overlay (L^ρ on the
    /// object's samples, Δ on real ones) with the object's coverage, and Δ.
    history: wgpu::Buffer,
}

/// The maps a frame's lights draw, edge in texels per light face.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct MapSizes {
    /// The shadow maps, depth alone: every engine's direct light is shadowed with them.
    pub shadow: u32,
    /// The reflective shadow maps a VPL engine samples its VPLs from (position, normal,
    /// albedo); `None` for an engine that uses the maps for visibility alone.
    pub rsm: Option<u32>,
    /// Whether `rsm` is the edge for up to [`RSM_BUDGET_FACES`] directional faces, shrunk
    /// for more ([`MapSizes::for_faces`]): an engine that injects every texel as a VPL.
    pub rsm_budget: bool,
}

/// A volume engine's VPL maps for directional lights alone hold at most as many texels in
/// all as this many faces at its `rsm_size`.
pub const RSM_BUDGET_FACES: u32 = 6;

impl MapSizes {
    /// Shadow maps and a VPL engine's reflective shadow maps, `rsm`² texels a face.
    pub fn with_rsm(shadow: u32, rsm: u32) -> Self {
        Self {
            shadow,
            rsm: Some(rsm),
            rsm_budget: false,
        }
    }

    /// Shadow maps and the reflective shadow maps of an engine that injects every texel into
    /// a volume (`dlpv`, `dvct`), `rsm`² a face, or fewer where the faces are many directional
    /// lights ([`MapSizes::for_faces`]).
    pub fn with_injected_rsm(shadow: u32, rsm: u32) -> Self {
        Self {
            rsm_budget: true,
            ..Self::with_rsm(shadow, rsm)
        }
    }

    /// Shadow maps alone (`differential`, `ibl`).
    pub fn shadows(size: u32) -> Self {
        Self {
            shadow: size,
            rsm: None,
            rsm_budget: false,
        }
    }

    /// The sizes drawn for `faces`. With [`MapSizes::rsm_budget`], when every face is a
    /// directional light's and there are more than [`RSM_BUDGET_FACES`] of them (an
    /// environment cut into 24 lights), the VPL maps' edge is scaled by √(6 / faces), down to
    /// a multiple of 8, so their texels together stay those of six faces.
    ///
    /// Why: a point light's six faces split the scene between them, so a surface takes the
    /// VPLs of one face; each of n directional lights' orthographic maps spans the whole
    /// scene, so a surface takes the VPLs of all n, each with a 1/n share of the light.
    /// Injection costs every texel, while the light and the cells that receive it do not grow
    /// with n. On window_env (24 faces, 160 × 120), 96² instead of 192² left `dlpv`'s Δ and
    /// object errors within 0.002 for 43 % of its frame, and 16 faces of 72² instead of 128² `dvct`'s
    /// (`docs/ALGORITHMS.md`, "Environment lights"). The maps are one texture array, so with a
    /// point or spot light among the faces, whose VPLs near the object need the full edge
    /// (desk_box's bleeding at 128² rather than 192²: 0.65 → 0.85), nothing is scaled.
    pub fn for_faces(self, faces: &[GpuFace]) -> Self {
        let n = faces.len() as u32;
        let directional = faces.iter().all(|f| f.light[1] == FACE_ORTHOGRAPHIC);
        let rsm = match self.rsm {
            Some(size) if self.rsm_budget && directional && n > RSM_BUDGET_FACES => {
                let scaled = f64::from(size) * (f64::from(RSM_BUDGET_FACES) / f64::from(n)).sqrt();
                Some(((scaled as u32) / 8 * 8).clamp(8.min(size), size))
            }
            rsm => rsm,
        };
        Self { rsm, ..self }
    }
}

/// Per-light-set resources: the shadow maps, the RSMs of a VPL engine, and the light/face
/// buffers (one face list serves both map sizes: `light_faces`).
#[derive(Debug)]
struct LightResources {
    sizes: MapSizes,
    layers: u32,
    shadow_rho: Targets,
    shadow_mu: Targets,
    /// R^ρ and R^μ, with [`MapSizes::rsm`].
    rsm: Option<(Targets, Targets)>,
    lights: wgpu::Buffer,
    faces: wgpu::Buffer,
}

/// The shadow maps of the frame's lights (after [`Deferred::prepare`]): what a pass that
/// shadows direct light binds (`lit` in `common.wgsl`).
#[derive(Debug, Clone, Copy)]
pub struct ShadowMaps<'a> {
    pub lights: &'a wgpu::Buffer,
    pub faces: &'a wgpu::Buffer,
    pub rho: &'a Targets,
    pub mu: &'a Targets,
    /// Edge in texels per light face.
    pub size: u32,
}

/// The shared passes and their resources; engines own one.
#[derive(Debug)]
pub struct Deferred {
    ctx: Arc<GpuContext>,
    gbuffer: GBufferPass,
    shadow: RsmPass,
    rsm: RsmPass,
    shade: wgpu::ComputePipeline,
    camera: wgpu::Buffer,
    params: wgpu::Buffer,
    scene: Option<(Arc<Scene>, GpuScene)>,
    /// [`change::scene_key`] of the last frame's scene: its content besides the camera (a live
    /// depth surface by its revision).
    scene_key: u64,
    /// The camera drawn from while it holds still ([`Self::still_camera`]), with the scene key
    /// it was held under.
    held_camera: Option<(u64, SceneCamera)>,
    accumulation: Accumulation,
    sample: Sample,
    frame: Option<FrameResources>,
    light: Option<LightResources>,
    /// What each light's μ and ρ maps were last drawn from ([`Self::rsm_keys`]).
    rsm_drawn: Option<Vec<[u64; 2]>>,
    light_count: u32,
    rgba: Vec<u8>,
    lights_cpu: Vec<GpuLight>,
    faces_cpu: Vec<GpuFace>,
    /// Lights an engine adds to the scene's own (DIR's and IBL's environment lights).
    extra_lights: Vec<Light>,
    extra_role: ExtraLights,
    /// Light with [`Scene::environment_lights`] (engines that do not sample the environment map
    /// themselves).
    environment_lights: bool,
    /// Directional lights cut from the scene's environment map when it has no
    /// `environment_lights` of its own (a scene file's map; the probe path sets them).
    derived_environment_lights: crate::dir::EnvironmentLights,
    /// How many lights [`Self::derived_environment_lights`] cuts ([`env_lights_param`]).
    derived_light_count: u32,
    timer: Option<GpuTimer>,
    /// Whether the shade pass skips a real pixel's shadow-map lookups where the virtual object
    /// cannot shadow it (`may_shadow` in shade.wgsl), and (with [`Self::real_indirect`] other
    /// than `Anywhere`) draws the real meshes into the G-buffer only where it can; off only to
    /// test that it changes nothing.
    shadow_reach_cull: bool,
    /// Where the engine's indirect term can be nonzero on real pixels
    /// ([`set_real_indirect`](Self::set_real_indirect)).
    real_indirect: RealIndirect,
    /// The pixels the shading covers, when not all: the object's reach, or a running mean's
    /// region (`prepare`). The real meshes are drawn within this frame's own reach.
    real_pixels: Option<PixelRect>,
    /// The real triangles that can cover them ([`shadow_reach::triangles_within`]), and the
    /// buffer they are uploaded to.
    camera_triangles: Vec<u32>,
    camera_triangle_buffer: Option<wgpu::Buffer>,
    /// Whether the shading adds the engine's indirect term ([`indirect_param`]).
    indirect_term: bool,
}

const MAX_LAYERS: u32 = 64;

/// Where an engine's indirect term can be nonzero on real pixels
/// ([`Deferred::set_real_indirect`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RealIndirect {
    /// Anywhere (bounced light can reach any real surface).
    Anywhere,
    /// Nowhere (`differential`, `ibl`): a real pixel's Δ is its direct term alone.
    Nowhere,
    /// Only at points within `bounds` (`dlpv`, `dvct`: their volume, beyond which their lookup
    /// or cones read nothing), and at pixels within `margin_px` of where those points are seen
    /// (`dvct`'s strided gather shares irradiance between neighbouring pixels).
    Within {
        bounds: (Vec3, Vec3),
        margin_px: u32,
    },
}

/// The `env_lights` parameter of the engines that light a scene file's environment map with
/// directional lights cut from it (`differential`, `dlpv`, `dvct`): how many, each with its own
/// shadow map (and VPLs, in the engines that have them). `default` is chosen per engine by
/// measured error (`docs/ALGORITHMS.md`, "Environment lights"). Without these lights those
/// engines lit an environment-only scene with nothing and drew the virtual object black. The
/// live probe path cuts its own map into `[scene] probe_lights` and ignores this.
pub fn env_lights_param(default: u32) -> ParamSpec {
    ParamSpec::int(
        "env_lights",
        "directional lights cut from a scene file's environment map (0: ignore it); each costs a shadow map",
        0,
        48,
        i64::from(default),
    )
}

/// The `indirect` parameter of the engines whose indirect light the shading adds from the
/// per-pixel indirect buffer: `off` shades their direct light alone, the same shadow-mapped
/// direct light as with it `on`. `relightd bench --terms` renders both and swaps each engine
/// term for the reference's, to say which term an error comes from.
pub fn indirect_param() -> ParamSpec {
    ParamSpec::choice(
        "indirect",
        "on: add the engine's indirect light; off: its direct light alone, to tell which term an error comes from",
        vec!["on", "off"],
    )
}

/// `LIGHT_SHADOW_ONLY` in `shaders/common.wgsl`, in `GpuLight::faces[2]`.
const LIGHT_SHADOW_ONLY: u32 = 1;

impl Deferred {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        let shade = shaders::compute_pipeline(&ctx.device, "shade", shaders::SHADE);
        let uniform = |label, size| shaders::params_buffer(&ctx.device, label, size);
        Self {
            gbuffer: GBufferPass::new(&ctx),
            shadow: RsmPass::depth_only(&ctx),
            rsm: RsmPass::new(&ctx),
            shade,
            camera: uniform("camera", size_of::<GpuCamera>()),
            params: uniform("shade params", size_of::<ShadeParams>()),
            scene: None,
            scene_key: 0,
            held_camera: None,
            accumulation: Accumulation::new(),
            sample: Sample::ALONE,
            frame: None,
            light: None,
            rsm_drawn: None,
            light_count: 0,
            rgba: Vec::new(),
            lights_cpu: Vec::new(),
            faces_cpu: Vec::new(),
            extra_lights: Vec::new(),
            extra_role: ExtraLights::Full,
            environment_lights: true,
            derived_environment_lights: crate::dir::EnvironmentLights::default(),
            derived_light_count: 8,
            timer: GpuTimer::new(&ctx),
            shadow_reach_cull: true,
            real_indirect: RealIndirect::Anywhere,
            real_pixels: None,
            camera_triangles: Vec::new(),
            camera_triangle_buffer: None,
            indirect_term: true,
            ctx,
        }
    }

    /// Where the engine's indirect term can be nonzero on real pixels, from the next
    /// [`prepare`](Self::prepare) on. Unless it is `Anywhere`, a real pixel's Δ is nonzero only
    /// where the virtual object can shadow it or that term reaches, so the real meshes are drawn
    /// into the camera's G-buffers, and the shading runs, only within the pixels that can hold
    /// such a point or the object ([`shadow_reach`]). The picture is the
    /// same.
    pub fn set_real_indirect(&mut self, reach: RealIndirect) {
        self.real_indirect = reach;
    }

    /// The pixels the last frame shaded (after [`prepare`](Self::prepare)), when
    /// [`set_real_indirect`](Self::set_real_indirect) limited them to the object's reach.
    pub fn real_pixels(&self) -> Option<PixelRect> {
        self.real_pixels
    }

    /// Shade every real pixel's shadow-map lookups, as without `may_shadow`.
    #[cfg(test)]
    pub(crate) fn without_shadow_reach_cull(&mut self) {
        self.shadow_reach_cull = false;
    }

    /// For an engine that lights with the scene's environment map itself (`dir`, `ibl`): the
    /// scene's [`Scene::environment_lights`] are left out, or that light would count twice.
    pub fn sampling_the_environment(ctx: Arc<GpuContext>) -> Self {
        Self {
            environment_lights: false,
            ..Self::new(ctx)
        }
    }

    /// Light a scene file's environment map with `count` directional lights cut from it
    /// ([`env_lights_param`]; for the engines built with [`Self::new`]).
    pub fn set_environment_light_count(&mut self, count: u32) {
        if count != self.derived_light_count {
            self.derived_light_count = count;
            self.derive_environment_lights();
        }
    }

    /// Cut the uploaded scene's environment map into [`Self::derived_light_count`] lights,
    /// where this engine lights with them and the scene has none of its own (the probe path's).
    fn derive_environment_lights(&mut self) {
        let map = self.scene.as_ref().and_then(|(scene, _)| {
            scene
                .environment
                .as_ref()
                .filter(|_| self.environment_lights && scene.environment_lights.is_empty())
        });
        self.derived_environment_lights
            .update(map, self.derived_light_count);
    }

    /// Average `frames` frames over sub-pixel offsets while the picture holds still
    /// ([`accumulate_param`]; 1: off). Starts the mean afresh, as any change of the engine's
    /// parameters must.
    pub fn set_accumulate(&mut self, frames: u32) {
        self.accumulation.set_frames(frames);
    }

    /// The parameters every engine on `Deferred` takes, from its validated `params`:
    /// [`accumulate_param`], and [`indirect_param`] where the engine's `schema` has it (without
    /// it the indirect term is always added). Starts the mean afresh.
    pub fn set_shared_params(&mut self, schema: &ParamsSchema, params: &Map<String, Value>) {
        self.set_accumulate(schema.int(params, "accumulate") as u32);
        self.indirect_term = !schema.has("indirect") || schema.choice(params, "indirect") == "on";
    }

    pub fn ctx(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// This frame's place in the running mean of still frames (after
    /// [`prepare`](Self::prepare)): 0 for the first frame after a change and for a frame shown
    /// alone; k for the k-th frame added to it; the last one's once the mean is complete (those
    /// frames only keep the mean, so nothing drawn for them need change). An engine may draw its
    /// own samples anew from it (`dir`'s VPLs), so that the mean averages them too.
    pub fn accumulation_index(&self) -> u32 {
        self.sample.index
    }

    /// Upload what changed for this frame and rasterise the G-buffers and shadow maps. Returns
    /// the colour image's size, for the engine's own passes and then [`finish`](Self::finish).
    ///
    /// `None` when the frame holds the complete running mean of still frames, whose inputs have
    /// not changed since: nothing is drawn, the mean is composited over the frame's own
    /// background and read back into `out` here, and the engine's frame is done. A still camera
    /// on a still scene costs that alone once its edges have converged.
    pub fn prepare(
        &mut self,
        engine: &'static str,
        frame: &SceneFrame,
        out: &mut RelitFrame,
        sizes: MapSizes,
    ) -> Result<Option<(u32, u32)>, EngineError> {
        let color = out.begin(engine, frame)?;
        let scene = frame.scene.as_ref().ok_or(EngineError::MissingInput {
            engine,
            stream: "scene",
        })?;
        let (width, height) = (color.width(), color.height());
        let ctx = self.ctx.clone();
        ctx.require(
            "max_texture_dimension_2d",
            u64::from(width.max(height)),
            "the camera resolution",
        )?;
        ctx.require(
            "max_texture_dimension_2d",
            u64::from(sizes.shadow),
            "the shadow-map size",
        )?;
        if let Some(rsm_size) = sizes.rsm {
            ctx.require("max_texture_dimension_2d", u64::from(rsm_size), "rsm_size")?;
        }

        let started = Instant::now();
        if let Some(timer) = self.timer.as_mut() {
            timer.reset();
        }
        let uploaded = self
            .scene
            .as_ref()
            .is_some_and(|(s, _)| Arc::ptr_eq(s, scene));
        if !uploaded {
            self.scene_key = change::scene_key(scene);
        }
        let camera = self.still_camera(scene, height);
        let pose = camera.world_from_camera;
        self.sample = self.accumulation.advance(KeptInputs::hash_of(&[
            &self.scene_key.to_le_bytes(),
            bytemuck::cast_slice(&[
                pose.rotation.to_array(),
                pose.translation.extend(camera.yfov_rad).to_array(),
            ]),
            bytemuck::cast_slice(&[width, height, sizes.shadow, sizes.rsm.unwrap_or(0)]),
        ]));
        if self.sample.holds()
            && self.scene.is_some()
            && self.frame.is_some()
            && self.light.is_some()
        {
            // The mean is complete and nothing it was drawn from changed: the frame shows it over
            // its own background, and nothing else is drawn. Its shading reads neither option.
            self.upload_background(color);
            out.timings.push(PassTiming {
                pass: "geometry",
                ms: started.elapsed().as_secs_f64() * 1e3,
            });
            self.finish(
                ShadeOptions {
                    shadow_bias_texels: 0.0,
                    direct_delta: false,
                },
                out,
            )?;
            return Ok(None);
        }
        if !uploaded {
            self.scene = Some((scene.clone(), GpuScene::new(&ctx, scene)));
            self.derive_environment_lights();
        }
        if !self
            .frame
            .as_ref()
            .is_some_and(|f| f.width == width && f.height == height)
        {
            self.frame = Some(FrameResources::new(&ctx, width, height));
        }
        self.upload_background(color);
        let Some((_, gpu_scene)) = &self.scene else {
            unreachable!("uploaded above")
        };
        let (bounds, light_bounds) = (gpu_scene.bounds, gpu_scene.light_bounds);
        let environment_lights: &[Light] = if !self.environment_lights {
            &[]
        } else if scene.environment_lights.is_empty() {
            self.derived_environment_lights.lights()
        } else {
            &scene.environment_lights
        };
        (self.lights_cpu, self.faces_cpu) =
            if self.extra_lights.is_empty() && environment_lights.is_empty() {
                light_faces(&scene.lights, light_bounds)
            } else {
                let all: Vec<Light> = scene
                    .lights
                    .iter()
                    .chain(environment_lights)
                    .chain(&self.extra_lights)
                    .copied()
                    .collect();
                let (mut lights, faces) = light_faces(&all, light_bounds);
                if self.extra_role == ExtraLights::ShadowOnly {
                    let extras = self.extra_lights.iter().filter(|l| is_shadowed(l)).count();
                    let first = lights.len().saturating_sub(extras);
                    for light in &mut lights[first..] {
                        light.faces[2] = LIGHT_SHADOW_ONLY;
                    }
                }
                (lights, faces)
            };
        let layers = (self.faces_cpu.len() as u32).max(1);
        ctx.require(
            "max_texture_array_layers",
            u64::from(layers),
            "the number of lights",
        )?;
        if layers > MAX_LAYERS {
            return Err(EngineError::TooManyLights {
                engine,
                faces: layers,
                max: MAX_LAYERS,
            });
        }
        let sizes = sizes.for_faces(&self.faces_cpu);
        if !self
            .light
            .as_ref()
            .is_some_and(|l| l.sizes == sizes && l.layers == layers)
        {
            self.light = Some(LightResources::new(&ctx, sizes, layers));
            self.rsm_drawn = None;
        }
        self.light_count = self.lights_cpu.len() as u32;
        let (Some(frame_res), Some(light_res)) = (&self.frame, &self.light) else {
            unreachable!("created above")
        };
        if !self.lights_cpu.is_empty() {
            ctx.queue
                .write_buffer(&light_res.lights, 0, bytemuck::cast_slice(&self.lights_cpu));
            ctx.queue
                .write_buffer(&light_res.faces, 0, bytemuck::cast_slice(&self.faces_cpu));
        }
        let camera = camera_uniform(&camera, width, height, bounds).jittered(self.sample.offset_px);
        ctx.queue
            .write_buffer(&self.camera, 0, bytemuck::bytes_of(&camera));
        let (indirect, margin_px): (&[(Vec3, Vec3)], u32) = match &self.real_indirect {
            RealIndirect::Within { bounds, margin_px } => {
                (std::slice::from_ref(bounds), *margin_px)
            }
            _ => (&[], 0),
        };
        let real_pixels = match gpu_scene.virtual_bounds {
            Some(object)
                if self.real_indirect != RealIndirect::Anywhere && self.shadow_reach_cull =>
            {
                Some(
                    shadow_reach::reach_rect(
                        Mat4::from_cols_array_2d(&camera.view_proj),
                        (width, height),
                        &self.lights_cpu,
                        &self.faces_cpu,
                        sizes.shadow,
                        (object, indirect),
                        bounds,
                    )
                    .grown(margin_px, width, height),
                )
            }
            _ => None,
        };
        // A running mean shades one region on all its frames, so that every pixel's mean takes
        // every frame's sample and no pixel outside it is read: the first frame's rectangle
        // grown by two pixels, which holds each later frame's (their sub-pixel offsets move a
        // projection by less than one pixel, and the rectangle's rounding by one more).
        self.real_pixels = match (real_pixels, self.real_pixels) {
            (Some(rect), Some(held)) if self.sample.index > 0 => {
                debug_assert!(held.contains(rect), "{rect:?} outside the mean's {held:?}");
                Some(held)
            }
            (Some(rect), _) if self.sample.write => Some(rect.grown(2, width, height)),
            _ => real_pixels,
        };

        let real_within = match real_pixels {
            Some(rect) if rect != PixelRect::full(width, height) => {
                self.camera_triangles.clear();
                shadow_reach::triangles_within(
                    Mat4::from_cols_array_2d(&camera.view_proj),
                    (width, height),
                    rect,
                    &gpu_scene.real_positions,
                    &gpu_scene.real_triangles,
                    &mut self.camera_triangles,
                );
                let bytes = (4 * self.camera_triangles.len()).max(12) as u64;
                if self
                    .camera_triangle_buffer
                    .as_ref()
                    .is_none_or(|b| b.size() < bytes)
                {
                    self.camera_triangle_buffer = Some(ctx.buffer(
                        "camera triangles",
                        bytes.next_power_of_two(),
                        wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
                    ));
                }
                let buffer = self.camera_triangle_buffer.as_ref().expect("created above");
                if !self.camera_triangles.is_empty() {
                    ctx.queue
                        .write_buffer(buffer, 0, bytemuck::cast_slice(&self.camera_triangles));
                }
                Some(RealWithin {
                    rect,
                    indices: buffer,
                    count: self.camera_triangles.len() as u32,
                })
            }
            _ => None,
        };
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("geometry"),
            });
        let camera_group = self.gbuffer.bind_group(&ctx, &self.camera, gpu_scene);
        let gbuffer_work = self.gbuffer.render(
            &mut encoder,
            &camera_group,
            gpu_scene,
            (&frame_res.gb_rho, &frame_res.gb_mu),
            real_within,
            self.timer.as_mut(),
        );
        out.work.push(PassWork {
            pass: "gbuffer",
            work: gbuffer_work,
        });
        let drawn = self.rsm_keys(gpu_scene, sizes, layers);
        let before = self
            .rsm_drawn
            .as_ref()
            .filter(|before| before.len() == drawn.len());
        let redraw: Vec<LayerRedraw> = self
            .lights_cpu
            .iter()
            .zip(&drawn)
            .enumerate()
            .flat_map(|(i, (light, key))| {
                let mu = match before.map(|b| b[i]) {
                    Some(b) if b == *key => None,
                    Some([mu, _]) => Some(mu != key[0]),
                    None => Some(true),
                };
                let faces = light.faces[0]..light.faces[0] + light.faces[1];
                mu.into_iter()
                    .flat_map(move |mu| faces.clone().map(move |layer| LayerRedraw { layer, mu }))
            })
            .collect();
        if !redraw.is_empty() {
            let maps = [
                (
                    &self.shadow,
                    Some((&light_res.shadow_rho, &light_res.shadow_mu)),
                ),
                (&self.rsm, light_res.rsm.as_ref().map(|(rho, mu)| (rho, mu))),
            ];
            for (pass, targets) in maps {
                let Some(targets) = targets else { continue };
                let group = pass.bind_group(&ctx, &light_res.lights, &light_res.faces, gpu_scene);
                let work = pass.render(
                    &mut encoder,
                    &group,
                    gpu_scene,
                    targets,
                    &redraw,
                    self.timer.as_mut(),
                );
                out.work.push(PassWork {
                    pass: pass.name(),
                    work,
                });
            }
            self.rsm_drawn = Some(drawn);
        }
        encoder.clear_buffer(&frame_res.indirect, 0, None);
        ctx.queue.submit([encoder.finish()]);
        ctx.check()?;
        out.timings.push(PassTiming {
            pass: "geometry",
            ms: started.elapsed().as_secs_f64() * 1e3,
        });
        Ok(Some((width, height)))
    }

    /// The camera to draw `scene` from: the held one while the scene's content holds
    /// ([`change::scene_key`], after `prepare` set it) and the real camera is still from it
    /// ([`change::camera_still`]), else the real one, which is then held.
    fn still_camera(&mut self, scene: &Scene, height: u32) -> SceneCamera {
        let camera = match self.held_camera {
            Some((key, held)) if key == self.scene_key && camera_still(&held, scene, height) => {
                held
            }
            _ => scene.camera,
        };
        self.held_camera = Some((self.scene_key, camera));
        camera
    }

    /// The frame's colour image as the composite's background (RGBA8).
    fn upload_background(&mut self, color: &Image) {
        let Some(frame_res) = &self.frame else { return };
        self.rgba.clear();
        if let Some(rgb) = color.as_u8() {
            for px in rgb.chunks_exact(3) {
                self.rgba.extend_from_slice(&[px[0], px[1], px[2], 255]);
            }
        }
        self.ctx.queue.write_texture(
            frame_res.background.as_image_copy(),
            &self.rgba,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * frame_res.width),
                rows_per_image: Some(frame_res.height),
            },
            frame_res.background.size(),
        );
    }

    /// What each light's μ and ρ maps (shadow maps and RSMs) would hold for this frame, as
    /// hashes of everything they are drawn from: the light-space geometry
    /// ([`GpuScene::light_fingerprint`]), the light, its faces and the maps' sizes. A light
    /// whose hashes equal the last drawn needs no redraw of its faces.
    fn rsm_keys(&self, scene: &GpuScene, sizes: MapSizes, layers: u32) -> Vec<[u64; 2]> {
        self.lights_cpu
            .iter()
            .map(|light| {
                let first = light.faces[0] as usize;
                let faces = self
                    .faces_cpu
                    .get(first..first + light.faces[1] as usize)
                    .unwrap_or_default();
                let mut mu = DefaultHasher::new();
                scene.light_fingerprint[0].hash(&mut mu);
                bytemuck::bytes_of(light).hash(&mut mu);
                bytemuck::cast_slice::<_, u8>(faces).hash(&mut mu);
                (sizes, layers).hash(&mut mu);
                let mu = mu.finish();
                let mut rho = DefaultHasher::new();
                (mu, scene.light_fingerprint[1]).hash(&mut rho);
                [mu, rho.finish()]
            })
            .collect()
    }

    /// A hash of what this frame's shadow maps hold (after [`prepare`](Self::prepare)): equal
    /// on two frames, the maps, the lights and their faces are equal, so a result derived
    /// from them alone (DLPV's propagated volume, DVCT's injected radiance) may be kept.
    pub fn light_inputs(&self) -> u64 {
        let mut hasher = DefaultHasher::new();
        if self.faces_cpu.is_empty() {
            hasher.write_u8(0);
        } else {
            self.rsm_drawn.hash(&mut hasher);
        }
        hasher.finish()
    }

    /// The uploaded scene (after [`prepare`](Self::prepare)).
    pub fn scene(&self) -> Option<&GpuScene> {
        self.scene.as_ref().map(|(_, s)| s)
    }

    /// Lights added to the scene's own from the next [`prepare`](Self::prepare) on, in `role`.
    pub fn set_extra_lights(&mut self, lights: Vec<Light>, role: ExtraLights) {
        self.extra_lights = lights;
        self.extra_role = role;
        self.accumulation.key = None;
    }

    /// The camera uniform (`Camera` in `shaders/common.wgsl`).
    pub fn camera_buffer(&self) -> &wgpu::Buffer {
        &self.camera
    }

    pub fn lights(&self) -> &[GpuLight] {
        &self.lights_cpu
    }

    pub fn faces(&self) -> &[GpuFace] {
        &self.faces_cpu
    }

    /// The VPL maps' edge in texels as drawn for this frame's faces (after `prepare`;
    /// [`MapSizes::for_faces`]), `None` without them.
    pub fn rsm_size(&self) -> Option<u32> {
        self.light.as_ref().and_then(|l| l.sizes.rsm)
    }

    /// The light and face buffers and the R^ρ / R^μ targets (after `prepare` with an RSM
    /// size).
    pub fn light_buffers(&self) -> Option<(&wgpu::Buffer, &wgpu::Buffer, &Targets, &Targets)> {
        let l = self.light.as_ref()?;
        let (rho, mu) = l.rsm.as_ref()?;
        Some((&l.lights, &l.faces, rho, mu))
    }

    /// The shadow maps (after `prepare`).
    pub fn shadow_maps(&self) -> Option<ShadowMaps<'_>> {
        self.light.as_ref().map(|l| ShadowMaps {
            lights: &l.lights,
            faces: &l.faces,
            rho: &l.shadow_rho,
            mu: &l.shadow_mu,
            size: l.sizes.shadow,
        })
    }

    /// The ρ and μ G-buffers and the per-pixel indirect buffer engines write (after `prepare`).
    pub fn frame_buffers(&self) -> Option<(&Targets, &Targets, &wgpu::Buffer)> {
        self.frame
            .as_ref()
            .map(|f| (&f.gb_rho, &f.gb_mu, &f.indirect))
    }

    /// Lend the frame's GPU pass timer to an engine's own passes (`None` without timestamp
    /// queries); give it back with [`return_timer`](Self::return_timer) before `finish`.
    pub fn lend_timer(&mut self) -> Option<GpuTimer> {
        self.timer.take()
    }

    pub fn return_timer(&mut self, timer: Option<GpuTimer>) {
        if timer.is_some() {
            self.timer = timer;
        }
    }

    /// Shade, composite and read back into `out`.
    pub fn finish(
        &mut self,
        options: ShadeOptions,
        out: &mut RelitFrame,
    ) -> Result<(), EngineError> {
        let started = Instant::now();
        let ctx = self.ctx.clone();
        let (Some(frame_res), Some(light_res), Some((_, gpu_scene))) =
            (&self.frame, &self.light, &self.scene)
        else {
            return Err(EngineError::NotPrepared);
        };
        let (width, height) = (frame_res.width, frame_res.height);
        let region = self.real_pixels.unwrap_or(PixelRect::full(width, height));
        // Bounds that hold everything the shade pass can meet disable the cull.
        const EVERYWHERE: f32 = 1e18;
        let (virtual_lo, virtual_hi) = match gpu_scene.virtual_bounds {
            Some(_) if !self.shadow_reach_cull => {
                (Vec4::splat(-EVERYWHERE), Vec4::splat(EVERYWHERE))
            }
            Some((lo, hi)) => (lo.extend(0.0), hi.extend(1.0)),
            None => (Vec4::ZERO, Vec4::ZERO),
        };
        let params = ShadeParams {
            size: [width, height, self.light_count, light_res.sizes.shadow],
            virtual_lo: virtual_lo.to_array(),
            virtual_hi: virtual_hi.to_array(),
            options: [
                options.shadow_bias_texels,
                if options.direct_delta { 1.0 } else { 0.0 },
                self.sample.weight,
                if self.sample.write { 1.0 } else { 0.0 },
            ],
            region: [
                region.x,
                region.y,
                region.x + region.width,
                region.y + region.height,
            ],
            terms: [f32::from(u8::from(self.indirect_term)), 0.0, 0.0, 0.0],
        };
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let view = Targets::view;
        let views = [
            view(&frame_res.gb_rho.position),
            view(&frame_res.gb_rho.normal),
            view(&frame_res.gb_rho.albedo),
            view(&frame_res.gb_mu.position),
            view(&frame_res.gb_mu.normal),
            view(&frame_res.gb_mu.albedo),
            light_res.shadow_rho.depth_array_view(),
            light_res.shadow_mu.depth_array_view(),
            view(&frame_res.background),
        ];
        let mut resources = vec![
            self.params.as_entire_binding(),
            self.camera.as_entire_binding(),
            light_res.lights.as_entire_binding(),
            light_res.faces.as_entire_binding(),
            gpu_scene.materials.as_entire_binding(),
        ];
        resources.extend(views.iter().map(wgpu::BindingResource::TextureView));
        resources.extend(
            [
                &frame_res.indirect,
                &frame_res.delta,
                &frame_res.composite,
                &frame_res.history,
            ]
            .map(|b| b.as_entire_binding()),
        );
        let group = shaders::bind_group(
            &ctx.device,
            "shade",
            &self.shade.get_bind_group_layout(0),
            &resources,
        );
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("shade"),
            });
        {
            let mut pass = timed_pass(&mut encoder, &mut self.timer, "gpu.shade");
            pass.set_pipeline(&self.shade);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(region.width.div_ceil(8), region.height.div_ceil(8), 1);
        }
        out.work.push(PassWork {
            pass: "shade",
            work: shade_work(region.area(), self.light_count, self.sample),
        });
        if let Some(timer) = &self.timer {
            timer.resolve(&mut encoder);
        }
        ctx.queue.submit([encoder.finish()]);
        if region != PixelRect::full(width, height) {
            // Outside the region no pixel holds a real surface Δ can change, nor the object:
            // the camera's own picture, and Δ = 0.
            if let (Some(composite), Some(delta)) =
                (out.composite.as_u8_mut(), out.delta.as_u16_mut())
            {
                copy_composite(&self.rgba, composite);
                let one = half::f16::ONE.to_bits();
                for px in delta.chunks_exact_mut(4) {
                    px.copy_from_slice(&[0, 0, 0, one]);
                }
            }
        }
        if !region.is_empty() {
            // The region's rows, whole: one range of each buffer.
            let rows = u64::from(region.y)..u64::from(region.y + region.height);
            let row = u64::from(width);
            let delta_bytes = (rows.end - rows.start) * row * 8;
            ctx.read_back_all(
                &[
                    (&frame_res.delta, rows.start * row * 8..rows.end * row * 8),
                    (
                        &frame_res.composite,
                        rows.start * row * 4..rows.end * row * 4,
                    ),
                ],
                &frame_res.staging,
                |bytes| {
                    let (delta, composite) = bytes.split_at(delta_bytes as usize);
                    out.non_finite = read_region(delta, composite, region, width, out);
                },
            )?;
        }
        out.timings.push(PassTiming {
            pass: "shade+readback",
            ms: started.elapsed().as_secs_f64() * 1e3,
        });
        if let Some(timer) = &mut self.timer {
            timer.read(&mut out.timings)?;
        }
        Ok(())
    }
}

/// The shading pass's least work over `pixels`: the ρ G-buffer (32 bytes a texel), the
/// background (4) and the indirect term (16) read, Δ (8) and the composite (4) written; per
/// light the test of whether the object can shadow the pixel (`may_shadow`, about 40
/// operations); the running mean's 32 bytes read and written as `sample` needs them. The
/// shadow-map lookups and BRDFs where the object can shadow, and the μ G-buffer on the
/// object's pixels, depend on the picture and are left out, so the model is a floor. A frame
/// that holds the mean reads it and the background, and nothing else.
fn shade_work(pixels: u64, lights: u32, sample: Sample) -> Work {
    if sample.holds() {
        // The mean read, the background read, Δ and the composite written.
        return Work::new(32.0 + 4.0 + 8.0 + 4.0, 20.0).times(pixels as f64);
    }
    let per_light = Work::new(0.0, 40.0).times(f64::from(lights));
    let read = if sample.weight < 1.0 { 32.0 } else { 0.0 };
    let written = if sample.write { 32.0 } else { 0.0 };
    (Work::new(32.0 + 4.0 + 16.0 + 8.0 + 4.0 + read + written, 50.0) + per_light)
        .times(pixels as f64)
}

/// Linear f32 RGBA → the frame's Rgba16F Δ (alpha 1); non-finite values become 0 (they never
/// should) and are counted, as are values beyond f16's range (clamped to its largest). The
/// source's alpha is ignored (`pt` keeps its variance there).
pub(crate) fn write_delta(bytes: &[u8], delta: &mut Image) -> usize {
    let Some(out) = delta.as_u16_mut() else {
        return 0;
    };
    let mut non_finite = 0;
    for (o, px) in out.chunks_exact_mut(4).zip(bytes.chunks_exact(16)) {
        for (o, chunk) in o[..3].iter_mut().zip(px.chunks_exact(4)) {
            let v = f32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
            let v = if v.is_finite() {
                v
            } else {
                non_finite += 1;
                0.0
            };
            let h = half::f16::from_f32(v);
            *o = if h.is_finite() {
                h
            } else {
                non_finite += 1;
                half::f16::MAX.copysign(h)
            }
            .to_bits();
        }
        // Alpha is 1 where Δ is defined (everywhere); what the source held there is not Δ.
        o[3] = half::f16::ONE.to_bits();
    }
    non_finite
}

/// The shading pass's packed f16 Δ (`pack_delta` in common.wgsl) → the frame's Rgba16F Δ: a
/// copy, then each alpha that is not 1 counted as that many channels the pass found not finite
/// or beyond f16's range (it wrote 0 or f16's largest value there) and set back to 1.
fn unpack_delta(bytes: &[u8], out: &mut [u16]) -> usize {
    let one = half::f16::ONE.to_bits();
    let mut non_finite = 0;
    let n = out.len().min(bytes.len() / 2);
    bytemuck::cast_slice_mut::<u16, u8>(&mut out[..n]).copy_from_slice(&bytes[..2 * n]);
    for alpha in out[..n].iter_mut().skip(3).step_by(4) {
        if *alpha != one {
            non_finite += (half::f16::from_bits(*alpha).to_f32() - 1.0).round() as usize;
            *alpha = one;
        }
    }
    non_finite
}

/// RGBA8 → the frame's RGB8 composite (alpha dropped).
pub(crate) fn write_composite(bytes: &[u8], composite: &mut Image) {
    debug_assert_eq!(composite.format(), PixelFormat::Rgb8);
    if let Some(out) = composite.as_u8_mut() {
        copy_composite(bytes, out);
    }
}

fn copy_composite(bytes: &[u8], out: &mut [u8]) {
    for (o, px) in out.chunks_exact_mut(3).zip(bytes.chunks_exact(4)) {
        o.copy_from_slice(&px[..3]);
    }
}

/// The shading pass's Δ and composite of `region`'s rows (`delta`, `composite`: whole rows of a
/// `width`-pixel image, as read back) into `out`'s pixels of the region; returns the channels
/// the pass found not finite ([`unpack_delta`]).
fn read_region(
    delta: &[u8],
    composite: &[u8],
    region: PixelRect,
    width: u32,
    out: &mut RelitFrame,
) -> usize {
    let (Some(out_delta), Some(out_composite)) =
        (out.delta.as_u16_mut(), out.composite.as_u8_mut())
    else {
        return 0;
    };
    let (width, x, span) = (width as usize, region.x as usize, region.width as usize);
    let mut non_finite = 0;
    for row in 0..region.height as usize {
        let read = row * width + x;
        let pixel = (region.y as usize + row) * width + x;
        non_finite += unpack_delta(
            &delta[8 * read..8 * (read + span)],
            &mut out_delta[4 * pixel..4 * (pixel + span)],
        );
        copy_composite(
            &composite[4 * read..4 * (read + span)],
            &mut out_composite[3 * pixel..3 * (pixel + span)],
        );
    }
    non_finite
}

impl FrameResources {
    fn new(ctx: &GpuContext, width: u32, height: u32) -> Self {
        let pixels = u64::from(width) * u64::from(height);
        let buffer = |label, size, usage| ctx.buffer(label, size, usage);
        use wgpu::BufferUsages as U;
        Self {
            width,
            height,
            gb_rho: Targets::new(ctx, "g-buffer ρ", width, height, 1),
            gb_mu: Targets::new(ctx, "g-buffer μ", width, height, 1),
            background: ctx.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("background"),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                // Decoded to linear on load: the adapter's sRGB table, not a `pow` per channel
                // in the shade pass.
                format: wgpu::TextureFormat::Rgba8UnormSrgb,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            }),
            indirect: buffer("indirect", pixels * 16, U::STORAGE | U::COPY_DST),
            delta: buffer("delta", pixels * 8, U::STORAGE | U::COPY_SRC),
            composite: buffer("composite", pixels * 4, U::STORAGE | U::COPY_SRC),
            staging: buffer("frame staging", pixels * 12, U::MAP_READ | U::COPY_DST),
            history: buffer("accumulated", pixels * 32, U::STORAGE),
        }
    }
}

impl LightResources {
    fn new(ctx: &GpuContext, sizes: MapSizes, layers: u32) -> Self {
        let shadow = |label| Targets::depth_only(ctx, label, sizes.shadow, sizes.shadow, layers);
        let storage = |label, contents: &[u8]| {
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                })
        };
        Self {
            sizes,
            layers,
            shadow_rho: shadow("shadow ρ"),
            shadow_mu: shadow("shadow μ"),
            rsm: sizes.rsm.map(|size| {
                (
                    Targets::new(ctx, "R^ρ", size, size, layers),
                    Targets::new(ctx, "R^μ", size, size, layers),
                )
            }),
            lights: storage(
                "lights",
                bytemuck::cast_slice(&vec![GpuLight::zeroed(); layers as usize]),
            ),
            faces: storage(
                "faces",
                bytemuck::cast_slice(&vec![GpuFace::zeroed(); layers as usize]),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::light::Light;

    /// The VPL maps are thinned only for an injecting engine, and only where every face is one
    /// of more than six directional lights; their texels then stay within six faces'.
    #[test]
    fn only_many_directional_faces_thin_the_vpl_maps() {
        let directional = |n: usize| {
            (0..n)
                .map(|i| Light::Directional {
                    direction_in_world: Vec3::new(i as f32 * 0.1, -1.0, 0.2).normalize(),
                    irradiance: Vec3::ONE,
                })
                .collect::<Vec<_>>()
        };
        let point = Light::Point {
            position_in_world: Vec3::new(0.0, 2.0, 0.0),
            intensity: Vec3::ONE,
        };
        let bounds = (Vec3::splat(-1.0), Vec3::splat(1.0));
        let rsm = |sizes: MapSizes, lights: &[Light]| {
            let (_, faces) = light_faces(lights, bounds);
            let drawn = sizes.for_faces(&faces);
            assert_eq!(
                drawn.shadow, sizes.shadow,
                "the shadow maps keep their size"
            );
            drawn.rsm.unwrap()
        };
        let injected = MapSizes::with_injected_rsm(512, 192);
        assert_eq!(rsm(injected, &directional(24)), 96);
        assert_eq!(rsm(injected, &directional(16)), 112);
        assert_eq!(rsm(injected, &directional(6)), 192);
        assert_eq!(rsm(injected, &[point]), 192);
        let mut mixed = directional(24);
        mixed.push(point);
        assert_eq!(
            rsm(injected, &mixed),
            192,
            "a point light needs the full edge"
        );
        assert_eq!(rsm(MapSizes::with_rsm(512, 192), &directional(24)), 192);
        for n in 7..64 {
            let edge = rsm(injected, &directional(n));
            assert!(
                edge % 8 == 0 && edge.pow(2) * n as u32 <= 6 * 192 * 192,
                "{n}: {edge}"
            );
        }
    }

    #[test]
    fn non_finite_and_out_of_range_delta_is_counted_and_never_written() {
        // Pixel 0: finite, NaN, ∞ and an alpha that is not Δ (ignored); pixel 1: beyond f16.
        let values = [0.5f32, f32::NAN, f32::INFINITY, -1e6, -1e6, 0.0, 0.0, 7.0];
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let mut delta = Image::new(2, 1, PixelFormat::Rgba16F);
        assert_eq!(write_delta(&bytes, &mut delta), 3);
        let written: Vec<f32> = delta
            .as_u16()
            .unwrap()
            .iter()
            .map(|&b| half::f16::from_bits(b).to_f32())
            .collect();
        let largest = half::f16::MAX.to_f32();
        assert_eq!(written, [0.5, 0.0, 0.0, 1.0, -largest, 0.0, 0.0, 1.0]);
    }

    /// `pack_delta` on the GPU, then `unpack_delta`, give what `write_delta` gives on the CPU
    /// (the `half` crate's conversion): special values, ties, subnormals and a sweep of both
    /// signs over f16's whole range.
    #[test]
    fn packed_delta_is_write_delta_on_the_gpu() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
        let kernel = concat!(
            include_str!("../../shaders/common.wgsl"),
            "@group(0) @binding(0) var<storage, read> input: array<vec4<f32>>;
            @group(0) @binding(1) var<storage, read_write> output: array<vec2<u32>>;
            @compute @workgroup_size(1)
            fn main(@builtin(global_invocation_id) id: vec3<u32>) {
                output[id.x] = pack_delta(input[id.x].xyz);
            }"
        );
        let mut values = vec![
            [0.5f32, f32::NAN, f32::INFINITY, 0.0],
            [-1e6, -0.25, f32::NEG_INFINITY, 0.0],
            [1e-3, 65504.0, -65519.0, 0.0],
            // A subnormal, a tie between 2048 and 2050 (to even: 2048), an inexact fraction.
            [1e-6, 2049.0, 0.1, 0.0],
            [6e-8, -3e-8, 65520.0, 0.0],
        ];
        values.extend((0..3000).map(|i| {
            let v = 1e-8f32 * 1.0065f32.powi(i);
            [v, -v * 1.37, v * 0.71, 0.0]
        }));
        let bytes: Vec<u8> = bytemuck::cast_slice(&values).to_vec();
        let mut expected = Image::new(values.len() as u32, 1, PixelFormat::Rgba16F);
        let expected_non_finite = write_delta(&bytes, &mut expected);
        use wgpu::BufferUsages as U;
        let input = ctx.buffer_with("values", &bytes, U::STORAGE);
        let size = 8 * values.len() as u64;
        let output = ctx.buffer("packed", size, U::STORAGE | U::COPY_SRC);
        let pipeline = shaders::compute_pipeline(&ctx.device, "pack_delta", kernel);
        let mut delta = Image::new(values.len() as u32, 1, PixelFormat::Rgba16F);
        let non_finite = ctx
            .run_once(
                &pipeline,
                &[input.as_entire_binding(), output.as_entire_binding()],
                values.len() as u32,
                &output,
                size,
                |bytes| unpack_delta(bytes, delta.as_u16_mut().unwrap()),
            )
            .unwrap();
        assert_eq!((non_finite, expected_non_finite), (5, 5));
        let (got, want) = (delta.as_u16().unwrap(), expected.as_u16().unwrap());
        let wrong: Vec<_> = got
            .iter()
            .zip(want)
            .enumerate()
            .filter(|(_, (g, w))| g != w)
            .map(|(i, (g, w))| (values[i / 4][i % 4], *g, *w))
            .take(5)
            .collect();
        assert!(wrong.is_empty(), "(value, gpu bits, cpu bits): {wrong:?}");
    }

    #[test]
    fn halton_offsets_start_at_the_centre_and_stay_inside_the_pixel() {
        assert_eq!(halton_offset(0), Vec2::ZERO);
        let points: Vec<Vec2> = (1..32).map(halton_offset).collect();
        assert!(points.iter().all(|p| p.abs().max_element() <= 0.5));
        let mean = points.iter().sum::<Vec2>() / points.len() as f32;
        assert!(mean.abs().max_element() < 0.05, "{mean}");
    }
}
