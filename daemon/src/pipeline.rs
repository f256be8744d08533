//! The running daemon: devices → bus → synchroniser → engine → sinks, and the control surface
//! that steers it.
//!
//! Threads: one per device (its [`DeviceRunner`]), one render thread (synchronise, render,
//! write outputs and snapshots), the recorder, and the control server's. Commands from the
//! control socket reach the render thread through shared slots that it reads at frame
//! boundaries — an engine is built on the control thread and only swapped in by the render
//! thread, so a slow build never stalls a frame.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context as _;
use crossbeam_channel::{Receiver, Sender, bounded};
use relight_backends::device::{Backoff, DeviceStatus as BackendStatus, Stepper};
use relight_backends::sim::device::{SimDevice, SimSourceConfig};
use relight_backends::{Device as _, DeviceRunner, DeviceState, Replay, ReplayConfig, ReplayMode};
use relight_core::bus::Bus;
use relight_core::frame::host_now_ns;
use relight_core::recording::RecordingMeta;
use relight_core::sync::{FrameSet, SyncConfig as CoreSyncConfig, Synchronizer};
use relight_core::{Frame, ProbeImage, StreamKind, StreamMessage};
use relight_engines::gpu::GpuError;
use relight_engines::{Engine, EngineError, EngineRegistry, RelitFrame};
use serde_json::{Map, Value, json};

use crate::config::{self, Config, SourceConfig};
use crate::control::lights::LightsBoard;
use crate::control::types::{
    AlbedoStatus, ControlError, ControlTarget, DeviceStatus, EngineInfo, RecordingStatus,
    StageTiming, StatusReport, SyncStreamStatus, TrackingStatus,
};
use crate::live_frame::LiveFrames;
use crate::sinks::png_out::write_png;
use crate::sinks::recorder::Recorder;
use crate::timing::StageStats;
use crate::tracking::TrackingReport;
use relight_engines::surface_albedo::AlbedoReport;

/// How long a control request waits for the render thread to serve a snapshot.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(3);
/// Frames of timing history behind the percentiles in status reports.
const TIMING_WINDOW: usize = 512;

/// Options that are not in the configuration file (command-line only).
#[derive(Debug, Clone, Default)]
pub struct PipelineOptions {
    /// Stop the render thread once every source has ended and the last frame set is out.
    pub exit_at_end: bool,
}

/// A change the render thread applies at the next frame boundary.
enum Pending {
    Engine {
        engine: Box<dyn Engine>,
        name: String,
        params: Map<String, Value>,
    },
    Params(Map<String, Value>),
}

struct SnapshotRequest {
    dir: PathBuf,
    reply: Sender<Result<Vec<PathBuf>, String>>,
}

