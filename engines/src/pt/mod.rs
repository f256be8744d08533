//! `pt`: progressive differential path tracing on the GPU, the accuracy ceiling of the engines.
//!
//! Each frame traces a number of samples per pixel of L^ρ and, from the same random numbers,
//! L^μ (correlated sampling, as the CPU reference: L^μ is traced only where the ρ path touched
//! the virtual object, so Δ is exactly zero wherever the object plays no part) with the
//! reference's estimator (`shaders/pt_trace.wgsl`), over the reference's own triangles and BVH
//! ([`scene::PtScene`]). The samples are folded into per-pixel running means, so while the
//! scene, the lights and the camera hold still the picture converges to the reference's; any
//! change starts the means again (no reprojection: a moved camera sees other paths).
//!
//! What counts as a change:
//! - the geometry, materials, lights or environment map (hashed; a live depth surface by its
//!   [`Scene::surface_revision`], which the temporal depth merge advances only when it resets,
//!   so sensor noise on a held surface does not restart the means);
//! - the camera moving by more than [`STILL_PX`](crate::change::STILL_PX) of image motion
//!   at the object's depth ([`crate::change::camera_still`]); below that the held pose is
//!   traced, so a tracked camera's jitter does not restart them either;
//! - the image size or any parameter.
//!
//! Samples per frame follow `budget_ms` (measured per sample, so the frame fits the budget on
//! whatever adapter runs it) or are fixed by `spp`; after `max_spp` the means are kept. A
//! sample is traced in [`TILE_PHASES`] units, each the 8 × 8 tiles of one phase (tile index
//! mod [`TILE_PHASES`]), and a frame traces as many units as fit: where one sample per pixel
//! costs more than the budget (`pt` on a CPU adapter costs 27–41 ms a sample at 160 × 120), a
//! frame traces a share of one and still fits, and no pixel is more than one sample ahead of
//! another. Sample `s` of pixel `i` always draws from the stream seeded by (seed, i, s), `s`
//! the pixel's own count, so the picture after n samples does not depend on how they were
//! split between frames, and the same seed renders the same image. The composite follows
//! DLPV's Algorithm 1 per sample: L^ρ where the sample's camera ray met the object, the
//! background plus Δ elsewhere (so silhouettes are area-sampled). Each frame reports its own Monte Carlo error
//! ([`RelitFrame::estimated_relative_error`]): the standard error of Δ over the real pixels
//! relative to Δ itself.

pub mod scene;

use std::sync::Arc;
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use relight_core::scene::{Scene, SceneCamera};
use serde_json::{Map, Value};

use self::scene::PtScene;
use crate::change::{camera_still, scene_key};
use crate::deferred::KeptInputs;
use crate::engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::gpu::{GpuContext, GpuError};
use crate::params::{ParamSpec, ParamsSchema};
use crate::roofline::{PassWork, Work};
use crate::shaders;
use crate::timer::{GpuTimer, timed_pass};

/// Samples per pixel in one dispatch at most (a frame may submit several).
const DISPATCH_SPP: u32 = 64;

/// The units a sample per pixel is traced in: unit u traces the 8 × 8 tiles (row-major index)
/// ≡ u (mod this).
pub const TILE_PHASES: u32 = 16;

/// A frame aims at this share of the budget, after its fixed part: a frame's cost drifts by a
/// few per cent from the one it was fitted to, and the budget is a limit, not a target.
const BUDGET_SHARE: f64 = 0.95;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Params {
    size: [u32; 4],
    options: [u32; 4],
    seed: [u32; 4],
    units: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct PtCamera {
    position: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    back: [f32; 4],
}

/// [`Pt::statistics`]: the running means, per pixel, row-major from the top-left.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PtStatistics {
    /// Samples in every pixel (a pixel may hold one more).
    pub spp: u32,
    /// Δ = L^ρ − L^μ, the mean over the pixel's samples (its area).
    pub delta: Vec<glam::Vec3>,
    /// The standard error of `delta` from the pixel's samples' variance; ∞ below 2 samples.
    pub delta_std_error: Vec<glam::Vec3>,
    /// The overlay the composite is made of: the mean over the pixel's samples of L^ρ where
    /// the sample's camera ray met the virtual object and Δ where it did not (rgb), and the
    /// share of samples that met the object (w). Where w is 1, rgb is L^ρ.
    pub overlay: Vec<glam::Vec4>,
}

/// The parameters (see [`Pt::schema`]).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Settings {
    budget_ms: f64,
    spp: u32,
    max_spp: u32,
    bounces: u32,
    seed: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            budget_ms: 33.0,
            spp: 0,
            max_spp: 4096,
            bounces: 8,
            seed: 0,
        }
    }
}

