//! The tracked pocket lamp over a serial port: on/off, dimmer and colour temperature from its
//! line protocol ([`crate::lamp_protocol`]), position from the marker it carries.
//!
//! [`SerialLamp`] is a [`LampTracker`]: run it under the device contract with
//! [`crate::sources::SourceDevice`]. Each good report becomes one [`LampState`] frame:
//!
//! - `seq`: the report's `seq`, unwrapped from u32 to u64 (continuing across the wrap and across
//!   reconnects). A gap means reports lost on the line (a corrupted line is a lost report): each
//!   lost report is counted as one drop of the device ([`crate::DeviceStatus::drops`]) and in
//!   [`LampCounters::lost_reports`]. A jump back (the lamp rebooted) or forward by more than
//!   [`MAX_COUNTED_GAP`] is taken as a restart of the lamp's counter: `seq` continues at +1 and
//!   nothing is counted lost.
//! - `stamp`: the lamp has no clock, so `device_ns` = `host_ns` = the host time at which the read
//!   that completed the report's line returned. It lags the lamp by the line time (about 6 ms for
//!   70 bytes at 115200 baud) plus the USB-serial adapter's latency timer (FTDI: 16 ms by default).
//! - `payload`: [`LampReport::state`] at the lamp's position, with the calibrated
//!   `max_intensity_w_sr`.
//!
//! **Position.** A [`LampPositioner`] turns the newest marker detections (the `markers` topic's
//! latest value) into the light's centre in the world; [`MarkerPositioner`] is the default: it
//! finds the lamp's marker and applies `world_from_camera` (a [`WorldFromCamera`] source) and the
//! rig calibration's `lamp_marker_from_light`. The position is re-evaluated for every report
//! from the newest marker frame, so it lags the serial line by up to one camera frame (the
//! synchroniser matches streams on `host_ns` anyway). When the marker is not seen (occluded,
//! out of view, tracker stopped) the lamp keeps its **last known position**: a lamp in the hand
//! moves little between sightings, and a light that jumps to a default would be worse. Before
//! the first sighting the lamp uses `fallback_position` when one is configured; without one its
//! reports are **not published** (counted in [`LampCounters::unpositioned_reports`]), because
//! [`LampState`] has no "position unknown" flag and a made-up position would light the scene
//! from the wrong place. A non-finite position is never published.
//!
//! **Failures.** A missing port is `NotFound` (retried: the lamp may be plugged in later), a
//! path that is not a terminal device is `Config`, a read error or hang-up (unplug: EIO, EPIPE,
//! POLLHUP) is `Disconnected`, so the runner reports `Lost` and reopens the same path with
//! backoff. Bad lines — garbage, wrong checksums, cut lines, over-long lines, the noise of a
//! baud-rate mismatch — are skipped and counted in [`LampCounters::bad_lines`]; they never stop
//! the stream.

use std::collections::VecDeque;
use std::fmt;
use std::io::{self, Read};
use std::os::unix::fs::FileTypeExt;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use glam::Vec3;
use relight_core::bus::{Bus, Shared, Topic};
use relight_core::frame::host_now_ns;
use relight_core::rig::RigCalibration;
use relight_core::{Frame, LampState, MarkerSet, Pose, StreamKind, Timestamp};
use serde::Deserialize;

use crate::device::DeviceError;
use crate::lamp_protocol::{LampReport, LineError, LineParser};
use crate::sources::{Capture, FrameSource, LampTracker};

const BACKEND: &str = "lamp";

/// Largest forward `seq` jump counted as lost reports (about 11 minutes of reports at 100 Hz);
/// a longer jump is taken as a restart of the lamp's counter.
pub const MAX_COUNTED_GAP: u64 = 1 << 16;

/// ENOTTY as `serialport` reports it (nix's wording, and libc's in case it switches): the path
/// is a character device but not a terminal. Checked by the test that opens `/dev/null`.
const ENOTTY_TEXT: [&str; 2] = ["Not a typewriter", "Inappropriate ioctl for device"];

/// Bytes taken from the port per read: a few reports' worth.
const READ_CHUNK: usize = 256;

fn default_baud() -> u32 {
    115_200
}

fn default_timeout_ms() -> u64 {
    100
}

