//! What the control socket talks about: the [`ControlTarget`] the pipeline implements, the reports
//! it returns, and the errors it raises.

use std::path::{Path, PathBuf};

use relight_core::StreamKind;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::lights::LightsBoard;

/// JSON-RPC 2.0 error codes: the five the spec defines, then relightd's application codes
/// (the spec reserves −32000..−32099 for implementation-defined server errors).
pub mod codes {
    pub const PARSE_ERROR: i64 = -32700;
    pub const INVALID_REQUEST: i64 = -32600;
    pub const METHOD_NOT_FOUND: i64 = -32601;
    pub const INVALID_PARAMS: i64 = -32602;
    pub const INTERNAL_ERROR: i64 = -32603;
    /// The request was valid but the pipeline could not carry it out.
    pub const FAILED: i64 = -32000;
    /// No engine of that name is registered.
    pub const ENGINE_UNKNOWN: i64 = -32001;
    /// The pipeline is busy with something that excludes the request (e.g. already recording).
    pub const BUSY: i64 = -32002;
    /// A file could not be read or written.
    pub const IO: i64 = -32003;
    /// The peer's credentials do not allow it to use the socket.
    pub const PERMISSION_DENIED: i64 = -32004;
    /// The server already serves its maximum number of connections.
    pub const TOO_MANY_CONNECTIONS: i64 = -32005;
}

/// The pipeline, as seen from the control socket. Every method is called from a connection
/// thread, possibly concurrently; implementations hand commands to the pipeline and return.
pub trait ControlTarget: Send + Sync + 'static {
    fn status(&self) -> StatusReport;
    fn engine_list(&self) -> Vec<EngineInfo>;
    /// Switches engines at the next frame boundary.
    fn engine_set(&self, name: &str) -> Result<(), ControlError>;
    fn engine_params_get(&self) -> Value;
    /// Merges `params` into the current engine's parameters and returns the full new set.
    fn engine_params_set(
        &self,
        params: serde_json::Map<String, Value>,
    ) -> Result<Value, ControlError>;
    /// Starts recording to `request.path` (relative to the recorder directory; by default a
    /// timestamped file there); returns the file being written.
    fn record_start(&self, request: OutputRequest) -> Result<PathBuf, ControlError>;
    /// Stops recording; returns a summary (file, messages, bytes, duration…).
    fn record_stop(&self) -> Result<Value, ControlError>;
    /// Writes the current frame set's images to the directory `request.path` (relative to the
    /// snapshot directory; by default that directory); returns the files written.
    fn snapshot(&self, request: OutputRequest) -> Result<Vec<PathBuf>, ControlError>;
    /// Re-reads the configuration file and applies what can change at run time; returns what
    /// changed.
    fn config_reload(&self) -> Result<Value, ControlError>;
    /// Advances a stepped replay by `frames` frame sets (messages of the synchroniser's reference
    /// stream, with the others up to the next one); an error when no source is stepped.
    fn replay_step(&self, frames: u32) -> Result<Value, ControlError> {
        let _ = frames;
        Err(ControlError::failed("no stepped replay is running"))
    }

    /// Where the lighting estimate is published (`lights.get`, `lights.subscribe`); `None` when
    /// this target publishes none.
    fn lights(&self) -> Option<&LightsBoard> {
        None
    }

    /// Writes the HDR environment the estimate comes from to `path` (relative to the snapshot
    /// directory) as an EXR, replacing a file there only with `overwrite`; returns the file and
    /// its size.
    fn lights_export(&self, path: &Path, overwrite: bool) -> Result<Value, ControlError> {
        let _ = (path, overwrite);
        Err(ControlError::failed(
            "this daemon publishes no lighting estimate",
        ))
    }
}

/// Where a client asked a file to go (`record.start`, `snapshot`).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OutputRequest {
    /// As the client wrote it (free of control characters, checked by the protocol layer);
    /// relative paths are the target's to resolve.
    pub path: Option<PathBuf>,
    /// Replace an existing file instead of refusing it.
    pub overwrite: bool,
}

/// A JSON-RPC error object, as returned by a [`ControlTarget`] or raised by the server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, thiserror::Error)]
#[error("{message} (code {code})")]
pub struct ControlError {
    pub code: i64,
    pub message: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data: Option<Value>,
}