/// Russian roulette from this bounce on, as the reference's default.
const RR_START_BOUNCE: u32 = 3;

/// Per-size buffers.
#[derive(Debug)]
struct FrameBuffers {
    width: u32,
    height: u32,
    accum: wgpu::Buffer,
    background: wgpu::Buffer,
    delta: wgpu::Buffer,
    composite: wgpu::Buffer,
    /// The composite, then Δ: both read back in one copy.
    staging: wgpu::Buffer,
}

/// What the running means were traced from.
#[derive(Debug, Clone, Copy)]
struct Accumulated {
    /// The scene's key ([`scene_key`]) and the parameters.
    key: u64,
    /// The camera traced (held while the real one is still: [`crate::change::camera_still`]).
    camera: SceneCamera,
    /// Units traced ([`TILE_PHASES`] to a sample per pixel).
    units: u32,
}

#[derive(Debug)]
pub struct Pt {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    resolve: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    camera: wgpu::Buffer,
    settings: Settings,
    /// The uploaded scene, the `Arc` it came from and its key.
    scene: Option<(Arc<Scene>, u64, PtScene)>,
    frame: Option<FrameBuffers>,
    accumulated: Option<Accumulated>,
    /// The trace's measured time and units, each frame's added to half the sums before: their
    /// ratio is a unit's cost, weighted by units, so that a frame of few units (whose time is
    /// mostly the dispatch's fixed part) does not hold the next frames far under the budget. A
    /// frame that costs under half that per unit starts the sums again: the first frame may
    /// have compiled the pipeline (seconds on lavapipe).
    trace_sums: Option<(f64, f64)>,
    /// Measured cost of a frame's fixed part (upload, resolve, read-back), milliseconds (a
    /// running average).
    overhead_ms: Option<f64>,
    background: Vec<u32>,
    timer: Option<GpuTimer>,
}

impl Pt {
    pub const NAME: &'static str = "pt";

