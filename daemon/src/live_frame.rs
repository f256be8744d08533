//! One live frame's scene, from a synchronised frame set: the camera registered
//! ([`crate::tracking`]), depth reconstructed ([`DepthStage`]) with that pose, the real surface
//! triangulated around the virtual object(s) placed in the world frame, and the lighting
//! estimate (the light probe's, else the scene file's) published when it changes.
//!
//! The render thread and `relightd score` both build frames through [`LiveFrames`], so what is
//! scored is what runs live.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use glam::Vec3;
use relight_core::camera::CameraModel;
use relight_core::light::Light;
use relight_core::rig::RigCalibration;
use relight_core::scene::Scene;
use relight_core::sh::Sh9Rgb;
use relight_core::sync::FrameSet;
use relight_core::{Frame, LampState, ProbeImage, Timestamp};
use relight_engines::live_scene::{LightSource, LiveScene, RealGeometry};
use relight_engines::surface_albedo::{AlbedoReport, SurfaceAlbedo};
use relight_engines::{EngineRegistry, SceneFrame};
use relight_recon::albedo::{AlbedoSettings, ColorDecoding};
use relight_recon::estimate::LightingEstimate;
use relight_recon::irradiance::project_sh9;
use relight_recon::probe::{ProbeEstimate, ProbeLighting, ProbeSettings};

use crate::config::Config;
use crate::control::lights::LightsBoard;
use crate::depth_stage::{DepthOutcome, DepthStage};
use crate::tracking::{Tracker, TrackingReport};
use crate::worker::Worker;

/// A frame set turned into what an engine renders.
#[derive(Debug)]
pub struct LiveFrame {
    pub scene: SceneFrame,
    pub tracking: TrackingReport,
    /// What the depth stage made of the set's depth (`None` without a depth stage, or when the
    /// camera is untracked and nothing was built).
    pub depth: Option<DepthOutcome>,
    /// Stage timings, milliseconds, in data-flow order.
    pub timings: Vec<(&'static str, f64)>,
    /// What the albedo measurement did on this frame, when it runs.
    pub albedo: Option<AlbedoReport>,
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
                scene_lights = Some(SceneLights::new(
                    &scene,
                    probe.map(|p| ProbeRunner::Inline(Box::new(p))),
                ));
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
                        let gpu = registry
                            .gpu()
                            .inspect_err(
                                |error| tracing::info!(%error, "depth reconstruction on the CPU"),
                            )
                            .ok();
                        DepthStage::new(camera, gpu)
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
        if let Some(lights) = self.scene_lights.as_mut()
            && let Some(ProbeRunner::Inline(_)) = &lights.probe
            && let Some(ProbeRunner::Inline(probe)) = lights.probe.take()
        {
            lights.probe = Some(ProbeRunner::Thread(ProbeThread::spawn(*probe)?));
        }
        Ok(())
    }

    /// A report of the tracked lamp (every one, as it arrives): its disc is masked out of the
    /// probe's next estimates so the lamp counts once.
    pub fn lamp_report(&mut self, frame: &Frame<LampState>) {
        if let Some(probe) = self.scene_lights.as_mut().and_then(|s| s.probe.as_mut())
            && frame.payload.on
        {
            probe.track_light(frame.stamp.host_ns, frame.payload.position_in_world);
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
        let scene_lights = self.scene_lights.as_mut()?;
        let ms = scene_lights.take_new_estimate()?;
        if let (Some(estimate), Some(live)) =
            (&scene_lights.probe_estimate, self.live_scene.as_mut())
        {
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
        let mut timings = vec![("tracking", start.elapsed().as_secs_f64() * 1e3)];
        timings.extend(probe_ms.map(|ms| ("probe", ms)));
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
                (Some(stage), Some(depth)) => Some(stage.process(
                    &depth.payload,
                    set.color.as_ref().map(|c| &c.payload),
                    &world_from_camera,
                )),
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
                timings.push(("depth", depth_ms));
            }
            timings.push(("scene", start.elapsed().as_secs_f64() * 1e3 - depth_ms));
        }
        LiveFrame {
            scene,
            tracking,
            depth: reconstructed,
            timings,
            albedo: self.live_scene.as_ref().and_then(LiveScene::albedo_report),
        }
    }
}

