//! `dlpv`: Delta Light Propagation Volumes (Franke, ISMAR 2013).
//!
//! Per frame, after the shared G-buffers and reflective shadow maps (R^ρ, R^μ):
//! 1. **inject** (`dlpv_inject.wgsl`): every R^ρ texel adds its VPL to V^Δ and V^ρ, every R^μ
//!    texel subtracts its VPL from V^Δ (half a cell along the normal); with direct injection, the
//!    incident light of every texel along the light's direction of travel (half a cell back
//!    towards the light), ρ minus μ, into V^Δ: antiradiance where the object casts its shadow.
//!    Fixed-point atomics: WGSL has no float atomics; integer sums commute, so the result is
//!    deterministic and VPLs seen in both maps cancel to exactly zero (Δ = 0 without an object
//!    holds bit for bit). Additive blending into volume slices would need one render pass per
//!    slice and leave order-dependent float residues; a gather over all VPLs per cell costs
//!    cells × VPLs. A thread injects a 4 × 4 tile, summing runs of texels that land in one cell
//!    before adding them, and adds neither VPL of an R^ρ/R^μ pair that is the same texel (the
//!    counts would cancel): the same integers with far fewer atomics.
//! 2. **resolve** the counts to SH, stored as f16 (`SH_CELL_BYTES`); **propagate** N steps
//!    (gather from the six neighbours over their faces' solid angles, written out per
//!    direction: `dlpv_propagate.wgsl`, `propagate.rs`), accumulating every step; negative
//!    light is dampened per step. V^Δ takes `steps`. V^ρ, the light on the object, is read
//!    by default as patches (step 3), and does not propagate; with `object_light = "volume"`
//!    (the paper) it stops after `rho_steps` (4): nothing occludes in the volume, so later
//!    steps only carry the floor's light around and through the object onto it (object
//!    relative L2 0.28–0.80 at 32 steps, 0.13–0.28 at 8), and the light from beyond the volume
//!    comes from the far field instead (`far_field`, 0.10–0.13 at 4).
//!
//! The volume is 16³ and V^Δ takes 8 steps by default, against the paper's 32³ and 32: measured
//! over the five scenes, that is as close to the reference on Δ and the object as the paper's
//! setting or closer (later steps carry the object's lit faces' VPLs through it into its own
//! shadow; coarser cells smooth the halo they leave) in a third of the time
//! (`docs/ALGORITHMS.md`, `dlpv`, "`volume_size` and `steps`").
//! 3. **look up** (`dlpv_lookup.wgsl`): trilinear V^Δ on real pixels (plus the light the
//!    object blocks, `occlusion`), and on virtual ones the patches' light plus the far field's
//!    irradiance (`CellCounts::far_field`). **The patches** (`object_light = "patches"`, the
//!    default; not in the paper): V^ρ's injected light, R^ρ's VPLs within the volume, summed
//!    over 8³ blocks of cells (`volume::FarEmitters`), each block a square of Lambertian
//!    surface about its VPLs' mean normal whose light is Lambert's contour integral over it
//!    (`patch_irradiance` in `shaders/common.wgsl`), gathered at every `patch_stride`-th object
//!    pixel. Propagated 4 steps, V^ρ carried a face's light from the floor only half the
//!    object's edge, and a point's light under a grazing cosine gives almost nothing to the
//!    face standing right beside the floor it lights: object L2 on the bench's five scenes
//!    0.098–0.134 → 0.027–0.095 (`docs/ALGORITHMS.md`, `dlpv`). No visibility: within the
//!    volume, a real surface between a patch and the object does not block it.
//! 4. the shared shading pass composites (Algorithm 1): real pixels B + albedo · V^Δ (+ the
//!    shadow-mapped direct Δ when `shadows = "shadow_map"`), virtual pixels direct + albedo ·
//!    (the patches or V^ρ, + far field).
//!
//! The volume is `volume_scale` × the virtual object's largest edge on a side (the paper: about
//! 2×), centred on the object and then moved out of what lies beyond the scene's bounds
//! (`volume_placement`, `volume::placement`).
//!
//! The default is `shadows = "shadow_map"`, chosen by measurement: relative L2 of Δ against the
//! reference (160 × 120, 32 spp) with shadow maps / antiradiance: desk_box 0.41 / 0.74,
//! spot_bleed 0.20 / 0.77, touching_wall 0.69 / 1.17, glossy_floor 0.10 / 0.85, window_env
//! 0.27 / 0.89. Antiradiance holds a shadow only where the whole shadow lies inside the volume
//! and the propagation carries it undiluted; at 32³ and 32 steps it smears and leaks it.

