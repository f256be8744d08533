//! The status stage: what the other stages count, how late composites are, whether the render
//! loop is alive, and the report `relightctl status` shows.

use std::collections::VecDeque;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use relight_core::frame::host_now_ns;
use relight_core::sync::FrameSet;
use relight_engines::surface_albedo::AlbedoReport;

use super::Shared;
use super::live_frame::LiveFrame;
use super::tracking::TrackingReport;
use crate::control::types::{
    AlbedoStatus, DeviceStatus, FramesSkipped, Percentiles, RecordingStatus, StatusReport,
    SyncStreamStatus, TrackingStatus,
};
use crate::lock;
use crate::timing::StageStats;

/// Window behind `render_fps`.
const FPS_WINDOW: Duration = Duration::from_secs(2);
/// How long the render loop may go without a heartbeat before the watchdog is withheld: this
/// many times the slowest recent frame, and never less than the watchdog's own half-interval.
const STALL_FRAMES: u64 = 4;
/// The allowance before the first frame of an engine is timed (pipelines compile lazily).
const FIRST_FRAME_STALL_MS: u64 = 120_000;

/// What the stages count, for status reports.
#[derive(Debug)]
pub struct Counters {
    pub frame_sets: AtomicU64,
    pub frames_rendered: AtomicU64,
    pub skipped_superseded: AtomicU64,
    pub skipped_sync: AtomicU64,
    pub skipped_queue: AtomicU64,
    pub sync_missing: AtomicU64,
    pub render_errors: AtomicU64,
    pub untracked_frames: AtomicU64,
    sync_streams: Mutex<Vec<SyncStreamStatus>>,
    /// Host stamp (or arrival) to composite, milliseconds.
    latency: Mutex<StageStats>,
    /// When the recent composites were ready (the last `FPS_WINDOW`).
    rendered_at: Mutex<VecDeque<Instant>>,
    /// The last frame's registration and albedo measurement.
    tracking: Mutex<Option<TrackingReport>>,
    albedo: Mutex<Option<AlbedoReport>>,
    /// The running engine's own report ([`relight_engines::Engine::status`]) after its last
    /// frame.
    engine_status: Mutex<Option<serde_json::Value>>,
}

impl Counters {
    pub fn new(window: usize) -> Self {
        Self {
            frame_sets: AtomicU64::new(0),
            frames_rendered: AtomicU64::new(0),
            skipped_superseded: AtomicU64::new(0),
            skipped_sync: AtomicU64::new(0),
            skipped_queue: AtomicU64::new(0),
            sync_missing: AtomicU64::new(0),
            render_errors: AtomicU64::new(0),
            untracked_frames: AtomicU64::new(0),
            sync_streams: Mutex::new(Vec::new()),
            latency: Mutex::new(StageStats::new("latency", window)),
            rendered_at: Mutex::new(VecDeque::new()),
            tracking: Mutex::new(None),
            albedo: Mutex::new(None),
            engine_status: Mutex::new(None),
        }
    }

    /// The engine's report after a frame it rendered.
    pub fn engine_status(&self, status: Option<serde_json::Value>) {
        *lock(&self.engine_status) = status;
    }

    pub fn set_sync_streams(&self, streams: Vec<SyncStreamStatus>) {
        *lock(&self.sync_streams) = streams;
    }

    /// A set goes into the live path: its number.
    pub fn frame_set(&self, set: &FrameSet) -> u64 {
        if !set.missing.is_empty() {
            self.sync_missing.fetch_add(1, Ordering::Relaxed);
        }
        self.frame_sets.fetch_add(1, Ordering::Relaxed)
    }

