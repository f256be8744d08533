//! `[freenect]`: Kinect v1 depth and colour through libfreenect (OpenKinect; Debian
//! `libfreenect-dev`, `libfreenect.so.0.5`).
//!
//! - **Linking.** A small hand-written FFI (`ffi.rs`) against the C API, linked at build time:
//!   the feature has no dependencies.
//! - **One device, one or two streams.** The daemon asks for depth, colour or both; both come
//!   from one context and one device, opened with the camera subdevice only (tilt motor and LED
//!   are left alone, and stay free for other programs).
//! - **Depth** is published as `DepthU16Mm` 640 × 480 (0 = no measurement). By default
//!   (`depth_mode = "auto"`) it is `FREENECT_DEPTH_REGISTERED` — millimetres, already warped
//!   into the RGB camera by the device's factory calibration — when the library offers it;
//!   otherwise, and always under fakenect (whose dumps hold 11-bit codes and which computes mm
//!   only from a dump's `device.json`), `FREENECT_DEPTH_11BIT` converted with [`disparity`]
//!   (that depth is in the IR camera's view, not registered to colour: a WARN says so). **Colour** is `FREENECT_VIDEO_RGB` 640 × 480, published as `Rgb8`.
//! - **Time.** `device_ns` comes from the Kinect's 60 MHz frame counter, unwrapped; `seq` counts
//!   frames by that clock, so frames lost on the bus leave gaps (`clock.rs`); `host_ns` is
//!   the host clock when the frame's callback ran.
//! - **Failure contract.** No Kinect, or one that cannot be claimed → `NotFound` (retried). A
//!   mode the library does not offer → `Config`. A negative return from
//!   `freenect_process_events_timeout` (libusb error) or no frame for `stall_timeout_ms` (a
//!   pulled cable often shows as silence) → `Disconnected`.
//! - **fakenect.** Under libfreenect's replay library (see [`library_is_fakenect`]) every call
//!   is guarded so that fakenect's `exit()` paths become typed errors, and the end of the dump is
//!   `RunEnd::EndOfStream` (details in `fakenect.rs`). [`dump`] writes dumps from the simulator.
//!
//! **Testing against fakenect.** A binary linked to libfreenect runs against fakenect when the
//! dynamic loader finds fakenect's `libfreenect.so.0.5` first: start it with
//! `LD_LIBRARY_PATH=/usr/lib/<multiarch>/fakenect` and `FAKENECT_PATH=<dump dir>`. A test
//! binary does that by re-executing itself (`std::env::current_exe()` with `--exact <inner
//! test> --ignored`) for inner tests that are `#[ignore]`d and return at once unless a marker
//! variable says they run as such a child — see `backends/tests/freenect.rs`.

mod clock;
pub mod disparity;
pub mod dump;
mod fakenect;
mod ffi;

use std::ffi::CString;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use relight_core::bus::FramePool;
use relight_core::{Image, PixelFormat, StreamKind, StreamMessage, Timestamp};
use serde::Deserialize;

pub use clock::KINECT_CLOCK_HZ;
pub use ffi::library_is_fakenect;

use crate::device::{Device, DeviceContext, DeviceError, RunEnd};
use clock::StreamClock;
use fakenect::{Claim, Consumed, FrameLayout, Next};
use ffi::{FrameMode, OpenError, Selector, Session};

/// How long one `freenect_process_events_timeout` call may wait; bounds the reaction to a stop
/// request (fakenect ignores it and sleeps the dump's own frame gaps instead).
const EVENT_TIMEOUT: Duration = Duration::from_millis(100);

/// `LIBUSB_ERROR_INTERRUPTED`: a signal cut the wait short; not a device problem.
const LIBUSB_ERROR_INTERRUPTED: i32 = -10;

/// Which depth the Kinect delivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthMode {
    /// `registered` where the library offers it (never under fakenect), else `raw11`.
    #[default]
    Auto,
    /// `FREENECT_DEPTH_REGISTERED`: mm, in the RGB camera's view (factory calibration).
    Registered,
    /// `FREENECT_DEPTH_MM`: mm, in the IR camera's view.
    Mm,
    /// `FREENECT_DEPTH_11BIT`: raw codes, converted to mm with [`disparity`]; IR camera view.
    Raw11,
}