mod propagate;

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
use propagate::{Propagation, PropagationBuffers};

use crate::volume::{
    CellCounts, FarEmitters, InjectPass, ObjectBox, VolumeUniform, fixed_point_scale,
    frame_placement, volume_reach,
};

/// `env_lights` by default: chosen by measured error on window_env (`docs/ALGORITHMS.md`,
/// "Environment lights").
const ENV_LIGHTS_DEFAULT: u32 = 24;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct LookupUniform {
    size: [u32; 4],
}

/// The engine's settings (see [`Dlpv::schema`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DlpvSettings {
    pub rsm_size: u32,
    pub shadow_size: u32,
    pub volume_size: u32,
    pub steps: u32,
    pub rho_steps: u32,
    pub dampening: f32,
    pub antiradiance: bool,
    pub volume_scale: f32,
    pub shadow_bias: f32,
    pub lookup_offset: f32,
    /// Light the object with the far field too (`CellCounts::far_field`).
    pub far_field: bool,
    /// The volume moved out of what lies beyond the scene's bounds (`volume::placement`).
    pub volume_in_scene: bool,
    /// Real pixels also lose the real scene's first bounce that the object blocks on its way
    /// to them (`CellCounts::probe`, `blocked_irradiance` in `shaders/common.wgsl`); else
    /// they take V^Δ alone (the paper).
    pub probe_occlusion: bool,
    /// The object's pixels take V^ρ's injected light, summed into blocks of cells, as patches
    /// of Lambertian surface (`FarEmitters`, `patch_irradiance` in `shaders/common.wgsl`)
    /// instead of the propagated V^ρ, which then does not propagate.
    pub object_patches: bool,
    /// The patches' light is gathered at every `patch_stride`-th object pixel per axis and
    /// shared with the alike pixels between (`engines/src/strided.rs`).
    pub patch_stride: u32,
}

impl DlpvSettings {
    /// How many steps V^ρ propagates: none when the object takes its light from patches.
    fn rho_propagation_steps(&self) -> u32 {
        if self.object_patches {
            0
        } else {
            self.rho_steps.min(self.steps)
        }
    }
}

impl Default for DlpvSettings {
    fn default() -> Self {
        Self {
            rsm_size: 192,
            shadow_size: crate::deferred::SHADOW_SIZE_DEFAULT,
            volume_size: 16,
            steps: 8,
            rho_steps: 4,
            dampening: 0.5,
            antiradiance: false,
            volume_scale: 2.0,
            shadow_bias: 1.5,
            lookup_offset: 0.0,
            far_field: true,
            volume_in_scene: true,
            probe_occlusion: true,
            object_patches: true,
            patch_stride: 2,
        }
    }
}

/// One cell of V^Δ or V^ρ as stored between propagation steps: three channels of four L1 SH
/// coefficients in f16 (`pack_sh` in `shaders/common.wgsl`). f32 took 48 bytes, and
/// propagation, which moves every cell each step, ran a third faster at 24 on lavapipe
/// (desk_box, 32³ and 32 steps: 431 → 289 ms) with Δ and object errors equal to 4 digits.
pub(crate) const SH_CELL_BYTES: u64 = 24;

#[derive(Debug)]
struct VolumeBuffers {
    n: u32,
    cells: CellCounts,
    injected: wgpu::Buffer,
    ping: wgpu::Buffer,
    accumulated: wgpu::Buffer,
}

