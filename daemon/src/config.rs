//! relightd's configuration file (`/etc/relightd/relightd.toml`), validated with line-precise errors.
//!
//! Loading happens in three steps so that every error can name the file, the line, the column and
//! the key path (`relightd.toml:12:1: sync.tolerance_ms: must be > 0, got -3`):
//!
//! 1. the text is parsed into a spanned document ([`toml::de::DeTable`]); syntax errors stop here;
//! 2. the document is deserialized into raw section structs that deny unknown keys; type errors
//!    carry a byte span, which the `Locator` maps back to the key path that contains it;
//! 3. the raw sections are validated and converted into [`Config`]; each check names its key path,
//!    and the locator finds that key's position in the text.
//!
//! Sources: `[replay]` (an MCAP recording), `[sim]` (the simulated rig, live) and the hardware device
//! sections `[depth]`, `[color]`, `[probe]`, `[markers]`, `[lamp]` are mutually exclusive, because a
//! recording or the simulator supplies every stream on its own clock. A device section holds
//! `backend = "..."` (checked against the stream) and free backend settings, which are passed on
//! as JSON for the backend's own typed config to validate. `[sim]` is likewise a free table.
//! See `systemd/relightd.toml` for every key with its unit and default.

use std::collections::BTreeMap;
use std::fmt;
use std::net::SocketAddr;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Duration;

mod print;

use crate::pipeline::tracking::{TrackingConfig, TrackingSource};
use crate::sinks::recorder::RecordSettings;
use relight_core::StreamKind;
use relight_core::recording::{ColorEncoding, RecordingOptions, RecordingReader, TopicMap};
use relight_engines::live_scene::{LightSource, RealGeometry};
pub use relight_live::{ImageEncoding, LiveViewSettings};
use serde::Deserialize;
use toml::de::{DeTable, DeValue};

/// Where relightd reads its configuration unless `--config` says otherwise.
pub const DEFAULT_CONFIG_PATH: &str = "/etc/relightd/relightd.toml";
/// Default control socket path (inside systemd's `RuntimeDirectory=relightd`).
pub const DEFAULT_SOCKET_PATH: &str = "/run/relightd/control.sock";
/// Default permission bits of the control socket.
pub const DEFAULT_SOCKET_MODE: u32 = 0o660;
/// Default cap on one JSON-RPC request line, bytes.
pub const DEFAULT_MAX_REQUEST_BYTES: usize = 65_536;
/// Default directory of MCAP recordings (inside systemd's `StateDirectory=relightd`).
pub const DEFAULT_RECORDINGS_DIR: &str = "/var/lib/relightd/recordings";
/// Default directory of snapshots.
pub const DEFAULT_SNAPSHOTS_DIR: &str = "/var/lib/relightd/snapshots";

/// Smallest accepted `daemon.max_request_bytes`: a status request must always fit.
const MIN_REQUEST_BYTES: i64 = 256;
/// Largest accepted `daemon.max_request_bytes`: the line buffer is allocated up to this size.
const MAX_REQUEST_BYTES: i64 = 16 * 1024 * 1024;
/// `sun_path` of `sockaddr_un` holds 108 bytes including the terminating NUL.
const MAX_SOCKET_PATH_BYTES: usize = 107;
/// The largest configuration file read. A real one is a few KiB.
pub const MAX_CONFIG_BYTES: u64 = 1024 * 1024;
/// The longest `[sync]` tolerance and wait, milliseconds: a frame set waiting longer than this
/// is no longer live.
const MAX_SYNC_MS: f64 = 10_000.0;
/// `[recorder] jpeg_quality` when `color_encoding = "jpeg"` does not give one.
pub const DEFAULT_RECORDER_JPEG_QUALITY: u8 = 90;

/// The most frames the recorder may queue: each holds a whole image (a few MB at 640 × 480 with
/// depth), so more would hold gigabytes rather than smooth a slow disk.
const MAX_RECORDER_QUEUE_FRAMES: usize = 4096;

/// The validated configuration of relightd.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    /// The file this configuration was read from (used by `config.reload`).
    pub path: PathBuf,
    pub daemon: DaemonConfig,
    pub source: SourceConfig,
    pub sync: SyncConfig,
    pub engine: EngineConfig,
    pub scene: SceneConfig,
    pub recorder: RecorderConfig,
    pub snapshot: SnapshotConfig,
    pub output: OutputConfig,
    pub rig: RigConfig,
    pub tracking: TrackingConfig,
    /// `[live_view]`: the Foxglove WebSocket server and the browser page; both off by default.
    pub live_view: LiveViewSettings,
}

/// `[rig]`: the rig's calibration file, written by `relight-calibrate`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RigConfig {
    /// Where the calibration was read from.
    pub calibration_path: Option<PathBuf>,
    /// The calibration, parsed and checked when the configuration is loaded so that
    /// `check-config` catches a broken file. The hardware devices use it (the marker trackers
    /// need the colour camera) and the recorder embeds it; with `[replay]` it replaces the
    /// recording's own calibration (a rig recalibrated after recording).
    pub calibration: Option<relight_core::rig::RigCalibration>,
}

/// `[scene]`: what the relighting engines relight live.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneConfig {
    /// A scene directory (scene.toml + glTF): the virtual object(s), the lights, the camera's
    /// pose. Without it the GPU engines have no scene and only the diagnostic engines run.
    pub dir: Option<PathBuf>,
    /// Real geometry: triangulated from depth, or the scene file's real meshes.
    pub real: RealGeometry,
    /// Diffuse albedo of the depth-derived surface where nothing is measured (yet).
    pub real_albedo: f32,
    /// Measure the depth-derived surface's albedo from the colour camera (DLPV eq. 1), when the
    /// rig calibration has the colour camera's response; else `real_albedo` everywhere.
    pub measure_albedo: bool,
    /// Measure on every Nth frame (the frames between carry the last estimate).
    pub albedo_every: u32,
    /// Use every Nth depth pixel per axis for the surface.
    pub depth_stride: u32,
    /// Where the real scene's light comes from: the scene file, or the light probe.
    pub lighting: LightSource,
    /// Filter depth (guided by colour) and merge it over time before triangulating it.
    pub depth_filter: bool,
    /// Directional lights the probe's environment is cut into (median cut), each a shadow map
    /// for the engines that take discrete lights.
    pub probe_lights: usize,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            dir: None,
            real: RealGeometry::Depth,
            real_albedo: 0.6,
            measure_albedo: true,
            albedo_every: 1,
            depth_stride: 2,
            lighting: LightSource::Scene,
            depth_filter: true,
            probe_lights: 8,
        }
    }
}

/// `[daemon]`: the service itself and its control socket.
#[derive(Debug, Clone, PartialEq)]
pub struct DaemonConfig {
    pub socket: PathBuf,
    /// Permission bits of the socket file, e.g. `0o660`.
    pub socket_mode: u32,
    /// Group whose members may connect, besides root and the daemon's own user.
    pub socket_group: Option<GroupSpec>,
    pub max_request_bytes: usize,
    /// Send `WATCHDOG=1` to systemd (only has an effect when the unit sets `WatchdogSec=`).
    pub watchdog: bool,
}