/// Configuration of a serial pocket lamp (the TOML section of a `backend = "lamp"` device).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LampConfig {
    /// `port`: the lamp's serial device. Prefer udev's stable link
    /// (`/dev/serial/by-id/usb-…`) to `/dev/ttyUSB0`, whose number can change on a replug; the
    /// lamp reopens this same path after every loss.
    pub port: PathBuf,
    /// `baud` (default 115200): the line's rate, 8N1 without flow control.
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// `max_intensity_w_sr`: the lamp's calibrated radiant intensity at dimmer level 1, W/sr
    /// (luminance of the RGB intensity; the colour comes from the reported temperature).
    pub max_intensity_w_sr: f32,
    /// `marker_id`: the ID of the marker fixed to the lamp.
    pub marker_id: u32,
    /// `marker_family` (optional): the tag family of that marker (`tag36h11`, `aruco_4x4_50`);
    /// any family matches when unset. Set it when a board's detection (whose family is the
    /// board's name) could carry the same ID.
    #[serde(default)]
    pub marker_family: Option<String>,
    /// `timeout_ms` (default 100): the longest one read waits for bytes. It bounds how late a
    /// stop request is seen; a silent lamp is not an error (a lamp may send only on change).
    #[serde(default = "default_timeout_ms")]
    pub timeout_ms: u64,
    /// `fallback_position` (optional): `[x, y, z]` in the world frame, metres, used before the
    /// lamp's marker is first seen. Without it no state is published until that sighting.
    #[serde(default)]
    pub fallback_position: Option<[f32; 3]>,
    /// `usb_id` (optional): the USB-serial adapter's `vvvv:pppp` (hex vendor and product IDs,
    /// e.g. `10c4:ea60`), for a hot-plug watcher to cut the reconnect backoff short when the lamp
    /// is plugged in ([`SerialLamp::usb_id`]).
    #[serde(default)]
    pub usb_id: Option<String>,
}

impl LampConfig {
    /// A configuration with the defaults for everything but the three required keys.
    pub fn new(port: impl Into<PathBuf>, max_intensity_w_sr: f32, marker_id: u32) -> Self {
        Self {
            port: port.into(),
            baud: default_baud(),
            max_intensity_w_sr,
            marker_id,
            marker_family: None,
            timeout_ms: default_timeout_ms(),
            fallback_position: None,
            usb_id: None,
        }
    }

    /// Checks every value; the error names the key.
    pub fn validate(&self) -> Result<(), DeviceError> {
        let bad = |key: &str, reason: &str| DeviceError::Config {
            device: BACKEND.into(),
            reason: format!("`{key}`: {reason}"),
        };
        if self.port.as_os_str().is_empty() {
            return Err(bad("port", "is empty"));
        }
        if self.port.to_str().is_none() {
            return Err(bad("port", "is not valid UTF-8"));
        }
        if self.baud == 0 {
            return Err(bad("baud", "must be positive"));
        }
        if !(self.max_intensity_w_sr.is_finite() && self.max_intensity_w_sr >= 0.0) {
            return Err(bad("max_intensity_w_sr", "must be a finite number ≥ 0"));
        }
        if self.timeout_ms == 0 {
            return Err(bad("timeout_ms", "must be positive"));
        }
        if self
            .fallback_position
            .is_some_and(|p| !Vec3::from(p).is_finite())
        {
            return Err(bad("fallback_position", "must be three finite numbers"));
        }
        self.parsed_usb_id()?;
        Ok(())
    }

    fn parsed_usb_id(&self) -> Result<Option<(u16, u16)>, DeviceError> {
        let Some(text) = &self.usb_id else {
            return Ok(None);
        };
        let hex = |s: &str| (s.len() == 4).then(|| u16::from_str_radix(s, 16).ok())?;
        text.split_once(':')
            .and_then(|(vendor, product)| Some((hex(vendor)?, hex(product)?)))
            .map(Some)
            .ok_or_else(|| DeviceError::Config {
                device: BACKEND.into(),
                reason: format!("`usb_id`: `{text}` is not `vvvv:pppp` (four hex digits each)"),
            })
    }
}

/// Where the lamp's light is, from the newest marker detections.
pub trait LampPositioner: Send + 'static {
    /// The light's centre in the world frame, metres, or `None` when `markers` do not show the
    /// lamp (the tracker then keeps its last known position).
    fn position_in_world(&mut self, markers: &Frame<MarkerSet>) -> Option<Vec3>;
}

