//! The per-frame depth reconstruction on the GPU: guided filter of the depth with the colour
//! image as guide (He et al.), temporal warp and merge with the previous merged depth (Knecht et
//! al. 2012, Sec. 4.2) and normals from the position map, ported pass by pass from the CPU
//! oracle in `relight-recon` (`depth::guided_filter`, `temporal::TemporalMerge`,
//! `normals::normals`). Invalid depth (0, NaN, ±∞, negative) never becomes geometry here either:
//! every pass re-checks each value on its bits.
//!
//! A frame is one submission and one read-back:
//!
//! | pass | shader | reads | writes |
//! |---|---|---|---|
//! | filter 0/4 | `recon_guide.wgsl` | depth, guide | colour and disparity per pixel |
//! | filter 1/4 | `recon_moments.wgsl` | colour and disparity | 20 row sums of the window moments |
//! | filter 2/4 | `recon_solve.wgsl` | row sums | n_k, n_k a_k, n_k b_k per window |
//! | filter 3/4 | `recon_spread.wgsl` | window coefficients | their row sums |
//! | filter 4/4 | `recon_apply.wgsl` | row sums, depth, colour | filtered depth |
//! | merge | `recon_merge.wgsl` | filtered, rays, history | merged depth and weight, counts |
//! | agreement | `recon_select.wgsl` | counts, filtered | restart where too few agree |
//! | normals | `recon_normals.wgsl` | rays, final depth | (normal, depth) per pixel |
//!
//! The reset decisions that need only the pose and the camera (first frame, camera change,
//! non-finite pose, pose jump) are taken on the CPU before the frame, exactly as
//! `TemporalMerge` takes them; the agreement test needs the frame's counts and runs on the GPU,
//! so that the frame needs no round trip in the middle. The history lives in two GPU buffers
//! used in turn; buffers are allocated per image size and camera, not per frame.
//!
//! # Agreement with the oracle
//!
//! Every pass mirrors the oracle's arithmetic in f32, operation for operation and with every sum
//! in the same order (window sums as separable row-then-column passes adding offsets
//! −r..=r in ascending order, the same kernel values uploaded from the CPU, guide values from a
//! table of code / 255 as the CPU rounds them, the same unpivoted Cholesky). What can differ is
//! what WGSL leaves to the implementation: division and square root may be a few ULP off
//! (Vulkan allows 2.5 ULP for division), and `a * b + c` may be fused into one FMA. The tests
//! in `engines/tests/recon_gpu.rs` derive their tolerances from that (see there); the passes
//! whose output is a *decision* (the deviation guard, the merge's agreement test, the window
//! landing inside the previous image) can flip where the oracle's value sits on the threshold,
//! which the tests check separately. The merge projects into the previous camera in f32 where
//! the oracle uses f64; on a still camera that decides, where the pixel's own history is a
//! hole, whether a neighbour's history is read at all (the oracle's renormalised bilinear read
//! is discontinuous at a pixel centre; the f64 landing sits 10⁻⁷ px beside it, the f32 one on
//! it), so there the two may merge and restart respectively.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use relight_core::camera::Pinhole;
use relight_core::{Image, PixelFormat, Pose};
use relight_recon::depth::{DepthError, DepthMap, DepthNoise, GuidedFilterSettings};
use relight_recon::normals::{NormalMap, NormalSettings, PixelRays};
use relight_recon::temporal::{MergeReport, ResetReason, TemporalSettings, reset_reason};

use crate::engine::PassTiming;
use crate::gpu::{GpuContext, GpuError};
use crate::shaders;
use crate::timer::GpuTimer;
use crate::timer::timed_pass;

/// Why a frame could not be reconstructed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReconGpuError {
    #[error(transparent)]
    Depth(#[from] DepthError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// Everything [`DepthPass::run`] does, with the oracle's settings types.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthPassSettings {
    pub filter: GuidedFilterSettings,
    /// `None`: no merge, the output is the filtered depth (and no history is kept).
    pub temporal: Option<TemporalSettings>,
    pub normals: NormalSettings,
}

