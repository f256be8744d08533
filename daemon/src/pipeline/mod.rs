//! The running daemon: sources → bus → ingest (synchroniser) → tracking → reconstruction →
//! lighting → render → sinks, with status from every stage, and the control surface that
//! steers it.
//!
//! One module per stage, each with its inputs and outputs as types:
//! - [`sources`]: the configured replay, simulated rig or devices, one [`DeviceRunner`]
//!   thread each, publishing to the bus;
//! - [`ingest`]: the bus through the synchroniser into [`ReadySet`]s by the latency policy;
//! - [`live_frame`]: a set into the [`LiveFrame`] an engine renders, through [`tracking`],
//!   [`reconstruction`] and [`lighting`];
//! - [`render`]: the engine, swapped at frame boundaries;
//! - [`outputs`]: composites and snapshots to the image writer;
//! - [`status`]: counters, latency, the watchdog's view and the status report;
//! - [`control`]: what control requests do.
//!
//! Threads, named after their stage: one per device (its [`DeviceRunner`]), `render` (ingest
//! to outputs), `probe` (the light probe's estimates, [`LiveFrames::probe_on_own_thread`]),
//! `albedo` (the live surface's albedo estimates, [`LiveFrames::albedo_on_own_thread`]),
//! `image-writer` (outputs and snapshots), `recorder`, and the control server's. Commands from
//! the control socket reach the render thread through shared slots that it reads at frame
//! boundaries. The render thread never touches a file.
//!
//! Latency policy: with live sources (devices, the simulator, a realtime replay) the render
//! thread renders the newest complete frame set and skips the older ones, counting them, so a
//! slow engine shows the camera late by its own render time, not by a growing queue. Fast and
//! stepped replays are lossless instead: every frame set is rendered, and a fast replay waits
//! for the render thread ([`Backpressure`](relight_backends::Backpressure)).

pub mod control;
pub mod ingest;
pub mod lighting;
pub mod live_frame;
pub mod outputs;
pub mod reconstruction;
pub mod render;
pub mod sources;
pub mod status;
pub mod tracking;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, Weak};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context as _;
use crossbeam_channel::{Sender, bounded};
use relight_backends::device::{DeviceStatus as BackendStatus, Stepper};
use relight_backends::{DeviceRunner, DeviceState};
use relight_core::bus::Bus;
use relight_core::frame::host_now_ns;
use relight_core::recording::OutputMessage;
use relight_core::rig::RigCalibration;
use relight_core::sync::FrameSet;
use relight_core::sync::{SyncConfig as CoreSyncConfig, Synchronizer};
use relight_core::{Frame, StreamMessage};
use relight_engines::{EngineRegistry, PassTiming, RelitFrame};
use relight_live::{LiveView, Reports, RigFrames, ViewFrame};
use relight_recon::estimate::LightingEstimate;
use serde_json::{Map, Value};

use crate::config::Config;
use crate::control::lights::LightsBoard;
use crate::control::types::{ControlTarget, LiveViewStatus, StatusReport};
use crate::lock;
use crate::sinks::recorder::Recorder;
use crate::sinks::safe_file::Existing;
use crate::sinks::writer::ImageWriter;
use crate::timing::{PassTimers, StageTimer, Timings};
use ingest::{Ingest, ReadySet};
use live_frame::{LiveFrame, LiveFrames, LiveTimings};
use outputs::{Outputs, SnapshotRequest};
use render::{EngineSlot, RenderStage, Rendered};
use status::{Counters, Liveness};

/// Frames of timing history behind the percentiles in status reports.
const TIMING_WINDOW: usize = 512;
/// Messages the render thread's bus queue holds: several seconds of every stream.
const RENDER_QUEUE: usize = 1024;

/// Options that are not in the configuration file (command-line only).
#[derive(Debug, Clone, Default)]
pub struct PipelineOptions {
    /// Stop the render thread once every source has ended and the last frame set is out.
    pub exit_at_end: bool,
    /// Sleep this long in every render, standing in for a slow engine (tests of the latency
    /// policy and the watchdog).
    pub render_delay: Option<Duration>,
}