impl ControlError {
    pub fn new(code: i64, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
            data: None,
        }
    }

    /// Attaches structured detail (the `data` member of the error object).
    pub fn with_data(mut self, data: Value) -> Self {
        self.data = Some(data);
        self
    }

    pub fn parse_error(message: impl Into<String>) -> Self {
        Self::new(codes::PARSE_ERROR, message)
    }

    pub fn invalid_request(message: impl Into<String>) -> Self {
        Self::new(codes::INVALID_REQUEST, message)
    }

    pub fn method_not_found(method: &str) -> Self {
        Self::new(
            codes::METHOD_NOT_FOUND,
            format!("method not found: {method}"),
        )
    }

    pub fn invalid_params(message: impl Into<String>) -> Self {
        Self::new(codes::INVALID_PARAMS, message)
    }

    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(codes::INTERNAL_ERROR, message)
    }

    /// A valid request the pipeline could not carry out (generic application error).
    pub fn failed(message: impl Into<String>) -> Self {
        Self::new(codes::FAILED, message)
    }

    pub fn engine_unknown(name: &str) -> Self {
        Self::new(codes::ENGINE_UNKNOWN, format!("unknown engine: {name}"))
    }

    pub fn busy(message: impl Into<String>) -> Self {
        Self::new(codes::BUSY, message)
    }

    /// An I/O failure, with what was being done: `ControlError::io("cannot create /x", &err)`.
    pub fn io(context: impl std::fmt::Display, err: &std::io::Error) -> Self {
        Self::new(codes::IO, format!("{context}: {err}"))
    }

    /// A file that could not be created or written; `message` says why (the OS reason, or what
    /// was refused) and `data.path` names the file.
    pub fn file(path: &Path, message: impl Into<String>) -> Self {
        Self::new(codes::IO, message).with_data(serde_json::json!({ "path": path }))
    }

    pub fn permission_denied(uid: u32) -> Self {
        Self::new(
            codes::PERMISSION_DENIED,
            format!("permission denied: uid {uid} not allowed"),
        )
    }
}

/// Everything `relightctl status` shows.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct StatusReport {
    pub uptime_s: f64,
    /// The engine rendering now.
    pub engine: String,
    pub devices: Vec<DeviceStatus>,
    /// Pipeline stages in data-flow order.
    pub stages: Vec<StageTiming>,
    /// Frame sets taken to render (each one rendered, or counted in `render_errors`).
    pub frame_sets: u64,
    /// Messages of the synchroniser's reference stream the sources produced: every one is a
    /// frame set rendered, skipped (`frames_skipped`) or still on its way.
    #[serde(default)]
    pub reference_frames: u64,
    /// Composites rendered.
    #[serde(default)]
    pub frames_rendered: u64,
    /// Frame sets not rendered, by reason (see [`FramesSkipped`]).
    #[serde(default)]
    pub frames_skipped: FramesSkipped,
    /// Capture to composite: from the reference frame's host stamp (its arrival at the render
    /// thread in fast and stepped replays, whose stamps are the recording's clock) until the
    /// composite is ready, over the recent frames.
    #[serde(default)]
    pub latency_ms: Percentiles,
    /// Composites per second over the last two seconds.
    #[serde(default)]
    pub render_fps: f64,
    /// Output PNGs and snapshots dropped because the writer thread was behind, or whose write
    /// failed.
    #[serde(default)]
    pub outputs_dropped: u64,
    #[serde(default)]
    pub outputs_failed: u64,
    /// Frame sets emitted with a stream missing (after `sync.max_wait_ms`).
    pub sync_missing: u64,
    /// Frames dropped by bus queues (drop-oldest).
    pub bus_drops: u64,
    /// Frame sets the engine failed to render (missing input, GPU error); the daemon goes on.
    #[serde(default)]
    pub render_errors: u64,
    pub recording: Option<RecordingStatus>,
    /// Per expected stream: how the synchroniser used its messages.
    #[serde(default)]
    pub sync_streams: Vec<SyncStreamStatus>,
    /// The camera's registration at the last frame set (none before the first).
    #[serde(default)]
    pub tracking: Option<TrackingStatus>,
    /// The live surface's albedo measurement at the last frame set (none when it does not run:
    /// `[scene] albedo = "fixed"`, no colour response, no depth surface).
    #[serde(default)]
    pub albedo: Option<AlbedoStatus>,
    /// Where the live view listens (`[live_view]`, `--live-view`); none when it is off.
    #[serde(default)]
    pub live_view: Option<LiveViewStatus>,
    /// What the running engine reports of its own decisions (`auto`: the engine it chose and
    /// why, the scene's features, each candidate's predicted error and measured cost); none
    /// for an engine without decisions of its own.
    #[serde(default)]
    pub engine_status: Option<Value>,
}