#[derive(Debug)]
pub struct Dlpv {
    deferred: Deferred,
    settings: DlpvSettings,
    inject: InjectPass,
    resolve: wgpu::ComputePipeline,
    propagate: Propagation,
    lookup: wgpu::ComputePipeline,
    /// `dlpv_lookup.wgsl`'s `patches` and `fill`: the object's light from V^ρ's patches at
    /// strided pixels, then at every other object pixel.
    patches: [wgpu::ComputePipeline; 2],
    volume_uniform: wgpu::Buffer,
    lookup_uniform: wgpu::Buffer,
    rho_emitters: FarEmitters,
    /// The patches' irradiance at the object's pixels, and the picture size it was made for.
    object_irradiance: Option<((u32, u32), wgpu::Buffer)>,
    volume: Option<VolumeBuffers>,
    /// What `volume`'s accumulated V^Δ was propagated from: kept while the shadow maps, the
    /// lights and the volume's placement hold.
    propagated: KeptInputs,
}

impl Dlpv {
    pub const NAME: &'static str = "dlpv";

    pub fn schema() -> ParamsSchema {
        let (int, float) = (ParamSpec::int, ParamSpec::float);
        ParamsSchema::new(vec![
            int(
                "rsm_size",
                "reflective-shadow-map edge per light face; every texel is a VPL (the shadows \
                 have their own map, `shadow_size`). Scaled by √(6/n) where the faces are n > 6 \
                 directional lights alone, e.g. an environment's",
                32,
                2048,
                192,
            ),
            crate::deferred::shadow_size_param(),
            int(
                "volume_size",
                "cells per axis of V^Δ and V^ρ (the paper: 32; 16 by measured error, see docs/ALGORITHMS.md)",
                4,
                128,
                16,
            ),
            int(
                "steps",
                "propagation steps of V^Δ (the paper: 32; 8 by measured error, see docs/ALGORITHMS.md)",
                0,
                256,
                8,
            ),
            int(
                "rho_steps",
                "propagation steps of V^ρ, the light on the object (at most `steps`): nothing in the volume occludes, so more steps carry light around and through the object onto it",
                0,
                256,
                4,
            ),
            float(
                "dampening",
                "fraction of negative light (antiradiance, and L1 ringing) removed per propagation step",
                0.0,
                1.0,
                0.5,
            ),
            ParamSpec::choice(
                "shadows",
                "`shadow_map` (default, the lower error measured on every scene): the differential engine's shadows, volume for indirect only; `antiradiance`: direct injection as in the paper",
                vec!["shadow_map", "antiradiance"],
            ),
            float(
                "volume_scale",
                "volume edge as a multiple of the virtual object's largest bounding-box edge",
                1.0,
                8.0,
                2.0,
            ),
            float(
                "shadow_bias",
                "shadow-map depth bias in texel footprints",
                0.0,
                8.0,
                1.5,
            ),
            float(
                "lookup_offset",
                "lookup point moved along the surface normal, in cells",
                0.0,
                1.0,
                0.0,
            ),
            crate::volume::far_field_param(),
            crate::volume::volume_placement_param(),
            ParamSpec::choice(
                "occlusion",
                "`probe`: real pixels also lose the real scene's first bounce that the object blocks on its way to them (every real VPL's light gathered at the object's centre, over the solid angle the object covers from them); `none`: V^Δ alone, as in the paper",
                vec!["probe", "none"],
            ),
            ParamSpec::choice(
                "object_light",
                "`patches`: the object's pixels take V^ρ's injected light (R^ρ's VPLs in the volume), summed over 8³ blocks of cells, each a square of Lambertian surface, by Lambert's contour integral; `volume`: V^ρ propagated `rho_steps`, as in the paper",
                vec!["patches", "volume"],
            ),
            int(
                "patch_stride",
                "the object's light from the patches at every n-th pixel per axis; the pixels between take their alike neighbours' (1: every pixel)",
                1,
                4,
                2,
            ),
            crate::deferred::env_lights_param(ENV_LIGHTS_DEFAULT),
            crate::deferred::accumulate_param(),
            crate::deferred::indirect_param(),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let uniform = |label, size| shaders::params_buffer(&ctx.device, label, size);
        Ok(Self {
            inject: InjectPass::new(&ctx.device, "dlpv inject"),
            resolve: shaders::compute_pipeline(&ctx.device, "dlpv resolve", shaders::DLPV_RESOLVE),
            propagate: Propagation::new(&ctx.device),
            lookup: shaders::compute_pipeline(&ctx.device, "dlpv lookup", shaders::DLPV_LOOKUP),
            patches: ["patches", "fill"].map(|entry| {
                shaders::compute_pipeline_at(
                    &ctx.device,
                    "dlpv patches",
                    shaders::DLPV_LOOKUP,
                    entry,
                )
            }),
            volume_uniform: uniform("dlpv volume", size_of::<VolumeUniform>()),
            lookup_uniform: uniform("dlpv lookup", size_of::<LookupUniform>()),
            rho_emitters: FarEmitters::new(&ctx),
            object_irradiance: None,
            deferred: Deferred::new(ctx),
            settings: DlpvSettings::default(),
            volume: None,
            propagated: KeptInputs::default(),
        })
    }

    fn volume_buffers(&mut self) -> Result<&VolumeBuffers, EngineError> {
        let n = self.settings.volume_size;
        let ctx = self.deferred.ctx().clone();
        let cells = 2 * u64::from(n).pow(3);
        ctx.require(
            "max_storage_buffer_binding_size",
            cells * SH_CELL_BYTES,
            "volume_size",
        )?;
        ctx.require(
            "max_compute_workgroups_per_dimension",
            // Propagation dispatches one workgroup per slice of both volumes.
            u64::from(2 * n),
            "volume_size",
        )?;
        if self.volume.as_ref().is_none_or(|v| v.n != n) {
            let buffer = |label, usage| {
                ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: cells * SH_CELL_BYTES,
                    usage,
                    mapped_at_creation: false,
                })
            };
            use wgpu::BufferUsages as U;
            self.propagated.forget();
            self.volume = Some(VolumeBuffers {
                n,
                cells: CellCounts::new(&ctx, "dlpv cells", n, "volume_size")?,
                injected: buffer("dlpv injected", U::STORAGE),
                ping: buffer("dlpv ping", U::STORAGE),
                accumulated: buffer("dlpv accumulated", U::STORAGE | U::COPY_SRC),
            });
        }
        self.volume.as_ref().ok_or(EngineError::NotPrepared)
    }
}