/// The `[freenect]` table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FreenectConfig {
    /// Which Kinect, by libfreenect's enumeration order (0 = first). Ignored when `serial` is
    /// set.
    #[serde(default)]
    pub index: u32,
    /// The camera's serial number, to pick one of several Kinects whatever their USB order.
    #[serde(default)]
    pub serial: Option<String>,
    /// Publish depth (default true).
    #[serde(default = "yes")]
    pub depth: bool,
    /// Publish colour (default true).
    #[serde(default = "yes")]
    pub color: bool,
    /// `auto` (default), `registered`, `mm` or `raw11`; see [`DepthMode`].
    #[serde(default)]
    pub depth_mode: DepthMode,
    /// No frame on any stream for this long means the Kinect is gone (default 3000 ms).
    #[serde(default = "default_stall_timeout_ms")]
    pub stall_timeout_ms: u64,
    /// Frames per stream that consumers may hold at once before capture drops (default 8):
    /// size it above the bus subscribers' queue capacities.
    #[serde(default = "default_pool_frames")]
    pub pool_frames: usize,
}

fn yes() -> bool {
    true
}
fn default_stall_timeout_ms() -> u64 {
    3000
}
fn default_pool_frames() -> usize {
    8
}

impl Default for FreenectConfig {
    fn default() -> Self {
        Self {
            index: 0,
            serial: None,
            depth: true,
            color: true,
            depth_mode: DepthMode::Auto,
            stall_timeout_ms: default_stall_timeout_ms(),
            pool_frames: default_pool_frames(),
        }
    }
}

/// How a depth frame's `u16`s become millimetres.
#[derive(Debug)]
enum DepthDecode {
    Millimetres,
    /// Raw code → mm table.
    Raw11(Vec<u16>),
}

/// One stream of an open device.
#[derive(Debug)]
struct Stream {
    mode: FrameMode,
    clock: StreamClock,
    pool: FramePool<Image>,
}

impl Stream {
    fn new(mode: FrameMode, format: PixelFormat, pool_frames: usize) -> Self {
        Self {
            mode,
            clock: StreamClock::new(mode.framerate()),
            pool: FramePool::with_init(pool_frames, || {
                Image::new(mode.width(), mode.height(), format)
            }),
        }
    }

    fn layout(&self) -> FrameLayout {
        FrameLayout {
            width: self.mode.width(),
            height: self.mode.height(),
            bytes: self.mode.bytes(),
        }
    }
}

/// A Kinect v1 through libfreenect.
#[derive(Debug)]
pub struct FreenectDevice {
    config: FreenectConfig,
    label: String,
    selector: Selector,
    depth: Option<Stream>,
    color: Option<Stream>,
    depth_decode: DepthDecode,
    session: Option<Session>,
    playback: Option<Claim>,
}

impl FreenectDevice {
    /// Check the configuration; nothing is opened until [`Device::open`].
    pub fn new(config: FreenectConfig) -> Result<Self, DeviceError> {
        let label = match &config.serial {
            Some(serial) => format!("freenect (serial {serial})"),
            None => format!("freenect #{}", config.index),
        };
        let invalid = |reason: &str| DeviceError::Config {
            device: label.clone(),
            reason: reason.into(),
        };
        if !config.depth && !config.color {
            return Err(invalid("neither `depth` nor `color` is enabled"));
        }
        if config.stall_timeout_ms == 0 {
            return Err(invalid("`stall_timeout_ms` must be positive"));
        }
        if config.pool_frames == 0 {
            return Err(invalid("`pool_frames` must be at least 1"));
        }
        let selector = match &config.serial {
            Some(serial) => Selector::Serial(
                CString::new(serial.as_str())
                    .map_err(|_| invalid("`serial` contains a NUL character"))?,
            ),
            None => Selector::Index(config.index),
        };
        Ok(Self {
            config,
            label,
            selector,
            depth: None,
            color: None,
            depth_decode: DepthDecode::Millimetres,
            session: None,
            playback: None,
        })
    }