impl<F> LampPositioner for F
where
    F: FnMut(&Frame<MarkerSet>) -> Option<Vec3> + Send + 'static,
{
    fn position_in_world(&mut self, markers: &Frame<MarkerSet>) -> Option<Vec3> {
        self(markers)
    }
}

/// The pose of the camera whose detections the `markers` stream carries, in the world (marker
/// board) frame.
pub trait WorldFromCamera: Send + 'static {
    fn world_from_camera(&mut self, markers: &Frame<MarkerSet>) -> Option<Pose>;
}

/// A fixed camera, calibrated once against the board (identity when the camera frame is the
/// world frame).
impl WorldFromCamera for Pose {
    fn world_from_camera(&mut self, _: &Frame<MarkerSet>) -> Option<Pose> {
        Some(*self)
    }
}

/// Any pose source, e.g. the board pose the marker tracker estimates in the same frame.
impl<F> WorldFromCamera for F
where
    F: FnMut(&Frame<MarkerSet>) -> Option<Pose> + Send + 'static,
{
    fn world_from_camera(&mut self, markers: &Frame<MarkerSet>) -> Option<Pose> {
        self(markers)
    }
}

/// The world from the marker tracker's board detection: the tracker publishes a fitted board
/// as one [`relight_core::MarkerDetection`] whose `family` is the board's name and whose
/// `camera_from_marker` is `camera_from_board` (`markers::board::Board::detection`). The world
/// being the board's frame, `world_from_camera = camera_from_board⁻¹`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BoardPose {
    /// The board's name (its detections' `family`).
    pub board: String,
}

impl BoardPose {
    pub fn new(board: impl Into<String>) -> Self {
        Self {
            board: board.into(),
        }
    }
}

impl WorldFromCamera for BoardPose {
    fn world_from_camera(&mut self, markers: &Frame<MarkerSet>) -> Option<Pose> {
        markers
            .payload
            .detections
            .iter()
            .filter(|d| d.family == self.board)
            .min_by(|a, b| a.reprojection_rms_px.total_cmp(&b.reprojection_rms_px))
            .map(|d| d.camera_from_marker.inverse())
            .filter(|p| p.translation.is_finite() && p.rotation.is_finite())
    }
}

/// The default [`LampPositioner`]:
/// `world_from_light = world_from_camera * camera_from_marker * lamp_marker_from_light`, and the
/// light's centre is that pose's translation.
#[derive(Debug, Clone)]
pub struct MarkerPositioner<W> {
    pub marker_id: u32,
    /// Only detections of this family count (any family when `None`).
    pub family: Option<String>,
    /// The light's centre in the marker's frame (rig calibration).
    pub lamp_marker_from_light: Pose,
    pub world_from_camera: W,
}

impl<W: WorldFromCamera> MarkerPositioner<W> {
    /// The positioner for the lamp of `config`, with the rig's `lamp_marker_from_light`.
    pub fn new(config: &LampConfig, rig: &RigCalibration, world_from_camera: W) -> Self {
        Self {
            marker_id: config.marker_id,
            family: config.marker_family.clone(),
            lamp_marker_from_light: rig.lamp_marker_from_light,
            world_from_camera,
        }
    }
}

impl<W: WorldFromCamera> LampPositioner for MarkerPositioner<W> {
    fn position_in_world(&mut self, markers: &Frame<MarkerSet>) -> Option<Vec3> {
        // Seen more than once (two detectors, a reflection): trust the best pose fit.
        let detection = markers
            .payload
            .detections
            .iter()
            .filter(|d| d.marker_id == self.marker_id)
            .filter(|d| self.family.as_ref().is_none_or(|f| *f == d.family))
            .min_by(|a, b| a.reprojection_rms_px.total_cmp(&b.reprojection_rms_px))?;
        let world_from_camera = self.world_from_camera.world_from_camera(markers)?;
        let world_from_light =
            world_from_camera * detection.camera_from_marker * self.lamp_marker_from_light;
        Some(world_from_light.translation).filter(|p| p.is_finite())
    }
}

