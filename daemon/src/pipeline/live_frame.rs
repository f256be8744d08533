//! One live frame's scene, from a synchronised frame set: the camera registered
//! ([`super::tracking`]), depth reconstructed ([`super::reconstruction`]) with that pose, the
//! real surface triangulated around the virtual object(s) placed in the world frame, and the
//! lighting estimate ([`super::lighting`]: the light probe's, else the scene file's) published
//! when it changes.
//!
//! The render thread and `relightd score` both build frames through [`LiveFrames`], so what is
//! scored is what runs live.

use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use relight_core::camera::CameraModel;
use relight_core::rig::RigCalibration;
use relight_core::scene::Scene;
use relight_core::sync::FrameSet;
use relight_core::{Frame, LampState, ProbeImage};
use relight_engines::live_scene::{LightSource, LiveScene, RealGeometry};
use relight_engines::surface_albedo::{AlbedoReport, SurfaceAlbedo};
use relight_engines::{EngineRegistry, PassTiming, SceneFrame};
use relight_recon::albedo::{AlbedoSettings, ColorDecoding};
use relight_recon::probe::{ProbeLighting, ProbeSettings};

use super::lighting::SceneLights;
use super::reconstruction::{DepthOutcome, DepthStage};
use super::tracking::{Tracker, TrackingReport};
use crate::config::Config;
use crate::control::lights::LightsBoard;

/// A frame set turned into what an engine renders.
#[derive(Debug)]
pub struct LiveFrame {
    pub scene: SceneFrame,
    pub tracking: TrackingReport,
    /// What the depth stage made of the set's depth (`None` without a depth stage, or when the
    /// camera is untracked and nothing was built).
    pub depth: Option<DepthOutcome>,
    pub timings: LiveTimings,
    /// The depth stage's parts on this frame ([`DepthStage::passes`]); empty when it did not
    /// run.
    pub depth_passes: Vec<PassTiming>,
    /// What the albedo measurement did on this frame, when it runs.
    pub albedo: Option<AlbedoReport>,
}

/// How long the stages of one live frame took, milliseconds: each present when its stage ran.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LiveTimings {
    pub tracking_ms: f64,
    /// Merging the probe bracket whose estimate this frame took up.
    pub probe_ms: Option<f64>,
    /// Depth reconstruction (with a depth stage and a pose).
    pub depth_ms: Option<f64>,
    /// Triangulating and lighting the live scene (with a pose).
    pub scene_ms: Option<f64>,
}

impl LiveTimings {
    /// The stages that ran, by the names status reports use, in data-flow order.
    pub fn named(&self) -> impl Iterator<Item = (&'static str, f64)> {
        [
            ("tracking", Some(self.tracking_ms)),
            ("probe", self.probe_ms),
            ("depth", self.depth_ms),
            ("scene", self.scene_ms),
        ]
        .into_iter()
        .filter_map(|(name, ms)| Some((name, ms?)))
    }
}

/// The per-frame state of the live path: tracker, depth reconstruction, live scene, lights.
pub struct LiveFrames {
    tracker: Tracker,
    live_scene: Option<LiveScene>,
    scene_lights: Option<SceneLights>,
    depth_stage: Option<DepthStage>,
}

impl std::fmt::Debug for LiveFrames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveFrames")
            .field("tracker", &self.tracker)
            .field("scene", &self.live_scene.is_some())
            .field("depth_stage", &self.depth_stage.is_some())
            .finish_non_exhaustive()
    }
}