/// What injection (with the resolve: the 48 bytes of counts read, the SH written to both the
/// start and the accumulation) and propagation must do for `n`³ cells of two volumes from
/// `faces` VPL maps of `rsm_size`². Every propagation step reads each cell's SH and writes it,
/// and adds it into the accumulation ([`SH_CELL_BYTES`] each way), with about 660 operations
/// per cell (`dlpv_propagate.wgsl`: six neighbours, five faces, three channels); V^Δ takes
/// `steps` of them, V^ρ `rho_propagation_steps`. With `patches`, the injection pass also sums
/// V^ρ into them (`patches`' work).
fn propagation_work(
    n: u32,
    faces: u32,
    rsm_size: u32,
    settings: DlpvSettings,
    patches: Option<Work>,
) -> [PassWork; 2] {
    let volume = f64::from(n).powi(3);
    let cells = 2.0 * volume;
    let sh = SH_CELL_BYTES as f64;
    let inject = InjectPass::work(rsm_size, faces, cells)
        + Work::new(48.0 + 2.0 * sh, 12.0).times(cells)
        + patches.unwrap_or_default();
    let step = Work::new(sh + sh + 2.0 * sh, 660.0).times(volume);
    let volume_steps = settings.steps + settings.rho_propagation_steps();
    [
        PassWork {
            pass: "inject",
            work: inject,
        },
        PassWork {
            pass: "propagate",
            work: step.times(f64::from(volume_steps)),
        },
    ]
}