/// Live counters of one lamp, beside the device's own ([`crate::DeviceStatus`]).
#[derive(Debug, Default)]
pub struct LampCounters {
    reports: AtomicU64,
    bad_lines: AtomicU64,
    lost_reports: AtomicU64,
    restarts: AtomicU64,
    repeated_reports: AtomicU64,
    unpositioned_reports: AtomicU64,
}

impl LampCounters {
    /// Good reports received (published or not).
    pub fn reports(&self) -> u64 {
        self.reports.load(Ordering::Relaxed)
    }
    /// Lines rejected by the parser (garbage, checksum, cut, too long, noise).
    pub fn bad_lines(&self) -> u64 {
        self.bad_lines.load(Ordering::Relaxed)
    }
    /// Reports missing from the `seq` sequence (also counted as drops of the device).
    pub fn lost_reports(&self) -> u64 {
        self.lost_reports.load(Ordering::Relaxed)
    }
    /// Times the lamp's `seq` restarted (jumped back or far ahead).
    pub fn restarts(&self) -> u64 {
        self.restarts.load(Ordering::Relaxed)
    }
    /// Reports whose `seq` repeated the previous one; skipped.
    pub fn repeated_reports(&self) -> u64 {
        self.repeated_reports.load(Ordering::Relaxed)
    }
    /// Reports not published because the lamp had no position yet.
    pub fn unpositioned_reports(&self) -> u64 {
        self.unpositioned_reports.load(Ordering::Relaxed)
    }
}

/// What one report's `seq` means for the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SeqStep {
    /// The next frame, after `lost` missing reports.
    Next { seq: u64, lost: u64 },
    /// The lamp's counter restarted; the stream continues at `seq`.
    Restart { seq: u64 },
    /// Same `seq` as the previous report.
    Repeat,
}

/// Unwraps the lamp's u32 `seq` into the stream's u64.
#[derive(Debug, Default)]
struct SeqUnwrapper {
    /// The previous report's raw and unwrapped `seq`.
    last: Option<(u32, u64)>,
    /// The port was reopened since the previous report: a repeated `seq` is then a lamp that
    /// rebooted, not a duplicate.
    reopened: bool,
}

impl SeqUnwrapper {
    fn reopened(&mut self) {
        self.reopened = true;
    }

    fn advance(&mut self, raw: u32) -> SeqStep {
        let reopened = std::mem::take(&mut self.reopened);
        let step = match self.last {
            None => SeqStep::Next {
                seq: u64::from(raw),
                lost: 0,
            },
            Some((last_raw, last)) => match u64::from(raw.wrapping_sub(last_raw)) {
                0 if !reopened => return SeqStep::Repeat,
                delta if (1..=MAX_COUNTED_GAP + 1).contains(&delta) => SeqStep::Next {
                    seq: last.saturating_add(delta),
                    lost: delta - 1,
                },
                _ => SeqStep::Restart {
                    seq: last.saturating_add(1),
                },
            },
        };
        let (SeqStep::Next { seq, .. } | SeqStep::Restart { seq }) = step else {
            return step;
        };
        self.last = Some((raw, seq));
        step
    }
}

/// The pocket lamp on a serial port. See the module documentation.
pub struct SerialLamp {
    config: LampConfig,
    usb_id: Option<(u16, u16)>,
    markers: Topic<Shared<MarkerSet>>,
    positioner: Box<dyn LampPositioner>,
    port: Option<Box<dyn serialport::SerialPort>>,
    parser: LineParser,
    buf: [u8; READ_CHUNK],
    /// Good reports read but not yet returned, with their arrival time.
    ready: VecDeque<(LampReport, u64)>,
    seq: SeqUnwrapper,
    /// Lost reports still to be reported as drops, one per `read`.
    lost_pending: u64,
    position_in_world: Option<Vec3>,
    /// `(seq, host_ns)` of the marker frame last given to the positioner.
    markers_seen: Option<(u64, u64)>,
    counters: Arc<LampCounters>,
    /// Whether this connection already warned about a bad line.
    warned_bad_line: bool,
    warned_unpositioned: bool,
}

impl fmt::Debug for SerialLamp {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SerialLamp")
            .field("config", &self.config)
            .field("open", &self.port.is_some())
            .field("position_in_world", &self.position_in_world)
            .field("counters", &self.counters)
            .finish_non_exhaustive()
    }
}