/// What the render thread and the control threads share.
struct Shared {
    started: Instant,
    config: Mutex<Config>,
    registry: EngineRegistry,
    bus: Arc<Bus>,
    /// The engine the render thread runs now, and its full parameters.
    engine_name: Mutex<String>,
    engine_params: Mutex<Map<String, Value>>,
    pending: Mutex<Option<Pending>>,
    pending_sync: Mutex<Option<CoreSyncConfig>>,
    stages: Mutex<Vec<StageStats>>,
    frame_sets: AtomicU64,
    sync_missing: AtomicU64,
    sync_streams: Mutex<Vec<SyncStreamStatus>>,
    render_errors: AtomicU64,
    /// The last frame's registration, and how many frames were shown without Δ (untracked).
    tracking: Mutex<Option<TrackingReport>>,
    albedo: Mutex<Option<AlbedoReport>>,
    untracked_frames: AtomicU64,
    snapshots: (Sender<SnapshotRequest>, Receiver<SnapshotRequest>),
    devices: Vec<Arc<BackendStatus>>,
    /// Present when the source is a stepped replay.
    steppers: Vec<Stepper>,
    recorder: Recorder,
    /// The lighting estimate published on the control socket (`lights.*`).
    lights: Arc<LightsBoard>,
    /// Milliseconds since `started` at the render loop's last iteration (the watchdog's view).
    heartbeat_ms: AtomicU64,
    stop: AtomicBool,
    finished: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The running pipeline. Dropping it stops every thread.
pub struct Pipeline {
    shared: Arc<Shared>,
    runners: Vec<DeviceRunner>,
    /// Wakes the runners' reconnects on USB arrivals; outlives nothing it serves.
    _hotplug: crate::devices::Hotplug,
    render: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Pipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pipeline")
            .field("devices", &self.runners.len())
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

fn params_map(value: &Value) -> Map<String, Value> {
    value.as_object().cloned().unwrap_or_default()
}

impl Pipeline {
    /// Open the configured sources, build the configured engine and start every thread.
    pub fn start(config: Config, options: PipelineOptions) -> anyhow::Result<Self> {
        let registry = EngineRegistry::new();
        let built = registry
            .build(&config.engine.name, &params_map(&config.engine.params))
            .with_context(|| format!("{}: [engine]", config.path.display()))?;
        let bus = Arc::new(Bus::new());

        let mut meta = RecordingMeta {
            calibration: None,
            source: format!("relightd {}", env!("CARGO_PKG_VERSION")),
        };
        let mut runners = Vec::new();
        let mut hotplug = crate::devices::Hotplug::default();
        let mut sync = core_sync_config(&config.sync);
        match &config.source {
            SourceConfig::Replay(replay) => {
                let device = Replay::new(ReplayConfig {
                    path: replay.path.clone(),
                    mode: match replay.mode {
                        config::ReplayMode::Realtime => ReplayMode::Realtime {
                            speed: replay.speed,
                        },
                        config::ReplayMode::Fast => ReplayMode::Fast,
                        config::ReplayMode::Stepped => ReplayMode::Stepped,
                    },
                    looping: replay.loop_playback,
                })
                .with_context(|| format!("{}: [replay]", config.path.display()))?;
                meta.calibration = device.reader().and_then(|r| r.meta().calibration.clone());
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
                    crate::devices::spawn(devices, config.rig.calibration.as_ref(), &bus)
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
        let synchronizer = Synchronizer::new(sync)
            .with_context(|| format!("{}: [sync]", config.path.display()))?;
        let live = LiveFrames::new(&config, meta.calibration.as_ref(), &registry)?;
        let passthrough = registry.build("passthrough", &Map::new())?.engine;
        let recorder = Recorder::spawn(&bus, config.recorder.queue_frames, meta)?;
        let autostart = config
            .recorder
            .autostart
            .then(|| config.recorder.dir.clone());
        let steppers = match &config.source {
            SourceConfig::Replay(r) if r.mode == config::ReplayMode::Stepped => {
                runners.iter().map(DeviceRunner::stepper).collect()
            }
            _ => Vec::new(),
        };
        let shared = Arc::new(Shared {
            started: Instant::now(),
            registry,
            bus,
            engine_name: Mutex::new(config.engine.name.clone()),
            engine_params: Mutex::new(built.params),
            config: Mutex::new(config),
            pending: Mutex::new(None),
            pending_sync: Mutex::new(None),
            stages: Mutex::new(Vec::new()),
            frame_sets: AtomicU64::new(0),
            sync_missing: AtomicU64::new(0),
            sync_streams: Mutex::new(Vec::new()),
            render_errors: AtomicU64::new(0),
            tracking: Mutex::new(None),
            albedo: Mutex::new(None),
            untracked_frames: AtomicU64::new(0),
            snapshots: bounded(8),
            devices: runners.iter().map(|r| r.status().clone()).collect(),
            steppers,
            recorder,
            lights: Arc::new(LightsBoard::new()),
            heartbeat_ms: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            finished: AtomicBool::new(false),
        });
        if let Some(dir) = autostart {
            let path = recording_path(&dir);
            shared
                .recorder
                .start(path)
                .map_err(anyhow::Error::msg)
                .context("[recorder] autostart")?;
        }
        let render = {
            let shared = shared.clone();
            let subscription = shared.bus.all.subscribe_named("sync", 1024);
            std::thread::Builder::new()
                .name("render".into())
                .spawn(move || {
                    RenderLoop {
                        shared: &shared,
                        synchronizer,
                        engine: built.engine,
                        passthrough,
                        live,
                        relit: RelitFrame::default(),
                        arrivals: VecDeque::new(),
                        exit_at_end: options.exit_at_end,
                        sync_stats_at: 0,
                        sync_stats_time: Instant::now(),
                    }
                    .run(&subscription)
                })?
        };
        Ok(Self {
            shared,
            runners,
            _hotplug: hotplug,
            render: Some(render),
        })
    }

    /// The control surface for the socket server.
    pub fn control(&self) -> Arc<dyn ControlTarget> {
        Arc::new(PipelineControl {
            shared: self.shared.clone(),
        })
    }

    /// Where the lighting estimate is published; what `lights.get` and `lights.subscribe` serve.
    /// Estimates from the light probe go here too ([`LightsBoard::publish`]).
    pub fn lights(&self) -> Arc<LightsBoard> {
        Arc::clone(&self.shared.lights)
    }

    /// True once every source has ended and every frame set has been rendered.
    pub fn is_finished(&self) -> bool {
        self.shared.finished.load(Ordering::Acquire)
    }

    /// Whether the render loop iterated within `within` (for the systemd watchdog).
    pub fn is_healthy(&self, within: Duration) -> bool {
        let now_ms = self.shared.started.elapsed().as_millis() as u64;
        let beat = self.shared.heartbeat_ms.load(Ordering::Acquire);
        !self.render.as_ref().is_none_or(JoinHandle::is_finished)
            && now_ms.saturating_sub(beat) <= within.as_millis() as u64
    }

    pub fn status(&self) -> StatusReport {
        status_report(&self.shared)
    }

    /// Stop devices, render thread and recorder (finishing an open recording).
    pub fn shutdown(&mut self) {
        for runner in &mut self.runners {
            runner.stop();
        }
        self.shared.stop.store(true, Ordering::Release);
        if let Some(render) = self.render.take()
            && render.join().is_err()
        {
            tracing::error!("render thread panicked");
        }
        if self.shared.recorder.status().current().is_some()
            && let Err(error) = self.shared.recorder.stop_recording()
        {
            tracing::error!(%error, "recording not finished cleanly");
        }
    }
}

impl Drop for Pipeline {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn recording_path(dir: &Path) -> PathBuf {
    dir.join(format!("relight-{}.mcap", host_now_ns() / 1_000_000))
}

struct RenderLoop<'a> {
    shared: &'a Shared,
    synchronizer: Synchronizer,
    engine: Box<dyn Engine>,
    /// Shows the camera image while the camera is untracked (no Δ rather than a wrong one).
    passthrough: Box<dyn Engine>,
    /// Registers the camera and builds each frame's scene for the GPU engines.
    live: LiveFrames,
    relit: RelitFrame,
    /// Wall-clock arrival of recent reference frames, to time how long sets wait in the sync.
    arrivals: VecDeque<(u64, Instant)>,
    exit_at_end: bool,
    /// Frame sets and time at the last copy of the sync counters into `Shared`.
    sync_stats_at: u64,
    sync_stats_time: Instant,
}

impl RenderLoop<'_> {
    fn run(mut self, subscription: &relight_core::bus::Subscription<StreamMessage>) {
        let shared = self.shared;
        // The synchroniser's clock: the wall clock, or the data when a replay runs ahead of it.
        // A stepped replay runs on the data alone, or every pause would emit incomplete sets.
        let mut data_clock_ns = 0u64;
        let stepped = !shared.steppers.is_empty();
        while !shared.stop.load(Ordering::Acquire) {
            shared.heartbeat_ms.store(
                shared.started.elapsed().as_millis() as u64,
                Ordering::Release,
            );
            if let Some(sync) = lock(&shared.pending_sync).take() {
                match Synchronizer::new(sync) {
                    Ok(s) => self.synchronizer = s,
                    Err(error) => tracing::warn!(%error, "sync settings not applied"),
                }
            }
            let mut received = subscription.recv_timeout(Duration::from_millis(10));
            while let Some(msg) = received {
                let host_ns = msg.stamp().host_ns;
                data_clock_ns = data_clock_ns.max(host_ns);
                if msg.kind() == self.synchronizer.config().reference {
                    if self.arrivals.len() == 64 {
                        self.arrivals.pop_front();
                    }
                    self.arrivals.push_back((host_ns, Instant::now()));
                }
                match &msg {
                    StreamMessage::Probe(frame) => self.probe_frame(frame),
                    StreamMessage::Lamp(frame) => self.live.lamp_report(frame),
                    _ => {}
                }
                self.synchronizer.push(msg);
                received = subscription.try_recv();
            }
            let now_ns = if stepped {
                data_clock_ns
            } else {
                host_now_ns().max(data_clock_ns)
            };
            while let Some(set) = self.synchronizer.pop_ready(now_ns) {
                self.process(set);
            }
            self.publish_sync_stats();
            let sources_ended = shared
                .devices
                .iter()
                .all(|d| d.state() == DeviceState::Stopped);
            if sources_ended && subscription.is_empty() && !shared.finished.load(Ordering::Acquire)
            {
                for set in self.synchronizer.flush() {
                    self.process(set);
                }
                self.sync_stats_time = Instant::now() - Duration::from_secs(1);
                self.publish_sync_stats();
                shared.finished.store(true, Ordering::Release);
                tracing::info!(
                    frame_sets = shared.frame_sets.load(Ordering::Relaxed),
                    "all sources ended"
                );
                if self.exit_at_end {
                    break;
                }
            }
            if sources_ended {
                self.serve_snapshots(false);
            }
        }
    }

    /// Copy the synchroniser's counters for status reports, a few times a second.
    fn publish_sync_stats(&mut self) {
        let sets = self.shared.frame_sets.load(Ordering::Relaxed);
        if sets == self.sync_stats_at {
            return;
        }
        if sets < self.sync_stats_at + 10
            && self.sync_stats_time.elapsed() < Duration::from_millis(250)
        {
            return;
        }
        self.sync_stats_at = sets;
        self.sync_stats_time = Instant::now();
        let expected = &self.synchronizer.config().expected;
        *lock(&self.shared.sync_streams) = self
            .synchronizer
            .stats()
            .streams
            .iter()
            .filter(|s| expected.contains(&s.kind))
            .map(|s| SyncStreamStatus {
                stream: s.kind,
                matched: s.matched,
                missing: s.missing,
                late: s.late,
                dropped: s.dropped + s.unused,
            })
            .collect();
    }

    fn record_stage(&self, name: &str, ms: f64) {
        let mut stages = lock(&self.shared.stages);
        match stages.iter_mut().find(|s| s.name == name) {
            Some(stage) => stage.record(ms),
            None => {
                let mut stage = StageStats::new(leak_stage_name(name), TIMING_WINDOW);
                stage.record(ms);
                stages.push(stage);
            }
        }
    }

    fn apply_pending(&mut self) {
        let Some(pending) = lock(&self.shared.pending).take() else {
            return;
        };
        match pending {
            Pending::Engine {
                engine,
                name,
                params,
            } => {
                self.engine = engine;
                *lock(&self.shared.engine_params) = params;
                tracing::info!(engine = %name, "engine switched");
                *lock(&self.shared.engine_name) = name;
            }
            Pending::Params(params) => {
                self.engine.set_params(&params);
                *lock(&self.shared.engine_params) = params;
            }
        }
    }

    /// After a GPU device loss: build the same engine with the same parameters on a new
    /// device (the registry's shared context is recreated once lost). Until that works, frames
    /// keep failing and counting as render errors; the daemon stays up.
    fn rebuild_engine(&mut self) {
        let name = lock(&self.shared.engine_name).clone();
        let params = lock(&self.shared.engine_params).clone();
        match self.shared.registry.build(&name, &params) {
            Ok(built) => {
                tracing::warn!(engine = %name, "GPU device lost; engine rebuilt on a new device");
                self.engine = built.engine;
            }
            Err(error) => tracing::error!(engine = %name, %error, "rebuilding the engine failed"),
        }
    }

    fn probe_frame(&mut self, frame: &Arc<Frame<ProbeImage>>) {
        if let Some(ms) = self.live.probe_frame(frame) {
            self.record_stage("probe", ms);
        }
    }

    fn process(&mut self, set: FrameSet) {
        let shared = self.shared;
        self.apply_pending();
        let sync_ms = self
            .arrivals
            .iter()
            .find(|(host_ns, _)| *host_ns == set.stamp.host_ns)
            .map_or(0.0, |(_, t)| t.elapsed().as_secs_f64() * 1e3);
        self.record_stage("sync", sync_ms);
        if !set.missing.is_empty() {
            shared.sync_missing.fetch_add(1, Ordering::Relaxed);
        }
        let seq = shared.frame_sets.fetch_add(1, Ordering::Relaxed);
        let frame = self.live.frame(&set, seq, &shared.lights);
        for (name, ms) in &frame.timings {
            self.record_stage(name, *ms);
        }
        *lock(&shared.tracking) = Some(frame.tracking);
        *lock(&shared.albedo) = frame.albedo;
        let engine = if frame.tracking.is_usable() {
            &mut self.engine
        } else {
            shared.untracked_frames.fetch_add(1, Ordering::Relaxed);
            &mut self.passthrough
        };
        let start = Instant::now();
        let rendered = engine.render(&frame.scene, &mut self.relit);
        self.record_stage("render", start.elapsed().as_secs_f64() * 1e3);
        match rendered {
            Ok(()) => {
                let passes: Vec<(String, f64)> = self
                    .relit
                    .timings
                    .iter()
                    .map(|t| (format!("render.{}", t.pass), t.ms))
                    .collect();
                for (name, ms) in passes {
                    self.record_stage(&name, ms);
                }
            }
            Err(error) => {
                let n = shared.render_errors.fetch_add(1, Ordering::Relaxed);
                if n.is_power_of_two() || n == 0 {
                    tracing::warn!(%error, errors = n + 1, "frame not rendered");
                }
                if matches!(error, EngineError::Gpu(GpuError::Lost { .. })) {
                    self.rebuild_engine();
                }
                return;
            }
        }
        let start = Instant::now();
        self.write_output(seq);
        self.record_stage("output", start.elapsed().as_secs_f64() * 1e3);
        self.serve_snapshots(true);
    }

    fn write_output(&self, seq: u64) {
        let output = lock(&self.shared.config).output.clone();
        let Some(dir) = output.dir else { return };
        if !seq.is_multiple_of(u64::from(output.every_n.max(1))) {
            return;
        }
        let path = dir.join(format!("composite_{seq:06}.png"));
        if let Err(error) = std::fs::create_dir_all(&dir)
            .map_err(|e| e.to_string())
            .and_then(|()| write_png(&path, &self.relit.composite).map_err(|e| e.to_string()))
        {
            tracing::warn!(%error, "output frame not written");
        }
    }

    /// Answer snapshot requests with the last rendered frame. Called after each frame, and
    /// when idle (`fresh = false`) once sources have ended, so a finished replay can still be
    /// snapshotted.
    fn serve_snapshots(&self, fresh: bool) {
        if !fresh && self.relit.composite.pixel_count() == 0 {
            return;
        }
        while let Ok(request) = self.shared.snapshots.1.try_recv() {
            let _ = request.reply.send(self.write_snapshot(&request.dir));
        }
    }

    fn write_snapshot(&self, dir: &Path) -> Result<Vec<PathBuf>, String> {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        let stem = format!("snapshot_{:06}", self.relit.seq);
        let path = dir.join(format!("{stem}_composite.png"));
        write_png(&path, &self.relit.composite).map_err(|e| e.to_string())?;
        Ok(vec![path])
    }
}

/// Stage names are few (fixed passes per engine) and live for the whole run.
fn leak_stage_name(name: &str) -> &'static str {
    static NAMES: Mutex<Vec<&'static str>> = Mutex::new(Vec::new());
    let mut names = lock(&NAMES);
    if let Some(known) = names.iter().find(|n| **n == name) {
        return known;
    }
    let leaked: &'static str = Box::leak(name.to_owned().into_boxed_str());
    names.push(leaked);
    leaked
}

fn status_report(shared: &Shared) -> StatusReport {
    let devices = shared
        .devices
        .iter()
        .flat_map(|d| {
            d.streams.iter().map(move |&stream| DeviceStatus {
                name: d.name.clone(),
                stream,
                backend: d.backend.to_owned(),
                state: d.state(),
                fps: d.fps(stream),
                frames: d.stream_frames(stream),
                drops: d.drops(),
                last_error: d.last_error(),
            })
        })
        .collect();
    let stages = lock(&shared.stages)
        .iter()
        .map(|s| StageTiming {
            name: s.name.to_owned(),
            frames: s.frames(),
            last_ms: s.last_ms(),
            mean_ms: s.mean_ms(),
            p50_ms: s.quantile_ms(0.5),
            p99_ms: s.quantile_ms(0.99),
        })
        .collect();
    StatusReport {
        uptime_s: shared.started.elapsed().as_secs_f64(),
        engine: lock(&shared.engine_name).clone(),
        devices,
        stages,
        frame_sets: shared.frame_sets.load(Ordering::Relaxed),
        sync_missing: shared.sync_missing.load(Ordering::Relaxed),
        bus_drops: shared.bus.total_dropped(),
        render_errors: shared.render_errors.load(Ordering::Relaxed),
        recording: shared
            .recorder
            .status()
            .current()
            .map(|(path, messages)| RecordingStatus { path, messages }),
        sync_streams: lock(&shared.sync_streams).clone(),
        tracking: lock(&shared.tracking).map(|t| TrackingStatus {
            source: t.source.name().to_owned(),
            state: t.state,
            pose_age_ms: t.pose_age_ms,
            reprojection_rms_px: t.reprojection_rms_px,
            tags_used: t.tags_used,
            world_from_camera: t.world_from_camera,
            untracked_frames: shared.untracked_frames.load(Ordering::Relaxed),
        }),
        albedo: lock(&shared.albedo).map(|a| {
            let c = a.census;
            AlbedoStatus {
                estimated: a.estimated,
                measured_vertices: a.measured_vertices,
                vertices: a.vertices,
                skipped_cells: c.saturated + c.unlit + c.shadowed + c.highlight + c.above_one,
            }
        }),
    }
}

/// The pipeline as the control socket sees it.
struct PipelineControl {
    shared: Arc<Shared>,
}

impl PipelineControl {
    fn build_engine(
        &self,
        name: &str,
        params: &Map<String, Value>,
    ) -> Result<Pending, ControlError> {
        let built = self
            .shared
            .registry
            .build(name, params)
            .map_err(|e| match e {
                relight_engines::registry::RegistryError::UnknownEngine { .. } => {
                    ControlError::engine_unknown(name)
                        .with_data(json!({ "known": self.shared.registry.names() }))
                }
                other => ControlError::invalid_params(other.to_string()),
            })?;
        Ok(Pending::Engine {
            engine: built.engine,
            name: name.to_owned(),
            params: built.params,
        })
    }
}

impl ControlTarget for PipelineControl {
    fn status(&self) -> StatusReport {
        status_report(&self.shared)
    }