/// The live view's addresses, as a viewer opens them.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LiveViewStatus {
    /// The Foxglove WebSocket server, `ws://host:port`.
    pub foxglove: Option<String>,
    /// The browser page, `http://host:port/`.
    pub page: Option<String>,
}

/// What the live surface's albedo measurement (DLPV eq. 1) did on the last frame set.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AlbedoStatus {
    /// Whether eq. 1 ran on that frame (else the last estimate was carried, `albedo_every`).
    pub estimated: bool,
    /// Surface vertices with an estimate of their own, and all of them (the rest take their
    /// neighbours' or `real_albedo`).
    pub measured_vertices: usize,
    pub vertices: usize,
    /// Grid cells eq. 1 skipped this frame: in shadow, under a highlight, clipped, too dimly
    /// lit, or above 1 (light the estimate misses).
    pub skipped_cells: usize,
}

/// Where the camera is, as the tracker last said (`[tracking]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackingStatus {
    /// `markers` or `scene`.
    pub source: String,
    /// `fixed` (scene pose), `tracked`, `held` (last pose, younger than `max_age_ms`) or
    /// `untracked` (no Δ is drawn).
    pub state: crate::pipeline::tracking::TrackingState,
    /// Milliseconds since the frame set the pose was fitted in.
    pub pose_age_ms: Option<f64>,
    /// Corner reprojection RMS of that fit, pixels.
    pub reprojection_rms_px: Option<f64>,
    pub tags_used: usize,
    /// glTF convention (the camera looks down its −Z); absent when untracked.
    pub world_from_camera: Option<relight_core::Pose>,
    /// Frame sets shown without Δ because the camera was untracked.
    pub untracked_frames: u64,
}

/// Frame sets (reference frames) that were not rendered, by reason. With live sources the
/// render thread renders the newest complete set and skips older ones; fast and stepped
/// replays skip nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct FramesSkipped {
    pub total: u64,
    /// A newer set was ready when this one's turn came (the engine is slower than the camera).
    pub superseded: u64,
    /// Reference frames the synchroniser discarded: late, out of order or over its buffer.
    pub sync_discarded: u64,
    /// Messages (of any stream) the render thread's bus queue dropped before it read them.
    pub queue_dropped: u64,
}

/// Median and 99th percentile, milliseconds.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p99: f64,
}

/// The synchroniser's counters for one stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SyncStreamStatus {
    pub stream: StreamKind,
    /// Frame sets this stream was part of.
    pub matched: u64,
    /// Frame sets emitted without it (nothing within the tolerance by `max_wait`).
    pub missing: u64,
    /// Messages that arrived after the set they belonged to was emitted.
    pub late: u64,
    /// Messages discarded (out of order, over the buffer bound, or unused).
    pub dropped: u64,
}

/// One source device (or the replay/sim source of one stream).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DeviceStatus {
    pub name: String,
    pub stream: StreamKind,
    pub backend: String,
    pub state: DeviceState,
    /// Frames per second over the last few seconds.
    pub fps: f64,
    pub frames: u64,
    pub drops: u64,
    pub last_error: Option<String>,
}

/// A device's life cycle as reported on the control socket.
/// A device's state as the backends report it (`"connecting"`, `"running"`, `"lost"`, `"stopped"`).
pub use relight_backends::DeviceState;

/// Wall-clock time of one pipeline stage per frame set, milliseconds.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct StageTiming {
    pub name: String,
    pub frames: u64,
    pub last_ms: f64,
    pub mean_ms: f64,
    pub p50_ms: f64,
    pub p99_ms: f64,
}

/// The recording in progress.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordingStatus {
    pub path: PathBuf,
    /// Messages written so far.
    pub messages: u64,
}

/// A registered engine and the JSON schema of its parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EngineInfo {
    pub name: String,
    pub description: String,
    pub params_schema: Value,
}
