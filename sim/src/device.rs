//! `[sim]`: the simulated rig as a live source, for running the daemon with neither hardware
//! nor a recording. Frames are rendered as they are published, at most at `fps`; path tracing
//! sets the real pace (at 160 × 120 and 1 spp a few tens of frames per second on a desktop, a
//! few on this 2-core machine), so for paper-quality input record with `relightd simulate` and
//! replay instead.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use relight_core::StreamKind;
use relight_core::frame::host_now_ns;
use relight_core::rig::RigCalibration;
use relight_core::scene::Scene;
use serde::Deserialize;

use crate::rig::{CameraPath, SimRig, SimSettings};
use relight_backends::device::{Device, DeviceContext, DeviceError, RunEnd};

/// The `[sim]` table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimSourceConfig {
    /// Directory holding `scene.toml` and its glTF.
    pub scene: PathBuf,
    #[serde(default = "default_width")]
    pub width: u32,
    #[serde(default = "default_height")]
    pub height: u32,
    #[serde(default = "default_fps")]
    pub fps: u32,
    /// Path-traced samples per pixel of each colour frame.
    #[serde(default = "default_spp")]
    pub spp: u32,
    /// `static`, `shake` or `orbit`.
    #[serde(default = "default_trajectory")]
    pub trajectory: String,
    #[serde(default = "yes")]
    pub board: bool,
    #[serde(default = "yes")]
    pub lamp: bool,
    #[serde(default = "yes")]
    pub probe: bool,
    #[serde(default = "default_seed")]
    pub seed: u64,
}

fn default_width() -> u32 {
    160
}
fn default_height() -> u32 {
    120
}
fn default_fps() -> u32 {
    30
}
fn default_spp() -> u32 {
    1
}
fn default_trajectory() -> String {
    "shake".into()
}
fn yes() -> bool {
    true
}
fn default_seed() -> u64 {
    1
}

/// The live simulated rig.
#[derive(Debug)]
pub struct SimDevice {
    rig: SimRig,
    streams: Vec<StreamKind>,
}

impl SimDevice {
    /// Loads the scene and builds the rig now, so a bad `[sim]` section fails at start-up.
    pub fn new(config: &SimSourceConfig) -> Result<Self, DeviceError> {
        let invalid = |reason: String| DeviceError::Config {
            device: "sim".into(),
            reason,
        };
        let scene = Scene::load(&config.scene).map_err(|e| invalid(e.to_string()))?;
        let path = match config.trajectory.as_str() {
            "static" => CameraPath::Static,
            "shake" => CameraPath::Shake,
            "orbit" => CameraPath::Orbit,
            "walk" => CameraPath::Walk,
            other => {
                return Err(invalid(format!(
                    "trajectory `{other}`: expected `static`, `shake`, `orbit` or `walk`"
                )));
            }
        };
        let mut settings = SimSettings {
            width: config.width,
            height: config.height,
            fps: config.fps,
            frames: u32::MAX,
            color_spp: config.spp,
            truth_every: 0,
            seed: config.seed,
            trajectory: Some(path.trajectory(&scene)),
            ..SimSettings::placed_in(&scene)
        };
        if !config.board {
            settings.board = None;
        }
        if !config.lamp {
            settings.lamp = None;
        }
        if !config.probe {
            settings.probe = None;
        }
        let mut streams = vec![StreamKind::Depth, StreamKind::Color];
        for (present, kind) in [
            (settings.board.is_some(), StreamKind::Markers),
            (settings.probe.is_some(), StreamKind::Probe),
            (settings.lamp.is_some(), StreamKind::Lamp),
        ] {
            if present {
                streams.push(kind);
            }
        }
        let rig = SimRig::new(&scene, settings).map_err(|e| invalid(e.to_string()))?;
        Ok(Self { rig, streams })
    }

    pub fn calibration(&self) -> RigCalibration {
        self.rig.calibration()
    }
}

impl Device for SimDevice {
    fn backend(&self) -> &'static str {
        "sim"
    }

    fn streams(&self) -> Vec<StreamKind> {
        self.streams.clone()
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }

    /// Renders frame after frame; each message is stamped with the host time it is published
    /// at (device time stays the simulated sensor clock), paced to at most `fps`.
    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        let period = Duration::from_secs_f64(1.0 / f64::from(self.rig.settings().fps));
        let start = Instant::now();
        for i in 0..self.rig.settings().frames {
            let due = period * i;
            let wait = due.saturating_sub(start.elapsed());
            if !wait.is_zero() && !ctx.sleep(wait) {
                return Ok(RunEnd::StopRequested);
            }
            for mut msg in self.rig.frame(i).messages {
                if ctx.should_stop() {
                    return Ok(RunEnd::StopRequested);
                }
                msg.header_mut().1.host_ns = host_now_ns();
                ctx.publish(msg);
            }
        }
        Ok(RunEnd::EndOfStream)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use relight_core::bus::Bus;

    use super::*;
    use relight_backends::device::{Backoff, DeviceRunner};

    fn desk() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box")
    }

    fn config(toml_like: serde_json::Value) -> Result<SimSourceConfig, serde_json::Error> {
        serde_json::from_value(toml_like)
    }

    #[test]
    fn live_sim_publishes_every_stream() {
        let cfg = config(serde_json::json!({
            "scene": desk(), "width": 32, "height": 24, "fps": 200
        }))
        .unwrap();
        let device = SimDevice::new(&cfg).unwrap();
        assert_eq!(device.streams().len(), 5);
        let bus = Arc::new(Bus::new());
        let sub = bus.all.subscribe(64);
        let mut runner =
            DeviceRunner::spawn("sim", Box::new(device), bus, Backoff::default()).unwrap();
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut kinds = std::collections::BTreeSet::new();
        while kinds.len() < 5 && Instant::now() < deadline {
            if let Some(msg) = sub.recv_timeout(Duration::from_millis(20)) {
                kinds.insert(msg.kind());
            }
        }
        runner.stop();
        assert_eq!(kinds.len(), 5, "{kinds:?}");
    }

    #[test]
    fn bad_sections_are_clear_errors() {
        assert!(
            config(serde_json::json!({ "scene": desk(), "colour": 1 }))
                .unwrap_err()
                .to_string()
                .contains("unknown field `colour`")
        );
        let missing = config(serde_json::json!({ "scene": "/nonexistent" })).unwrap();
        assert!(
            SimDevice::new(&missing)
                .unwrap_err()
                .to_string()
                .contains("nonexistent")
        );
        let bad_path =
            config(serde_json::json!({ "scene": desk(), "trajectory": "loop" })).unwrap();
        assert!(
            SimDevice::new(&bad_path)
                .unwrap_err()
                .to_string()
                .contains("trajectory `loop`")
        );
        let zero_fps = config(serde_json::json!({ "scene": desk(), "fps": 0 })).unwrap();
        assert!(
            SimDevice::new(&zero_fps)
                .unwrap_err()
                .to_string()
                .contains("fps")
        );
    }
}
