//! `ibl`: reflection-map convolution for AR (Kan, Unterguggenberger, Kaufmann).
//!
//! - **Maps** ([`maps`], `shaders/ibl_convolve.wgsl`): the environment (the probe's HDR map, or
//!   the scene file's) resampled to `input_width`, then per output texel the full convolution
//!   with the BRDF — a diffuse irradiance map E_d(n) and one specular map E_s^n(r) per Phong
//!   exponent, all in one pass. The exponents are the ones the scene needs (the virtual
//!   materials' own, up to eight) unless `levels` asks for a fixed log-spaced set.
//! - **The environment**: live with the rig's probe, the probe's picture (it sees the room as
//!   well as the sky). Otherwise, by default (`environment = "local"`), the picture a probe at
//!   the object's centre would take ([`local_probe()`]): the real meshes (live, the held shadow
//!   proxy) under the scene's lights where its rays meet them, a scene file's map where they
//!   escape. The file's map alone (`"map"`, the paper's input) leaves out the room's bounce
//!   light: window_env's front face came out black, and a room lit by lamps alone, live or not,
//!   lit the object with its lamps' direct light only.
//! - **Recomputed only on change**: the maps are kept until the environment differs from the one
//!   they were made from by more than `update_threshold` (relative L1 over the resampled map),
//!   or the exponents change. Comparing with the map they were made from, not the previous
//!   frame, lets slow drift add up and trigger an update.
//! - **Shading** (`shaders/ibl_shade.wgsl`): virtual pixels L_o = k_d E_d(n)·AO + k_s E_s^n(r),
//!   where a local picture's surfaces give their diffuse light from where they are instead
//!   (`near_field`, [`local_probe::NearPatch`], gathered at every `near_stride`-th pixel);
//!   the scene's point, spot and directional lights add their shadow-mapped direct light as in
//!   `differential`.
//! - **Occlusion**: `env_lights` lights importance-sampled from the map each get a shadow
//!   map; on real pixels they give Δ = the light the virtual object takes away (shadows and
//!   contact occlusion, nothing added: no bounce off the object), on the object the ambient
//!   occlusion of its diffuse term.

pub mod local_probe;
pub mod maps;

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use relight_core::PixelRect;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Scene};
use serde_json::{Map, Value};

use crate::deferred::{Deferred, ExtraLights, MapSizes, RealIndirect, ShadeOptions};
use crate::engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::gbuffer::Targets;
use crate::gpu::{GpuContext, GpuError};
use crate::params::{ParamSpec, ParamsSchema};
use crate::roofline::{PassWork, Work};
use crate::shaders;
use crate::timer::timed_pass;
use crate::volume::ObjectBox;
use local_probe::{LocalPicture, local_probe};
use maps::{IblUniform, MAX_LEVELS, ReflectionMaps, input_texels, log_spaced_shininess, resample};
use relight_core::sh::Sh9Rgb;

/// The engine's settings (see [`Ibl::schema`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IblSettings {
    pub map_size: u32,
    pub input_width: u32,
    pub levels: u32,
    pub env_lights: u32,
    pub rsm_size: u32,
    pub shadow_bias: f32,
    pub update_threshold: f32,
    /// Where no probe picture lights the object (a scene file, a live rig without a probe), it
    /// is lit by the picture from its centre ([`local_probe()`]).
    pub local_probe: bool,
    /// The local picture's surfaces light each point of the object from where they are
    /// (`LocalPicture::near`), not only as the centre sees them.
    pub near_field: bool,
    /// The near patches' light is gathered at every `near_stride`-th pixel per axis and shared
    /// between alike pixels (`ibl_shade.wgsl`).
    pub near_stride: u32,
    /// Real pixels also lose the light of the local picture's surfaces that the object blocks
    /// on its way to them (`LocalPicture::probe`, `blocked_irradiance`); else (the default)
    /// their Δ is the shadows alone (the paper). Off by default: `ibl` is the engine chosen for
    /// its frame rate, and shading the whole frame halved it live (28 → 16 fps on the bundled
    /// recording) for a Δ 0.5398 → 0.5302, where `dlpv` reads 0.5209 at 14 fps.
    pub probe_occlusion: bool,
}