/// Push one probe frame; the estimate when it completes a bracket.
fn merge_probe_frame(
    probe: &mut ProbeLighting,
    frame: &Arc<Frame<ProbeImage>>,
) -> Option<ProbeEstimate> {
    probe
        .push(frame)
        .inspect_err(|error| tracing::warn!(%error, "probe bracket not used"))
        .ok()
        .flatten()
}

/// Where probe frames become estimates.
enum ProbeRunner {
    Inline(Box<ProbeLighting>),
    Thread(ProbeThread),
}

impl ProbeRunner {
    fn track_light(&mut self, host_ns: u64, position_in_world: Vec3) {
        match self {
            Self::Inline(probe) => probe.track_light(host_ns, position_in_world),
            Self::Thread(thread) => thread.send(ProbeInput::Light(host_ns, position_in_world)),
        }
    }
}

enum ProbeInput {
    Frame(Arc<Frame<ProbeImage>>),
    Light(u64, Vec3),
}

/// Probe frames and lamp reports queued for the probe's thread before new ones are dropped:
/// several brackets' worth, so that only a thread that has fallen far behind loses frames.
const PROBE_QUEUE: usize = 32;

/// [`ProbeLighting`] on its own thread. Its newest estimate waits in a one-slot mailbox (a newer
/// one replaces it) for the next frame to take.
struct ProbeThread {
    worker: Worker<ProbeInput>,
    latest: Arc<Mutex<Option<(ProbeEstimate, f64)>>>,
    dropped: u64,
}

impl ProbeThread {
    fn spawn(mut probe: ProbeLighting) -> std::io::Result<Self> {
        let latest = Arc::new(Mutex::new(None));
        let worker = {
            let latest = Arc::clone(&latest);
            Worker::spawn("probe", PROBE_QUEUE, move |item| match item {
                ProbeInput::Light(host_ns, position) => probe.track_light(host_ns, position),
                ProbeInput::Frame(frame) => {
                    let start = Instant::now();
                    if let Some(estimate) = merge_probe_frame(&mut probe, &frame) {
                        let ms = start.elapsed().as_secs_f64() * 1e3;
                        *latest.lock().unwrap_or_else(PoisonError::into_inner) =
                            Some((estimate, ms));
                    }
                }
            })?
        };
        Ok(Self {
            worker,
            latest,
            dropped: 0,
        })
    }

    fn send(&mut self, item: ProbeInput) {
        if self.worker.offer(item).is_err() {
            self.dropped += 1;
            if self.dropped.is_power_of_two() {
                tracing::warn!(
                    dropped = self.dropped,
                    "the probe's thread is behind; probe input dropped"
                );
            }
        }
    }