/// A group named in the config, by name or by numeric gid.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GroupSpec {
    Name(String),
    Gid(u32),
}

/// Where the frames come from. An empty device map means no source is configured: the daemon
/// still serves its control socket.
#[derive(Debug, Clone, PartialEq)]
pub enum SourceConfig {
    Replay(ReplayConfig),
    Sim(SimConfig),
    Devices(BTreeMap<StreamKind, DeviceConfig>),
}

/// `[replay]`: play an MCAP recording instead of live devices.
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayConfig {
    pub path: PathBuf,
    pub mode: ReplayMode,
    /// Start again from the beginning at the end of the file (`loop` in the file).
    pub loop_playback: bool,
    /// Playback speed factor for `realtime` mode (1.0 = recorded speed).
    pub speed: f64,
    /// Streams read from another topic than relight's own (`[replay] topics`), for bags other
    /// tools recorded.
    pub topics: BTreeMap<StreamKind, String>,
}

/// How a recording is paced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplayMode {
    /// Messages are published at their recorded times, scaled by `speed`.
    Realtime,
    /// As fast as the pipeline consumes them.
    Fast,
    /// One frame set per step command.
    Stepped,
}

impl ReplayMode {
    pub const ALL: [ReplayMode; 3] = [ReplayMode::Realtime, ReplayMode::Fast, ReplayMode::Stepped];

    pub fn name(self) -> &'static str {
        match self {
            ReplayMode::Realtime => "realtime",
            ReplayMode::Fast => "fast",
            ReplayMode::Stepped => "stepped",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }
}

/// `[sim]`: the simulated rig as a live source. Its settings are validated by
/// `relight_sim::device::SimSourceConfig`.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// The `[sim]` table as a JSON object.
    pub settings: serde_json::Value,
}

/// A hardware device section (`[depth]`, `[color]`, `[probe]`, `[markers]`, `[lamp]`).
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceConfig {
    pub backend: DeviceBackend,
    /// Every key of the section except `backend`, as a JSON object for the backend's typed config.
    pub settings: serde_json::Value,
}

/// The hardware backends, each behind a cargo feature of `relight-backends`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DeviceBackend {
    Openni2,
    Freenect,
    V4l2,
    Ueye,
    Apriltag,
    Aruco,
    LampSerial,
}

impl DeviceBackend {
    pub const ALL: [DeviceBackend; 7] = [
        DeviceBackend::Openni2,
        DeviceBackend::Freenect,
        DeviceBackend::V4l2,
        DeviceBackend::Ueye,
        DeviceBackend::Apriltag,
        DeviceBackend::Aruco,
        DeviceBackend::LampSerial,
    ];

    pub fn name(self) -> &'static str {
        match self {
            DeviceBackend::Openni2 => "openni2",
            DeviceBackend::Freenect => "freenect",
            DeviceBackend::V4l2 => "v4l2",
            DeviceBackend::Ueye => "ueye",
            DeviceBackend::Apriltag => "apriltag",
            DeviceBackend::Aruco => "aruco",
            DeviceBackend::LampSerial => "lamp_serial",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|b| b.name() == name)
    }

    /// The cargo feature of relight-daemon (and relight-backends) that compiles this backend in.
    pub fn feature(self) -> &'static str {
        match self {
            DeviceBackend::Aruco => "opencv",
            DeviceBackend::LampSerial => "lamp",
            other => other.name(),
        }
    }

    /// The streams this backend can supply.
    pub fn streams(self) -> &'static [StreamKind] {
        match self {
            DeviceBackend::Openni2 | DeviceBackend::Freenect => {
                &[StreamKind::Depth, StreamKind::Color]
            }
            DeviceBackend::V4l2 | DeviceBackend::Ueye => &[StreamKind::Color, StreamKind::Probe],
            DeviceBackend::Apriltag | DeviceBackend::Aruco => &[StreamKind::Markers],
            DeviceBackend::LampSerial => &[StreamKind::Lamp],
        }
    }
}

impl fmt::Display for DeviceBackend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// `[sync]`: how frames of different streams are grouped into one frame set.
#[derive(Debug, Clone, PartialEq)]
pub struct SyncConfig {
    /// Largest timestamp distance from the reference frame for a frame to join its set.
    pub tolerance: Duration,
    /// How long a frame set waits for missing streams before it is emitted incomplete.
    pub max_wait: Duration,
    /// The streams a frame set contains, in file order, without duplicates.
    pub streams: Vec<StreamKind>,
    /// The stream whose frames define the frame-set clock.
    pub reference: StreamKind,
}

/// `[engine]`: the relighting engine started at boot.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineConfig {
    pub name: String,
    /// Engine parameters (a JSON object), validated by the engine registry.
    pub params: serde_json::Value,
}

/// `[recorder]`: the MCAP recorder sink.
#[derive(Debug, Clone, PartialEq)]
pub struct RecorderConfig {
    pub dir: PathBuf,
    /// Start recording when the daemon starts.
    pub autostart: bool,
    /// Frames buffered between the bus and the writer before the oldest are dropped.
    pub queue_frames: usize,
    /// How 8-bit colour images and the composite are stored: `raw` (`sensor_msgs/Image`),
    /// `png` (lossless) or `jpeg` at `jpeg_quality` (`sensor_msgs/CompressedImage`).
    pub color_encoding: ColorEncoding,
    /// Also record the composite, Δ and the lighting estimate of every rendered frame.
    pub outputs: bool,
}

impl RecorderConfig {
    /// How a recording started now is written.
    pub fn settings(&self) -> RecordSettings {
        RecordSettings {
            options: RecordingOptions {
                color_encoding: self.color_encoding,
                ..RecordingOptions::default()
            },
            outputs: self.outputs,
        }
    }
}

/// `[snapshot]`: where `snapshot` writes its images when no path is given.
#[derive(Debug, Clone, PartialEq)]
pub struct SnapshotConfig {
    pub dir: PathBuf,
}

/// `[output]`: composite PNGs written every `every_n`-th frame (for demos); off without `dir`.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputConfig {
    pub dir: Option<PathBuf>,
    pub every_n: u32,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            path: PathBuf::from(DEFAULT_CONFIG_PATH),
            daemon: DaemonConfig::default(),
            source: SourceConfig::Devices(BTreeMap::new()),
            sync: SyncConfig::default(),
            engine: EngineConfig::default(),
            scene: SceneConfig::default(),
            recorder: RecorderConfig::default(),
            snapshot: SnapshotConfig::default(),
            output: OutputConfig::default(),
            rig: RigConfig::default(),
            tracking: TrackingConfig::default(),
            live_view: LiveViewSettings::default(),
        }
    }
}

impl Default for DaemonConfig {
    fn default() -> Self {
        Self {
            socket: PathBuf::from(DEFAULT_SOCKET_PATH),
            socket_mode: DEFAULT_SOCKET_MODE,
            socket_group: None,
            max_request_bytes: DEFAULT_MAX_REQUEST_BYTES,
            watchdog: true,
        }
    }
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self {
            tolerance: Duration::from_millis(20),
            max_wait: Duration::from_millis(100),
            streams: StreamKind::ALL.to_vec(),
            reference: StreamKind::Depth,
        }
    }
}