impl SerialLamp {
    /// A lamp that reads its marker from `markers` (the bus's `markers` topic) through
    /// `positioner`. `Config` error when a key is invalid.
    pub fn new(
        config: LampConfig,
        markers: Topic<Shared<MarkerSet>>,
        positioner: impl LampPositioner,
    ) -> Result<Self, DeviceError> {
        config.validate()?;
        Ok(Self {
            usb_id: config.parsed_usb_id()?,
            config,
            markers,
            positioner: Box::new(positioner),
            port: None,
            parser: LineParser::new(),
            buf: [0; READ_CHUNK],
            ready: VecDeque::new(),
            seq: SeqUnwrapper::default(),
            lost_pending: 0,
            position_in_world: None,
            markers_seen: None,
            counters: Arc::default(),
            warned_bad_line: false,
            warned_unpositioned: false,
        })
    }

    /// The daemon's constructor: the lamp on `bus`, positioned by [`MarkerPositioner`] with the
    /// rig's `lamp_marker_from_light` and the camera pose `world_from_camera`.
    pub fn on_bus(
        config: LampConfig,
        bus: &Bus,
        rig: &RigCalibration,
        world_from_camera: impl WorldFromCamera,
    ) -> Result<Self, DeviceError> {
        let positioner = MarkerPositioner::new(&config, rig, world_from_camera);
        Self::new(config, bus.markers.clone(), positioner)
    }

    pub fn config(&self) -> &LampConfig {
        &self.config
    }

    /// The USB-serial adapter's (vendor, product) IDs from `usb_id`, for a hot-plug filter.
    pub fn usb_id(&self) -> Option<(u16, u16)> {
        self.usb_id
    }

    /// The lamp's counters, shared with the device thread.
    pub fn counters(&self) -> Arc<LampCounters> {
        self.counters.clone()
    }

    fn error(&self, kind: fn(String, String) -> DeviceError, reason: String) -> DeviceError {
        kind(format!("{BACKEND} {}", self.config.port.display()), reason)
    }

    fn not_found(&self, reason: String) -> DeviceError {
        self.error(
            |device, reason| DeviceError::NotFound { device, reason },
            reason,
        )
    }

    fn config_error(&self, reason: String) -> DeviceError {
        self.error(
            |device, reason| DeviceError::Config { device, reason },
            reason,
        )
    }

    fn disconnected(&self, reason: String) -> DeviceError {
        self.error(
            |device, reason| DeviceError::Disconnected { device, reason },
            reason,
        )
    }

    /// Maps a failed `serialport` open to the device contract. `serialport` keeps only the
    /// errno's text for most errors, so the two that can never work are recognised by it.
    fn open_error(&self, error: serialport::Error) -> DeviceError {
        use serialport::ErrorKind;
        match error.kind() {
            ErrorKind::Io(io::ErrorKind::NotFound) => {
                self.not_found(format!("{error} (unplugged?)"))
            }
            ErrorKind::Io(io::ErrorKind::PermissionDenied) => self.not_found(format!(
                "{error}: is the daemon's user in the port's group (dialout)?"
            )),
            ErrorKind::NoDevice => self.not_found(format!("{error} (in use by another program?)")),
            ErrorKind::InvalidInput => self.config_error(error.to_string()),
            ErrorKind::Unknown if ENOTTY_TEXT.contains(&error.description.as_str()) => {
                self.config_error(format!("not a terminal device ({error})"))
            }
            ErrorKind::Unknown if error.description == "Invalid argument" => {
                self.config_error(format!("the driver refuses these settings ({error})"))
            }
            _ => self.not_found(error.to_string()),
        }
    }

    /// One read from the port into the parser; good reports are queued in `ready`.
    fn fill(&mut self) -> Result<(), DeviceError> {
        let Some(port) = self.port.as_mut() else {
            return Err(self.disconnected("read before open".into()));
        };
        let read = port.read(&mut self.buf);
        let arrival_ns = host_now_ns();
        let n = match read {
            Ok(0) => return Err(self.disconnected("end of file: the port hung up".into())),
            Ok(n) => n.min(self.buf.len()),
            Err(error)
                if matches!(
                    error.kind(),
                    io::ErrorKind::TimedOut
                        | io::ErrorKind::WouldBlock
                        | io::ErrorKind::Interrupted
                ) =>
            {
                return Ok(());
            }
            Err(error) => {
                return Err(self.disconnected(format!("read: {error} (unplugged?)")));
            }
        };
        let bytes = self.buf.get(..n).unwrap_or_default();
        for result in self.parser.push(bytes) {
            match result {
                Ok(report) => {
                    self.counters.reports.fetch_add(1, Ordering::Relaxed);
                    self.ready.push_back((report, arrival_ns));
                }
                Err(error) => self.bad_line(&error),
            }
        }
        Ok(())
    }