impl Default for IblSettings {
    fn default() -> Self {
        Self {
            map_size: 64,
            input_width: 128,
            levels: 0,
            env_lights: 16,
            rsm_size: 512,
            shadow_bias: 1.5,
            update_threshold: 0.02,
            local_probe: true,
            near_field: true,
            near_stride: 2,
            probe_occlusion: false,
        }
    }
}

/// What the current maps and shadow lights were made from.
#[derive(Debug)]
struct Environment {
    scene: Arc<Scene>,
    /// The resampled map the maps were convolved from (`None`: the scene has no environment).
    input: Option<EnvironmentMap>,
    shininess: Vec<f32>,
    settings: IblSettings,
    /// What the local picture was taken of (`None` for the map alone or a probe's picture).
    picture_of: Option<PictureKey>,
    /// The local picture's later bounces (`LocalPicture::bounce`; zero without one), added to
    /// the diffuse map's light at shading.
    bounce: Sh9Rgb,
    /// The local picture's real surfaces (`LocalPicture::probe`; zero without one).
    probe: Sh9Rgb,
    /// The direct light on the object's faces (`LocalPicture::object_faces`).
    object_faces: [Vec3; 6],
    /// The local picture's surface patches on the GPU and their count (`LocalPicture::near`;
    /// `None` without a picture or with `near_field` off).
    near: Option<(wgpu::Buffer, u32)>,
}

/// `NearPatch` in `shaders/ibl_shade.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct GpuNearPatch {
    position_area: [f32; 4],
    normal: [f32; 4],
    radiance: [f32; 4],
}

/// `picture`'s surface patches in a storage buffer, and their count; `None` without any.
fn near_patches(ctx: &GpuContext, picture: &LocalPicture) -> Option<(wgpu::Buffer, u32)> {
    if picture.near.is_empty() {
        return None;
    }
    let patches: Vec<GpuNearPatch> = picture
        .near
        .iter()
        .map(|p| GpuNearPatch {
            position_area: p.position.extend(p.area).to_array(),
            normal: p.normal.extend(0.0).to_array(),
            radiance: p.radiance.extend(0.0).to_array(),
        })
        .collect();
    let buffer = ctx.buffer_with(
        "ibl near patches",
        bytemuck::cast_slice(&patches),
        wgpu::BufferUsages::STORAGE,
    );
    Some((buffer, patches.len() as u32))
}

/// The width of the local picture of a live depth surface (its held shadow proxy; height
/// half). It is taken on the render thread whenever the proxy changes: on the bundled recording
/// 128 × 64 rays held the frame for most of a second, 32 × 16 for a few tens of ms.
const LIVE_PICTURE_WIDTH: u32 = 32;

/// What a local picture was taken of ([`local_probe()`]): the real geometry (a live scene's held
/// shadow proxy by identity, a scene file's real meshes by content), the lights, the distant
/// map (resampled), and the object's bounds. A live scene is a new `Arc` every frame; while
/// these hold, so does the picture, and the object may move by [`PICTURE_HOLDS_WITHIN`] of its
/// size before it is taken again (marker tracking moves it a little on every frame).
#[derive(Debug, Clone, PartialEq)]
struct PictureKey {
    /// The real geometry and the distant map, hashed.
    real: u64,
    lights: Vec<Light>,
    object: Option<(Vec3, Vec3)>,
}

/// How far (a share of its largest edge) the object may move before its picture is taken again.
const PICTURE_HOLDS_WITHIN: f32 = 0.05;