    fn lights(&self) -> Option<&LightsBoard> {
        Some(&self.shared.lights)
    }

    fn engine_list(&self) -> Vec<EngineInfo> {
        self.shared
            .registry
            .specs()
            .iter()
            .map(|spec| EngineInfo {
                name: spec.name.to_owned(),
                description: spec.description.to_owned(),
                params_schema: serde_json::to_value(&spec.schema).unwrap_or(Value::Null),
            })
            .collect()
    }

    fn engine_set(&self, name: &str) -> Result<(), ControlError> {
        let pending = self.build_engine(name, &Map::new())?;
        *lock(&self.shared.pending) = Some(pending);
        Ok(())
    }

    fn engine_params_get(&self) -> Value {
        json!({
            "engine": *lock(&self.shared.engine_name),
            "params": Value::Object(lock(&self.shared.engine_params).clone()),
        })
    }

    /// Validate against the engine that renders the next frame: the one waiting to be swapped
    /// in after an `engine.set`, if any (so `engine set X` then `params set` applies to X),
    /// else the running one.
    fn engine_params_set(&self, params: Map<String, Value>) -> Result<Value, ControlError> {
        let mut pending = lock(&self.shared.pending);
        let (name, current) = match pending.as_ref() {
            Some(Pending::Engine { name, params, .. }) => (name.clone(), params.clone()),
            _ => (
                lock(&self.shared.engine_name).clone(),
                lock(&self.shared.engine_params).clone(),
            ),
        };
        let spec = self
            .shared
            .registry
            .spec(&name)
            .map_err(|e| ControlError::failed(e.to_string()))?;
        let merged = spec
            .schema
            .validate(&current, &params)
            .map_err(|e| ControlError::invalid_params(e.to_string()))?;
        match pending.as_mut() {
            Some(Pending::Engine { engine, params, .. }) => {
                engine.set_params(&merged);
                *params = merged.clone();
            }
            _ => {
                *lock(&self.shared.engine_params) = merged.clone();
                *pending = Some(Pending::Params(merged.clone()));
            }
        }
        Ok(Value::Object(merged))
    }