impl Engine for Dlpv {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, frame: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let settings = self.settings;
        // The lookup reads no cell beyond the volume (a trilinear tap reaches half a cell past
        // its faces, from `lookup_offset` cells off the surface), so a real pixel farther out
        // takes its direct Δ alone.
        let n = settings.volume_size;
        let volume = frame_placement(frame, n, settings.volume_scale, settings.volume_in_scene);
        // The light the object blocks reaches real surfaces anywhere.
        self.deferred
            .set_real_indirect(if settings.probe_occlusion {
                RealIndirect::Anywhere
            } else {
                volume_reach(volume, n, 0.51 + settings.lookup_offset.abs(), 0)
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
        let bounds = match self.deferred.scene() {
            Some(scene) => scene.bounds,
            None => return Err(EngineError::NotPrepared),
        };
        let faces = self.deferred.faces().len() as u32;
        let rsm_size = self.deferred.rsm_size().ok_or(EngineError::NotPrepared)?;
        if let (Some((origin, cell)), true) = (volume, faces > 0) {
            let scale =
                fixed_point_scale(self.deferred.lights(), (bounds.1 - bounds.0).length() / 2.0);
            let volume = VolumeUniform {
                origin: origin.extend(cell).to_array(),
                dims: [n, rsm_size, faces, self.deferred.lights().len() as u32],
                scale: [
                    scale,
                    if settings.antiradiance { 1.0 } else { 0.0 },
                    settings.dampening,
                    settings.lookup_offset,
                ],
                options: [
                    u32::from(settings.far_field),
                    u32::from(settings.probe_occlusion),
                    u32::from(settings.object_patches),
                    0,
                ],
                object: ObjectBox::of_frame(frame).uniform(),
            };
            ctx.queue
                .write_buffer(&self.volume_uniform, 0, bytemuck::bytes_of(&volume));
            ctx.queue.write_buffer(
                &self.lookup_uniform,
                0,
                bytemuck::bytes_of(&LookupUniform {
                    size: [width, height, settings.patch_stride, 0],
                }),
            );
            self.volume_buffers()?;
            if self.object_irradiance.as_ref().map(|(size, _)| *size) != Some((width, height)) {
                let bytes = u64::from(width) * u64::from(height) * 16;
                let buffer = ctx.buffer(
                    "dlpv object irradiance",
                    bytes.max(16),
                    wgpu::BufferUsages::STORAGE,
                );
                self.object_irradiance = Some(((width, height), buffer));
            }
            let inputs = KeptInputs::hash_of(&[
                bytemuck::bytes_of(&volume),
                &settings.steps.to_le_bytes(),
                &settings.rho_propagation_steps().to_le_bytes(),
                &self.deferred.light_inputs().to_le_bytes(),
            ]);
            let repropagate = !self.propagated.holds(inputs);
            let mut timer = self.deferred.lend_timer();
            let (
                Some(v),
                Some((_, object_irradiance)),
                Some(light_buffers),
                Some((gb_rho, _, indirect)),
            ) = (
                self.volume.as_ref(),
                self.object_irradiance.as_ref(),
                self.deferred.light_buffers(),
                self.deferred.frame_buffers(),
            )
            else {
                return Err(EngineError::NotPrepared);
            };
            let inject_group =
                self.inject
                    .bind_group(&ctx.device, &self.volume_uniform, light_buffers, &v.cells);
            let group = |pipeline, label, resources: &[wgpu::BindingResource]| {
                shaders::pipeline_bind_group(&ctx.device, pipeline, label, resources)
            };
            let resolve_group = group(
                &self.resolve,
                "dlpv resolve",
                &[
                    self.volume_uniform.as_entire_binding(),
                    v.cells.binding(0),
                    v.cells.binding(1),
                    v.injected.as_entire_binding(),
                    v.accumulated.as_entire_binding(),
                ],
            );
            let gb_views = [
                Targets::view(&gb_rho.position),
                Targets::view(&gb_rho.normal),
                Targets::view(&gb_rho.albedo),
            ];
            let mut lookup_resources = vec![
                self.volume_uniform.as_entire_binding(),
                self.lookup_uniform.as_entire_binding(),
                v.accumulated.as_entire_binding(),
            ];
            lookup_resources.extend(gb_views.iter().map(wgpu::BindingResource::TextureView));
            lookup_resources.extend([
                indirect.as_entire_binding(),
                v.cells.far_field(),
                v.cells.probe(),
                self.rho_emitters.buffer.as_entire_binding(),
                self.deferred.camera_buffer().as_entire_binding(),
                object_irradiance.as_entire_binding(),
            ]);
            let group_of = |pipeline, bindings: &[u32]| {
                shaders::pipeline_bind_group_of(
                    &ctx.device,
                    pipeline,
                    "dlpv lookup",
                    &lookup_resources,
                    bindings,
                )
            };
            // Each entry's derived layout holds the bindings it reads: `main` one value of the
            // patches' per object pixel, `patches` the patches, `fill` them and the camera.
            let lookup_group = group_of(&self.lookup, &[0, 1, 2, 3, 4, 5, 6, 7, 8, 11]);
            let patches_groups = [
                group_of(&self.patches[0], &[0, 1, 3, 4, 9, 11]),
                group_of(&self.patches[1], &[0, 1, 3, 4, 9, 10, 11]),
            ];

            let mut encoder = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("dlpv"),
                });
            if repropagate {
                out.work.extend(propagation_work(
                    n,
                    faces,
                    rsm_size,
                    settings,
                    settings.object_patches.then(|| FarEmitters::work(n)),
                ));
                encoder.clear_buffer(&v.cells.buffer, 0, None);
                {
                    let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.inject");
                    self.inject
                        .dispatch(&mut pass, &inject_group, rsm_size, faces);
                    pass.set_pipeline(&self.resolve);
                    pass.set_bind_group(0, &resolve_group, &[]);
                    pass.dispatch_workgroups((2 * n.pow(3) * 3).div_ceil(64), 1, 1);
                    if settings.object_patches {
                        self.rho_emitters.dispatch(
                            &ctx.device,
                            &mut pass,
                            &self.volume_uniform,
                            &v.cells,
                            1,
                        );
                    }
                }
                let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.propagate");
                self.propagate.record(
                    &ctx.device,
                    &mut pass,
                    &PropagationBuffers {
                        uniform: &self.volume_uniform,
                        injected: &v.injected,
                        ping: &v.ping,
                        accumulated: &v.accumulated,
                    },
                    n,
                    settings.steps,
                    settings.rho_propagation_steps(),
                );
            }
            {
                let mut pass = timed_pass(&mut encoder, &mut timer, "gpu.lookup");
                if settings.object_patches {
                    crate::strided::dispatch(
                        &mut pass,
                        &self.patches,
                        &patches_groups,
                        (width, height),
                        settings.patch_stride,
                    );
                }
                pass.set_pipeline(&self.lookup);
                pass.set_bind_group(0, &lookup_group, &[]);
                pass.dispatch_workgroups(width.div_ceil(8), height.div_ceil(8), 1);
            }
            out.work.push(PassWork {
                pass: "lookup",
                // The G-buffer texel read and the result written; the volume read once (eight
                // cells per pixel, trilinear, but neighbouring pixels share them). The patches'
                // sums are left out: how many object pixels and listed patches they take is
                // known on the GPU alone, so with them on this pass's roofline fraction reads low.
                work: Work::new(32.0 + 16.0, 250.0).times(f64::from(width) * f64::from(height))
                    + Work::new(SH_CELL_BYTES as f64, 0.0).times(2.0 * f64::from(n).powi(3)),
            });
            ctx.queue.submit([encoder.finish()]);
            ctx.check()?;
            self.propagated.record(inputs);
            self.deferred.return_timer(timer);
        }
        out.timings.push(PassTiming {
            pass: "volume",
            ms: started.elapsed().as_secs_f64() * 1e3,
        });
        self.deferred.finish(
            ShadeOptions {
                shadow_bias_texels: settings.shadow_bias,
                direct_delta: !settings.antiradiance,
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
        self.settings = DlpvSettings {
            rsm_size: int("rsm_size"),
            shadow_size: int("shadow_size"),
            volume_size: int("volume_size"),
            steps: int("steps"),
            rho_steps: int("rho_steps"),
            dampening: float("dampening"),
            antiradiance: schema.choice(params, "shadows") == "antiradiance",
            volume_scale: float("volume_scale"),
            shadow_bias: float("shadow_bias"),
            lookup_offset: float("lookup_offset"),
            far_field: schema.choice(params, "far_field") == "probe",
            volume_in_scene: schema.choice(params, "volume_placement") == "scene",
            probe_occlusion: schema.choice(params, "occlusion") == "probe",
            object_patches: schema.choice(params, "object_light") == "patches",
            patch_stride: int("patch_stride"),
        };
        self.deferred
            .set_environment_light_count(schema.int(params, "env_lights") as u32);
        self.deferred.set_shared_params(&schema, params);
    }
}

#[cfg(test)]
impl crate::shadow_reach::tests::WithDeferred for Dlpv {
    fn deferred_mut(&mut self) -> &mut Deferred {
        &mut self.deferred
    }
}
