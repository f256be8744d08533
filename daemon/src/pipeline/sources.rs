//! The sources stage: the configured replay, simulated rig or devices, each on its own
//! [`DeviceRunner`] thread publishing to the bus, and what the rest of the pipeline learns from
//! them: the rig calibration, the streams to synchronise, and how a replay is paced.

use std::path::Path;

use anyhow::Context as _;
use relight_backends::device::{Backoff, Stepper};
use relight_backends::{Backpressure, Device as _, DeviceRunner, Replay, ReplayConfig, ReplayMode};
use relight_core::StreamKind;
use relight_core::bus::Bus;
use relight_core::camera::CameraModel;
use relight_core::recording::{RecordingMeta, RecordingReader, TopicMap};
use relight_core::rig::RigCalibration;
use relight_core::sync::SyncConfig as CoreSyncConfig;
use relight_sim::device::{SimDevice, SimSourceConfig};
use std::sync::Arc;

use crate::config::{self, Config, SourceConfig};

/// Reference frames a fast replay may run ahead of the render thread. More than the
/// synchroniser's `max_wait` spans at 30 Hz, so a set can always be decided on the data alone,
/// and well under its buffer bound.
const FAST_REPLAY_WINDOW: u64 = 16;

/// The running sources.
pub struct Sources {
    pub runners: Vec<DeviceRunner>,
    /// Wakes the runners' reconnects on USB arrivals.
    pub hotplug: crate::devices::Hotplug,
    /// The source's own calibration (a recording's, the simulator's) or the rig's.
    pub meta: RecordingMeta,
    /// What to synchronise: the configured streams the source has.
    pub sync: CoreSyncConfig,
    /// Render every frame set (fast and stepped replays) instead of the newest one.
    pub lossless: bool,
    /// A fast replay's flow control.
    pub backpressure: Option<Arc<Backpressure>>,
    /// Present when the source is a stepped replay.
    pub steppers: Vec<Stepper>,
}

impl std::fmt::Debug for Sources {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sources")
            .field("runners", &self.runners.len())
            .field("lossless", &self.lossless)
            .finish_non_exhaustive()
    }
}

pub fn core_sync_config(sync: &config::SyncConfig) -> CoreSyncConfig {
    CoreSyncConfig {
        reference: sync.reference,
        expected: sync.streams.clone(),
        tolerance_ns: u64::try_from(sync.tolerance.as_nanos()).unwrap_or(u64::MAX),
        max_wait_ns: u64::try_from(sync.max_wait.as_nanos()).unwrap_or(u64::MAX),
    }
}

/// A recording without, say, a lamp channel would leave every frame set waiting for a lamp
/// message that never comes; expect only what the recording holds, and say so.
pub fn expect_only_recorded_streams(
    sync: &mut CoreSyncConfig,
    recorded: &[StreamKind],
    path: &Path,
) {
    let absent: Vec<StreamKind> = sync
        .expected
        .iter()
        .copied()
        .filter(|k| !recorded.contains(k))
        .collect();
    if !absent.is_empty() {
        tracing::warn!(path = %path.display(), ?absent, "recording lacks configured streams; not waiting for them");
        sync.expected.retain(|k| recorded.contains(k));
    }
}

/// The rig calibration a recording carries: relight's own, or for another tool's bag the
/// cameras its `camera_info` topics describe (depth taken as registered to colour).
fn recording_calibration(reader: &RecordingReader, path: &Path) -> Option<RigCalibration> {
    if let Some(calibration) = &reader.meta().calibration {
        return Some(calibration.clone());
    }
    match reader.calibration_from_camera_info() {
        Ok(Some(calibration)) => {
            tracing::info!(path = %path.display(), "no relight calibration in the recording: the cameras are its camera_info topics'");
            let sizes = |c: &Option<CameraModel>| c.map(|c| (c.width(), c.height()));
            if calibration.depth.is_some() && sizes(&calibration.depth) != sizes(&calibration.color)
            {
                tracing::warn!(path = %path.display(), "depth and colour differ in size: relight takes depth as registered to the colour camera; replay an aligned depth topic or give [rig] calibration");
            }
            Some(calibration)
        }
        Ok(None) => {
            tracing::warn!(path = %path.display(), "the recording has no calibration and no camera_info topics: give [rig] calibration");
            None
        }
        Err(error) => {
            tracing::warn!(path = %path.display(), %error, "camera_info does not decode: give [rig] calibration");
            None
        }
    }
}