    fn error_config(&self, reason: String) -> DeviceError {
        DeviceError::Config {
            device: self.label.clone(),
            reason,
        }
    }

    /// Pick the modes from what the library offers; `Config` when the wanted one is missing.
    fn choose_modes(
        &self,
        fakenect: bool,
    ) -> Result<(Option<FrameMode>, Option<FrameMode>, DepthMode, DepthDecode), DeviceError> {
        let medium = |m: &FrameMode| m.is_valid() && m.resolution() == ffi::RESOLUTION_MEDIUM;
        let mut decode = DepthDecode::Millimetres;
        let mut chosen = self.config.depth_mode;
        let depth = if self.config.depth {
            let offered: Vec<FrameMode> = ffi::depth_modes().into_iter().filter(medium).collect();
            let find = |format| offered.iter().copied().find(|m| m.format() == format);
            // fakenect computes mm (newer versions) only from the registration data of a
            // dump's `device.json`, and dereferences missing tables without it.
            let registration_data = !fakenect
                || std::env::var_os("FAKENECT_PATH")
                    .is_some_and(|dir| PathBuf::from(dir).join("device.json").is_file());
            chosen = match self.config.depth_mode {
                DepthMode::Auto if fakenect => DepthMode::Raw11,
                DepthMode::Auto if find(ffi::DEPTH_REGISTERED).is_some() => DepthMode::Registered,
                DepthMode::Auto => DepthMode::Raw11,
                explicit => explicit,
            };
            let wanted = match chosen {
                DepthMode::Registered if registration_data => find(ffi::DEPTH_REGISTERED),
                DepthMode::Mm if registration_data => find(ffi::DEPTH_MM),
                DepthMode::Raw11 => find(ffi::DEPTH_11BIT),
                _ => None,
            };
            let Some(mode) = wanted else {
                let names: Vec<&str> = offered
                    .iter()
                    .map(|m| depth_format_name(m.format()))
                    .collect();
                return Err(self.error_config(format!(
                    "depth_mode `{chosen:?}` is not available from this libfreenect{} \
                     (640×480 depth modes: {})",
                    if fakenect {
                        " (fakenect: 11-bit dumps, mm only with the dump's device.json)"
                    } else {
                        ""
                    },
                    names.join(", ")
                )));
            };
            if mode.bytes() != mode.width() as usize * mode.height() as usize * 2 {
                return Err(self.error_config(format!(
                    "depth mode {} has an unexpected layout ({} bytes for {}×{})",
                    depth_format_name(mode.format()),
                    mode.bytes(),
                    mode.width(),
                    mode.height()
                )));
            }
            if mode.format() == ffi::DEPTH_11BIT {
                decode = DepthDecode::Raw11(disparity::raw_to_mm_table());
            }
            Some(mode)
        } else {
            None
        };
        let color = if self.config.color {
            let mode = ffi::video_modes()
                .into_iter()
                .find(|m| medium(m) && m.format() == ffi::VIDEO_RGB)
                .ok_or_else(|| {
                    self.error_config("this libfreenect offers no 640×480 RGB mode".into())
                })?;
            if mode.bytes() != mode.width() as usize * mode.height() as usize * 3 {
                return Err(self.error_config(format!(
                    "RGB mode has an unexpected layout ({} bytes for {}×{})",
                    mode.bytes(),
                    mode.width(),
                    mode.height()
                )));
            }
            Some(mode)
        } else {
            None
        };
        Ok((depth, color, chosen, decode))
    }