impl DepthPassSettings {
    /// The oracle's defaults for a Kinect v1 whose depth camera has `focal_px` at the working
    /// resolution.
    pub fn kinect_v1(focal_px: f32) -> Self {
        Self {
            filter: GuidedFilterSettings::kinect_v1(focal_px),
            temporal: Some(TemporalSettings::kinect_v1(focal_px)),
            normals: NormalSettings::default(),
        }
    }
}

/// One reconstructed frame, read back from the GPU.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthFrame {
    /// Merged depth (the filtered depth without a merge), current camera; 0 = no geometry.
    pub depth: DepthMap,
    /// Unit normals, glTF camera frame, facing the camera.
    pub normals: NormalMap,
    /// What the merge did; `None` without temporal settings.
    pub merge: Option<MergeReport>,
    /// Wall clock of the upload (`recon upload`) and of the GPU work with the read-back and
    /// unpacking (`recon gpu and read-back`), then `gpu.recon_filter`, `gpu.recon_merge` and
    /// `gpu.recon_normals` where the adapter has timestamp queries.
    pub timings: Vec<PassTiming>,
}

impl Default for DepthFrame {
    fn default() -> Self {
        Self {
            depth: DepthMap::invalid(0, 0),
            normals: NormalMap {
                width: 0,
                height: 0,
                normals_in_camera: Vec::new(),
            },
            merge: None,
            timings: Vec::new(),
        }
    }
}

/// Largest window radius a kernel table holds (`depth::MAX_RADIUS_PX`).
const MAX_TAPS: usize = 2 * relight_recon::depth::MAX_RADIUS_PX as usize + 1;

/// `Recon` in `shaders/recon_common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct ReconUniform {
    dims: [u32; 4],
    flags: [u32; 4],
    settings: [f32; 4],
    guard_noise: [f32; 4],
    guard_optics: [f32; 4],
    merge_noise: [f32; 4],
    merge_optics: [f32; 4],
    previous_k: [f32; 4],
    previous_distortion: [f32; 4],
    previous_field: [f32; 4],
    merge: [f32; 4],
    previous_from_current: [[f32; 4]; 4],
    current_from_previous: [[f32; 4]; 4],
    code_values: [[f32; 4]; 64],
}

/// Counts the merge writes: merged, rejected, fresh, valid depth, reset flag (and padding).
const COUNTERS: usize = 8;

/// The compute pipelines, built once.
#[derive(Debug)]
struct Pipelines {
    guide: wgpu::ComputePipeline,
    moments: wgpu::ComputePipeline,
    solve: wgpu::ComputePipeline,
    spread: wgpu::ComputePipeline,
    apply: wgpu::ComputePipeline,
    merge: wgpu::ComputePipeline,
    select: wgpu::ComputePipeline,
    normals: wgpu::ComputePipeline,
}

/// Bind groups of one image size; the merge and the agreement test per history slot written,
/// the normals per depth source (filtered, slot 0, slot 1).
#[derive(Debug)]
struct Groups {
    guide: wgpu::BindGroup,
    moments: wgpu::BindGroup,
    solve: wgpu::BindGroup,
    spread: wgpu::BindGroup,
    apply: wgpu::BindGroup,
    merge: [wgpu::BindGroup; 2],
    select: [wgpu::BindGroup; 2],
    normals: [wgpu::BindGroup; 3],
}

/// The buffers of one image size.
#[derive(Debug)]
struct Sized {
    width: u32,
    height: u32,
    depth: wgpu::Buffer,
    guide: wgpu::Buffer,
    rays: wgpu::Buffer,
    counters: wgpu::Buffer,
    output: wgpu::Buffer,
    staging: wgpu::Buffer,
    groups: Groups,
    /// The camera whose rays `rays` holds.
    rays_of: Option<Pinhole>,
}

/// What the next frame merges with.
#[derive(Debug, Clone, Copy)]
struct History {
    /// Slot holding the last merged depth.
    slot: usize,
    world_from_camera: Pose,
    camera: Pinhole,
}

/// The GPU depth reconstruction with its persistent buffers and merge history; see the module
/// docs. Belongs to the context it was built from.
#[derive(Debug)]
pub struct DepthPass {
    ctx: Arc<GpuContext>,
    pipelines: Pipelines,
    uniform: wgpu::Buffer,
    kernel: wgpu::Buffer,
    sized: Option<Sized>,
    history: Option<History>,
    timer: Option<GpuTimer>,
    /// Settings the oracle accepted last (validation is skipped while they stay the same).
    validated: Option<DepthPassSettings>,
    guide_bytes: Vec<u8>,
}