impl LiveFrames {
    /// The live path `config` asks for, on a rig with `calibration`; the depth reconstruction runs
    /// on `registry`'s GPU when it has one.
    pub fn new(
        config: &Config,
        calibration: Option<&RigCalibration>,
        registry: &EngineRegistry,
    ) -> anyhow::Result<Self> {
        let mut scene_pose = relight_core::Pose::IDENTITY;
        let mut scene_lights = None;
        let mut depth_stage = None;
        let live_scene = match &config.scene.dir {
            Some(dir) => {
                let scene = Scene::load(dir)
                    .map_err(|e| anyhow::anyhow!("{}: [scene] dir: {e}", config.path.display()))?;
                scene_pose = scene.camera.world_from_camera;
                let probe = calibration.and_then(|rig| {
                    let mut settings = ProbeSettings::default();
                    settings.lights.light_count = config.scene.probe_lights;
                    ProbeLighting::new(rig, settings)
                        .inspect_err(|error| {
                            if rig.probe.is_some() {
                                tracing::warn!(%error, "the light probe is not used");
                            }
                        })
                        .ok()
                });
                if probe.as_ref().is_some_and(|p| !p.is_absolute()) {
                    tracing::warn!(
                        "the rig calibration has no radiance scale for the probe: its light estimate is in relative units"
                    );
                }
                if probe.is_none() && config.scene.lighting == LightSource::Probe {
                    tracing::warn!(
                        "[scene] lighting = \"probe\" but the rig has no usable probe calibration: only the lamp lights the scene"
                    );
                }
                scene_lights = Some(SceneLights::new(&scene, probe));
                let depth_camera =
                    calibration.and_then(|c| match c.depth.as_ref().or(c.color.as_ref()) {
                        Some(CameraModel::Pinhole(p)) => Some(*p),
                        _ => None,
                    });
                if depth_camera.is_none() && config.scene.real == RealGeometry::Depth {
                    tracing::warn!(
                        "[scene] real = \"depth\" but the source has no pinhole depth calibration: the GPU engines get no scene"
                    );
                }
                depth_stage = depth_camera
                    .filter(|_| {
                        config.scene.real == RealGeometry::Depth && config.scene.depth_filter
                    })
                    .map(|camera| {
                        // On a software rasteriser the GPU pass runs on the cores the CPU
                        // path would use, and slower than its native code: the bundled
                        // recording's depth stage took 32 ms p50 through lavapipe, 20 ms on
                        // the CPU (2 cores, replayed live with `differential`).
                        let gpu = registry
                            .gpu()
                            .inspect_err(
                                |error| tracing::info!(%error, "depth reconstruction on the CPU"),
                            )
                            .ok()
                            .filter(|ctx| {
                                if ctx.is_software() {
                                    tracing::info!(
                                        adapter = %ctx.info.name,
                                        "depth reconstruction on the CPU: the adapter is a software rasteriser"
                                    );
                                }
                                !ctx.is_software()
                            });
                        DepthStage::new(camera, gpu, config.scene.depth_stride)
                    });
                let mut live = LiveScene::new(
                    scene,
                    config.scene.real,
                    config.scene.real_albedo,
                    depth_camera,
                    config.scene.depth_stride,
                );
                live.set_light_source(config.scene.lighting);
                if config.scene.real == RealGeometry::Depth && config.scene.measure_albedo {
                    match calibration.map(surface_albedo_decoding) {
                        Some(Ok(decoding)) => live.measure_albedo(SurfaceAlbedo::new(
                            AlbedoSettings::default(),
                            decoding,
                            Vec3::splat(config.scene.real_albedo),
                            config.scene.albedo_every,
                        )),
                        Some(Err(error)) => tracing::warn!(
                            %error,
                            "the real surface's albedo is not measured: it is [scene] real_albedo"
                        ),
                        None => {}
                    }
                }
                Some(live)
            }
            None => None,
        };
        let tracker = Tracker::new(&config.tracking, calibration, scene_pose)
            .map_err(|e| anyhow::anyhow!("{}: {e}", config.path.display()))?;
        Ok(Self {
            tracker,
            live_scene,
            scene_lights,
            depth_stage,
        })
    }

    /// Turn probe frames into estimates on a thread of their own from now on (the daemon), so
    /// that merging a bracket never delays a frame. Without this they are merged inline, in
    /// frame order (`relightd score`, whose estimates must not depend on thread timing).
    pub fn probe_on_own_thread(&mut self) -> std::io::Result<()> {
        match self.scene_lights.as_mut() {
            Some(lights) => lights.probe_on_own_thread(),
            None => Ok(()),
        }
    }

    /// Estimate the live surface's albedo on a thread of its own from now on (the daemon), so
    /// eq. 1 never delays a frame: frames take the newest estimate. Without this it runs inline,
    /// in frame order (`relightd score`).
    pub fn albedo_on_own_thread(&mut self) -> std::io::Result<()> {
        match self.live_scene.as_mut() {
            Some(live) => live.albedo_on_own_thread(),
            None => Ok(()),
        }
    }

    /// A report of the tracked lamp (every one, as it arrives): its disc is masked out of the
    /// probe's next estimates so the lamp counts once.
    pub fn lamp_report(&mut self, frame: &Frame<LampState>) {
        if let Some(lights) = self.scene_lights.as_mut()
            && frame.payload.on
        {
            lights.lamp_on(frame.stamp.host_ns, frame.payload.position_in_world);
        }
    }