    /// Publish what the callbacks landed; true when any frame arrived.
    fn publish_landed(&mut self, ctx: &DeviceContext) -> bool {
        let Some(session) = self.session.as_mut() else {
            return false;
        };
        let sink = session.sink();
        let mut arrived = false;
        if let Some(stream) = self.depth.as_mut() {
            let landing = &mut sink.depth;
            for _ in 0..std::mem::take(&mut landing.overwritten) {
                ctx.count_drop();
            }
            if std::mem::take(&mut landing.fresh) {
                arrived = true;
                let (seq, device_ns) = stream.clock.frame(landing.ticks);
                let (width, height) = (stream.mode.width(), stream.mode.height());
                match stream.pool.acquire() {
                    Some(mut slot) => {
                        slot.seq = seq;
                        slot.stamp = Timestamp::new(device_ns, landing.host_ns);
                        slot.payload.reshape(width, height, PixelFormat::DepthU16Mm);
                        if let Some(depth_mm) = slot.payload.as_u16_mut() {
                            decode_depth(&landing.bytes, &self.depth_decode, depth_mm);
                        }
                        ctx.publish(StreamMessage::Depth(slot.share()));
                    }
                    None => ctx.count_drop(),
                }
            }
        }
        if let Some(stream) = self.color.as_mut() {
            let landing = &mut sink.video;
            for _ in 0..std::mem::take(&mut landing.overwritten) {
                ctx.count_drop();
            }
            if std::mem::take(&mut landing.fresh) {
                arrived = true;
                let (seq, device_ns) = stream.clock.frame(landing.ticks);
                let (width, height) = (stream.mode.width(), stream.mode.height());
                match stream.pool.acquire() {
                    Some(mut slot) => {
                        slot.seq = seq;
                        slot.stamp = Timestamp::new(device_ns, landing.host_ns);
                        slot.payload.reshape(width, height, PixelFormat::Rgb8);
                        if let Some(rgb) = slot.payload.as_u8_mut() {
                            let n = rgb.len().min(landing.bytes.len());
                            rgb[..n].copy_from_slice(&landing.bytes[..n]);
                        }
                        ctx.publish(StreamMessage::Color(slot.share()));
                    }
                    None => ctx.count_drop(),
                }
            }
        }
        arrived
    }
}

fn disconnected(device: &str, reason: String) -> DeviceError {
    DeviceError::Disconnected {
        device: device.to_string(),
        reason,
    }
}

/// libfreenect's `u16`s (host byte order; the frame may be unaligned, so it lands as bytes)
/// into millimetres.
fn decode_depth(bytes: &[u8], decode: &DepthDecode, out: &mut [u16]) {
    let values = bytes
        .chunks_exact(2)
        .map(|pair| u16::from_ne_bytes([pair[0], pair[1]]));
    match decode {
        DepthDecode::Millimetres => out.iter_mut().zip(values).for_each(|(o, v)| *o = v),
        DepthDecode::Raw11(table) => out
            .iter_mut()
            .zip(values)
            .for_each(|(o, v)| *o = table.get(usize::from(v)).copied().unwrap_or(0)),
    }
}

fn depth_format_name(format: i32) -> &'static str {
    match format {
        0 => "11bit",
        1 => "10bit",
        2 => "11bit_packed",
        3 => "10bit_packed",
        4 => "registered",
        5 => "mm",
        _ => "unknown",
    }
}