/// What the render thread and the control threads share.
struct Shared {
    started: Instant,
    config: Mutex<Config>,
    registry: EngineRegistry,
    bus: Arc<Bus>,
    engine: EngineSlot,
    pending_sync: Mutex<Option<CoreSyncConfig>>,
    timings: Arc<Timings>,
    counters: Counters,
    liveness: Liveness,
    snapshots: Sender<SnapshotRequest>,
    devices: Vec<Arc<BackendStatus>>,
    /// Present when the source is a stepped replay.
    steppers: Vec<Stepper>,
    recorder: Recorder,
    /// The lighting estimate published on the control socket (`lights.*`).
    lights: Arc<LightsBoard>,
    /// Writes outputs and snapshots off the render thread.
    writer: ImageWriter,
    stop: AtomicBool,
    finished: AtomicBool,
    /// The live view's addresses, once it listens.
    live_view: OnceLock<LiveViewStatus>,
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

fn params_map(value: &Value) -> Map<String, Value> {
    value.as_object().cloned().unwrap_or_default()
}

fn recording_path(dir: &Path) -> PathBuf {
    dir.join(format!("relight-{}.mcap", host_now_ns() / 1_000_000))
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
        let sources = sources::start(&config, &bus)?;
        let synchronizer = Synchronizer::new(sources.sync.clone())
            .with_context(|| format!("{}: [sync]", config.path.display()))?;
        let mut live = LiveFrames::new(&config, sources.meta.calibration.as_ref(), &registry)?;
        live.probe_on_own_thread()?;
        live.albedo_on_own_thread()?;
        let passthrough = registry.build("passthrough", &Map::new())?.engine;
        let recorder = Recorder::spawn(&bus, config.recorder.queue_frames, sources.meta.clone())?;
        let autostart = config
            .recorder
            .autostart
            .then(|| (config.recorder.dir.clone(), config.recorder.settings()));
        let started = Instant::now();
        let timings = Arc::new(Timings::new(TIMING_WINDOW));
        let (snapshots, snapshot_requests) = bounded(8);
        let shared = Arc::new(Shared {
            started,
            registry,
            bus,
            engine: EngineSlot {
                name: Mutex::new(config.engine.name.clone()),
                params: Mutex::new(built.params),
                pending: Mutex::new(None),
            },
            config: Mutex::new(config),
            pending_sync: Mutex::new(None),
            timings: Arc::clone(&timings),
            counters: Counters::new(TIMING_WINDOW),
            liveness: Liveness::new(started),
            snapshots,
            devices: sources.runners.iter().map(|r| r.status().clone()).collect(),
            steppers: sources.steppers,
            recorder,
            lights: Arc::new(LightsBoard::new()),
            writer: ImageWriter::spawn()?,
            stop: AtomicBool::new(false),
            finished: AtomicBool::new(false),
            live_view: OnceLock::new(),
        });
        let live_view = start_live_view(&shared, sources.meta.calibration.as_ref())?;
        if let Some((dir, settings)) = autostart {
            shared
                .recorder
                .start(recording_path(&dir), Existing::Refuse, settings)
                .map_err(anyhow::Error::new)
                .context("[recorder] autostart")?;
        }
        let ingest = Ingest::new(
            subscription,
            synchronizer,
            sources.lossless,
            sources.backpressure,
            timings.stage("queue"),
        );
        let live_timers = LiveTimers::new(&timings);
        let render_stage = RenderStage::new(
            built.engine,
            passthrough,
            options.render_delay,
            timings.clone(),
        );
        let outputs = Outputs::new(snapshot_requests, timings.stage("output"));
        let render = {
            let shared = shared.clone();
            std::thread::Builder::new()
                .name("render".into())
                .spawn(move || {
                    RenderLoop {
                        shared: &shared,
                        ingest,
                        live,
                        live_timers,
                        render: render_stage,
                        outputs,
                        live_view,
                        recorded_lighting: None,
                        exit_at_end: options.exit_at_end,
                    }
                    .run()
                })?
        };
        Ok(Self {
            shared,
            runners: sources.runners,
            _hotplug: sources.hotplug,
            render: Some(render),
        })
    }