    fn record_start(&self, path: Option<PathBuf>) -> Result<PathBuf, ControlError> {
        let path = match path {
            Some(path) => path,
            None => {
                let dir = lock(&self.shared.config).recorder.dir.clone();
                std::fs::create_dir_all(&dir).map_err(|e| {
                    ControlError::io(format!("cannot create {}", dir.display()), &e)
                })?;
                recording_path(&dir)
            }
        };
        self.shared.recorder.start(path).map_err(ControlError::busy)
    }

    fn record_stop(&self) -> Result<Value, ControlError> {
        self.shared
            .recorder
            .stop_recording()
            .map_err(ControlError::failed)
    }

    fn snapshot(&self, path: Option<PathBuf>) -> Result<Vec<PathBuf>, ControlError> {
        let dir = path.unwrap_or_else(|| lock(&self.shared.config).snapshot.dir.clone());
        let (reply, answer) = bounded(1);
        self.shared
            .snapshots
            .0
            .try_send(SnapshotRequest { dir, reply })
            .map_err(|_| ControlError::busy("too many snapshots pending"))?;
        answer
            .recv_timeout(SNAPSHOT_TIMEOUT)
            .map_err(|_| {
                ControlError::failed(format!(
                    "no frame rendered within {} s; is a source running? (see `relightctl status`)",
                    SNAPSHOT_TIMEOUT.as_secs()
                ))
            })?
            .map_err(ControlError::failed)
    }

