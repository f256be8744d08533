//! The lighting estimate stage: what lights the virtual object, and what `lights.*` publishes.
//! The light probe's brackets become estimates ([`ProbeLighting`]) inline, in frame order
//! (`relightd score`), or on the probe's own thread (the daemon), so that merging a bracket never
//! delays a frame; the tracked lamp is masked out of the probe's view so it counts once.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use glam::Vec3;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Scene};
use relight_core::sh::Sh9Rgb;
use relight_core::{Frame, ProbeImage, Timestamp};
use relight_engines::live_scene::LiveScene;
use relight_recon::estimate::LightingEstimate;
use relight_recon::irradiance::project_sh9;
use relight_recon::probe::{ProbeEstimate, ProbeLighting};

use crate::control::lights::LightsBoard;
use crate::worker::Worker;

/// The lighting estimate, seen from the virtual object: the light probe's (its median-cut
/// lights and SH9, stamped with the probe's time) once it has given one, else the scene file's
/// lights and environment map; the lamp where it is now in both cases. Published when it
/// changes (a new probe bracket, the lamp moves or switches), not every frame.
pub struct SceneLights {
    /// Centre of the virtual object's bounds (the world origin without one).
    reference_point: Vec3,
    /// The scene file's environment map as SH (zero without one).
    scene_sh9: Sh9Rgb,
    scene_environment: Option<Arc<EnvironmentMap>>,
    /// The probe's estimate of the live scene (with a probe in the rig's calibration).
    probe: Option<ProbeRunner>,
    probe_estimate: Option<ProbeEstimate>,
    /// How long the estimate in `probe_estimate` took, until the frames' side has taken it.
    new_estimate_ms: Option<f64>,
    /// What the last published estimate was made of.
    published: Option<(Vec<Light>, Option<Timestamp>)>,
}

impl std::fmt::Debug for SceneLights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SceneLights")
            .field("probe", &self.probe.is_some())
            .field("published", &self.published.is_some())
            .finish_non_exhaustive()
    }
}

impl SceneLights {
    /// The lights of `scene`, replaced by `probe`'s estimates once it gives one.
    pub fn new(scene: &Scene, probe: Option<ProbeLighting>) -> Self {
        Self {
            reference_point: scene
                .virtual_bounds()
                .map_or(Vec3::ZERO, |(lo, hi)| (lo + hi) * 0.5),
            scene_sh9: scene
                .environment
                .as_ref()
                .and_then(|env| project_sh9(env).ok())
                .unwrap_or(Sh9Rgb::ZERO),
            scene_environment: scene.environment.clone().map(Arc::new),
            probe: probe.map(|p| ProbeRunner::Inline(Box::new(p))),
            probe_estimate: None,
            new_estimate_ms: None,
            published: None,
        }
    }

    /// Turn probe frames into estimates on a thread of their own from now on.
    pub fn probe_on_own_thread(&mut self) -> std::io::Result<()> {
        if let Some(ProbeRunner::Inline(_)) = &self.probe
            && let Some(ProbeRunner::Inline(probe)) = self.probe.take()
        {
            self.probe = Some(ProbeRunner::Thread(ProbeThread::spawn(*probe)?));
        }
        Ok(())
    }

    /// The lamp is on at `position_in_world`: mask its disc out of the probe's next estimates.
    pub fn lamp_on(&mut self, host_ns: u64, position_in_world: Vec3) {
        match &mut self.probe {
            Some(ProbeRunner::Inline(probe)) => probe.track_light(host_ns, position_in_world),
            Some(ProbeRunner::Thread(thread)) => {
                thread.send(ProbeInput::Light(host_ns, position_in_world))
            }
            None => {}
        }
    }

    /// Take a probe frame; true when it was merged here, inline (the time it took is the
    /// probe's), false when it went to the probe's thread or there is no probe.
    pub fn probe_frame(&mut self, frame: &Arc<Frame<ProbeImage>>) -> bool {
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

    /// The newest estimate and the time it took, once, when there is one the frames have not
    /// used.
    pub fn take_new_estimate(&mut self) -> Option<(&ProbeEstimate, f64)> {
        if let Some(ProbeRunner::Thread(thread)) = &self.probe
            && let Some((estimate, ms)) = thread.take_latest()
        {
            self.probe_estimate = Some(estimate);
            self.new_estimate_ms = Some(ms);
        }
        let ms = self.new_estimate_ms.take()?;
        Some((self.probe_estimate.as_ref()?, ms))
    }

    /// Publish what `live` is lit by now, if it changed since the last time.
    pub fn publish_if_changed(&mut self, live: &LiveScene, board: &LightsBoard) {
        let (lights, lights_in_sh9, sh9, stamp) = match &self.probe_estimate {
            Some(probe) => {
                // The probe sees every other light (its median cut is its map, `sh9`); the
                // lamp's disc is masked out of the map.
                let lights: Vec<Light> = probe
                    .lights
                    .iter()
                    .copied()
                    .chain(live.lamp_light())
                    .collect();
                (lights, probe.lights.len(), probe.sh9, Some(probe.stamp))
            }
            None => (live.lights(), 0, self.scene_sh9, None),
        };
        let key = (lights, stamp);
        if self.published.as_ref() == Some(&key) {
            return;
        }
        let mut estimate = LightingEstimate::from_lights(
            key.0.clone(),
            lights_in_sh9,
            sh9,
            stamp,
            self.reference_point,
        );
        estimate.relative_units = self.probe_estimate.as_ref().is_some_and(|p| !p.absolute);
        self.published = Some(key);
        board.publish_environment(match &self.probe_estimate {
            Some(probe) => Some(Arc::clone(&probe.environment)),
            None => self.scene_environment.clone(),
        });
        if board.publish(estimate) {
            tracing::trace!("lighting estimate published");
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

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::LampState;
    use relight_engines::live_scene::RealGeometry;

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
            shadow_proxy: None,
            surface_revision: None,
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