impl Device for FreenectDevice {
    fn backend(&self) -> &'static str {
        "freenect"
    }

    fn streams(&self) -> Vec<StreamKind> {
        let mut streams = Vec::new();
        if self.config.depth {
            streams.push(StreamKind::Depth);
        }
        if self.config.color {
            streams.push(StreamKind::Color);
        }
        streams
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        self.close();
        let fakenect = library_is_fakenect();
        // fakenect exits the process on a missing dump: check it before any call into it.
        let playback = if fakenect {
            Some(Claim::take(&self.label)?)
        } else {
            None
        };
        let (depth_mode, color_mode, chosen, decode) = self.choose_modes(fakenect)?;
        let session = Session::open(&self.selector, depth_mode, color_mode).map_err(|error| {
            let not_found = |reason: String| DeviceError::NotFound {
                device: self.label.clone(),
                reason,
            };
            match error {
                OpenError::Init(code) => {
                    not_found(format!("libfreenect could not start libusb (code {code})"))
                }
                OpenError::Open { code, devices } => not_found(format!(
                    "cannot open the Kinect (code {code}; libfreenect sees {devices} Kinect(s); \
                     is it plugged in, powered, and readable by this user — udev rules?)"
                )),
                OpenError::Mode { stream, code } => self.error_config(format!(
                    "the Kinect refused the {stream} mode (code {code})"
                )),
                OpenError::Start { stream, code } => {
                    not_found(format!("the {stream} stream did not start (code {code})"))
                }
            }
        })?;
        if let Some(mode) = depth_mode {
            if self.config.depth_mode == DepthMode::Auto
                && chosen == DepthMode::Raw11
                && self.config.color
            {
                tracing::warn!(
                    device = %self.label,
                    "no registered depth from this libfreenect{}: converting 11-bit codes to mm \
                     with a generic fit; depth is in the IR camera's view, not the colour's",
                    if fakenect { " (fakenect)" } else { "" }
                );
            }
            match self.depth.as_mut() {
                Some(stream) if stream.mode == mode => stream.clock.new_session(),
                _ => {
                    self.depth = Some(Stream::new(
                        mode,
                        PixelFormat::DepthU16Mm,
                        self.config.pool_frames,
                    ))
                }
            }
        }
        if let Some(mode) = color_mode {
            match self.color.as_mut() {
                Some(stream) if stream.mode == mode => stream.clock.new_session(),
                _ => {
                    self.color = Some(Stream::new(
                        mode,
                        PixelFormat::Rgb8,
                        self.config.pool_frames,
                    ))
                }
            }
        }
        self.depth_decode = decode;
        tracing::info!(
            device = %self.label,
            depth = ?depth_mode.map(|_| chosen),
            color = color_mode.is_some(),
            fakenect,
            "Kinect opened"
        );
        self.session = Some(session);
        self.playback = playback;
        Ok(())
    }

    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        let stall = Duration::from_millis(self.config.stall_timeout_ms);
        let mut last_frame = Instant::now();
        loop {
            if ctx.should_stop() {
                return Ok(RunEnd::StopRequested);
            }
            let Some(session) = self.session.as_mut() else {
                return Err(disconnected(
                    &self.label,
                    "run without an open device".into(),
                ));
            };
            let mut skipped = None;
            if let Some(playback) = &self.playback {
                let depth = self.depth.as_ref().map(Stream::layout);
                let color = self.color.as_ref().map(Stream::layout);
                match playback.next(depth, color) {
                    Next::Ready | Next::End => {}
                    Next::Missing(reason) => return Err(disconnected(&self.label, reason)),
                    Next::Malformed(reason) => {
                        // Let fakenect read the line with no stream running: it then skips
                        // the pixels.
                        session.set_streaming(false).map_err(|_| {
                            disconnected(&self.label, "could not pause fakenect's streams".into())
                        })?;
                        skipped = Some(reason);
                    }
                }
            }
            let code = session.process_events(EVENT_TIMEOUT);
            if skipped.is_some() {
                session.set_streaming(true).map_err(|_| {
                    disconnected(&self.label, "could not restart fakenect's streams".into())
                })?;
            }
            if let Some(playback) = &self.playback {
                match playback.consumed(code) {
                    Consumed::Line | Consumed::Looped => {}
                    Consumed::End => {
                        tracing::info!(device = %playback.device(), "end of the fakenect dump");
                        return Ok(RunEnd::EndOfStream);
                    }
                    Consumed::Unreadable(reason) => skipped = Some(reason),
                }
            } else if code < 0 && code != LIBUSB_ERROR_INTERRUPTED {
                return Err(disconnected(
                    &self.label,
                    format!("libfreenect event handling failed (libusb code {code})"),
                ));
            }
            if let Some(reason) = skipped {
                tracing::debug!(device = %self.label, %reason, "dropped a bad frame");
                ctx.count_drop();
            }
            if self.publish_landed(ctx) {
                last_frame = Instant::now();
            } else if last_frame.elapsed() > stall {
                return Err(disconnected(
                    &self.label,
                    format!("no frame for {} ms", last_frame.elapsed().as_millis()),
                ));
            }
        }
    }

    fn close(&mut self) {
        // The session first: fakenect must not be called once the claim is released.
        self.session = None;
        self.playback = None;
    }
}