impl Default for EngineConfig {
    fn default() -> Self {
        Self {
            name: "passthrough".to_owned(),
            params: serde_json::Value::Object(serde_json::Map::new()),
        }
    }
}

impl Default for RecorderConfig {
    fn default() -> Self {
        Self {
            dir: PathBuf::from(DEFAULT_RECORDINGS_DIR),
            autostart: false,
            queue_frames: 64,
            color_encoding: ColorEncoding::Raw,
            outputs: false,
        }
    }
}

impl Default for SnapshotConfig {
    fn default() -> Self {
        Self {
            dir: PathBuf::from(DEFAULT_SNAPSHOTS_DIR),
        }
    }
}

impl Default for OutputConfig {
    fn default() -> Self {
        Self {
            dir: None,
            every_n: 30,
        }
    }
}

/// One located problem in a config file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Diagnostic {
    pub file: PathBuf,
    /// 1-based line.
    pub line: usize,
    /// 1-based column, in characters.
    pub column: usize,
    /// Dotted key path (`sync.streams[2]`), when the problem belongs to a key.
    pub key: Option<String>,
    pub message: String,
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}: ", self.file.display(), self.line, self.column)?;
        if let Some(key) = &self.key {
            write!(f, "{key}: ")?;
        }
        f.write_str(&self.message)
    }
}

/// Why a configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The reason is in the message, not a `source`: an error chain printed whole would say it
    /// twice.
    #[error("{}: cannot read config: {reason}", path.display())]
    Read {
        path: PathBuf,
        reason: std::io::Error,
    },
    /// The text is not valid TOML.
    #[error("{0}")]
    Syntax(Diagnostic),
    /// The TOML does not describe a valid configuration; one diagnostic per problem, in file order.
    #[error("{}", DiagnosticList(.0))]
    Invalid(Vec<Diagnostic>),
}

impl ConfigError {
    /// The located problems (empty for read errors).
    pub fn diagnostics(&self) -> &[Diagnostic] {
        match self {
            ConfigError::Read { .. } => &[],
            ConfigError::Syntax(d) => std::slice::from_ref(d),
            ConfigError::Invalid(list) => list,
        }
    }
}

struct DiagnosticList<'a>(&'a [Diagnostic]);

impl fmt::Display for DiagnosticList<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, d) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str("\n")?;
            }
            write!(f, "{d}")?;
        }
        Ok(())
    }
}

impl Config {
    /// Reads the configuration file at `path` (a regular file of at most
    /// [`MAX_CONFIG_BYTES`]) and runs every check [`Config::validate`] runs. `run`,
    /// `check-config` and `config.reload` all load through here, so what one accepts the others
    /// accept.
    pub fn load(path: impl AsRef<Path>) -> Result<Config, ConfigError> {
        let path = path.as_ref();
        let text = read_bounded(path).map_err(|reason| ConfigError::Read {
            path: path.to_owned(),
            reason,
        })?;
        Config::validate(&text, path)
    }

    /// Parses configuration text and checks its shape: types, ranges, engine names and
    /// parameters, exclusive sources. The only file it reads is the rig calibration. `path`
    /// names the file in messages, is kept in [`Config::path`], and is the directory relative
    /// paths are taken from.
    pub fn parse(text: &str, path: impl AsRef<Path>) -> Result<Config, ConfigError> {
        Config::check(text, path.as_ref(), Checks::Shape)
    }

    /// [`Config::parse`], and also what the configuration names outside itself, as `run` will
    /// meet it: the scene directory loads, the replay file opens as a recording, the `[sim]`
    /// settings build a rig, the socket group exists. Every problem is one located diagnostic.
    pub fn validate(text: &str, path: impl AsRef<Path>) -> Result<Config, ConfigError> {
        Config::check(text, path.as_ref(), Checks::Resources)
    }

    fn check(text: &str, path: &Path, checks: Checks) -> Result<Config, ConfigError> {
        let doc = match DeTable::parse(text) {
            Ok(doc) => doc,
            Err(err) => {
                let (partial, _) = DeTable::parse_recoverable(text);
                let locator = Locator::new(partial.get_ref(), text);
                let offset = err.span().map_or(0, |s| s.start);
                let key = locator.path_near(text, offset);
                return Err(ConfigError::Syntax(diagnostic(
                    path,
                    text,
                    offset,
                    key,
                    err.message().trim_end().to_owned(),
                )));
            }
        };
        let locator = Locator::new(doc.get_ref(), text);
        let raw: RawConfig = match toml::from_str(text) {
            Ok(raw) => raw,
            Err(err) => {
                let offset = err.span().map_or(0, |s| s.start);
                let message = friendly_serde_message(err.message());
                let mut key = locator.path_at(offset);
                if let Some(field) = missing_field(&message) {
                    key = Some(match key {
                        Some(parent) => format!("{parent}.{field}"),
                        None => field.to_owned(),
                    });
                }
                return Err(ConfigError::Invalid(vec![diagnostic(
                    path, text, offset, key, message,
                )]));
            }
        };
        let mut v = Validator {
            file: path,
            text,
            locator: &locator,
            errors: Vec::new(),
        };
        let config = v.config(raw, path);
        if checks == Checks::Resources {
            v.resources(&config);
        }
        if v.errors.is_empty() {
            Ok(config)
        } else {
            let mut errors = v.errors;
            errors.sort_by_key(|d| (d.line, d.column));
            Err(ConfigError::Invalid(errors))
        }
    }
}

impl GroupSpec {
    /// The numeric gid of this group: a name is looked up through the system's group database
    /// (`getgrnam`, so NSS groups such as LDAP's count), a number is taken as it is.
    pub fn resolve_gid(&self) -> Result<u32, GroupLookupError> {
        match self {
            GroupSpec::Gid(gid) => Ok(*gid),
            GroupSpec::Name(name) => match nix::unistd::Group::from_name(name) {
                Ok(Some(group)) => Ok(group.gid.as_raw()),
                Ok(None) => Err(GroupLookupError::Unknown { name: name.clone() }),
                Err(errno) => Err(GroupLookupError::Lookup {
                    name: name.clone(),
                    reason: errno.desc(),
                }),
            },
        }
    }
}

impl fmt::Display for GroupSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GroupSpec::Name(name) => f.write_str(name),
            GroupSpec::Gid(gid) => write!(f, "{gid}"),
        }
    }
}