    /// The control surface for the socket server.
    pub fn control(&self) -> Arc<dyn ControlTarget> {
        Arc::new(control::PipelineControl {
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

    /// Whether the render loop is alive (for the systemd watchdog): running, and its last
    /// heartbeat recent enough for its frame times ([`Liveness::is_recent`]).
    pub fn is_healthy(&self, within: Duration) -> bool {
        !self.render.as_ref().is_none_or(JoinHandle::is_finished)
            && self.shared.liveness.is_recent(within)
    }

    pub fn status(&self) -> StatusReport {
        status::report(&self.shared)
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

/// What the live view shows besides frames: the status report and the lighting estimate,
/// read through a weak reference, so the view never keeps a stopped pipeline alive.
struct PipelineReports(Weak<Shared>);

impl Reports for PipelineReports {
    fn status(&self) -> Value {
        self.0
            .upgrade()
            .and_then(|shared| serde_json::to_value(status::report(&shared)).ok())
            .unwrap_or(Value::Null)
    }

    fn lighting(&self) -> Option<Value> {
        let estimate = self.0.upgrade()?.lights.latest()?;
        serde_json::to_value(&*estimate).ok()
    }
}

/// Start the `[live_view]` servers the configuration asks for, and note where they listen.
fn start_live_view(
    shared: &Arc<Shared>,
    calibration: Option<&RigCalibration>,
) -> anyhow::Result<LiveView> {
    let settings = lock(&shared.config).live_view.clone();
    if settings.foxglove.is_none() && settings.page.is_none() {
        return Ok(LiveView::disabled());
    }
    let rig = RigFrames {
        world_from_board: calibration.map(|c| c.world_from_board),
        world_from_probe: calibration
            .filter(|c| c.probe.is_some())
            .map(|c| c.world_from_probe),
    };
    let view = LiveView::start(
        &settings,
        rig,
        Arc::new(PipelineReports(Arc::downgrade(shared))),
    )
    .context("[live_view]")?;
    // Set once, here, before the render thread starts.
    drop(shared.live_view.set(LiveViewStatus {
        foxglove: view.foxglove_addr().map(|a| format!("ws://{a}")),
        page: view.page_addr().map(|a| format!("http://{a}/")),
    }));
    Ok(view)
}

/// A rendered frame for the live view: images are copied (the render thread reuses its own),
/// streams and the scene shared.
fn view_frame(set: &FrameSet, frame: &LiveFrame, relit: &RelitFrame) -> ViewFrame {
    ViewFrame {
        seq: relit.seq,
        host_ns: set.stamp.host_ns,
        composite: relit.composite.clone(),
        delta: relit.delta.clone(),
        color: frame.scene.color.clone(),
        depth: frame.scene.depth.clone(),
        scene: frame.scene.scene.clone(),
        world_from_camera: frame.tracking.world_from_camera,
        markers: set.markers.clone(),
        lamp: set.lamp.as_ref().map(|lamp| lamp.payload),
    }
}

/// The live path's stage timers, filled from each frame's [`LiveTimings`].
struct LiveTimers {
    tracking: StageTimer,
    probe: StageTimer,
    depth: StageTimer,
    /// The depth stage's parts, `depth.<pass>`.
    depth_passes: PassTimers,
    scene: StageTimer,
}

impl LiveTimers {
    fn new(timings: &Arc<Timings>) -> Self {
        Self {
            tracking: timings.stage("tracking"),
            probe: timings.stage("probe"),
            depth: timings.stage("depth"),
            depth_passes: PassTimers::new("depth", timings.clone()),
            scene: timings.stage("scene"),
        }
    }

    fn record(&mut self, t: &LiveTimings, depth_passes: &[PassTiming]) {
        self.depth_passes.record(depth_passes);
        self.tracking.record(t.tracking_ms);
        for (timer, ms) in [
            (&self.probe, t.probe_ms),
            (&self.depth, t.depth_ms),
            (&self.scene, t.scene_ms),
        ] {
            if let Some(ms) = ms {
                timer.record(ms);
            }
        }
    }
}

/// The render thread: ingest to outputs, one frame set at a time.
struct RenderLoop<'a> {
    shared: &'a Shared,
    ingest: Ingest,
    /// Registers the camera and builds each frame's scene for the GPU engines.
    live: LiveFrames,
    live_timers: LiveTimers,
    render: RenderStage,
    outputs: Outputs,
    /// Owned by the render thread, so its publisher stops before the thread ends.
    live_view: LiveView,
    /// The lighting estimate last handed to the recorder (it records one when it changes).
    recorded_lighting: Option<Arc<LightingEstimate>>,
    exit_at_end: bool,
}

impl RenderLoop<'_> {
    /// While a recording takes outputs: the frame's composite and Δ, and the lighting estimate
    /// when it changed (or the recording is new), copied for the recorder.
    fn offer_outputs(&mut self, set: &FrameSet) {
        let recorder = &self.shared.recorder;
        if !recorder.wants_outputs() {
            self.recorded_lighting = None;
            return;
        }
        let relit = self.render.relit();
        let frame = |payload| Frame::new(relit.seq, set.stamp, payload);
        recorder.offer_output(OutputMessage::Composite(frame(relit.composite.clone())));
        if relit.delta.pixel_count() > 0 {
            recorder.offer_output(OutputMessage::Delta(frame(relit.delta.clone())));
        }
        let Some(estimate) = self.shared.lights.latest() else {
            return;
        };
        if self
            .recorded_lighting
            .as_ref()
            .is_some_and(|last| Arc::ptr_eq(last, &estimate))
        {
            return;
        }
        match serde_json::to_string(&*estimate) {
            Ok(json) => recorder.offer_output(OutputMessage::Lighting(Frame::new(
                relit.seq, set.stamp, json,
            ))),
            Err(error) => tracing::warn!(%error, "lighting estimate not recorded"),
        }
        self.recorded_lighting = Some(estimate);
    }

    fn run(mut self) {
        let shared = self.shared;
        while !shared.stop.load(Ordering::Acquire) {
            shared.liveness.beat();
            if let Some(sync) = lock(&shared.pending_sync).take() {
                self.ingest.reconfigure(sync);
            }
            let mut wait = Duration::from_millis(10);
            while let Some(msg) = self.ingest.recv(wait) {
                wait = Duration::ZERO;
                self.receive(msg);
            }
            self.render_ready();
            self.ingest.publish_stats(&shared.counters, false);
            let sources_ended = shared
                .devices
                .iter()
                .all(|d| d.state() == DeviceState::Stopped);
            if sources_ended && self.ingest.is_drained() && !shared.finished.load(Ordering::Acquire)
            {
                for ready in self.ingest.flush(&shared.counters) {
                    self.process(ready);
                }
                self.ingest.publish_stats(&shared.counters, true);
                shared.finished.store(true, Ordering::Release);
                tracing::info!(
                    frame_sets = shared.counters.frame_sets.load(Ordering::Relaxed),
                    "all sources ended"
                );
                if self.exit_at_end {
                    break;
                }
            }
            self.outputs
                .serve_snapshots(&shared.writer, self.render.relit(), false);
        }
    }

    /// One message off the bus: the probe and the lamp go to the lighting stage at once (a
    /// bracket needs every exposure), then everything to the synchroniser. A lossless replay
    /// renders what it can decide as it reads.
    fn receive(&mut self, msg: StreamMessage) {
        match &msg {
            StreamMessage::Probe(frame) => {
                if let Some(ms) = self.live.probe_frame(frame) {
                    self.live_timers.probe.record(ms);
                }
            }
            StreamMessage::Lamp(frame) => self.live.lamp_report(frame),
            _ => {}
        }
        self.ingest.push(msg);
        if self.ingest.is_lossless() {
            self.render_ready();
        }
    }

    /// Render what is decided: every set in a lossless replay; live, one set, right after the
    /// bus was drained. Deciding again after a render, on a wall clock that moved on while the
    /// partners that arrived meanwhile are still unread on the bus, would time them out and
    /// make sets without colour.
    fn render_ready(&mut self) {
        while let Some(ready) = self.ingest.next_set(&self.shared.counters) {
            self.process(ready);
            if !self.ingest.is_lossless() {
                break;
            }
        }
    }

    /// One frame set through the stages.
    fn process(&mut self, ReadySet { set, arrived }: ReadySet) {
        let shared = self.shared;
        let started = Instant::now();
        if self.render.apply_pending(&shared.engine) {
            shared.liveness.allow_first_frame();
        }
        let seq = shared.counters.frame_set(&set);
        let frame: LiveFrame = self.live.frame(&set, seq, &shared.lights);
        shared.liveness.beat();
        self.live_timers.record(&frame.timings, &frame.depth_passes);
        shared.counters.live_frame(&frame);
        let (rendered, rebuilt) =
            self.render
                .render(&frame, &shared.counters, &shared.engine, &shared.registry);
        shared.liveness.beat();
        if rebuilt {
            shared.liveness.allow_first_frame();
        }
        if rendered == Rendered::Failed {
            return;
        }
        self.outputs
            .composite(&shared.config, &shared.writer, seq, self.render.relit());
        if self.live_view.wants_frame() {
            self.live_view
                .offer(view_frame(&set, &frame, self.render.relit()));
        }
        self.offer_outputs(&set);
        shared
            .counters
            .composite(&set, arrived, self.ingest.is_lossless());
        shared.liveness.frame_timed(
            started.elapsed().as_millis() as u64,
            self.render.slowest_ms() as u64,
        );
    }
}