/// Open and start what `config` names, publishing to `bus`.
pub fn start(config: &Config, bus: &Arc<Bus>) -> anyhow::Result<Sources> {
    let mut meta = RecordingMeta {
        calibration: None,
        source: format!("relightd {}", env!("CARGO_PKG_VERSION")),
    };
    let mut runners = Vec::new();
    let mut hotplug = crate::devices::Hotplug::default();
    let mut backpressure = None;
    let mut sync = core_sync_config(&config.sync);
    match &config.source {
        SourceConfig::Replay(replay) => {
            let device = Replay::with_topics(
                ReplayConfig {
                    path: replay.path.clone(),
                    mode: match replay.mode {
                        config::ReplayMode::Realtime => ReplayMode::Realtime {
                            speed: replay.speed,
                        },
                        config::ReplayMode::Fast => ReplayMode::Fast,
                        config::ReplayMode::Stepped => ReplayMode::Stepped,
                    },
                    looping: replay.loop_playback,
                },
                TopicMap::new(replay.topics.clone()),
            )
            .with_context(|| format!("{}: [replay]", config.path.display()))?;
            let device = match replay.mode {
                config::ReplayMode::Fast => {
                    let gate = Backpressure::new(config.sync.reference, FAST_REPLAY_WINDOW);
                    backpressure = Some(gate.clone());
                    device.with_backpressure(gate)
                }
                config::ReplayMode::Stepped => device.stepping_by(config.sync.reference),
                config::ReplayMode::Realtime => device,
            };
            meta.calibration = match device.reader() {
                Some(reader) if config.rig.calibration.is_none() => {
                    recording_calibration(reader, &replay.path)
                }
                _ => None,
            };
            expect_only_recorded_streams(&mut sync, &device.streams(), &replay.path);
            runners.push(DeviceRunner::spawn(
                "replay",
                Box::new(device),
                bus.clone(),
                Backoff::default(),
            )?);
        }
        SourceConfig::Sim(sim) => {
            let context = || format!("{}: [sim]", config.path.display());
            let settings: SimSourceConfig =
                serde_json::from_value(sim.settings.clone()).with_context(context)?;
            let device = SimDevice::new(&settings).with_context(context)?;
            meta.calibration = Some(device.calibration());
            expect_only_recorded_streams(&mut sync, &device.streams(), &settings.scene);
            runners.push(DeviceRunner::spawn(
                "sim",
                Box::new(device),
                bus.clone(),
                Backoff::default(),
            )?);
        }
        SourceConfig::Devices(devices) => {
            meta.calibration = config.rig.calibration.clone();
            if devices.is_empty() {
                tracing::warn!("no source configured: serving the control socket only");
            }
            let (devices, watcher) =
                crate::devices::spawn(devices, config.rig.calibration.as_ref(), bus)
                    .with_context(|| config.path.display().to_string())?;
            runners.extend(devices);
            hotplug = watcher;
        }
    }
    if let (Some(calibration), SourceConfig::Replay(_) | SourceConfig::Sim(_)) =
        (&config.rig.calibration, &config.source)
    {
        tracing::info!("[rig] calibration replaces the source's own");
        meta.calibration = Some(calibration.clone());
    }
    let lossless = matches!(
        &config.source,
        SourceConfig::Replay(r) if r.mode != config::ReplayMode::Realtime
    );
    let steppers = match &config.source {
        SourceConfig::Replay(r) if r.mode == config::ReplayMode::Stepped => {
            runners.iter().map(DeviceRunner::stepper).collect()
        }
        _ => Vec::new(),
    };
    Ok(Sources {
        runners,
        hotplug,
        meta,
        sync,
        lossless,
        backpressure,
        steppers,
    })
}