    fn replay_step(&self, frames: u32) -> Result<Value, ControlError> {
        if self.shared.steppers.is_empty() {
            return Err(ControlError::failed(
                "the source is not a stepped replay (set [replay] mode = \"stepped\")",
            ));
        }
        if !self.shared.steppers.iter().all(|s| s.step(frames)) {
            return Err(ControlError::failed("the replay has ended"));
        }
        Ok(json!({ "frames": frames }))
    }

    fn config_reload(&self) -> Result<Value, ControlError> {
        let path = lock(&self.shared.config).path.clone();
        let new = Config::load(&path).map_err(|e| {
            ControlError::invalid_params(format!("configuration not reloaded: {e}"))
        })?;
        let old = lock(&self.shared.config).clone();
        let mut applied = Vec::new();
        let mut restart_required = Vec::new();
        if new.engine != old.engine {
            let pending = self.build_engine(&new.engine.name, &params_map(&new.engine.params))?;
            *lock(&self.shared.pending) = Some(pending);
            applied.push("engine");
        }
        if new.sync != old.sync {
            *lock(&self.shared.pending_sync) = Some(core_sync_config(&new.sync));
            applied.push("sync");
        }
        for (name, changed) in [
            ("recorder.dir", new.recorder.dir != old.recorder.dir),
            ("snapshot", new.snapshot != old.snapshot),
            ("output", new.output != old.output),
        ] {
            if changed {
                applied.push(name);
            }
        }
        for (name, changed) in [
            ("daemon", new.daemon != old.daemon),
            ("source", new.source != old.source),
            ("tracking", new.tracking != old.tracking),
            (
                "recorder.queue_frames",
                new.recorder.queue_frames != old.recorder.queue_frames,
            ),
        ] {
            if changed {
                restart_required.push(name);
            }
        }
        *lock(&self.shared.config) = new;
        tracing::info!(?applied, ?restart_required, "configuration reloaded");
        Ok(json!({ "applied": applied, "restart_required": restart_required }))
    }
}