impl DepthPass {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        let device = &ctx.device;
        let pipelines = Pipelines {
            guide: shaders::compute_pipeline(device, "recon guide", shaders::RECON_GUIDE),
            moments: shaders::compute_pipeline(device, "recon moments", shaders::RECON_MOMENTS),
            solve: shaders::compute_pipeline(device, "recon solve", shaders::RECON_SOLVE),
            spread: shaders::compute_pipeline(device, "recon spread", shaders::RECON_SPREAD),
            apply: shaders::compute_pipeline(device, "recon apply", shaders::RECON_APPLY),
            merge: shaders::compute_pipeline(device, "recon merge", shaders::RECON_MERGE),
            select: shaders::compute_pipeline(device, "recon select", shaders::RECON_SELECT),
            normals: shaders::compute_pipeline(device, "recon normals", shaders::RECON_NORMALS),
        };
        // A storage buffer, not a uniform one: lavapipe (Mesa) compiles a shader variant for
        // every new set of UBO values its branches read and keeps them all, which grew the
        // daemon by 0.5 MB per frame as the camera moved.
        let uniform = storage(
            &ctx,
            "recon settings",
            size_of::<ReconUniform>() as u64,
            wgpu::BufferUsages::empty(),
        );
        let kernel = storage(
            &ctx,
            "recon kernel",
            (2 * MAX_TAPS * size_of::<f32>()) as u64,
            wgpu::BufferUsages::empty(),
        );
        let timer = GpuTimer::new(&ctx);
        Self {
            ctx,
            pipelines,
            uniform,
            kernel,
            sized: None,
            history: None,
            timer,
            validated: None,
            guide_bytes: Vec::new(),
        }
    }

    /// Drop the merge history: the next frame is the current depth alone.
    pub fn reset(&mut self) {
        self.history = None;
    }

    /// Reconstruct one frame: `depth` (as `DepthMap::from_image` decodes it) seen by `camera` at
    /// `world_from_camera` (glTF convention), `guide` the registered colour image (`Rgb8` or
    /// `Mono8`, same size).
    pub fn run(
        &mut self,
        depth: &DepthMap,
        guide: &Image,
        camera: &Pinhole,
        world_from_camera: &Pose,
        settings: &DepthPassSettings,
    ) -> Result<DepthFrame, ReconGpuError> {
        let mut out = DepthFrame::default();
        self.run_into(depth, guide, camera, world_from_camera, settings, &mut out)?;
        Ok(out)
    }

    /// [`Self::run`] into `out`, whose vectors are reused from frame to frame.
    pub fn run_into(
        &mut self,
        depth: &DepthMap,
        guide: &Image,
        camera: &Pinhole,
        world_from_camera: &Pose,
        settings: &DepthPassSettings,
        out: &mut DepthFrame,
    ) -> Result<(), ReconGpuError> {
        let result = self.frame(depth, guide, camera, world_from_camera, settings, out);
        if result.is_err() {
            // The history buffers may hold half a frame.
            self.history = None;
        }
        result
    }

    fn frame(
        &mut self,
        depth: &DepthMap,
        guide: &Image,
        camera: &Pinhole,
        world_from_camera: &Pose,
        settings: &DepthPassSettings,
        out: &mut DepthFrame,
    ) -> Result<(), ReconGpuError> {
        let started = Instant::now();
        self.validate(settings)?;
        check_inputs(depth, guide, camera)?;
        let (width, height) = (depth.width, depth.height);
        self.prepare(width, height, camera)?;
        let Some(sized) = &self.sized else {
            return Err(GpuError::Validation("recon buffers missing".into()).into());
        };

        // The merge's reset decisions that need no pixels, as TemporalMerge takes them.
        let (force_reset, slot) = match (&settings.temporal, &self.history) {
            (None, _) => (None, 0),
            (Some(temporal), history) => (
                reset_reason(
                    history.as_ref().map(|h| (&h.camera, &h.world_from_camera)),
                    camera,
                    world_from_camera,
                    temporal,
                ),
                history.map_or(0, |h| 1 - h.slot),
            ),
        };
        let channels = guide_channels(guide);
        let uniform = self.uniform_for(
            (width, height, channels),
            force_reset.is_some(),
            world_from_camera,
            settings,
        );
        let queue = &self.ctx.queue;
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
        queue.write_buffer(
            &self.kernel,
            0,
            bytemuck::cast_slice(&kernel(settings.filter.radius_px)),
        );
        queue.write_buffer(&sized.depth, 0, bytemuck::cast_slice(&depth.metres));
        pack_guide(guide, &mut self.guide_bytes);
        queue.write_buffer(&sized.guide, 0, &self.guide_bytes);
        let uploaded = Instant::now();

        let pixels = u64::from(width) * u64::from(height);
        let groups = (width.div_ceil(8), height.div_ceil(8));
        let mut encoder = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("recon"),
            });
        encoder.clear_buffer(&sized.counters, 0, None);
        if let Some(timer) = self.timer.as_mut() {
            timer.reset();
        }
        let p = &self.pipelines;
        let g = &sized.groups;
        {
            let mut pass = timed_pass(&mut encoder, &mut self.timer, "gpu.recon_filter");
            for (pipeline, group) in [
                (&p.guide, &g.guide),
                (&p.moments, &g.moments),
                (&p.solve, &g.solve),
                (&p.spread, &g.spread),
                (&p.apply, &g.apply),
            ] {
                dispatch(&mut pass, pipeline, group, groups);
            }
        }
        if settings.temporal.is_some() {
            let mut pass = timed_pass(&mut encoder, &mut self.timer, "gpu.recon_merge");
            dispatch(&mut pass, &p.merge, &g.merge[slot], groups);
            dispatch(&mut pass, &p.select, &g.select[slot], groups);
        }
        {
            let source = if settings.temporal.is_some() {
                1 + slot
            } else {
                0
            };
            let mut pass = timed_pass(&mut encoder, &mut self.timer, "gpu.recon_normals");
            dispatch(&mut pass, &p.normals, &g.normals[source], groups);
        }
        let output_bytes = pixels * 16;
        encoder.copy_buffer_to_buffer(&sized.output, 0, &sized.staging, 0, output_bytes);
        encoder.copy_buffer_to_buffer(
            &sized.counters,
            0,
            &sized.staging,
            output_bytes,
            (COUNTERS * 4) as u64,
        );
        if let Some(timer) = &self.timer {
            timer.resolve(&mut encoder);
        }
        self.ctx.queue.submit([encoder.finish()]);
        self.ctx.check()?;

        let counts = map_read(&self.ctx, &sized.staging, |bytes| {
            let (output, counters) = bytes.split_at(output_bytes as usize);
            unpack(output, width, height, out);
            let mut counts = [0u32; COUNTERS];
            for (c, b) in counts.iter_mut().zip(counters.chunks_exact(4)) {
                *c = u32::from_le_bytes(b.try_into().unwrap_or([0; 4]));
            }
            counts
        })?;
        let read = Instant::now();

        out.merge = settings.temporal.map(|_| merge_report(counts, force_reset));
        self.history = settings.temporal.map(|_| History {
            slot,
            world_from_camera: *world_from_camera,
            camera: *camera,
        });
        out.timings.clear();
        out.timings.push(PassTiming {
            pass: "recon upload",
            ms: (uploaded - started).as_secs_f64() * 1e3,
        });
        out.timings.push(PassTiming {
            pass: "recon gpu and read-back",
            ms: (read - uploaded).as_secs_f64() * 1e3,
        });
        if let Some(timer) = &mut self.timer {
            timer.read(&mut out.timings)?;
        }
        Ok(())
    }

    /// The oracle's own checks of the settings, so that the GPU accepts exactly what it
    /// accepts (once per change of settings).
    fn validate(&mut self, settings: &DepthPassSettings) -> Result<(), DepthError> {
        if self.validated.as_ref() == Some(settings) {
            return Ok(());
        }
        settings.filter.validate()?;
        if let Some(temporal) = &settings.temporal {
            temporal.validate()?;
        }
        self.validated = Some(*settings);
        Ok(())
    }

    /// Buffers for `width × height` (kept while the size stays) and the rays of `camera`.
    fn prepare(&mut self, width: u32, height: u32, camera: &Pinhole) -> Result<(), GpuError> {
        if self
            .sized
            .as_ref()
            .is_none_or(|s| (s.width, s.height) != (width, height))
        {
            self.sized = None;
            self.history = None;
            self.sized = Some(self.allocate(width, height)?);
        }
        let Some(sized) = self.sized.as_mut() else {
            return Ok(());
        };
        if sized.rays_of.as_ref() != Some(camera) {
            let rays: Vec<[f32; 4]> = PixelRays::new(camera)
                .rays
                .iter()
                .map(|ray| ray.map_or([0.0; 4], |r| [r.x, r.y, 1.0, 0.0]))
                .collect();
            self.ctx
                .queue
                .write_buffer(&sized.rays, 0, bytemuck::cast_slice(&rays));
            sized.rays_of = Some(*camera);
        }
        Ok(())
    }

    fn allocate(&self, width: u32, height: u32) -> Result<Sized, GpuError> {
        let ctx = &self.ctx;
        let pixels = (u64::from(width) * u64::from(height)).max(1);
        let largest = pixels * 5 * 16;
        let setting = "the depth resolution";
        ctx.require("max_storage_buffer_binding_size", largest, setting)?;
        ctx.require("max_buffer_size", largest, setting)?;
        ctx.require(
            "max_compute_workgroups_per_dimension",
            u64::from(width.max(height).div_ceil(8)),
            setting,
        )?;
        let none = wgpu::BufferUsages::empty();
        let depth = storage(ctx, "recon depth", pixels * 4, none);
        // Three bytes per pixel at most, in whole words.
        let guide = storage(ctx, "recon guide", (pixels * 3).div_ceil(4) * 4, none);
        let rays = storage(ctx, "recon rays", pixels * 16, none);
        let guided = storage(ctx, "recon colour and disparity", pixels * 16, none);
        let rows = storage(ctx, "recon moment rows", pixels * 5 * 16, none);
        let coefficients = storage(ctx, "recon coefficients", pixels * 2 * 16, none);
        let coefficient_rows = storage(ctx, "recon coefficient rows", pixels * 2 * 16, none);
        let filtered = storage(ctx, "recon filtered", pixels * 4, none);
        let history_depth = [0, 1].map(|_| storage(ctx, "recon history depth", pixels * 4, none));
        let history_weight = [0, 1].map(|_| storage(ctx, "recon history weight", pixels * 4, none));
        let counters = storage(
            ctx,
            "recon counters",
            (COUNTERS * 4) as u64,
            wgpu::BufferUsages::COPY_SRC,
        );
        let output = storage(
            ctx,
            "recon output",
            pixels * 16,
            wgpu::BufferUsages::COPY_SRC,
        );
        let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("recon staging"),
            size: pixels * 16 + (COUNTERS * 4) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });

        let p = &self.pipelines;
        let group = |pipeline: &wgpu::ComputePipeline, label: &str, buffers: &[&wgpu::Buffer]| {
            let mut resources = vec![self.uniform.as_entire_binding()];
            resources.extend(buffers.iter().map(|b| b.as_entire_binding()));
            shaders::pipeline_bind_group(&ctx.device, pipeline, label, &resources)
        };
        let k = &self.kernel;
        let groups = Groups {
            guide: group(&p.guide, "recon guide", &[&depth, &guide, &guided]),
            moments: group(&p.moments, "recon moments", &[k, &guided, &rows]),
            solve: group(&p.solve, "recon solve", &[k, &rows, &coefficients]),
            spread: group(
                &p.spread,
                "recon spread",
                &[k, &coefficients, &coefficient_rows],
            ),
            apply: group(
                &p.apply,
                "recon apply",
                &[k, &coefficient_rows, &depth, &guided, &filtered],
            ),
            merge: [0, 1].map(|slot| {
                let previous = 1 - slot;
                group(
                    &p.merge,
                    "recon merge",
                    &[
                        &filtered,
                        &rays,
                        &history_depth[previous],
                        &history_weight[previous],
                        &history_depth[slot],
                        &history_weight[slot],
                        &counters,
                    ],
                )
            }),
            select: [0, 1].map(|slot| {
                group(
                    &p.select,
                    "recon select",
                    &[
                        &filtered,
                        &counters,
                        &history_depth[slot],
                        &history_weight[slot],
                    ],
                )
            }),
            normals: [&filtered, &history_depth[0], &history_depth[1]]
                .map(|source| group(&p.normals, "recon normals", &[&rays, source, &output])),
        };
        Ok(Sized {
            width,
            height,
            depth,
            guide,
            rays,
            counters,
            output,
            staging,
            groups,
            rays_of: None,
        })
    }

    fn uniform_for(
        &self,
        (width, height, channels): (u32, u32, u32),
        restart: bool,
        world_from_camera: &Pose,
        settings: &DepthPassSettings,
    ) -> ReconUniform {
        let filter = &settings.filter;
        let span = settings.normals.span_px.max(1);
        // normals.rs: the jump test is off for a non-finite max_relative_jump; the guard is off
        // for an infinite max_deviation_sigmas.
        let jump = settings.normals.max_relative_jump;
        let jump_on = jump.is_finite();
        let guard_on = filter.max_deviation_sigmas.is_finite();
        let noise = |n: &DepthNoise| {
            [
                n.sigma_a_m,
                n.sigma_b_per_m,
                n.sigma_z0_m,
                n.disparity_step_px,
            ]
        };
        let mut uniform = ReconUniform::zeroed();
        uniform.dims = [width, height, filter.radius_px, channels];
        uniform.flags = [
            span,
            u32::from(restart),
            u32::from(guard_on),
            u32::from(jump_on),
        ];
        uniform.settings = [
            filter.eps,
            filter.eps_position,
            if guard_on {
                filter.max_deviation_sigmas
            } else {
                0.0
            },
            if jump_on {
                jump.max(0.0) * span as f32
            } else {
                0.0
            },
        ];
        uniform.guard_noise = noise(&filter.noise);
        uniform.guard_optics = [filter.noise.focal_px, filter.noise.baseline_m, 0.0, 0.0];
        for (code, value) in uniform
            .code_values
            .as_flattened_mut()
            .iter_mut()
            .enumerate()
        {
            *value = f32::from(code as u8) / 255.0;
        }
        let (Some(temporal), Some(history)) = (&settings.temporal, &self.history) else {
            return uniform;
        };
        uniform.merge_noise = noise(&temporal.noise);
        uniform.merge_optics = [
            temporal.noise.focal_px,
            temporal.noise.baseline_m,
            temporal.reject_sigmas,
            temporal.max_weight,
        ];
        uniform.merge = [temporal.min_agreement, 0.0, 0.0, 0.0];
        // T_warp = T_prev⁻¹ T_cur, composed as the oracle composes it.
        let previous_from_current = history.world_from_camera.inverse() * *world_from_camera;
        let current_from_previous = previous_from_current.inverse();
        uniform.previous_from_current = previous_from_current.to_mat4().to_cols_array_2d();
        uniform.current_from_previous = current_from_previous.to_mat4().to_cols_array_2d();
        let previous = &history.camera;
        uniform.previous_k = [previous.fx, previous.fy, previous.cx, previous.cy].map(|v| v as f32);
        uniform.previous_distortion =
            [previous.k1, previous.k2, previous.p1, previous.p2].map(|v| v as f32);
        // Pinhole::project's valid field: r² below the first root of the radial slope.
        let max_radius_sq = previous.max_radius_sq().min(f64::from(f32::MAX)) as f32;
        uniform.previous_field = [
            previous.k3 as f32,
            max_radius_sq,
            previous.width as f32,
            previous.height as f32,
        ];
        uniform
    }
}

