//! The running daemon: devices → bus → synchroniser → engine → sinks, and the control surface
//! that steers it.
//!
//! Threads: one per device (its [`DeviceRunner`]), one render thread (synchronise, register,
//! reconstruct, render), the light probe's ([`LiveFrames::probe_on_own_thread`]), the image
//! writer (outputs and snapshots), the recorder, and the control server's. Commands from the
//! control socket reach the render thread through shared slots that it reads at frame
//! boundaries — an engine is built on the control thread and only swapped in by the render
//! thread, so a slow build never stalls a frame. The render thread never touches a file.
//!
//! Latency policy: with live sources (devices, the simulator, a realtime replay) the render
//! thread renders the newest complete frame set and skips the older ones, counting them
//! ([`FramesSkipped`]), so a slow engine shows the camera late by its own render time, not by a
//! growing queue. Fast and stepped replays are lossless instead: every frame set is rendered,
//! and a fast replay waits for the render thread ([`Backpressure`]).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context as _;
use crossbeam_channel::{Receiver, Sender, bounded};
use relight_backends::device::{Backoff, DeviceStatus as BackendStatus, Stepper};
use relight_backends::{
    Backpressure, Device as _, DeviceRunner, DeviceState, Replay, ReplayConfig, ReplayMode,
};
use relight_core::bus::{Bus, Subscription};
use relight_core::frame::host_now_ns;
use relight_core::recording::RecordingMeta;
use relight_core::sync::{FrameSet, SyncConfig as CoreSyncConfig, Synchronizer};
use relight_core::{Frame, ProbeImage, StreamKind, StreamMessage};
use relight_engines::gpu::GpuError;
use relight_engines::{Engine, EngineError, EngineRegistry, RelitFrame};
use relight_sim::device::{SimDevice, SimSourceConfig};
use serde_json::{Map, Value, json};

use crate::config::{self, Config, SourceConfig};
use crate::control::lights::LightsBoard;
use crate::control::types::{
    AlbedoStatus, ControlError, ControlTarget, DeviceStatus, EngineInfo, FramesSkipped,
    Percentiles, RecordingStatus, StageTiming, StatusReport, SyncStreamStatus, TrackingStatus,
};
use crate::live_frame::LiveFrames;
use crate::sinks::recorder::{Recorder, RecorderError};
use crate::sinks::writer::{ImageWriter, Write};
use crate::timing::StageStats;
use crate::tracking::TrackingReport;
use relight_engines::surface_albedo::AlbedoReport;

/// How long a control request waits for the render thread to serve a snapshot.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(3);
/// Frames of timing history behind the percentiles in status reports.
const TIMING_WINDOW: usize = 512;
/// Messages the render thread's bus queue holds: several seconds of every stream.
const RENDER_QUEUE: usize = 1024;
/// Reference frames a fast replay may run ahead of the render thread. More than the
/// synchroniser's `max_wait` spans at 30 Hz, so a set can always be decided on the data alone,
/// and well under its buffer bound.
const FAST_REPLAY_WINDOW: u64 = 16;
/// How long the render loop may go without a heartbeat before the watchdog is withheld: this
/// many times the slowest recent frame, and never less than the watchdog's own half-interval.
const STALL_FRAMES: u64 = 4;
/// The allowance before the first frame of an engine is timed (pipelines compile lazily).
const FIRST_FRAME_STALL_MS: u64 = 120_000;
/// Window behind `render_fps`.
const FPS_WINDOW: Duration = Duration::from_secs(2);