    /// What the live path made of a set.
    pub fn live_frame(&self, frame: &LiveFrame) {
        *lock(&self.tracking) = Some(frame.tracking);
        *lock(&self.albedo) = frame.albedo;
        if !frame.tracking.is_usable() {
            self.untracked_frames.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// A composite is ready: count it and time its latency. In lossless replays, whose stamps
    /// are the recording's clock, latency counts from the set's arrival at the render thread.
    pub fn composite(&self, set: &FrameSet, arrived: Option<Instant>, lossless: bool) {
        let now = Instant::now();
        let latency_ms = match (lossless, arrived) {
            (true, Some(arrived)) => now.duration_since(arrived).as_secs_f64() * 1e3,
            _ => host_now_ns().saturating_sub(set.stamp.host_ns) as f64 * 1e-6,
        };
        lock(&self.latency).record(latency_ms);
        self.frames_rendered.fetch_add(1, Ordering::Relaxed);
        let mut rendered_at = lock(&self.rendered_at);
        rendered_at.push_back(now);
        while rendered_at
            .front()
            .is_some_and(|t| now.duration_since(*t) > FPS_WINDOW)
        {
            rendered_at.pop_front();
        }
    }

    /// A render failed; true when it is worth a log line (the first, then at powers of two).
    pub fn render_failed(&self) -> (u64, bool) {
        let n = self.render_errors.fetch_add(1, Ordering::Relaxed);
        (n + 1, n == 0 || n.is_power_of_two())
    }

    fn render_fps(&self, uptime: Duration) -> f64 {
        let rendered_at = lock(&self.rendered_at);
        let window = uptime.min(FPS_WINDOW).as_secs_f64();
        let recent = rendered_at
            .iter()
            .filter(|t| t.elapsed() <= FPS_WINDOW)
            .count();
        if window > 0.0 {
            recent as f64 / window
        } else {
            0.0
        }
    }
}

/// The render loop's heartbeat, for the systemd watchdog.
#[derive(Debug)]
pub struct Liveness {
    started: Instant,
    /// Milliseconds since `started` at the render loop's last heartbeat (between iterations
    /// and between a frame's stages), and how long it may go without one.
    heartbeat_ms: AtomicU64,
    stall_limit_ms: AtomicU64,
}

impl Liveness {
    pub fn new(started: Instant) -> Self {
        Self {
            started,
            heartbeat_ms: AtomicU64::new(0),
            stall_limit_ms: AtomicU64::new(FIRST_FRAME_STALL_MS),
        }
    }

    pub fn beat(&self) {
        self.heartbeat_ms
            .store(self.started.elapsed().as_millis() as u64, Ordering::Release);
    }

    /// A new engine's first frame compiles its pipelines: the first-frame allowance until it
    /// is timed.
    pub fn allow_first_frame(&self) {
        self.stall_limit_ms
            .fetch_max(FIRST_FRAME_STALL_MS, Ordering::AcqRel);
    }

    /// A frame took `frame_ms`, and the slowest recent render `slowest_ms`: the limit follows.
    pub fn frame_timed(&self, frame_ms: u64, slowest_ms: u64) {
        self.stall_limit_ms
            .store(STALL_FRAMES * frame_ms.max(slowest_ms), Ordering::Release);
    }

    /// The last heartbeat is no older than `within`, or than `STALL_FRAMES` times the slowest
    /// recent frame (the first frame of an engine gets `FIRST_FRAME_STALL_MS`), so a slow
    /// adapter is not mistaken for a hung one.
    pub fn is_recent(&self, within: Duration) -> bool {
        let now_ms = self.started.elapsed().as_millis() as u64;
        let beat = self.heartbeat_ms.load(Ordering::Acquire);
        let limit_ms = (within.as_millis() as u64).max(self.stall_limit_ms.load(Ordering::Acquire));
        now_ms.saturating_sub(beat) <= limit_ms
    }
}

/// The status report of the running pipeline.
pub(super) fn report(shared: &Shared) -> StatusReport {
    let counters = &shared.counters;
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
    let reference = lock(&shared.config).sync.reference;
    let reference_frames = shared
        .devices
        .iter()
        .map(|d| d.stream_frames(reference))
        .sum();
    let superseded = counters.skipped_superseded.load(Ordering::Relaxed);
    let sync_discarded = counters.skipped_sync.load(Ordering::Relaxed);
    let queue_dropped = counters.skipped_queue.load(Ordering::Relaxed);
    StatusReport {
        uptime_s: shared.started.elapsed().as_secs_f64(),
        engine: lock(&shared.engine.name).clone(),
        devices,
        stages: shared.timings.report(),
        frame_sets: counters.frame_sets.load(Ordering::Relaxed),
        reference_frames,
        frames_rendered: counters.frames_rendered.load(Ordering::Relaxed),
        frames_skipped: FramesSkipped {
            total: superseded + sync_discarded + queue_dropped,
            superseded,
            sync_discarded,
            queue_dropped,
        },
        latency_ms: {
            let latency = lock(&counters.latency);
            Percentiles {
                p50: latency.quantile_ms(0.5),
                p99: latency.quantile_ms(0.99),
            }
        },
        render_fps: counters.render_fps(shared.started.elapsed()),
        outputs_dropped: shared.writer.dropped(),
        outputs_failed: shared.writer.failed(),
        sync_missing: counters.sync_missing.load(Ordering::Relaxed),
        bus_drops: shared.bus.total_dropped(),
        render_errors: counters.render_errors.load(Ordering::Relaxed),
        recording: shared
            .recorder
            .status()
            .current()
            .map(|(path, messages)| RecordingStatus { path, messages }),
        sync_streams: lock(&counters.sync_streams).clone(),
        tracking: lock(&counters.tracking).map(|t| TrackingStatus {
            source: t.source.name().to_owned(),
            state: t.state,
            pose_age_ms: t.pose_age_ms,
            reprojection_rms_px: t.reprojection_rms_px,
            tags_used: t.tags_used,
            world_from_camera: t.world_from_camera,
            untracked_frames: counters.untracked_frames.load(Ordering::Relaxed),
        }),
        albedo: lock(&counters.albedo).map(|a| {
            let c = a.census;
            AlbedoStatus {
                estimated: a.estimated,
                measured_vertices: a.measured_vertices,
                vertices: a.vertices,
                skipped_cells: c.saturated + c.unlit + c.shadowed + c.highlight + c.above_one,
            }
        }),
        live_view: shared.live_view.get().cloned(),
        engine_status: lock(&counters.engine_status).clone(),
    }
}