    fn bad_line(&mut self, error: &LineError) {
        self.counters.bad_lines.fetch_add(1, Ordering::Relaxed);
        if self.warned_bad_line {
            tracing::trace!(port = %self.config.port.display(), %error, "bad lamp line skipped");
        } else {
            self.warned_bad_line = true;
            tracing::warn!(
                port = %self.config.port.display(),
                baud = self.config.baud,
                %error,
                "bad lamp line skipped (further ones are only counted); noise suggests a wrong `baud`"
            );
        }
    }

    /// The light's position for the next frame: from the newest marker frame when it shows the
    /// lamp, else the last known one, else the configured fallback.
    fn locate(&mut self) -> Option<Vec3> {
        if let Some(markers) = self.markers.latest() {
            let key = (markers.seq, markers.stamp.host_ns);
            if self.markers_seen != Some(key) {
                self.markers_seen = Some(key);
                if let Some(p) = self
                    .positioner
                    .position_in_world(&markers)
                    .filter(|p| p.is_finite())
                {
                    self.position_in_world = Some(p);
                }
            }
        }
        self.position_in_world
            .or(self.config.fallback_position.map(Vec3::from))
    }
}

impl FrameSource for SerialLamp {
    type Payload = LampState;

    fn backend(&self) -> &'static str {
        BACKEND
    }

    fn stream(&self) -> StreamKind {
        StreamKind::Lamp
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        self.close();
        let path = &self.config.port;
        let metadata = match std::fs::metadata(path) {
            Ok(metadata) => metadata,
            Err(error) if error.kind() == io::ErrorKind::NotFound => {
                return Err(self.not_found("no such device (unplugged?)".into()));
            }
            Err(error) => return Err(self.not_found(error.to_string())),
        };
        let file_type = metadata.file_type();
        if !file_type.is_char_device() {
            let what = if file_type.is_dir() {
                "a directory"
            } else if file_type.is_file() {
                "a regular file"
            } else {
                "not a character device"
            };
            return Err(self.config_error(format!("not a serial port: {what}")));
        }
        let Some(path) = path.to_str() else {
            return Err(self.config_error("the path is not valid UTF-8".into()));
        };
        let port = serialport::new(path, self.config.baud)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(Duration::from_millis(self.config.timeout_ms))
            .open()
            .map_err(|error| self.open_error(error))?;
        self.port = Some(port);
        self.parser.reset();
        self.seq.reopened();
        self.warned_bad_line = false;
        tracing::info!(port = %self.config.port.display(), baud = self.config.baud, "lamp port open");
        Ok(())
    }

    fn read(&mut self, frame: &mut Frame<LampState>) -> Result<Capture, DeviceError> {
        if self.lost_pending > 0 {
            self.lost_pending -= 1;
            return Err(DeviceError::BadData {
                device: format!("{BACKEND} {}", self.config.port.display()),
                reason: "a lamp report never arrived (gap in seq)".into(),
            });
        }
        if self.ready.is_empty() {
            self.fill()?;
        }
        let Some((report, arrival_ns)) = self.ready.pop_front() else {
            return Ok(Capture::Idle);
        };
        let seq = match self.seq.advance(report.seq) {
            SeqStep::Next { seq, lost } => {
                if lost > 0 {
                    self.counters
                        .lost_reports
                        .fetch_add(lost, Ordering::Relaxed);
                    self.lost_pending = lost;
                }
                seq
            }
            SeqStep::Restart { seq } => {
                self.counters.restarts.fetch_add(1, Ordering::Relaxed);
                tracing::info!(
                    port = %self.config.port.display(),
                    lamp_seq = report.seq,
                    "lamp seq restarted (lamp rebooted?)"
                );
                seq
            }
            SeqStep::Repeat => {
                self.counters
                    .repeated_reports
                    .fetch_add(1, Ordering::Relaxed);
                tracing::debug!(lamp_seq = report.seq, "repeated lamp report skipped");
                return Ok(Capture::Idle);
            }
        };
        let Some(position_in_world) = self.locate() else {
            self.counters
                .unpositioned_reports
                .fetch_add(1, Ordering::Relaxed);
            if !self.warned_unpositioned {
                self.warned_unpositioned = true;
                tracing::info!(
                    marker_id = self.config.marker_id,
                    "lamp marker not seen yet; its reports wait for it (or set `fallback_position`)"
                );
            }
            return Ok(Capture::Idle);
        };
        frame.seq = seq;
        frame.stamp = Timestamp::new(arrival_ns, arrival_ns);
        frame.payload = report.state(position_in_world, self.config.max_intensity_w_sr);
        Ok(Capture::Frame)
    }

    fn close(&mut self) {
        if self.port.take().is_some() {
            tracing::debug!(port = %self.config.port.display(), "lamp port closed");
        }
    }
}