    fn take_latest(&self) -> Option<(ProbeEstimate, f64)> {
        self.latest
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
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

/// The lighting estimate, seen from the virtual object: the light probe's (its median-cut
/// lights and SH9, stamped with the probe's time) once it has given one, else the scene file's
/// lights and environment map; the lamp where it is now in both cases. Published when it
/// changes (a new probe bracket, the lamp moves or switches), not every frame.
struct SceneLights {
    /// Centre of the virtual object's bounds (the world origin without one).
    reference_point: Vec3,
    /// The scene file's environment map as SH (zero without one).
    scene_sh9: Sh9Rgb,
    /// The probe's estimate of the live scene (with a probe in the rig's calibration).
    probe: Option<ProbeRunner>,
    probe_estimate: Option<ProbeEstimate>,
    /// How long the estimate in `probe_estimate` took, until the frames' side has taken it.
    new_estimate_ms: Option<f64>,
    /// What the last published estimate was made of.
    published: Option<(Vec<Light>, Option<Timestamp>)>,
}

impl SceneLights {
    fn new(scene: &Scene, probe: Option<ProbeRunner>) -> Self {
        Self {
            reference_point: scene
                .virtual_bounds()
                .map_or(Vec3::ZERO, |(lo, hi)| (lo + hi) * 0.5),
            scene_sh9: scene
                .environment
                .as_ref()
                .and_then(|env| project_sh9(env).ok())
                .unwrap_or(Sh9Rgb::ZERO),
            probe,
            probe_estimate: None,
            new_estimate_ms: None,
            published: None,
        }
    }

    /// Take a probe frame; true when it was merged here, inline (the time it took is the
    /// probe's), false when it went to the probe's thread or there is no probe.
    fn probe_frame(&mut self, frame: &Arc<Frame<ProbeImage>>) -> bool {
        match self.probe.as_mut() {
            Some(ProbeRunner::Inline(probe)) => {
                let start = Instant::now();
                if let Some(estimate) = merge_probe_frame(probe, frame) {
                    self.probe_estimate = Some(estimate);
                    self.new_estimate_ms = Some(start.elapsed().as_secs_f64() * 1e3);
                }
                true
            }
            Some(ProbeRunner::Thread(thread)) => {
                thread.send(ProbeInput::Frame(Arc::clone(frame)));
                false
            }
            None => false,
        }
    }

    /// The time the newest estimate took, once, when there is one the frames have not used.
    fn take_new_estimate(&mut self) -> Option<f64> {
        if let Some(ProbeRunner::Thread(thread)) = &self.probe
            && let Some((estimate, ms)) = thread.take_latest()
        {
            self.probe_estimate = Some(estimate);
            self.new_estimate_ms = Some(ms);
        }
        self.new_estimate_ms.take()
    }

    /// Publish what `live` is lit by now, if it changed since the last time.
    fn publish_if_changed(&mut self, live: &LiveScene, board: &LightsBoard) {
        let (lights, sh9, stamp) = match &self.probe_estimate {
            Some(probe) => {
                // The probe sees every other light; the lamp's disc is masked out of its map.
                let lights: Vec<Light> = probe
                    .lights
                    .iter()
                    .copied()
                    .chain(live.lamp_light())
                    .collect();
                (lights, probe.sh9, Some(probe.stamp))
            }
            None => (live.lights(), self.scene_sh9, None),
        };
        let key = (lights, stamp);
        if self.published.as_ref() == Some(&key) {
            return;
        }
        let mut estimate =
            LightingEstimate::from_lights(key.0.clone(), sh9, stamp, self.reference_point);
        estimate.relative_units = self.probe_estimate.as_ref().is_some_and(|p| !p.absolute);
        self.published = Some(key);
        if board.publish(estimate) {
            tracing::trace!("lighting estimate published");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_lights_publish_only_changes() {
        let board = LightsBoard::new();
        let scene = Scene {
            name: "t".into(),
            meshes: vec![relight_core::scene::Mesh::cuboid(
                "box",
                Vec3::new(-0.1, 0.0, -0.1),
                Vec3::new(0.1, 0.2, 0.1),
                0,
                true,
            )],
            materials: Vec::new(),
            camera: relight_core::scene::SceneCamera {
                world_from_camera: relight_core::Pose::IDENTITY,
                yfov_rad: 1.0,
                width: 8,
                height: 6,
            },
            lights: Vec::new(),
            environment: None,
            environment_lights: Vec::new(),
        };
        let mut scene_lights = SceneLights::new(&scene, None);
        assert_eq!(scene_lights.reference_point, Vec3::new(0.0, 0.1, 0.0));
        let mut live = LiveScene::new(scene, RealGeometry::Scene, 0.5, None, 1);
        let lamp = LampState {
            on: true,
            position_in_world: Vec3::new(0.0, 1.1, 0.0),
            intensity: Vec3::splat(2.0),
        };
        live.frame(None, None, Some(&lamp));
        scene_lights.publish_if_changed(&live, &board);
        scene_lights.publish_if_changed(&live, &board);
        assert_eq!(board.published(), 1);
        let estimate = board.latest().expect("published");
        let main = estimate.main_light.expect("the lamp");
        assert!((main.direction_in_world - Vec3::NEG_Y).length() < 1e-6);
        assert!((main.intensity - 2.0).abs() < 1e-5);
        live.frame(None, None, Some(&LampState::default()));
        scene_lights.publish_if_changed(&live, &board);
        assert_eq!(board.published(), 2);
        assert_eq!(board.latest().expect("published").main_light, None);
    }
}