fn dispatch(
    pass: &mut wgpu::ComputePass,
    pipeline: &wgpu::ComputePipeline,
    group: &wgpu::BindGroup,
    (x, y): (u32, u32),
) {
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, group, &[]);
    pass.dispatch_workgroups(x, y, 1);
}

fn storage(ctx: &GpuContext, label: &str, size: u64, extra: wgpu::BufferUsages) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | extra,
        mapped_at_creation: false,
    })
}

/// Sizes and formats, with the oracle's errors.
fn check_inputs(depth: &DepthMap, guide: &Image, camera: &Pinhole) -> Result<(), DepthError> {
    depth.check()?;
    for (what, width, height) in [
        ("guide image", guide.width(), guide.height()),
        ("camera", camera.width, camera.height),
    ] {
        if (width, height) != (depth.width, depth.height) {
            return Err(DepthError::SizeMismatch {
                what,
                width: depth.width,
                height: depth.height,
                actual_width: width,
                actual_height: height,
            });
        }
    }
    match (guide.format(), guide.as_u8()) {
        (PixelFormat::Rgb8 | PixelFormat::Mono8, Some(bytes))
            if bytes.len() == guide.pixel_count() * guide.format().channels() =>
        {
            Ok(())
        }
        (format, _) => Err(DepthError::BadGuide { format }),
    }
}