impl LampTracker for SerialLamp {}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;
    use relight_core::MarkerDetection;

    #[test]
    fn seq_unwraps_across_the_u32_wrap_and_counts_gaps() {
        let mut seq = SeqUnwrapper::default();
        let start = u32::MAX - 2;
        assert_eq!(
            seq.advance(start),
            SeqStep::Next {
                seq: u64::from(start),
                lost: 0
            }
        );
        assert_eq!(
            seq.advance(u32::MAX),
            SeqStep::Next {
                seq: u64::from(u32::MAX),
                lost: 1
            }
        );
        assert_eq!(
            seq.advance(0),
            SeqStep::Next {
                seq: 1 << 32,
                lost: 0
            }
        );
        assert_eq!(
            seq.advance(3),
            SeqStep::Next {
                seq: (1 << 32) + 3,
                lost: 2
            }
        );
        assert_eq!(seq.advance(3), SeqStep::Repeat);
        assert_eq!(
            seq.advance(4),
            SeqStep::Next {
                seq: (1 << 32) + 4,
                lost: 0
            }
        );
    }

    #[test]
    fn a_rebooted_lamp_restarts_without_lost_reports() {
        let mut seq = SeqUnwrapper::default();
        seq.advance(1000);
        assert_eq!(seq.advance(0), SeqStep::Restart { seq: 1001 });
        assert_eq!(seq.advance(1), SeqStep::Next { seq: 1002, lost: 0 });
        // After a reopen, the same `seq` again is a lamp that rebooted right after sending it.
        seq.reopened();
        assert_eq!(seq.advance(1), SeqStep::Restart { seq: 1003 });
        assert_eq!(seq.advance(1), SeqStep::Repeat);
        // A forward jump too long to be losses on the line is a restart too.
        let far = 1 + u32::try_from(MAX_COUNTED_GAP).unwrap() + 1;
        assert_eq!(seq.advance(1 + far), SeqStep::Restart { seq: 1004 });
        let longest = 1 + far + u32::try_from(MAX_COUNTED_GAP).unwrap() + 1;
        assert_eq!(
            seq.advance(longest),
            SeqStep::Next {
                seq: 1004 + MAX_COUNTED_GAP + 1,
                lost: MAX_COUNTED_GAP
            }
        );
    }

    fn detection(
        family: &str,
        marker_id: u32,
        rms: f32,
        camera_from_marker: Pose,
    ) -> MarkerDetection {
        MarkerDetection {
            family: family.into(),
            marker_id,
            corners_px: [glam::Vec2::ZERO; 4],
            camera_from_marker,
            reprojection_rms_px: rms,
        }
    }

    #[test]
    fn marker_positioner_chains_world_camera_marker_and_light() {
        let world_from_camera = Pose::new(Quat::from_rotation_y(0.7), Vec3::new(1.0, 1.5, 2.0));
        let camera_from_marker = Pose::new(Quat::from_rotation_x(-0.4), Vec3::new(0.1, -0.2, -1.2));
        let lamp_marker_from_light = Pose::from_translation(Vec3::new(0.0, 0.05, -0.03));
        let mut positioner = MarkerPositioner {
            marker_id: 7,
            family: Some("tag36h11".into()),
            lamp_marker_from_light,
            world_from_camera,
        };
        let elsewhere = Pose::from_translation(Vec3::splat(9.0));
        let markers = Frame::new(
            1,
            Timestamp::default(),
            MarkerSet {
                detections: vec![
                    detection("tag36h11", 3, 0.1, elsewhere),
                    detection("aruco_4x4_50", 7, 0.1, elsewhere),
                    detection("tag36h11", 7, 2.0, elsewhere),
                    detection("tag36h11", 7, 0.3, camera_from_marker),
                ],
            },
        );
        let expected = world_from_camera.transform_point(
            camera_from_marker.transform_point(lamp_marker_from_light.translation),
        );
        let got = positioner.position_in_world(&markers).unwrap();
        assert!((got - expected).length() < 1e-5, "{got} vs {expected}");

        let unseen = Frame::new(2, Timestamp::default(), MarkerSet::default());
        assert_eq!(positioner.position_in_world(&unseen), None);
        // A broken pose never becomes a position.
        let nan = Pose {
            rotation: Quat::IDENTITY,
            translation: Vec3::NAN,
        };
        let broken = Frame::new(
            3,
            Timestamp::default(),
            MarkerSet {
                detections: vec![detection("tag36h11", 7, 0.1, nan)],
            },
        );
        assert_eq!(positioner.position_in_world(&broken), None);
    }

    #[test]
    fn the_board_detection_gives_the_camera_in_the_world() {
        let world_from_camera = Pose::new(Quat::from_rotation_z(0.3), Vec3::new(0.4, 0.0, 1.1));
        let camera_from_board = world_from_camera.inverse();
        let camera_from_marker = Pose::from_translation(Vec3::new(0.0, 0.1, -0.9));
        let markers = Frame::new(
            1,
            Timestamp::default(),
            MarkerSet {
                detections: vec![
                    detection("tag36h11", 0, 0.1, Pose::IDENTITY),
                    detection("desk-board", 0, 0.4, camera_from_board),
                    detection("tag36h11", 7, 0.2, camera_from_marker),
                ],
            },
        );
        let mut positioner = MarkerPositioner {
            marker_id: 7,
            family: Some("tag36h11".into()),
            lamp_marker_from_light: Pose::IDENTITY,
            world_from_camera: BoardPose::new("desk-board"),
        };
        let got = positioner.position_in_world(&markers).unwrap();
        let expected = world_from_camera.transform_point(camera_from_marker.translation);
        assert!((got - expected).length() < 1e-5, "{got} vs {expected}");
        // No board in view: no world, so no position from this frame.
        let mut other_board = positioner.clone();
        other_board.world_from_camera = BoardPose::new("wall-board");
        assert_eq!(other_board.position_in_world(&markers), None);
    }

    #[test]
    fn invalid_keys_are_config_errors() {
        let ok = LampConfig::new("/dev/ttyACM0", 2.0, 5);
        assert!(ok.validate().is_ok());
        let cases: [(&str, LampConfig); 6] = [
            (
                "baud",
                LampConfig {
                    baud: 0,
                    ..ok.clone()
                },
            ),
            (
                "max_intensity_w_sr",
                LampConfig {
                    max_intensity_w_sr: f32::NAN,
                    ..ok.clone()
                },
            ),
            (
                "timeout_ms",
                LampConfig {
                    timeout_ms: 0,
                    ..ok.clone()
                },
            ),
            (
                "fallback_position",
                LampConfig {
                    fallback_position: Some([0.0, f32::INFINITY, 0.0]),
                    ..ok.clone()
                },
            ),
            (
                "usb_id",
                LampConfig {
                    usb_id: Some("10c4-ea60".into()),
                    ..ok.clone()
                },
            ),
            ("port", LampConfig::new("", 2.0, 5)),
        ];
        for (key, config) in cases {
            let error = config.validate().unwrap_err();
            assert!(
                matches!(&error, DeviceError::Config { reason, .. } if reason.contains(key)),
                "{key}: {error}"
            );
        }
        let with_id = LampConfig {
            usb_id: Some("10C4:ea60".into()),
            ..ok
        };
        assert_eq!(with_id.parsed_usb_id().unwrap(), Some((0x10c4, 0xea60)));
    }
}