/// Why a group name could not be turned into a gid.
#[derive(Debug, thiserror::Error)]
pub enum GroupLookupError {
    #[error("cannot look group `{name}` up: {reason}")]
    Lookup { name: String, reason: &'static str },
    #[error("group `{name}` does not exist (`getent group {name}` finds nothing)")]
    Unknown { name: String },
}

// ---------------------------------------------------------------------------------------------
// Raw sections, as they appear in the file. Integers are i64 so that range checks can report the
// value that was written; every key is optional so that defaults are applied in one place.

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawConfig {
    daemon: RawDaemon,
    replay: Option<RawReplay>,
    sim: Option<toml::Table>,
    depth: Option<toml::Table>,
    color: Option<toml::Table>,
    probe: Option<toml::Table>,
    markers: Option<toml::Table>,
    lamp: Option<toml::Table>,
    sync: RawSync,
    engine: RawEngine,
    scene: RawScene,
    recorder: RawRecorder,
    snapshot: RawSnapshot,
    output: RawOutput,
    rig: RawRig,
    tracking: RawTracking,
    live_view: RawLiveView,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawLiveView {
    bind: Option<String>,
    page: Option<String>,
    image: Option<String>,
    jpeg_quality: Option<i64>,
    max_rate_hz: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawTracking {
    source: Option<String>,
    max_age_ms: Option<f64>,
    max_rms_px: Option<f64>,
    board: Option<relight_backends::markers::board::BoardConfig>,
    smoothing: Option<relight_backends::markers::one_euro::OneEuroConfig>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawRig {
    calibration: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawDaemon {
    socket: Option<String>,
    socket_mode: Option<String>,
    socket_group: Option<toml::Value>,
    max_request_bytes: Option<i64>,
    watchdog: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawReplay {
    path: Option<String>,
    mode: Option<String>,
    #[serde(rename = "loop")]
    loop_playback: Option<bool>,
    speed: Option<f64>,
    topics: Option<BTreeMap<String, String>>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawSync {
    tolerance_ms: Option<f64>,
    max_wait_ms: Option<f64>,
    streams: Option<Vec<String>>,
    reference: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawEngine {
    name: Option<String>,
    params: Option<toml::Table>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawScene {
    dir: Option<String>,
    real: Option<String>,
    real_albedo: Option<f64>,
    albedo: Option<String>,
    albedo_every: Option<i64>,
    depth_stride: Option<i64>,
    lighting: Option<String>,
    depth_filter: Option<bool>,
    probe_lights: Option<i64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawRecorder {
    dir: Option<String>,
    autostart: Option<bool>,
    queue_frames: Option<i64>,
    color_encoding: Option<String>,
    jpeg_quality: Option<i64>,
    outputs: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawSnapshot {
    dir: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RawOutput {
    dir: Option<String>,
    every_n: Option<i64>,
}

// ---------------------------------------------------------------------------------------------

/// How far [`Config::check`] goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Checks {
    /// The text alone (and the rig calibration it names).
    Shape,
    /// Also the scene, the recording, the simulator and the group it names.
    Resources,
}

struct Validator<'a> {
    file: &'a Path,
    text: &'a str,
    locator: &'a Locator,
    errors: Vec<Diagnostic>,
}

impl Validator<'_> {
    fn error(&mut self, key: &str, message: String) {
        let offset = self.locator.offset_of(key).unwrap_or(0);
        let (line, column) = self.locator.lines.line_column(self.text, offset);
        self.errors.push(Diagnostic {
            file: self.file.to_owned(),
            line,
            column,
            key: Some(key.to_owned()),
            message,
        });
    }

    /// A path as written, or taken relative to the configuration file's directory (as the
    /// service runs with `/` as its working directory, that is the only useful meaning).
    fn relative_to_config(&self, path: PathBuf) -> PathBuf {
        match self.file.parent() {
            Some(dir) if path.is_relative() => dir.join(path),
            _ => path,
        }
    }

    /// The checks that read what the configuration names: each is what `run` does first with it
    /// (device sections: everything short of opening the hardware).
    fn resources(&mut self, config: &Config) {
        if let Some(dir) = &config.scene.dir
            && let Err(error) = relight_core::scene::Scene::load(dir)
        {
            self.error("scene.dir", error.to_string());
        }
        match &config.source {
            SourceConfig::Replay(replay) => {
                let topics = TopicMap::new(replay.topics.clone());
                match RecordingReader::open(&replay.path) {
                    Ok(reader) => {
                        let reader = reader.with_topics(topics);
                        if reader.messages().next().is_none() {
                            let read: Vec<&str> = StreamKind::ALL
                                .map(|kind| reader.topic_map().topic(kind))
                                .to_vec();
                            self.error(
                                "replay.path",
                                format!(
                                    "{}: the recording holds no messages on the streams' topics ({}); its topics are {} (map them to streams with [replay] topics)",
                                    replay.path.display(),
                                    read.join(", "),
                                    reader.topics().join(", "),
                                ),
                            );
                        }
                    }
                    Err(error) => self.error("replay.path", error.to_string()),
                }
            }
            SourceConfig::Sim(sim) => {
                let built = serde_json::from_value::<relight_sim::device::SimSourceConfig>(
                    sim.settings.clone(),
                )
                .map_err(|e| e.to_string())
                .and_then(|settings| {
                    relight_sim::device::SimDevice::new(&settings).map_err(|e| e.to_string())
                });
                if let Err(error) = built {
                    self.error("sim", error);
                }
            }
            SourceConfig::Devices(devices) => {
                if let Err((stream, error)) =
                    crate::devices::check(devices, config.rig.calibration.as_ref())
                {
                    self.error(stream.name(), error);
                }
            }
        }
        if let Some(group) = &config.daemon.socket_group
            && let Err(error) = group.resolve_gid()
        {
            self.error("daemon.socket_group", error.to_string());
        }
    }

    fn config(&mut self, raw: RawConfig, path: &Path) -> Config {
        let source = self.source(&raw);
        Config {
            path: path.to_owned(),
            daemon: self.daemon(raw.daemon),
            source,
            sync: self.sync(raw.sync),
            engine: self.engine(raw.engine),
            scene: self.scene(raw.scene),
            recorder: self.recorder(raw.recorder),
            snapshot: SnapshotConfig {
                dir: self
                    .dir("snapshot.dir", raw.snapshot.dir)
                    .unwrap_or_else(|| PathBuf::from(DEFAULT_SNAPSHOTS_DIR)),
            },
            output: self.output(raw.output),
            rig: self.rig(raw.rig),
            tracking: self.tracking(raw.tracking),
            live_view: self.live_view(raw.live_view),
        }
    }

    fn live_view(&mut self, raw: RawLiveView) -> LiveViewSettings {
        let mut live = LiveViewSettings {
            foxglove: self.socket_addr("live_view.bind", raw.bind),
            page: self.socket_addr("live_view.page", raw.page),
            ..LiveViewSettings::default()
        };
        match raw.image.as_deref() {
            None => {}
            Some("jpeg") => live.image = ImageEncoding::Jpeg,
            Some("raw") => live.image = ImageEncoding::Raw,
            Some(other) => self.error(
                "live_view.image",
                format!("must be \"jpeg\" or \"raw\", got {other:?}"),
            ),
        }
        if let Some(quality) = self.jpeg_quality("live_view.jpeg_quality", raw.jpeg_quality) {
            live.jpeg_quality = quality;
        }
        if let Some(hz) = raw.max_rate_hz {
            if hz.is_finite() && (0.1..=1000.0).contains(&hz) {
                live.max_rate_hz = hz;
            } else {
                self.error(
                    "live_view.max_rate_hz",
                    format!("must be in 0.1..=1000, got {hz}"),
                );
            }
        }
        live
    }

    /// `host:port` (an IP address; port 0 picks a free one).
    fn socket_addr(&mut self, key: &str, value: Option<String>) -> Option<SocketAddr> {
        let value = value?;
        match value.parse() {
            Ok(addr) => Some(addr),
            Err(_) => {
                self.error(
                    key,
                    format!(
                        "must be an IP address and port such as \"127.0.0.1:8765\", got {value:?}"
                    ),
                );
                None
            }
        }
    }

    fn tracking(&mut self, raw: RawTracking) -> TrackingConfig {
        let mut tracking = TrackingConfig {
            board: raw.board,
            ..TrackingConfig::default()
        };
        match raw.source.as_deref() {
            None => {}
            Some("markers") => tracking.source = Some(TrackingSource::Markers),
            Some("scene") => tracking.source = Some(TrackingSource::Scene),
            Some(other) => self.error(
                "tracking.source",
                format!("must be \"markers\" or \"scene\", got \"{other}\""),
            ),
        }
        if let Some(ms) = raw.max_age_ms {
            match non_negative_ms(ms, 3_600_000.0) {
                Ok(age) => tracking.max_age = age,
                Err(_) => self.error(
                    "tracking.max_age_ms",
                    format!("must be in [0, 3600000] ms, got {ms}"),
                ),
            }
        }
        if let Some(rms) = raw.max_rms_px {
            if rms.is_finite() && rms > 0.0 && rms <= 100.0 {
                tracking.max_rms_px = rms;
            } else {
                self.error(
                    "tracking.max_rms_px",
                    format!("must be in (0, 100] pixels, got {rms}"),
                );
            }
        }
        if let Some(smoothing) = raw.smoothing {
            match smoothing.validate() {
                Ok(()) => tracking.smoothing = smoothing,
                Err(message) => self.error("tracking.smoothing", message),
            }
        }
        if let Some(board) = &tracking.board
            && let Err(error) = relight_backends::markers::board::Board::from_config(board)
        {
            self.error("tracking.board", error.to_string());
        }
        tracking
    }

    /// A relative calibration path is taken relative to the configuration file's directory.
    fn rig(&mut self, raw: RawRig) -> RigConfig {
        let Some(path) = self.dir("rig.calibration", raw.calibration) else {
            return RigConfig::default();
        };
        let path = self.relative_to_config(path);
        let parsed = std::fs::read_to_string(&path)
            .map_err(|e| e.to_string())
            .and_then(|text| {
                relight_core::rig::RigCalibration::from_toml(&text).map_err(|e| e.to_string())
            });
        match parsed {
            Ok(calibration) => RigConfig {
                calibration_path: Some(path),
                calibration: Some(calibration),
            },
            Err(error) => {
                self.error("rig.calibration", format!("{}: {error}", path.display()));
                RigConfig::default()
            }
        }
    }

    fn daemon(&mut self, raw: RawDaemon) -> DaemonConfig {
        let mut daemon = DaemonConfig::default();
        if let Some(socket) = raw.socket {
            if socket.is_empty() {
                self.error("daemon.socket", "must not be empty".to_owned());
            } else if socket.len() > MAX_SOCKET_PATH_BYTES {
                self.error(
                    "daemon.socket",
                    format!(
                        "a Unix socket path holds at most {MAX_SOCKET_PATH_BYTES} bytes, got {}",
                        socket.len()
                    ),
                );
            } else {
                daemon.socket = PathBuf::from(socket);
            }
        }
        if let Some(mode) = raw.socket_mode {
            match parse_octal_mode(&mode) {
                Some(bits) => daemon.socket_mode = bits,
                None => self.error(
                    "daemon.socket_mode",
                    format!("must be an octal mode between \"0000\" and \"0777\" like \"0660\", got {mode:?}"),
                ),
            }
        }
        if let Some(group) = raw.socket_group {
            daemon.socket_group = self.group("daemon.socket_group", group);
        }
        if let Some(bytes) = raw.max_request_bytes {
            if (MIN_REQUEST_BYTES..=MAX_REQUEST_BYTES).contains(&bytes) {
                daemon.max_request_bytes = bytes as usize;
            } else {
                self.error(
                    "daemon.max_request_bytes",
                    format!(
                        "must be between {MIN_REQUEST_BYTES} and {MAX_REQUEST_BYTES}, got {bytes}"
                    ),
                );
            }
        }
        if let Some(watchdog) = raw.watchdog {
            daemon.watchdog = watchdog;
        }
        daemon
    }

    fn group(&mut self, key: &str, value: toml::Value) -> Option<GroupSpec> {
        match value {
            toml::Value::String(name) if valid_group_name(&name) => Some(GroupSpec::Name(name)),
            toml::Value::String(name) => {
                self.error(key, format!("not a valid group name: {name:?}"));
                None
            }
            toml::Value::Integer(gid) => match u32::try_from(gid) {
                Ok(gid) => Some(GroupSpec::Gid(gid)),
                Err(_) => {
                    self.error(
                        key,
                        format!("a gid is between 0 and {}, got {gid}", u32::MAX),
                    );
                    None
                }
            },
            other => {
                self.error(
                    key,
                    format!(
                        "expected a group name or a numeric gid, got a {}",
                        other.type_str()
                    ),
                );
                None
            }
        }
    }

    fn source(&mut self, raw: &RawConfig) -> SourceConfig {
        let device_sections = [
            (StreamKind::Depth, &raw.depth),
            (StreamKind::Color, &raw.color),
            (StreamKind::Probe, &raw.probe),
            (StreamKind::Markers, &raw.markers),
            (StreamKind::Lamp, &raw.lamp),
        ];
        let mut devices = BTreeMap::new();
        for (stream, section) in device_sections {
            if let Some(table) = section
                && let Some(device) = self.device(stream, table)
            {
                devices.insert(stream, device);
            }
        }
        let first_device = devices.keys().next().copied();
        match (&raw.replay, &raw.sim) {
            (Some(_), Some(_)) => {
                self.error(
                    "sim",
                    "[replay] and [sim] are both set; choose one source".to_owned(),
                );
                SourceConfig::Devices(devices)
            }
            (Some(replay), None) => {
                if let Some(stream) = first_device {
                    self.error(
                        stream.name(),
                        "a device section cannot be combined with [replay]; remove one".to_owned(),
                    );
                }
                match self.replay(replay) {
                    Some(replay) => SourceConfig::Replay(replay),
                    None => SourceConfig::Devices(devices),
                }
            }
            (None, Some(sim)) => {
                if let Some(stream) = first_device {
                    self.error(
                        stream.name(),
                        "a device section cannot be combined with [sim]; remove one".to_owned(),
                    );
                }
                let mut settings = self.table_to_json("sim", sim);
                if let Some(scene) = settings.get_mut("scene")
                    && let Some(dir) = scene.as_str()
                {
                    let dir = self.relative_to_config(PathBuf::from(dir));
                    *scene = serde_json::Value::String(dir.to_string_lossy().into_owned());
                }
                SourceConfig::Sim(SimConfig { settings })
            }
            (None, None) => SourceConfig::Devices(devices),
        }
    }

    fn replay(&mut self, raw: &RawReplay) -> Option<ReplayConfig> {
        let mut ok = true;
        let path = match &raw.path {
            Some(path) if !path.is_empty() => Some(self.relative_to_config(PathBuf::from(path))),
            Some(_) => {
                self.error("replay.path", "must not be empty".to_owned());
                None
            }
            None => {
                self.error(
                    "replay.path",
                    "missing: [replay] needs the MCAP file to play".to_owned(),
                );
                None
            }
        };
        let mode = match raw.mode.as_deref() {
            None => ReplayMode::Realtime,
            Some(name) => ReplayMode::from_name(name).unwrap_or_else(|| {
                ok = false;
                ReplayMode::Realtime
            }),
        };
        if !ok {
            self.error(
                "replay.mode",
                format!(
                    "must be one of \"realtime\", \"fast\", \"stepped\", got {:?}",
                    raw.mode.as_deref().unwrap_or_default()
                ),
            );
        }
        let speed = raw.speed.unwrap_or(1.0);
        if !(speed.is_finite() && speed > 0.0) {
            self.error("replay.speed", format!("must be > 0, got {speed}"));
            ok = false;
        }
        let mut topics = BTreeMap::new();
        for (stream, topic) in raw.topics.iter().flatten() {
            let key = format!("replay.topics.{stream}");
            match StreamKind::from_name(stream) {
                None => {
                    self.error(
                        &key,
                        format!("not a stream; the streams are {}", stream_names()),
                    );
                    ok = false;
                }
                Some(_) if topic.is_empty() => {
                    self.error(&key, "must name a topic".to_owned());
                    ok = false;
                }
                Some(kind) => {
                    if let Some((other, _)) = topics.iter().find(|(_, t)| *t == topic) {
                        self.error(
                            &key,
                            format!("{topic:?} is already the {other} stream's topic"),
                        );
                        ok = false;
                    }
                    topics.insert(kind, topic.clone());
                }
            }
        }
        Some(ReplayConfig {
            path: path?,
            mode,
            loop_playback: raw.loop_playback.unwrap_or(false),
            speed,
            topics,
        })
        .filter(|_| ok)
    }

    fn device(&mut self, stream: StreamKind, table: &toml::Table) -> Option<DeviceConfig> {
        let section = stream.name();
        let key = format!("{section}.backend");
        let backend = match table.get("backend") {
            None => {
                self.error(
                    &key,
                    format!(
                        "missing: [{section}] needs a backend, one of {}",
                        backends_for(stream)
                    ),
                );
                return None;
            }
            Some(toml::Value::String(name)) => match DeviceBackend::from_name(name) {
                Some(b) if b.streams().contains(&stream) => b,
                Some(b) => {
                    self.error(
                        &key,
                        format!(
                            "backend \"{b}\" cannot supply the {stream} stream; use one of {}",
                            backends_for(stream)
                        ),
                    );
                    return None;
                }
                None => {
                    self.error(
                        &key,
                        format!(
                            "unknown backend {name:?}; the {stream} stream takes one of {}",
                            backends_for(stream)
                        ),
                    );
                    return None;
                }
            },
            Some(other) => {
                self.error(
                    &key,
                    format!("expected a string, got a {}", other.type_str()),
                );
                return None;
            }
        };
        let mut settings = table.clone();
        settings.remove("backend");
        Some(DeviceConfig {
            backend,
            settings: self.table_to_json(section, &settings),
        })
    }

    fn sync(&mut self, raw: RawSync) -> SyncConfig {
        let mut sync = SyncConfig::default();
        if let Some(ms) = raw.tolerance_ms {
            match positive_ms(ms, MAX_SYNC_MS) {
                Ok(d) => sync.tolerance = d,
                Err(reason) => {
                    self.error("sync.tolerance_ms", format!("{reason}, got {}", show(ms)))
                }
            }
        }
        if let Some(ms) = raw.max_wait_ms {
            match non_negative_ms(ms, MAX_SYNC_MS) {
                Ok(d) => sync.max_wait = d,
                Err(reason) => {
                    self.error("sync.max_wait_ms", format!("{reason}, got {}", show(ms)))
                }
            }
        }
        if let Some(names) = raw.streams {
            if names.is_empty() {
                self.error("sync.streams", "must name at least one stream".to_owned());
            }
            let mut streams = Vec::with_capacity(names.len());
            for (i, name) in names.iter().enumerate() {
                let key = format!("sync.streams[{i}]");
                match StreamKind::from_name(name) {
                    Some(kind) if streams.contains(&kind) => {
                        self.error(&key, format!("stream \"{kind}\" is listed twice"));
                    }
                    Some(kind) => streams.push(kind),
                    None => self.error(
                        &key,
                        format!(
                            "unknown stream {name:?}; expected one of {}",
                            stream_names()
                        ),
                    ),
                }
            }
            if !streams.is_empty() {
                sync.streams = streams;
            }
        }
        match raw.reference {
            Some(name) => match StreamKind::from_name(&name) {
                Some(kind) if sync.streams.contains(&kind) => sync.reference = kind,
                Some(kind) => self.error(
                    "sync.reference",
                    format!("stream \"{kind}\" is not in sync.streams"),
                ),
                None => self.error(
                    "sync.reference",
                    format!(
                        "unknown stream {name:?}; expected one of {}",
                        stream_names()
                    ),
                ),
            },
            None => {
                if !sync.streams.contains(&sync.reference)
                    && let Some(&first) = sync.streams.first()
                {
                    sync.reference = first;
                }
            }
        }
        sync
    }

    fn engine(&mut self, raw: RawEngine) -> EngineConfig {
        let mut engine = EngineConfig::default();
        if let Some(name) = raw.name {
            if name.trim().is_empty() {
                self.error("engine.name", "must not be empty".to_owned());
            } else {
                engine.name = name;
            }
        }
        if let Some(params) = raw.params {
            engine.params = self.table_to_json("engine.params", &params);
        }
        let registry = relight_engines::EngineRegistry::new();
        match registry.spec(&engine.name) {
            Ok(spec) => {
                let params = engine.params.as_object().cloned().unwrap_or_default();
                if let Err(error) = spec.schema.validate(&spec.schema.defaults(), &params) {
                    self.error(
                        &format!("engine.params.{}", error.name()),
                        error.to_string(),
                    );
                }
            }
            Err(error) => self.error("engine.name", error.to_string()),
        }
        engine
    }

    fn scene(&mut self, raw: RawScene) -> SceneConfig {
        let mut scene = SceneConfig {
            dir: self
                .dir("scene.dir", raw.dir)
                .map(|dir| self.relative_to_config(dir)),
            ..SceneConfig::default()
        };
        match raw.real.as_deref() {
            None | Some("depth") => {}
            Some("scene") => scene.real = RealGeometry::Scene,
            Some(other) => self.error(
                "scene.real",
                format!("must be \"depth\" or \"scene\", got \"{other}\""),
            ),
        }
        if let Some(filter) = raw.depth_filter {
            scene.depth_filter = filter;
        }
        match raw.lighting.as_deref() {
            None | Some("scene") => {}
            Some("probe") => scene.lighting = LightSource::Probe,
            Some(other) => self.error(
                "scene.lighting",
                format!("must be \"scene\" or \"probe\", got \"{other}\""),
            ),
        }
        if let Some(albedo) = raw.real_albedo {
            if (0.0..=1.0).contains(&albedo) {
                scene.real_albedo = albedo as f32;
            } else {
                self.error(
                    "scene.real_albedo",
                    format!("must be in [0, 1], got {albedo}"),
                );
            }
        }
        match raw.albedo.as_deref() {
            None | Some("measured") => {}
            Some("fixed") => scene.measure_albedo = false,
            Some(other) => self.error(
                "scene.albedo",
                format!("must be \"measured\" or \"fixed\", got \"{other}\""),
            ),
        }
        if let Some(n) = raw.albedo_every {
            match u32::try_from(n) {
                Ok(n) if (1..=300).contains(&n) => scene.albedo_every = n,
                _ => self.error("scene.albedo_every", format!("must be in 1..=300, got {n}")),
            }
        }
        if let Some(n) = raw.probe_lights {
            match usize::try_from(n) {
                Ok(n) if (1..=32).contains(&n) => scene.probe_lights = n,
                _ => self.error("scene.probe_lights", format!("must be in 1..=32, got {n}")),
            }
        }
        if let Some(stride) = raw.depth_stride {
            match u32::try_from(stride) {
                Ok(n) if (1..=16).contains(&n) => scene.depth_stride = n,
                _ => self.error(
                    "scene.depth_stride",
                    format!("must be in 1..=16, got {stride}"),
                ),
            }
        }
        scene
    }

    fn recorder(&mut self, raw: RawRecorder) -> RecorderConfig {
        let mut recorder = RecorderConfig::default();
        if let Some(dir) = self.dir("recorder.dir", raw.dir) {
            recorder.dir = dir;
        }
        if let Some(autostart) = raw.autostart {
            recorder.autostart = autostart;
        }
        if let Some(frames) = raw.queue_frames {
            match usize::try_from(frames) {
                Ok(n) if (1..=MAX_RECORDER_QUEUE_FRAMES).contains(&n) => recorder.queue_frames = n,
                _ => self.error(
                    "recorder.queue_frames",
                    format!("must be in 1..={MAX_RECORDER_QUEUE_FRAMES}, got {frames}"),
                ),
            }
        }
        let quality = self
            .jpeg_quality("recorder.jpeg_quality", raw.jpeg_quality)
            .unwrap_or(DEFAULT_RECORDER_JPEG_QUALITY);
        match raw.color_encoding.as_deref() {
            None | Some("raw") => {}
            Some("png") => recorder.color_encoding = ColorEncoding::Png,
            Some("jpeg") => recorder.color_encoding = ColorEncoding::Jpeg { quality },
            Some(other) => self.error(
                "recorder.color_encoding",
                format!("`{other}` is not one of raw, png, jpeg"),
            ),
        }
        if let Some(outputs) = raw.outputs {
            recorder.outputs = outputs;
        }
        recorder
    }

    /// A JPEG quality, 1 to 100.
    fn jpeg_quality(&mut self, key: &str, raw: Option<i64>) -> Option<u8> {
        let quality = raw?;
        match u8::try_from(quality) {
            Ok(q) if (1..=100).contains(&q) => Some(q),
            _ => {
                self.error(key, format!("must be in 1..=100, got {quality}"));
                None
            }
        }
    }

    fn output(&mut self, raw: RawOutput) -> OutputConfig {
        let mut output = OutputConfig {
            dir: self.dir("output.dir", raw.dir),
            ..OutputConfig::default()
        };
        if let Some(n) = raw.every_n {
            match u32::try_from(n) {
                Ok(n) if n > 0 => output.every_n = n,
                _ => self.error("output.every_n", format!("must be > 0, got {n}")),
            }
        }
        output
    }

    fn dir(&mut self, key: &str, value: Option<String>) -> Option<PathBuf> {
        match value {
            Some(dir) if dir.is_empty() => {
                self.error(key, "must not be empty".to_owned());
                None
            }
            Some(dir) => Some(PathBuf::from(dir)),
            None => None,
        }
    }

    fn table_to_json(&mut self, key: &str, table: &toml::Table) -> serde_json::Value {
        match serde_json::to_value(table) {
            Ok(value) => value,
            Err(err) => {
                self.error(key, format!("cannot be represented as JSON: {err}"));
                serde_json::Value::Object(serde_json::Map::new())
            }
        }
    }
}

fn parse_octal_mode(text: &str) -> Option<u32> {
    let digits = text.strip_prefix("0o").unwrap_or(text);
    if digits.is_empty() || digits.len() > 4 || !digits.bytes().all(|b| (b'0'..=b'7').contains(&b))
    {
        return None;
    }
    u32::from_str_radix(digits, 8)
        .ok()
        .filter(|&bits| bits <= 0o777)
}

fn valid_group_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 32
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-' | b'.'))
}

/// `ms` milliseconds in (0, `max_ms`], checked before the conversion (which panics on huge
/// values); the reason otherwise.
fn positive_ms(ms: f64, max_ms: f64) -> Result<Duration, String> {
    if ms.is_nan() || ms <= 0.0 {
        return Err("must be > 0".into());
    }
    at_most_ms(ms, max_ms)
}

/// `ms` milliseconds in [0, `max_ms`].
fn non_negative_ms(ms: f64, max_ms: f64) -> Result<Duration, String> {
    if ms.is_nan() || ms < 0.0 {
        return Err("must be >= 0".into());
    }
    at_most_ms(ms, max_ms)
}

/// A number as a message quotes it: huge ones in exponent form, not 300 digits.
fn show(x: f64) -> String {
    if x.abs() >= 1e9 {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

fn at_most_ms(ms: f64, max_ms: f64) -> Result<Duration, String> {
    if ms > max_ms {
        return Err(format!("must be at most {max_ms} ms"));
    }
    Ok(Duration::from_secs_f64(ms / 1e3))
}

/// The text of a configuration file: a regular file of at most [`MAX_CONFIG_BYTES`]. Opened
/// without blocking, so a path linked to a FIFO, a device or a huge file is refused at once
/// instead of stalling or filling memory (a `config.reload` must not do either).
fn read_bounded(path: &Path) -> std::io::Result<String> {
    use std::io::Read as _;
    let invalid = |what: String| std::io::Error::new(std::io::ErrorKind::InvalidInput, what);
    let file = relight_core::input_file::open_regular(path)?;
    let mut bytes = Vec::new();
    file.take(MAX_CONFIG_BYTES + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(invalid(format!(
            "larger than {} KiB; not a relightd configuration",
            MAX_CONFIG_BYTES / 1024
        )));
    }
    String::from_utf8(bytes).map_err(|_| invalid("not UTF-8 text".into()))
}

/// The streams' names, comma-separated, for messages that list them.
pub fn stream_names() -> String {
    StreamKind::ALL.map(StreamKind::name).join(", ")
}

fn backends_for(stream: StreamKind) -> String {
    DeviceBackend::ALL
        .into_iter()
        .filter(|b| b.streams().contains(&stream))
        .map(|b| format!("\"{b}\""))
        .collect::<Vec<_>>()
        .join(", ")
}

/// serde names Rust types in its messages; say what the file should contain instead.
fn friendly_serde_message(message: &str) -> String {
    message
        .trim_end()
        .replace("expected i64", "expected an integer")
        .replace("expected f64", "expected a number")
        .replace("expected a boolean", "expected true or false")
        .replace("expected a map", "expected a table")
        .replace("unknown field", "unknown key")
}

fn is_bare_key_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.')
}

fn missing_field(message: &str) -> Option<&str> {
    let rest = message.strip_prefix("missing field `")?;
    rest.split('`').next()
}

fn diagnostic(
    file: &Path,
    text: &str,
    offset: usize,
    key: Option<String>,
    message: String,
) -> Diagnostic {
    let (line, column) = line_column(text, offset);
    Diagnostic {
        file: file.to_owned(),
        line,
        column,
        key,
        message,
    }
}

/// 1-based line and character column of a byte offset (clamped to the text), for a single
/// diagnostic; many go through the [`Locator`]'s [`LineIndex`].
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    LineIndex::new(text).line_column(text, offset)
}

/// Where each line of a text starts, so that a byte offset's line is a binary search: with one
/// diagnostic per entry of a 40 000-item list, scanning the text each time was quadratic.
struct LineIndex {
    starts: Vec<usize>,
}

impl LineIndex {
    fn new(text: &str) -> Self {
        let starts = std::iter::once(0)
            .chain(text.match_indices('\n').map(|(i, _)| i + 1))
            .collect();
        Self { starts }
    }

    /// 1-based line and character column of a byte offset (clamped to the text).
    fn line_column(&self, text: &str, offset: usize) -> (usize, usize) {
        let mut offset = offset.min(text.len());
        while !text.is_char_boundary(offset) {
            offset -= 1;
        }
        let line = self.starts.partition_point(|&start| start <= offset);
        let line_start = self.starts.get(line - 1).copied().unwrap_or(0);
        let column = text
            .get(line_start..offset)
            .unwrap_or_default()
            .chars()
            .count()
            + 1;
        (line, column)
    }
}

/// Maps byte offsets to key paths and key paths to offsets, from the spanned TOML document.
struct Locator {
    entries: Vec<LocatedKey>,
    /// The first entry of each path.
    by_path: std::collections::HashMap<String, usize>,
    lines: LineIndex,
}

struct LocatedKey {
    path: String,
    /// The key itself, or the element for array items.
    key_span: Range<usize>,
    /// The value; for a `[table]` header only the header, since its keys follow separately.
    value_span: Range<usize>,
}

impl Locator {
    fn new(root: &DeTable<'_>, text: &str) -> Self {
        let mut entries = Vec::new();
        Self::walk_table(root, "", &mut entries);
        let mut by_path = std::collections::HashMap::with_capacity(entries.len());
        for (i, entry) in entries.iter().enumerate() {
            by_path.entry(entry.path.clone()).or_insert(i);
        }
        Self {
            entries,
            by_path,
            lines: LineIndex::new(text),
        }
    }

    fn walk_table(table: &DeTable<'_>, prefix: &str, out: &mut Vec<LocatedKey>) {
        for (key, value) in table {
            let path = if prefix.is_empty() {
                key.get_ref().to_string()
            } else {
                format!("{prefix}.{}", key.get_ref())
            };
            out.push(LocatedKey {
                path: path.clone(),
                key_span: key.span(),
                value_span: value.span(),
            });
            Self::walk_value(value.get_ref(), &path, out);
        }
    }

    fn walk_value(value: &DeValue<'_>, path: &str, out: &mut Vec<LocatedKey>) {
        match value {
            DeValue::Table(table) => Self::walk_table(table, path, out),
            DeValue::Array(items) => {
                for (i, item) in items.iter().enumerate() {
                    let item_path = format!("{path}[{i}]");
                    out.push(LocatedKey {
                        path: item_path.clone(),
                        key_span: item.span(),
                        value_span: item.span(),
                    });
                    Self::walk_value(item.get_ref(), &item_path, out);
                }
            }
            _ => {}
        }
    }

    /// The most deeply nested key whose key or value contains `offset`.
    fn path_at(&self, offset: usize) -> Option<String> {
        let contains = |r: &Range<usize>| r.start <= offset && offset < r.end.max(r.start + 1);
        self.entries
            .iter()
            .filter(|e| contains(&e.key_span) || contains(&e.value_span))
            .max_by_key(|e| (e.path.matches(['.', '[']).count(), e.path.len()))
            .map(|e| e.path.clone())
    }

    /// [`Self::path_at`], or else the last key that starts on the same line before `offset`
    /// (a syntax error usually follows the key it belongs to), or else the bare key written at
    /// `offset` under the nearest `[table]` header above it (e.g. a duplicate key, which the
    /// parser drops from the document).
    fn path_near(&self, text: &str, offset: usize) -> Option<String> {
        if let Some(path) = self.path_at(offset) {
            return Some(path);
        }
        let (line, _) = self.lines.line_column(text, offset);
        let on_line = self
            .entries
            .iter()
            .filter(|e| {
                e.key_span.start <= offset
                    && self.lines.line_column(text, e.key_span.start).0 == line
            })
            .max_by_key(|e| e.key_span.start)
            .map(|e| e.path.clone());
        on_line.or_else(|| {
            let rest = text.get(offset..)?;
            let key: String = rest.chars().take_while(|&c| is_bare_key_char(c)).collect();
            if key.is_empty() {
                return None;
            }
            let before = text.get(..offset)?;
            let header = before.lines().rev().find_map(|l| {
                let l = l.trim();
                l.starts_with('[')
                    .then(|| l.trim_matches(|c| c == '[' || c == ']').trim().to_owned())
            });
            Some(match header {
                Some(table) if !table.is_empty() => format!("{table}.{key}"),
                _ => key,
            })
        })
    }

    /// Where `path` (or its nearest ancestor present in the file) starts.
    fn offset_of(&self, path: &str) -> Option<usize> {
        let mut path = path;
        loop {
            if let Some(e) = self.by_path.get(path).and_then(|&i| self.entries.get(i)) {
                return Some(e.key_span.start);
            }
            let cut = path.rfind(['.', '['])?;
            path = path.get(..cut)?;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn octal_modes() {
        assert_eq!(parse_octal_mode("0660"), Some(0o660));
        assert_eq!(parse_octal_mode("600"), Some(0o600));
        assert_eq!(parse_octal_mode("0o770"), Some(0o770));
        assert_eq!(parse_octal_mode("0999"), None);
        assert_eq!(parse_octal_mode("1777"), None);
        assert_eq!(parse_octal_mode(""), None);
        assert_eq!(parse_octal_mode("rw-rw----"), None);
    }

    #[test]
    fn line_column_counts_characters() {
        let text = "a = 1\nbé = 2\n";
        assert_eq!(line_column(text, 0), (1, 1));
        assert_eq!(line_column(text, 6), (2, 1));
        assert_eq!(line_column(text, 9), (2, 3));
        assert_eq!(line_column(text, 1000), (3, 1));
    }
}