/// Guide channels the shaders read per pixel: 1 (grey, replicated) or 3.
fn guide_channels(guide: &Image) -> u32 {
    if guide.format() == PixelFormat::Mono8 {
        1
    } else {
        3
    }
}

/// The guide's bytes padded to whole words (`queue.write_buffer` writes multiples of 4).
fn pack_guide(guide: &Image, bytes: &mut Vec<u8>) {
    bytes.clear();
    bytes.extend_from_slice(guide.as_u8().unwrap_or_default());
    bytes.resize(bytes.len().div_ceil(4) * 4, 0);
}

/// The window weights d/r, then (d/r)², for d = −r..=r, computed as `depth::BoxWeight` does.
fn kernel(radius_px: u32) -> Vec<f32> {
    let r = i64::from(radius_px);
    let d = |offset: i64| offset as f32 / r.max(1) as f32;
    let offsets = || (-r..=r).map(d);
    offsets().chain(offsets().map(|d| d * d)).collect()
}

/// The merge's report from the GPU's counts (merged, rejected, fresh, valid, reset by the
/// agreement test) and the reset decided before the frame.
fn merge_report(counts: [u32; COUNTERS], restart: Option<ResetReason>) -> MergeReport {
    let [merged, rejected, fresh, valid, disagreed, ..] = counts.map(|c| c as usize);
    if restart.is_some() {
        return MergeReport {
            reset: restart,
            fresh: valid,
            ..MergeReport::default()
        };
    }
    if disagreed != 0 {
        let compared = merged + rejected;
        let agreement = if compared == 0 {
            1.0
        } else {
            merged as f32 / compared as f32
        };
        return MergeReport {
            reset: Some(ResetReason::Disagreement { agreement }),
            fresh: valid,
            ..MergeReport::default()
        };
    }
    MergeReport {
        reset: None,
        merged,
        rejected,
        fresh,
    }
}