    /// Take a probe frame (every one, not only those matched to a frame set: a bracket needs
    /// each of its exposures). Inline, returns how long it took, milliseconds, when there is a
    /// scene to light; on the probe's own thread it only queues the frame.
    pub fn probe_frame(&mut self, frame: &Arc<Frame<ProbeImage>>) -> Option<f64> {
        let scene_lights = self.scene_lights.as_mut()?;
        let start = Instant::now();
        let merged = scene_lights.probe_frame(frame);
        self.apply_probe_estimate();
        merged.then(|| start.elapsed().as_secs_f64() * 1e3)
    }

    /// Light the live scene with the probe's newest estimate, when it has a new one. Returns
    /// how long the probe's thread took to make it, milliseconds.
    fn apply_probe_estimate(&mut self) -> Option<f64> {
        let (estimate, ms) = self.scene_lights.as_mut()?.take_new_estimate()?;
        if let Some(live) = self.live_scene.as_mut() {
            live.set_probe_estimate(&estimate.environment, &estimate.lights);
        }
        Some(ms)
    }

    /// The scene frame of `set` (number `seq`). Untracked, it carries the camera image alone
    /// (nothing is reconstructed with a pose that is not known).
    pub fn frame(&mut self, set: &FrameSet, seq: u64, lights: &LightsBoard) -> LiveFrame {
        let probe_ms = self.apply_probe_estimate();
        let start = Instant::now();
        let tracking = self
            .tracker
            .update(set.stamp.host_ns, set.markers.as_ref().map(|m| &m.payload));
        let mut timings = LiveTimings {
            tracking_ms: start.elapsed().as_secs_f64() * 1e3,
            probe_ms,
            ..LiveTimings::default()
        };
        let mut scene = SceneFrame {
            stamp: set.stamp,
            seq,
            color: set.color.clone(),
            depth: set.depth.clone(),
            scene: None,
        };
        let mut reconstructed = None;
        if let (Some(live), Some(world_from_camera)) =
            (self.live_scene.as_mut(), tracking.world_from_camera)
        {
            live.set_world_from_camera(world_from_camera);
            let start = Instant::now();
            reconstructed = match (&mut self.depth_stage, &set.depth) {
                (Some(stage), Some(depth)) => {
                    let outcome = stage.process(
                        &depth.payload,
                        set.color.as_ref().map(|c| &c.payload),
                        &world_from_camera,
                    );
                    // Only this frame's merge says whether its surface is the last one's.
                    if stage.surface_held() {
                        live.hold_surface();
                    }
                    Some(outcome)
                }
                _ => None,
            };
            let depth_ms = start.elapsed().as_secs_f64() * 1e3;
            let depth = match &reconstructed {
                Some(DepthOutcome::Depth(image)) => Some(image),
                Some(DepthOutcome::Proxy) => None,
                None => set.depth.as_ref().map(|d| &d.payload),
            };
            scene.scene = live.frame(
                depth,
                set.color.as_ref().map(|c| &c.payload),
                set.lamp.as_ref().map(|l| &l.payload),
            );
            if let Some(scene_lights) = &mut self.scene_lights {
                scene_lights.publish_if_changed(live, lights);
            }
            if self.depth_stage.is_some() {
                timings.depth_ms = Some(depth_ms);
            }
            timings.scene_ms = Some(start.elapsed().as_secs_f64() * 1e3 - depth_ms);
        }
        let depth_passes = match (&self.depth_stage, &reconstructed) {
            (Some(stage), Some(_)) => stage.passes().to_vec(),
            _ => Vec::new(),
        };
        LiveFrame {
            scene,
            tracking,
            depth: reconstructed,
            timings,
            depth_passes,
            albedo: self.live_scene.as_ref().and_then(LiveScene::albedo_report),
        }
    }
}

/// The colour camera's decoding for albedo measurement, from the rig calibration.
fn surface_albedo_decoding(rig: &RigCalibration) -> anyhow::Result<ColorDecoding> {
    if rig.color_response.is_empty() {
        anyhow::bail!("the rig calibration has no color_response for the colour camera");
    }
    Ok(SurfaceAlbedo::decoding(
        &rig.color_response,
        rig.color_radiance_scale,
    )?)
}