impl PictureKey {
    fn of(scene: &Scene, distant: Option<&EnvironmentMap>) -> Self {
        use std::hash::{Hash, Hasher};
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        match &scene.shadow_proxy {
            Some(proxy) => (Arc::as_ptr(proxy) as usize).hash(&mut hasher),
            None => {
                for mesh in scene.meshes.iter().filter(|m| !m.is_virtual) {
                    for p in &mesh.positions_in_world {
                        p.to_array().map(f32::to_bits).hash(&mut hasher);
                    }
                    mesh.triangles.hash(&mut hasher);
                    mesh.material.hash(&mut hasher);
                }
            }
        }
        for l in distant.iter().flat_map(|env| &env.radiance) {
            l.to_array().map(f32::to_bits).hash(&mut hasher);
        }
        Self {
            real: hasher.finish(),
            lights: scene.lights.clone(),
            object: scene.virtual_bounds(),
        }
    }

    fn holds(&self, other: &Self) -> bool {
        let near = match (self.object, other.object) {
            (Some((a_lo, a_hi)), Some((b_lo, b_hi))) => {
                let tolerance = PICTURE_HOLDS_WITHIN * (a_hi - a_lo).max_element();
                (a_lo - b_lo).abs().max_element() <= tolerance
                    && (a_hi - b_hi).abs().max_element() <= tolerance
            }
            (None, None) => true,
            _ => false,
        };
        near && self.real == other.real && self.lights == other.lights
    }
}

#[derive(Debug)]
pub struct Ibl {
    deferred: Deferred,
    settings: IblSettings,
    /// `ibl_shade.wgsl`'s `main`, `fill` and `resolve` (see its strided gather), and `real`.
    shade: [wgpu::ComputePipeline; 4],
    uniform: wgpu::Buffer,
    maps: ReflectionMaps,
    environment: Option<Environment>,
    convolutions: u64,
    /// Bound in place of the near patches where there are none.
    no_patches: wgpu::Buffer,
}

impl Ibl {
    pub const NAME: &'static str = "ibl";