/// The read-back (normal, depth) texels into `out`'s maps.
fn unpack(bytes: &[u8], width: u32, height: u32, out: &mut DepthFrame) {
    let texels: &[[f32; 4]] = bytemuck::cast_slice(bytes);
    let depth = &mut out.depth;
    depth.width = width;
    depth.height = height;
    depth.metres.clear();
    depth.metres.extend(texels.iter().map(|t| t[3]));
    let normals = &mut out.normals;
    normals.width = width;
    normals.height = height;
    normals.normals_in_camera.clear();
    normals.normals_in_camera.extend(texels.iter().map(|t| {
        let n = Vec3::new(t[0], t[1], t[2]);
        (n != Vec3::ZERO && n.is_finite()).then_some(n)
    }));
}

/// Map `staging` (after the submission that filled it), wait, and hand its bytes to `read`.
fn map_read<T>(
    ctx: &GpuContext,
    staging: &wgpu::Buffer,
    read: impl FnOnce(&[u8]) -> T,
) -> Result<T, GpuError> {
    let slice = staging.slice(..);
    let result = Arc::new(Mutex::new(None));
    {
        let result = result.clone();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            if let Ok(mut slot) = result.lock() {
                *slot = Some(r);
            }
        });
    }
    ctx.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    ctx.check()?;
    match result.lock().ok().and_then(|mut r| r.take()) {
        Some(Ok(())) => {}
        Some(Err(e)) => return Err(GpuError::Readback(e.to_string())),
        None => return Err(GpuError::Readback("the buffer was never mapped".into())),
    }
    let out = {
        let view = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        read(&view)
    };
    staging.unmap();
    Ok(out)
}