    pub fn schema() -> ParamsSchema {
        ParamsSchema::new(vec![
            ParamSpec::float(
                "budget_ms",
                "frame time the samples per frame are fitted to (with spp = 0)",
                1.0,
                60_000.0,
                33.0,
            ),
            ParamSpec::int(
                "spp",
                "samples per pixel each frame; 0 follows budget_ms",
                0,
                4096,
                0,
            ),
            ParamSpec::int(
                "max_spp",
                "samples per pixel after which a still picture is kept as it is",
                1,
                1 << 20,
                4096,
            ),
            ParamSpec::int(
                "bounces",
                "scattering events after the first hit (the reference's max_bounces)",
                0,
                64,
                8,
            ),
            ParamSpec::int("seed", "seeds every sample's random stream", 0, 1 << 31, 0),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let pipeline = shaders::compute_pipeline(&ctx.device, "pt trace", shaders::PT_TRACE);
        let resolve = shaders::compute_pipeline(&ctx.device, "pt resolve", shaders::PT_RESOLVE);
        let uniform = |label, size| shaders::params_buffer(&ctx.device, label, size);
        ctx.check()?;
        Ok(Self {
            pipeline,
            resolve,
            params: uniform("pt params", size_of::<Params>()),
            camera: uniform("pt camera", size_of::<PtCamera>()),
            settings: Settings::default(),
            scene: None,
            frame: None,
            accumulated: None,
            trace_sums: None,
            overhead_ms: None,
            background: Vec::new(),
            timer: GpuTimer::new(&ctx),
            ctx,
        })
    }

    /// Samples in every pixel of the running means (a pixel may hold one more).
    pub fn samples(&self) -> u32 {
        self.accumulated.map_or(0, |a| a.units / TILE_PHASES)
    }

    /// The running means as they stand after the last frame, read back: per pixel Δ and its
    /// standard error per channel (as the reference's [`ReferenceImages`] gives them), and
    /// the overlay with the object's coverage.
    ///
    /// [`ReferenceImages`]: relight_reference::ReferenceImages
    pub fn statistics(&self) -> Result<PtStatistics, GpuError> {
        let spp = self.samples();
        let Some(frame) = &self.frame else {
            return Ok(PtStatistics::default());
        };
        let pixels = u64::from(frame.width) * u64::from(frame.height);
        let staging = self.ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pt means staging"),
            size: pixels * 48,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.ctx
            .read_back(&frame.accum, &staging, pixels * 48, |bytes| {
                let means: &[[[f32; 4]; 3]] = bytemuck::cast_slice(bytes);
                // The pixel's own sample count is the w of its Δ mean.
                let std_error = |n: f32, m2: f32| {
                    let n = f64::from(n);
                    if n < 2.0 {
                        f32::INFINITY
                    } else {
                        (f64::from(m2.max(0.0)) / (n - 1.0) / n).sqrt() as f32
                    }
                };
                PtStatistics {
                    spp,
                    delta: means
                        .iter()
                        .map(|[_, d, _]| glam::Vec3::new(d[0], d[1], d[2]))
                        .collect(),
                    delta_std_error: means
                        .iter()
                        .map(|[_, d, m2]| {
                            glam::Vec3::from_array(
                                [m2[0], m2[1], m2[2]].map(|m| std_error(d[3], m)),
                            )
                        })
                        .collect(),
                    overlay: means
                        .iter()
                        .map(|[overlay, _, _]| glam::Vec4::from_array(*overlay))
                        .collect(),
                }
            })
    }

    /// Units to trace this frame, `remaining` short of `max_spp`: at least one while any remain.
    fn units_this_frame(&self, remaining: u32) -> u32 {
        let per_unit = self.trace_sums.map(|(ms, units)| ms / units);
        let wanted = match (self.settings.spp, per_unit) {
            (0, None) => 1,
            (0, Some(per_unit)) => {
                let left = BUDGET_SHARE * self.settings.budget_ms - self.overhead_ms.unwrap_or(0.0);
                (left / per_unit.max(1e-6))
                    .floor()
                    .clamp(1.0, f64::from(4096 * TILE_PHASES)) as u32
            }
            (spp, _) => spp * TILE_PHASES,
        };
        wanted.min(remaining)
    }

    /// Upload the scene if it changed; its key.
    fn upload(&mut self, scene: &Arc<Scene>) -> u64 {
        if let Some((held, key, _)) = &self.scene
            && Arc::ptr_eq(held, scene)
        {
            return *key;
        }
        let key = scene_key(scene);
        match &mut self.scene {
            Some((held, held_key, _)) if *held_key == key => *held = scene.clone(),
            _ => self.scene = Some((scene.clone(), key, PtScene::new(&self.ctx, scene))),
        }
        key
    }
}

impl FrameBuffers {
    fn new(ctx: &GpuContext, width: u32, height: u32) -> Self {
        let pixels = u64::from(width) * u64::from(height);
        let buffer = |label, size, usage| ctx.buffer(label, size, usage);
        use wgpu::BufferUsages as U;
        Self {
            width,
            height,
            accum: buffer(
                "pt means",
                pixels * 48,
                U::STORAGE | U::COPY_DST | U::COPY_SRC,
            ),
            background: buffer("pt background", pixels * 4, U::STORAGE | U::COPY_DST),
            delta: buffer("pt delta", pixels * 16, U::STORAGE | U::COPY_SRC),
            composite: buffer("pt composite", pixels * 4, U::STORAGE | U::COPY_SRC),
            staging: buffer("pt frame staging", pixels * 20, U::MAP_READ | U::COPY_DST),
        }
    }
}

fn camera_uniform(camera: &SceneCamera, width: u32, height: u32) -> PtCamera {
    let pose = camera.world_from_camera;
    let axis = |v: glam::Vec3| pose.rotation.mul_vec3(v);
    PtCamera {
        position: pose
            .translation
            .extend((camera.yfov_rad / 2.0).tan())
            .to_array(),
        right: axis(glam::Vec3::X)
            .extend(width as f32 / height.max(1) as f32)
            .to_array(),
        up: axis(glam::Vec3::Y).extend(0.0).to_array(),
        back: axis(glam::Vec3::Z).extend(0.0).to_array(),
    }
}

/// What `spp` samples per pixel (a share of one where a frame traces some of the rows) cost at
/// most, for the roofline: per sample a path of up to `bounces + 2`
/// rays per solution, each a BVH walk of about 2·log2(triangles) box tests (40 operations) and
/// a few triangle tests (60), plus a shadow ray per light and the environment; the means read
/// and written once.
fn trace_work(pixels: u64, spp: f64, triangles: u32, lights: u32, bounces: u32) -> Work {
    let walk = 2.0 * f64::from(triangles.max(2)).log2() * 40.0 + 4.0 * 60.0;
    let rays_per_path = f64::from(bounces + 2) * (1.0 + f64::from(lights) + 1.0);
    Work::new(48.0 * 2.0, walk * rays_per_path * 2.0 * spp).times(pixels as f64)
}

/// The resolve pass over `pixels`: the running means (48 bytes) and the background read, Δ
/// (16) and the composite (4) written; about 40 operations for the variance and the blend.
fn resolve_work(pixels: u64) -> Work {
    Work::new(48.0 + 4.0 + 16.0 + 4.0, 40.0).times(pixels as f64)
}

impl Engine for Pt {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, frame: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let started = Instant::now();
        let color = out.begin(Self::NAME, frame)?;
        let scene = frame.scene.as_ref().ok_or(EngineError::MissingInput {
            engine: Self::NAME,
            stream: "scene",
        })?;
        let (width, height) = (color.width(), color.height());
        let ctx = self.ctx.clone();
        ctx.require(
            "max_storage_buffer_binding_size",
            u64::from(width) * u64::from(height) * 48,
            "the camera resolution",
        )?;
        if !self
            .frame
            .as_ref()
            .is_some_and(|f| f.width == width && f.height == height)
        {
            self.frame = Some(FrameBuffers::new(&ctx, width, height));
            self.accumulated = None;
        }
        // The estimator's own settings; the budget and the sample counts change how fast the
        // means converge, not what to.
        let key = KeptInputs::hash_of(&[
            &self.upload(scene).to_le_bytes(),
            &self.settings.bounces.to_le_bytes(),
            &self.settings.seed.to_le_bytes(),
        ]);
        let still = self
            .accumulated
            .filter(|a| a.key == key && camera_still(&a.camera, scene, height));
        let mut accumulated = still.unwrap_or(Accumulated {
            key,
            camera: scene.camera,
            units: 0,
        });
        if still.is_none() {
            let frame_res = self.frame.as_ref().ok_or(EngineError::NotPrepared)?;
            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("pt reset"),
                });
            encoder.clear_buffer(&frame_res.accum, 0, None);
            ctx.queue.submit([encoder.finish()]);
        }
        let units = self.units_this_frame(
            (self.settings.max_spp * TILE_PHASES).saturating_sub(accumulated.units),
        );
        let (Some(frame_res), Some((_, _, gpu_scene))) = (&self.frame, &self.scene) else {
            return Err(EngineError::NotPrepared);
        };
        self.background.clear();
        if let Some(rgb) = color.as_u8() {
            self.background.extend(
                rgb.chunks_exact(3)
                    .map(|px| u32::from_le_bytes([px[0], px[1], px[2], 255])),
            );
        }
        ctx.queue.write_buffer(
            &frame_res.background,
            0,
            bytemuck::cast_slice(&self.background),
        );
        ctx.queue.write_buffer(
            &self.camera,
            0,
            bytemuck::bytes_of(&camera_uniform(&accumulated.camera, width, height)),
        );
        let params = |batch: u32, first: u32| Params {
            size: [width, height, batch, first],
            options: [
                self.settings.bounces,
                RR_START_BOUNCE,
                gpu_scene.light_count,
                gpu_scene.root,
            ],
            seed: [
                self.settings.seed as u32,
                (self.settings.seed >> 32) as u32,
                gpu_scene.env_size.0,
                gpu_scene.env_size.1,
            ],
            units: [TILE_PHASES, 0, 0, 0],
        };
        let trace_group = shaders::pipeline_bind_group(
            &ctx.device,
            &self.pipeline,
            "pt trace",
            &[
                self.params.as_entire_binding(),
                self.camera.as_entire_binding(),
                gpu_scene.tris.as_entire_binding(),
                gpu_scene.shades.as_entire_binding(),
                gpu_scene.nodes.as_entire_binding(),
                gpu_scene.materials.as_entire_binding(),
                gpu_scene.lights.as_entire_binding(),
                gpu_scene.env_radiance.as_entire_binding(),
                gpu_scene.env_tables.as_entire_binding(),
                frame_res.accum.as_entire_binding(),
            ],
        );
        if let Some(timer) = self.timer.as_mut() {
            timer.reset();
        }
        // Tile slots per phase: the trace's workgroups along x.
        let slots = (width.div_ceil(8) * height.div_ceil(8)).div_ceil(TILE_PHASES);
        let trace_started = Instant::now();
        let mut traced = 0;
        while traced < units {
            let batch = (units - traced).min(DISPATCH_SPP * TILE_PHASES);
            ctx.queue.write_buffer(
                &self.params,
                0,
                bytemuck::bytes_of(&params(batch, accumulated.units + traced)),
            );
            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("pt trace"),
                });
            {
                let mut pass = timed_pass(&mut encoder, &mut self.timer, "gpu.trace");
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &trace_group, &[]);
                pass.dispatch_workgroups(slots, batch.min(TILE_PHASES), 1);
            }
            ctx.queue.submit([encoder.finish()]);
            traced += batch;
            // Each batch's parameters must reach the GPU before the next overwrites them.
            ctx.wait()?;
        }
        let trace_ms = trace_started.elapsed().as_secs_f64() * 1e3;
        if units > 0 {
            out.work.push(PassWork {
                pass: "trace",
                work: trace_work(
                    u64::from(width) * u64::from(height),
                    f64::from(units) / f64::from(TILE_PHASES),
                    gpu_scene.triangles,
                    gpu_scene.light_count,
                    self.settings.bounces,
                ),
            });
        }
        accumulated.units += units;
        self.accumulated = Some(accumulated);
        // Every frame resolves: the background is new even when the means are not.
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params(0, 0)));
        let resolve_group = shaders::pipeline_bind_group(
            &ctx.device,
            &self.resolve,
            "pt resolve",
            &[
                self.params.as_entire_binding(),
                frame_res.accum.as_entire_binding(),
                frame_res.background.as_entire_binding(),
                frame_res.delta.as_entire_binding(),
                frame_res.composite.as_entire_binding(),
            ],
        );
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("pt resolve"),
            });
        {
            let mut pass = timed_pass(&mut encoder, &mut self.timer, "gpu.resolve");
            pass.set_pipeline(&self.resolve);
            pass.set_bind_group(0, &resolve_group, &[]);
            pass.dispatch_workgroups(width.div_ceil(8), height.div_ceil(8), 1);
        }
        if let Some(timer) = &self.timer {
            timer.resolve(&mut encoder);
        }
        out.work.push(PassWork {
            pass: "resolve",
            work: resolve_work(u64::from(width) * u64::from(height)),
        });
        ctx.queue.submit([encoder.finish()]);
        let pixels = u64::from(width) * u64::from(height);
        // The composite's alpha holds the object's coverage: pixels under half covered are
        // the real ones Δ's error is estimated over.
        let composite_bytes = pixels * 4;
        let (variance, square) = ctx.read_back_all(
            &[
                (&frame_res.composite, 0..composite_bytes),
                (&frame_res.delta, 0..pixels * 16),
            ],
            &frame_res.staging,
            |bytes| {
                let (composite, delta) = bytes.split_at(composite_bytes as usize);
                crate::deferred::write_composite(composite, &mut out.composite);
                out.non_finite = crate::deferred::write_delta(delta, &mut out.delta);
                let values: &[[f32; 4]] = bytemuck::cast_slice(delta);
                values
                    .iter()
                    .zip(composite.chunks_exact(4))
                    .filter(|(_, px)| px[3] < 128)
                    .fold((0.0, 0.0), |(variance, square), (v, _)| {
                        let delta = glam::Vec3::new(v[0], v[1], v[2]);
                        (
                            variance + f64::from(v[3].max(0.0)),
                            square + f64::from(delta.length_squared()),
                        )
                    })
            },
        )?;
        let phases = f64::from(TILE_PHASES);
        out.path_samples = f64::from(accumulated.units) / phases;
        out.path_samples_traced = f64::from(units) / phases;
        out.estimated_relative_error = (accumulated.units >= 2 * TILE_PHASES && square > 0.0)
            .then(|| (variance / square).sqrt());
        out.timings.push(PassTiming {
            pass: "trace",
            ms: trace_ms,
        });
        if let Some(timer) = &mut self.timer {
            timer.read(&mut out.timings)?;
        }
        let total_ms = started.elapsed().as_secs_f64() * 1e3;
        if units > 0 {
            let units = f64::from(units);
            let (ms, traced) = self
                .trace_sums
                .filter(|(ms, traced)| trace_ms / units >= 0.5 * ms / traced)
                .unwrap_or_default();
            self.trace_sums = Some((0.5 * ms + trace_ms, 0.5 * traced + units));
            let overhead = (total_ms - trace_ms).max(0.0);
            self.overhead_ms = Some(self.overhead_ms.map_or(overhead, |m| 0.5 * (m + overhead)));
        }
        Ok(())
    }

    fn set_params(&mut self, params: &Map<String, Value>) {
        let schema = Self::schema();
        self.settings = Settings {
            budget_ms: schema.float(params, "budget_ms"),
            spp: schema.int(params, "spp") as u32,
            max_spp: schema.int(params, "max_spp") as u32,
            bounces: schema.int(params, "bounces") as u32,
            seed: schema.int(params, "seed") as u64,
        };
    }
}