/// Options that are not in the configuration file (command-line only).
#[derive(Debug, Clone, Default)]
pub struct PipelineOptions {
    /// Stop the render thread once every source has ended and the last frame set is out.
    pub exit_at_end: bool,
    /// Sleep this long in every render, standing in for a slow engine (tests of the latency
    /// policy and the watchdog).
    pub render_delay: Option<Duration>,
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
    latency: Mutex<StageStats>,
    /// When the recent composites were ready (the last `FPS_WINDOW`).
    rendered_at: Mutex<VecDeque<Instant>>,
    frame_sets: AtomicU64,
    frames_rendered: AtomicU64,
    skipped_superseded: AtomicU64,
    skipped_sync: AtomicU64,
    skipped_queue: AtomicU64,
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
    /// Writes outputs and snapshots off the render thread.
    writer: ImageWriter,
    /// Milliseconds since `started` at the render loop's last heartbeat (between iterations
    /// and between a frame's stages), and how long it may go without one (the watchdog's view).
    heartbeat_ms: AtomicU64,
    stall_limit_ms: AtomicU64,
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
        // Before any source runs, so the render thread sees their first messages.
        let subscription = bus.all.subscribe_named("render", RENDER_QUEUE);
        let mut backpressure = None;

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
                let device = match replay.mode {
                    config::ReplayMode::Fast => {
                        let gate = Backpressure::new(config.sync.reference, FAST_REPLAY_WINDOW);
                        backpressure = Some(gate.clone());
                        device.with_backpressure(gate)
                    }
                    _ => device,
                };
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
        let mut live = LiveFrames::new(&config, meta.calibration.as_ref(), &registry)?;
        live.probe_on_own_thread()?;
        let passthrough = registry.build("passthrough", &Map::new())?.engine;
        let recorder = Recorder::spawn(&bus, config.recorder.queue_frames, meta)?;
        let autostart = config
            .recorder
            .autostart
            .then(|| config.recorder.dir.clone());
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
            latency: Mutex::new(StageStats::new("latency", TIMING_WINDOW)),
            rendered_at: Mutex::new(VecDeque::new()),
            frame_sets: AtomicU64::new(0),
            frames_rendered: AtomicU64::new(0),
            skipped_superseded: AtomicU64::new(0),
            skipped_sync: AtomicU64::new(0),
            skipped_queue: AtomicU64::new(0),
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
            writer: ImageWriter::spawn()?,
            heartbeat_ms: AtomicU64::new(0),
            stall_limit_ms: AtomicU64::new(FIRST_FRAME_STALL_MS),
            stop: AtomicBool::new(false),
            finished: AtomicBool::new(false),
        });
        if let Some(dir) = autostart {
            let path = recording_path(&dir);
            shared
                .recorder
                .start(path)
                .map_err(anyhow::Error::new)
                .context("[recorder] autostart")?;
        }
        let render = {
            let shared = shared.clone();
            std::thread::Builder::new()
                .name("render".into())
                .spawn(move || {
                    RenderLoop {
                        shared: &shared,
                        subscription,
                        synchronizer,
                        engine: built.engine,
                        passthrough,
                        live,
                        relit: RelitFrame::default(),
                        arrivals: VecDeque::new(),
                        exit_at_end: options.exit_at_end,
                        render_delay: options.render_delay,
                        lossless,
                        backpressure,
                        data_clock_ns: 0,
                        references_received: 0,
                        newest: None,
                        sync_stats_at: 0,
                        sync_stats_time: Instant::now(),
                    }
                    .run()
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

    /// Whether the render loop is alive (for the systemd watchdog): its last heartbeat is no
    /// older than `within`, or than [`STALL_FRAMES`] times its slowest recent frame (the first
    /// frame of an engine gets [`FIRST_FRAME_STALL_MS`]), so a slow adapter is not mistaken
    /// for a hung one.
    pub fn is_healthy(&self, within: Duration) -> bool {
        let now_ms = self.shared.started.elapsed().as_millis() as u64;
        let beat = self.shared.heartbeat_ms.load(Ordering::Acquire);
        let limit_ms =
            (within.as_millis() as u64).max(self.shared.stall_limit_ms.load(Ordering::Acquire));
        !self.render.as_ref().is_none_or(JoinHandle::is_finished)
            && now_ms.saturating_sub(beat) <= limit_ms
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
    /// Every message of every stream, subscribed before the sources started.
    subscription: Subscription<StreamMessage>,
    synchronizer: Synchronizer,
    engine: Box<dyn Engine>,
    /// Shows the camera image while the camera is untracked (no Δ rather than a wrong one).
    passthrough: Box<dyn Engine>,
    /// Registers the camera and builds each frame's scene for the GPU engines.
    live: LiveFrames,
    relit: RelitFrame,
    /// Wall-clock arrival of recent reference frames, to time how long sets wait to render.
    arrivals: VecDeque<(u64, Instant)>,
    exit_at_end: bool,
    render_delay: Option<Duration>,
    /// Render every frame set (fast and stepped replays) instead of the newest one.
    lossless: bool,
    /// A fast replay's flow control: told how many reference frames are done with.
    backpressure: Option<Arc<Backpressure>>,
    /// The newest host stamp seen: the synchroniser's clock in lossless replays, whose stamps
    /// are the recording's and run ahead of (or behind) the wall clock.
    data_clock_ns: u64,
    references_received: u64,
    /// The newest decided set not rendered yet (live sources).
    newest: Option<FrameSet>,
    /// Frame sets and time at the last copy of the sync counters into `Shared`.
    sync_stats_at: u64,
    sync_stats_time: Instant,
}

impl RenderLoop<'_> {
    fn run(mut self) {
        let shared = self.shared;
        while !shared.stop.load(Ordering::Acquire) {
            self.heartbeat();
            if let Some(sync) = lock(&shared.pending_sync).take() {
                match Synchronizer::new(sync) {
                    Ok(s) => self.synchronizer = s,
                    Err(error) => tracing::warn!(%error, "sync settings not applied"),
                }
            }
            let mut received = self.subscription.recv_timeout(Duration::from_millis(10));
            while let Some(msg) = received {
                self.receive(msg);
                received = self.subscription.try_recv();
            }
            self.take_ready();
            if let Some(set) = self.newest.take() {
                self.process(set);
            }
            self.publish_sync_stats();
            let sources_ended = shared
                .devices
                .iter()
                .all(|d| d.state() == DeviceState::Stopped);
            if sources_ended
                && self.subscription.is_empty()
                && !shared.finished.load(Ordering::Acquire)
            {
                for set in self.synchronizer.flush() {
                    self.offer(set);
                }
                if let Some(set) = self.newest.take() {
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
            self.serve_snapshots(false);
        }
    }

    fn heartbeat(&self) {
        self.shared.heartbeat_ms.store(
            self.shared.started.elapsed().as_millis() as u64,
            Ordering::Release,
        );
    }

    /// One message off the bus: the probe and the lamp take theirs at once (a bracket needs
    /// every exposure), then the synchroniser.
    fn receive(&mut self, msg: StreamMessage) {
        let host_ns = msg.stamp().host_ns;
        self.data_clock_ns = self.data_clock_ns.max(host_ns);
        if msg.kind() == self.synchronizer.config().reference {
            self.references_received += 1;
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
        // A live backlog is read whole first: on the wall clock its old reference frames are
        // already past max_wait, and would be decided before their partners, queued right
        // behind them, were read. A lossless replay runs on the data clock and can decide as
        // it reads (which also frees its back-pressure sooner).
        if self.lossless {
            self.take_ready();
        }
    }

    /// Every set the synchroniser has decided by now.
    fn take_ready(&mut self) {
        let now_ns = if self.lossless {
            self.data_clock_ns
        } else {
            host_now_ns().max(self.data_clock_ns)
        };
        while let Some(set) = self.synchronizer.pop_ready(now_ns) {
            self.offer(set);
        }
        self.release_backpressure();
    }

    /// A decided set: rendered now in a lossless replay, else kept as the newest, replacing
    /// (skipping) an older one not rendered yet.
    fn offer(&mut self, set: FrameSet) {
        if self.lossless {
            self.process(set);
            self.release_backpressure();
        } else if self.newest.replace(set).is_some() {
            self.shared
                .skipped_superseded
                .fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Tell a fast replay how many reference frames are done with: read, and no longer
    /// waiting in the synchroniser (rendered or discarded), plus what the queue dropped.
    fn release_backpressure(&self) {
        if let Some(gate) = &self.backpressure {
            gate.finished(
                (self.references_received + self.subscription.dropped())
                    .saturating_sub(self.synchronizer.pending() as u64),
            );
        }
    }

    /// Copy the synchroniser's counters for status reports, a few times a second.
    fn publish_sync_stats(&mut self) {
        let shared = self.shared;
        shared
            .skipped_queue
            .store(self.subscription.dropped(), Ordering::Relaxed);
        let sets = shared.frame_sets.load(Ordering::Relaxed);
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
        let config = self.synchronizer.config();
        let stats = self.synchronizer.stats();
        if let Some(reference) = stats.stream(config.reference) {
            shared
                .skipped_sync
                .store(reference.late + reference.dropped, Ordering::Relaxed);
        }
        *lock(&shared.sync_streams) = stats
            .streams
            .iter()
            .filter(|s| config.expected.contains(&s.kind))
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
                self.allow_first_frame();
            }
            Pending::Params(params) => {
                self.engine.set_params(&params);
                *lock(&self.shared.engine_params) = params;
            }
        }
    }

    /// A new engine's first frame compiles its pipelines: give the watchdog the first-frame
    /// allowance until it is timed.
    fn allow_first_frame(&self) {
        self.shared
            .stall_limit_ms
            .fetch_max(FIRST_FRAME_STALL_MS, Ordering::AcqRel);
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
                self.allow_first_frame();
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
        let started = Instant::now();
        self.apply_pending();
        let arrived = self
            .arrivals
            .iter()
            .find(|(host_ns, _)| *host_ns == set.stamp.host_ns)
            .map(|(_, t)| *t);
        self.record_stage(
            "queue",
            arrived.map_or(0.0, |t| t.elapsed().as_secs_f64() * 1e3),
        );
        if !set.missing.is_empty() {
            shared.sync_missing.fetch_add(1, Ordering::Relaxed);
        }
        let seq = shared.frame_sets.fetch_add(1, Ordering::Relaxed);
        let frame = self.live.frame(&set, seq, &shared.lights);
        self.heartbeat();
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
        if let Some(delay) = self.render_delay {
            std::thread::sleep(delay);
        }
        let rendered = engine.render(&frame.scene, &mut self.relit);
        self.heartbeat();
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
        self.serve_snapshots(true);
        self.record_stage("output", start.elapsed().as_secs_f64() * 1e3);
        self.composite_ready(&set, arrived, started);
    }

    /// Count the composite, time its latency, and derive the watchdog's limit from the frame
    /// times seen.
    fn composite_ready(&self, set: &FrameSet, arrived: Option<Instant>, started: Instant) {
        let shared = self.shared;
        let now = Instant::now();
        let latency_ms = match (self.lossless, arrived) {
            (true, Some(arrived)) => now.duration_since(arrived).as_secs_f64() * 1e3,
            _ => host_now_ns().saturating_sub(set.stamp.host_ns) as f64 * 1e-6,
        };
        lock(&shared.latency).record(latency_ms);
        shared.frames_rendered.fetch_add(1, Ordering::Relaxed);
        let mut rendered_at = lock(&shared.rendered_at);
        rendered_at.push_back(now);
        while rendered_at
            .front()
            .is_some_and(|t| now.duration_since(*t) > FPS_WINDOW)
        {
            rendered_at.pop_front();
        }
        drop(rendered_at);
        let frame_ms = started.elapsed().as_millis() as u64;
        let slowest_ms = lock(&shared.stages)
            .iter()
            .find(|s| s.name == "render")
            .map_or(0.0, StageStats::max_ms) as u64;
        shared
            .stall_limit_ms
            .store(STALL_FRAMES * frame_ms.max(slowest_ms), Ordering::Release);
    }

    fn write_output(&self, seq: u64) {
        let output = lock(&self.shared.config).output.clone();
        let Some(dir) = output.dir else { return };
        if !seq.is_multiple_of(u64::from(output.every_n.max(1))) {
            return;
        }
        self.shared.writer.offer(Write {
            dir,
            file_name: format!("composite_{seq:06}.png"),
            image: self.relit.composite.clone(),
            reply: None,
        });
    }

    /// Hand snapshot requests the last rendered frame, for the writer to write. Called after
    /// each frame, and on every idle turn of the loop (`fresh = false`, once a frame exists), so
    /// a paused or finished replay can still be snapshotted.
    fn serve_snapshots(&self, fresh: bool) {
        if !fresh && self.relit.composite.pixel_count() == 0 {
            return;
        }
        while let Ok(request) = self.shared.snapshots.1.try_recv() {
            self.shared.writer.offer(Write {
                dir: request.dir,
                file_name: format!("snapshot_{:06}_composite.png", self.relit.seq),
                image: self.relit.composite.clone(),
                reply: Some(request.reply),
            });
        }
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
    let reference = lock(&shared.config).sync.reference;
    let reference_frames = shared
        .devices
        .iter()
        .map(|d| d.stream_frames(reference))
        .sum();
    let superseded = shared.skipped_superseded.load(Ordering::Relaxed);
    let sync_discarded = shared.skipped_sync.load(Ordering::Relaxed);
    let queue_dropped = shared.skipped_queue.load(Ordering::Relaxed);
    let render_fps = {
        let rendered_at = lock(&shared.rendered_at);
        let window = shared.started.elapsed().min(FPS_WINDOW).as_secs_f64();
        let recent = rendered_at
            .iter()
            .filter(|t| t.elapsed() <= FPS_WINDOW)
            .count();
        if window > 0.0 {
            recent as f64 / window
        } else {
            0.0
        }
    };
    StatusReport {
        uptime_s: shared.started.elapsed().as_secs_f64(),
        engine: lock(&shared.engine_name).clone(),
        devices,
        stages,
        frame_sets: shared.frame_sets.load(Ordering::Relaxed),
        reference_frames,
        frames_rendered: shared.frames_rendered.load(Ordering::Relaxed),
        frames_skipped: FramesSkipped {
            total: superseded + sync_discarded + queue_dropped,
            superseded,
            sync_discarded,
            queue_dropped,
        },
        latency_ms: {
            let latency = lock(&shared.latency);
            Percentiles {
                p50: latency.quantile_ms(0.5),
                p99: latency.quantile_ms(0.99),
            }
        },
        render_fps,
        outputs_dropped: shared.writer.dropped(),
        outputs_failed: shared.writer.failed(),
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

fn recorder_error(error: RecorderError) -> ControlError {
    match error {
        RecorderError::Busy(message) => ControlError::busy(message),
        RecorderError::Failed(message) => ControlError::failed(message),
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
        self.shared.recorder.start(path).map_err(recorder_error)
    }

    fn record_stop(&self) -> Result<Value, ControlError> {
        self.shared
            .recorder
            .stop_recording()
            .map_err(recorder_error)
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