    pub fn schema() -> ParamsSchema {
        let d = IblSettings::default();
        let int = |name, doc, min, max, default: u32| {
            ParamSpec::int(name, doc, min, max, i64::from(default))
        };
        ParamsSchema::new(vec![
            int(
                "map_size",
                "edge of the octahedral irradiance and reflection maps, texels",
                8,
                512,
                d.map_size,
            ),
            int(
                "input_width",
                "width the environment is resampled to before the convolution (height: half)",
                16,
                2048,
                d.input_width,
            ),
            int(
                "levels",
                "specular maps: 0 = one per Phong exponent of the virtual materials (up to 8), N = N exponents log-spaced from 1 to 512",
                0,
                MAX_LEVELS as i64,
                d.levels,
            ),
            int(
                "env_lights",
                "lights importance-sampled from the environment whose shadow maps give the object's shadows and ambient occlusion",
                0,
                48,
                d.env_lights,
            ),
            int(
                "rsm_size",
                "shadow-map edge per light face, texels",
                64,
                4096,
                d.rsm_size,
            ),
            ParamSpec::float(
                "shadow_bias",
                "shadow-map depth bias in texel footprints (grows with the surface slope)",
                0.0,
                8.0,
                d.shadow_bias,
            ),
            ParamSpec::float(
                "update_threshold",
                "relative change of the environment (L1) that makes the maps be convolved again",
                0.0,
                1.0,
                d.update_threshold,
            ),
            int(
                "near_stride",
                "the near surfaces' light is gathered at every Nth pixel per axis, each pixel between taking its alike neighbours' (1: every pixel)",
                1,
                8,
                d.near_stride,
            ),
            ParamSpec::choice(
                "near_field",
                "`patches`: the local picture's surfaces light each point of the object from where they are, as small area lights (a lit floor lights the object's foot more than its top); `none`: as the object's centre sees them (the paper's distant light)",
                vec!["patches", "none"],
            ),
            ParamSpec::choice(
                "occlusion",
                "`none`: real pixels' Δ is the shadows alone, as in the paper; `probe`: they also lose the light of the local picture's surfaces that the object blocks on its way to them, over the solid angle it covers from them, and see its faces instead (a scene file, or a rig without a probe picture; the whole frame is shaded: live about half the frame rate)",
                vec!["none", "probe"],
            ),
            ParamSpec::choice(
                "environment",
                "what lights the object where no probe picture does (a scene file, a live rig without a probe): `local`, the picture a probe at the object's centre would take (the real meshes under the scene's lights, the map where rays escape); `map`, the scene's map alone (the paper's input)",
                vec!["local", "map"],
            ),
            crate::deferred::accumulate_param(),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        // The maps light the object alone; real pixels take the shadows of the direct and
        // environment lights.
        let mut deferred = Deferred::sampling_the_environment(ctx.clone());
        deferred.set_real_indirect(RealIndirect::Nowhere);
        Ok(Self {
            shade: ["main", "fill", "resolve", "real"].map(|entry| {
                shaders::compute_pipeline_at(&ctx.device, "ibl shade", shaders::IBL_SHADE, entry)
            }),
            uniform: shaders::params_buffer(&ctx.device, "ibl shade", size_of::<IblUniform>()),
            maps: ReflectionMaps::new(&ctx),
            deferred,
            settings: IblSettings::default(),
            environment: None,
            convolutions: 0,
            no_patches: ctx.buffer(
                "ibl no near patches",
                size_of::<GpuNearPatch>() as u64,
                wgpu::BufferUsages::STORAGE,
            ),
        })
    }

    /// How many times the maps have been convolved (they are kept while the environment holds).
    pub fn convolutions(&self) -> u64 {
        self.convolutions
    }

    /// The current maps (layer 0 diffuse, then one per [`ReflectionMaps::shininess`]).
    pub fn maps(&self) -> &ReflectionMaps {
        &self.maps
    }

    /// Convolve the maps and extract the shadow lights again if `scene`'s environment or the
    /// exponents it needs changed enough since the last time.
    fn update_environment(
        &mut self,
        scene: &Arc<Scene>,
    ) -> Result<Option<(PassTiming, PassWork)>, EngineError> {
        let s = self.settings;
        if let Some(e) = &self.environment
            && Arc::ptr_eq(&e.scene, scene)
            && e.settings == s
        {
            return Ok(None);
        }
        // A live scene's map, when it has one, is the rig's probe picture, which sees the room
        // already. A scene file's (no depth surface, no probe lights) is the distant sky alone.
        let scene_file = scene.surface_revision.is_none() && scene.environment_lights.is_empty();
        let distant = scene
            .environment
            .as_ref()
            .map(|env| resample(env, s.input_width));
        let picture_of = (s.local_probe && (scene_file || scene.environment.is_none()))
            .then(|| PictureKey::of(scene, distant.as_ref()));
        if let (Some(key), Some(e)) = (&picture_of, self.environment.as_mut())
            && e.settings == s
            && e.picture_of.as_ref().is_some_and(|k| k.holds(key))
        {
            e.scene = scene.clone();
            return Ok(None);
        }
        let ctx = self.deferred.ctx().clone();
        // With near patches, the texels they stand for are left out of the diffuse map.
        let (input, (bounce, probe, object_faces), near, specular_only) = match &picture_of {
            Some(_) => {
                let width = if scene.shadow_proxy.is_some() {
                    s.input_width.min(LIVE_PICTURE_WIDTH)
                } else {
                    s.input_width
                };
                match local_probe(scene, width, s.probe_occlusion) {
                    Some(picture) => {
                        let near = s.near_field.then(|| near_patches(&ctx, &picture)).flatten();
                        let specular_only = near.is_some().then_some(picture.surfaces);
                        let light = (picture.bounce, picture.probe, picture.object_faces);
                        (Some(picture.map), light, near, specular_only)
                    }
                    None => (
                        distant.clone(),
                        (Sh9Rgb::ZERO, Sh9Rgb::ZERO, [Vec3::ZERO; 6]),
                        None,
                        None,
                    ),
                }
            }
            None => (
                distant.clone(),
                (Sh9Rgb::ZERO, Sh9Rgb::ZERO, [Vec3::ZERO; 6]),
                None,
                None,
            ),
        };
        let shininess = specular_levels(scene, s.levels);
        let unchanged = self.environment.as_ref().is_some_and(|e| {
            e.settings == s
                && e.shininess == shininess
                && match (&e.input, &input) {
                    (None, None) => true,
                    (Some(a), Some(b)) => relative_change(a, b) <= s.update_threshold,
                    _ => false,
                }
        });
        if unchanged {
            if let Some(e) = self.environment.as_mut() {
                e.scene = scene.clone();
                e.picture_of = picture_of;
                e.bounce = bounce;
                e.probe = probe;
                e.object_faces = object_faces;
                e.near = near;
            }
            return Ok(None);
        }
        let started = Instant::now();
        let mut work = Work::default();
        let lights = match &input {
            Some(input) => {
                let mut timer = self.deferred.lend_timer();
                work = self.maps.convolve(
                    &ctx,
                    &input_texels(input, specular_only.as_deref()),
                    s.map_size,
                    &shininess,
                    &mut timer,
                )?;
                self.deferred.return_timer(timer);
                self.convolutions += 1;
                // The shadows on real pixels are the distant map's: the real surfaces in the
                // local picture cast none of their own.
                distant
                    .as_ref()
                    .map_or_else(Vec::new, |env| shadow_lights(env, s.env_lights))
            }
            None => Vec::new(),
        };
        self.deferred
            .set_extra_lights(lights, ExtraLights::ShadowOnly);
        self.environment = Some(Environment {
            scene: scene.clone(),
            input,
            shininess,
            settings: s,
            picture_of,
            bounce,
            probe,
            object_faces,
            near,
        });
        Ok(Some((
            PassTiming {
                pass: "convolve",
                ms: started.elapsed().as_secs_f64() * 1e3,
            },
            PassWork {
                pass: "convolve",
                work,
            },
        )))
    }
}

/// The lights standing in for `env` as shadow casters: `count` directions importance-sampled
/// from the map at fixed stratified points (DIR's environment lights), each carrying its share
/// of the irradiance. On window_env (16 lights, 80×60) their shadows score 0.154 relative L2
/// against the reference, the variance-minimising median cut's 16 region lights 0.189: the
/// stratified samples spread over the window's area, median cut puts one light per region.
fn shadow_lights(env: &EnvironmentMap, count: u32) -> Vec<Light> {
    crate::dir::environment_lights(env, count)
}

/// The Phong exponents to convolve: `levels` log-spaced from 1 to 512, or (`levels` = 0) the
/// distinct exponents of the virtual object's glossy materials, thinned log-evenly to
/// [`MAX_LEVELS`] when there are more.
fn specular_levels(scene: &Scene, levels: u32) -> Vec<f32> {
    if levels > 0 {
        return log_spaced_shininess(levels);
    }
    let mut exponents: Vec<f32> = scene
        .meshes
        .iter()
        .filter(|m| m.is_virtual)
        .filter_map(|m| scene.materials.get(m.material))
        .filter(|m| m.shininess > 0.0 && m.specular.max_element() > 0.0)
        .map(|m| m.shininess)
        .collect();
    exponents.sort_by(f32::total_cmp);
    exponents.dedup();
    if exponents.len() > MAX_LEVELS {
        let last = exponents.len() - 1;
        exponents = (0..MAX_LEVELS)
            .map(|k| exponents[k * last / (MAX_LEVELS - 1)])
            .collect();
    }
    exponents
}

/// Σ|b − a| / Σ|a| over the texels' RGB (1 when the sizes differ or `a` is black and `b` not).
fn relative_change(a: &EnvironmentMap, b: &EnvironmentMap) -> f32 {
    if a.width != b.width || a.height != b.height {
        return 1.0;
    }
    let (mut diff, mut norm) = (0f64, 0f64);
    for (x, y) in a.radiance.iter().zip(&b.radiance) {
        diff += f64::from((*y - *x).abs().element_sum());
        norm += f64::from(x.abs().element_sum());
    }
    if norm > 0.0 {
        (diff / norm) as f32
    } else if diff > 0.0 {
        1.0
    } else {
        0.0
    }
}

impl Engine for Ibl {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, frame: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let convolved = match &frame.scene {
            Some(scene) => self.update_environment(scene)?,
            None => None,
        };
        let s = self.settings;
        // The light the object blocks reaches real surfaces anywhere.
        let probe = self
            .environment
            .as_ref()
            .map(|e| e.probe)
            .filter(|p| s.probe_occlusion && *p != Sh9Rgb::ZERO);
        self.deferred.set_real_indirect(if probe.is_some() {
            RealIndirect::Anywhere
        } else {
            RealIndirect::Nowhere
        });
        let Some((width, height)) =
            self.deferred
                .prepare(Self::NAME, frame, out, MapSizes::shadows(s.rsm_size))?
        else {
            return Ok(());
        };
        // After `prepare`, which starts the frame's timings (the convolution's GPU timestamp
        // is lost with the timer's reset; `bench --ibl-maps` times the convolution alone).
        if let Some((timing, work)) = convolved {
            out.timings.push(timing);
            out.work.push(work);
        }
        let has_maps = self.environment.as_ref().is_some_and(|e| e.input.is_some());
        if has_maps {
            let started = Instant::now();
            let ctx = self.deferred.ctx().clone();
            // Only the object's pixels are shaded here, and they lie within the pixels it can
            // change.
            let region = self
                .deferred
                .real_pixels()
                .unwrap_or(PixelRect::full(width, height));
            let near = self.environment.as_ref().and_then(|e| e.near.as_ref());
            let patches = near.map_or(0, |(_, n)| *n);
            let mut uniform = IblUniform {
                dims: [
                    self.maps.size(),
                    self.maps.shininess().len() as u32,
                    0,
                    patches,
                ],
                frame: [
                    width,
                    height,
                    self.deferred.lights().len() as u32,
                    s.rsm_size,
                ],
                params: [s.shadow_bias, s.near_stride as f32, 0.0, 0.0],
                shininess: [0.0; MAX_LEVELS],
                region: [
                    region.x,
                    region.y,
                    region.x + region.width,
                    region.y + region.height,
                ],
                bounce: self
                    .environment
                    .as_ref()
                    .map_or(Sh9Rgb::ZERO, |e| e.bounce)
                    .coeffs
                    .map(|c| c.extend(0.0).to_array()),
                probe: probe
                    .unwrap_or(Sh9Rgb::ZERO)
                    .coeffs
                    .map(|c| c.extend(0.0).to_array()),
                object: ObjectBox::of_frame(frame).uniform(),
                object_faces: self
                    .environment
                    .as_ref()
                    .map_or([Vec3::ZERO; 6], |e| e.object_faces)
                    .map(|f| f.extend(0.0).to_array()),
            };
            uniform.shininess[..self.maps.shininess().len()].copy_from_slice(self.maps.shininess());
            ctx.queue
                .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
            let mut timer = self.deferred.lend_timer();
            let (Some(shadows), Some((gb_rho, _, indirect)), Some(gpu_scene), Some(maps)) = (
                self.deferred.shadow_maps(),
                self.deferred.frame_buffers(),
                self.deferred.scene(),
                self.maps.buffer(),
            ) else {
                return Err(EngineError::NotPrepared);
            };
            let views = [
                Targets::view(&gb_rho.position),
                Targets::view(&gb_rho.normal),
                Targets::view(&gb_rho.albedo),
                shadows.rho.depth_array_view(),
            ];
            let mut resources = vec![
                self.uniform.as_entire_binding(),
                self.deferred.camera_buffer().as_entire_binding(),
                shadows.lights.as_entire_binding(),
                shadows.faces.as_entire_binding(),
                gpu_scene.materials.as_entire_binding(),
            ];
            resources.extend(views.iter().map(wgpu::BindingResource::TextureView));
            let near_buffer = near.map_or(&self.no_patches, |(b, _)| b);
            resources.extend([maps, indirect, near_buffer].map(|b| b.as_entire_binding()));
            let [main, fill, resolve, real] = &self.shade;
            let groups = [
                shaders::pipeline_bind_group(&ctx.device, main, "ibl shade", &resources),
                shaders::pipeline_bind_group(&ctx.device, fill, "ibl shade fill", &resources),
                // `resolve` gathers nothing: every binding but the patches.
                shaders::pipeline_bind_group_of(
                    &ctx.device,
                    resolve,
                    "ibl shade resolve",
                    &resources,
                    &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10],
                ),
                // `real` reads the uniform, the G-buffer and the light.
                shaders::pipeline_bind_group_of(
                    &ctx.device,
                    real,
                    "ibl shade real",
                    &resources,
                    &[0, 5, 6, 7, 10],
                ),
            ];
            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("ibl shade"),
                });
            out.work.push(PassWork {
                pass: "ibl_shade",
                // Per pixel the G-buffer read and the result written, the diffuse and one
                // specular map read bilinearly (8 texels of 16 bytes), about 300 operations;
                // per gathered pixel (every `near_stride`-th per axis) and near patch about 25
                // operations; the patches (48 bytes) read once.
                work: Work::new(32.0 + 16.0 + 8.0 * 16.0, 300.0).times(region.area() as f64)
                    + Work::new(0.0, 25.0 * f64::from(patches)).times(
                        f64::from(region.width.div_ceil(s.near_stride))
                            * f64::from(region.height.div_ceil(s.near_stride)),
                    )
                    + Work::new(48.0 * f64::from(patches), 0.0)
                    // With the light the object blocks, about 200 operations a real pixel.
                    + Work::new(0.0, if probe.is_some() { 200.0 } else { 0.0 })
                        .times(region.area() as f64),
            });
            {
                let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.ibl_shade");
                // The strided pixels from the one at or before the region's first.
                let stride = s.near_stride;
                let strided =
                    |first: u32, end: u32| (end - first / stride * stride).div_ceil(stride);
                let gathered = (
                    strided(region.x, region.x + region.width),
                    strided(region.y, region.y + region.height),
                );
                let passes = if stride > 1 { 3 } else { 1 };
                for (k, (pipeline, group)) in
                    self.shade.iter().zip(&groups).take(passes).enumerate()
                {
                    pass.set_pipeline(pipeline);
                    pass.set_bind_group(0, group, &[]);
                    let (x, y) = if k == 1 {
                        (region.width, region.height)
                    } else {
                        gathered
                    };
                    pass.dispatch_workgroups(x.div_ceil(8), y.div_ceil(8), 1);
                }
                if probe.is_some() {
                    pass.set_pipeline(&self.shade[3]);
                    pass.set_bind_group(0, &groups[3], &[]);
                    pass.dispatch_workgroups(
                        region.width.div_ceil(8),
                        region.height.div_ceil(8),
                        1,
                    );
                }
            }
            ctx.queue.submit([encoder.finish()]);
            ctx.check()?;
            self.deferred.return_timer(timer);
            out.timings.push(PassTiming {
                pass: "ibl shade",
                ms: started.elapsed().as_secs_f64() * 1e3,
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
        self.settings = IblSettings {
            map_size: int("map_size"),
            input_width: int("input_width"),
            levels: int("levels"),
            env_lights: int("env_lights"),
            rsm_size: int("rsm_size"),
            shadow_bias: float("shadow_bias"),
            update_threshold: float("update_threshold"),
            local_probe: schema.choice(params, "environment") == "local",
            near_field: schema.choice(params, "near_field") == "patches",
            near_stride: int("near_stride"),
            probe_occlusion: schema.choice(params, "occlusion") == "probe",
        };
        self.deferred.set_shared_params(&schema, params);
    }
}

#[cfg(test)]
impl crate::shadow_reach::tests::WithDeferred for Ibl {
    fn deferred_mut(&mut self) -> &mut Deferred {
        &mut self.deferred
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn map(value: f32) -> EnvironmentMap {
        EnvironmentMap {
            width: 8,
            height: 4,
            radiance: vec![Vec3::splat(value); 32],
        }
    }

    #[test]
    fn relative_change_is_l1() {
        assert_eq!(relative_change(&map(1.0), &map(1.0)), 0.0);
        assert!((relative_change(&map(1.0), &map(1.05)) - 0.05).abs() < 1e-5);
        assert_eq!(relative_change(&map(0.0), &map(1.0)), 1.0);
        assert_eq!(relative_change(&map(0.0), &map(0.0)), 0.0);
    }

    /// A scene with nothing in it, for the tests to fill.
    fn empty_scene() -> Scene {
        Scene {
            name: String::new(),
            meshes: Vec::new(),
            materials: Vec::new(),
            camera: relight_core::scene::SceneCamera {
                world_from_camera: relight_core::Pose::IDENTITY,
                yfov_rad: 1.0,
                width: 4,
                height: 4,
            },
            lights: Vec::new(),
            environment: None,
            environment_lights: Vec::new(),
            shadow_proxy: None,
            surface_revision: None,
        }
    }

    /// The local picture is taken again when the real geometry, the lights or the map change,
    /// or when the object moves by more than 5 % of its size, not for a tracker's jitter.
    #[test]
    fn a_local_picture_holds_while_what_it_shows_holds() {
        let mut scene = Scene {
            meshes: vec![
                relight_core::scene::Mesh::cuboid("floor", Vec3::splat(-1.0), Vec3::ZERO, 0, false),
                relight_core::scene::Mesh::cuboid("box", Vec3::ZERO, Vec3::splat(0.2), 0, true),
            ],
            ..empty_scene()
        };
        let key = |scene: &Scene, env: Option<&EnvironmentMap>| PictureKey::of(scene, env);
        let first = key(&scene, None);
        let shift = |scene: &mut Scene, by: f32| {
            for p in &mut scene.meshes[1].positions_in_world {
                p.x += by;
            }
        };
        shift(&mut scene, 0.002);
        assert!(first.holds(&key(&scene, None)), "2 mm of jitter");
        shift(&mut scene, 0.02);
        assert!(!first.holds(&key(&scene, None)), "the object moved 2.2 cm");
        shift(&mut scene, -0.022);
        assert!(!first.holds(&key(&scene, Some(&map(1.0)))), "another map");
        scene.lights.push(Light::Directional {
            direction_in_world: Vec3::NEG_Y,
            irradiance: Vec3::ONE,
        });
        assert!(!first.holds(&key(&scene, None)), "another light");
        scene.lights.clear();
        scene.meshes[0].positions_in_world[0].y += 1e-5;
        assert!(!first.holds(&key(&scene, None)), "the real geometry moved");
    }

    #[test]
    fn fixed_levels_span_one_to_512() {
        let scene = empty_scene();
        let levels = specular_levels(&scene, 8);
        assert_eq!(levels.len(), 8);
        assert_eq!((levels[0], levels[7]), (1.0, 512.0));
        assert!(specular_levels(&scene, 0).is_empty());
    }
}
