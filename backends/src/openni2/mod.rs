//! OpenNI2 depth and colour cameras (PrimeSense Carmine, Asus Xtion, Kinect through its driver),
//! and playback of OpenNI's `.oni` recordings, through Debian's libopenni2 (`libopenni2-dev`).
//!
//! One [`OpenNi2Device`] opens one OpenNI device and publishes the streams the daemon asks for
//! (depth, colour or both): depth as [`PixelFormat::DepthU16Mm`] (`ONI_PIXEL_FORMAT_DEPTH_1_MM`)
//! or [`PixelFormat::DepthF32M`] (`DEPTH_100_UM`, converted to metres), colour as
//! [`PixelFormat::Rgb8`] (`RGB888`). With both streams it asks the device to register depth to
//! the colour camera. Frames carry OpenNI's frame index as `seq` and its device timestamp (µs,
//! stored as ns); a jump in the index counts the missing frames as drops.
//!
//! A `uri` ending in `.oni` plays that recording through OpenNI's OniFile driver, at
//! `playback_speed`, once (then [`RunEnd::EndOfStream`]) or looping. [`record_oni`] writes such
//! recordings with OpenNI's own recorder.
//!
//! Drivers: OpenNI loads `lib*.so` from `OpenNI2/Drivers` next to `libOpenNI2.so` (on Debian
//! `/usr/lib/x86_64-linux-gnu/OpenNI2/Drivers`), or from the `Repository` of
//! `/etc/openni2/OpenNI.ini`. Debian ships the drivers as `lib*.so.0` in `libopenni2-0` and the
//! unversioned `lib*.so` links OpenNI's glob needs only in `libopenni2-dev`: without that package
//! (or equivalent links) initialisation fails with "Found no files matching …/lib*.so".
//! The `Dummy` URI opens OpenNI's DummyDevice driver (a synthetic 320 × 240 depth + colour
//! source at 30 fps), which is not enumerated: it is reached by name only.

mod ffi;
mod oni_file;

use std::ffi::c_int;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use relight_core::bus::FramePool;
use relight_core::{Image, PixelFormat, StreamKind, StreamMessage, Timestamp};
use serde::Deserialize;

use crate::device::{Device, DeviceContext, DeviceError, RunEnd};
use ffi::{
    DeviceHandle, FrameReceiver, OpenNi, RawFrame, SensorType, StreamId, VideoMode, pixel_format,
};

pub use ffi::DeviceInfo;

/// How long one wait for a frame may block, so a stop request is seen within this time.
const POLL: Duration = Duration::from_millis(50);
/// How long OpenNI's recorder thread may take to start.
const RECORDER_START_TIMEOUT: Duration = Duration::from_secs(2);
/// How long frames raised before the recorder started may take to reach the reader.
const RECORDER_SETTLE: Duration = Duration::from_millis(50);
/// How long to wait for frames still on their way after a recording ended.
const END_DRAIN: Duration = Duration::from_millis(100);
/// Drops counted for one gap at most; a larger jump is a device reset, not lost frames.
const MAX_GAP_DROPS: u64 = 100_000;

/// The depth encoding to ask the device for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum DepthFormat {
    /// `ONI_PIXEL_FORMAT_DEPTH_1_MM`, published as `DepthU16Mm`.
    #[serde(rename = "depth_1_mm")]
    Depth1Mm,
    /// `ONI_PIXEL_FORMAT_DEPTH_100_UM`, published as `DepthF32M` (metres).
    #[serde(rename = "depth_100_um")]
    Depth100Um,
}

impl DepthFormat {
    fn oni(self) -> c_int {
        match self {
            DepthFormat::Depth1Mm => pixel_format::DEPTH_1_MM,
            DepthFormat::Depth100Um => pixel_format::DEPTH_100_UM,
        }
    }
}

/// The `openni2` backend's settings (every key of its section but `backend`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OpenNi2Config {
    /// `uri`: the OpenNI device URI (as OpenNI enumerates it, e.g. `1d27/0601@1/5`), `Dummy`
    /// for OpenNI's synthetic DummyDevice, or a path to an `.oni` recording to play back.
    /// Default: the first device OpenNI enumerates.
    pub uri: Option<String>,
    /// `width`, `height`, `fps`: the video mode of every opened stream; each left out keeps the
    /// device's current value. A mode the sensor does not list is a configuration error.
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub fps: Option<u32>,
    /// `depth_format`: `"depth_1_mm"` (→ `depth_u16_mm`) or `"depth_100_um"` (→ `depth_f32_m`).
    /// Default: the device's current depth format if it is one of those, else 1 mm.
    pub depth_format: Option<DepthFormat>,
    /// `registration`: with both streams open, map depth onto the colour camera
    /// (`ONI_IMAGE_REGISTRATION_DEPTH_TO_COLOR`). A device without it logs and runs unregistered.
    /// Default true.
    pub registration: bool,
    /// `loop`: playback of an `.oni` file rewinds at the end instead of ending. Default false.
    #[serde(rename = "loop")]
    pub loop_playback: bool,
    /// `playback_speed`: multiple of recorded time for `.oni` playback (> 0). Default 1.
    pub playback_speed: f32,
    /// `stall_timeout_ms`: no frame on any stream for this long means the device is gone
    /// (reported `Lost`, then reopened). Default 5000.
    pub stall_timeout_ms: u64,
    /// `pool_frames`: frames per stream that consumers may hold at once before capture drops
    /// (and counts) frames. Default 32.
    pub pool_frames: usize,
}

impl Default for OpenNi2Config {
    fn default() -> Self {
        Self {
            uri: None,
            width: None,
            height: None,
            fps: None,
            depth_format: None,
            registration: true,
            loop_playback: false,
            playback_speed: 1.0,
            stall_timeout_ms: 5000,
            pool_frames: 32,
        }
    }
}

impl OpenNi2Config {
    /// What errors and logs call this device.
    fn label(&self) -> String {
        match &self.uri {
            Some(uri) => format!("openni2 {uri}"),
            None => "openni2 (first device)".to_owned(),
        }
    }

    /// The `.oni` recording the URI names, if it names one.
    fn recording_path(&self) -> Option<&Path> {
        self.uri
            .as_deref()
            .filter(|uri| {
                Path::new(uri)
                    .extension()
                    .is_some_and(|ext| ext.eq_ignore_ascii_case("oni"))
            })
            .map(Path::new)
    }

    fn validate(&self, streams: &[StreamKind]) -> Result<(), String> {
        if streams.is_empty() {
            return Err("no stream requested (depth, color or both)".into());
        }
        if let Some(other) = streams
            .iter()
            .find(|k| !matches!(k, StreamKind::Depth | StreamKind::Color))
        {
            return Err(format!("OpenNI2 supplies depth and color, not {other}"));
        }
        if self.uri.as_deref().is_some_and(str::is_empty) {
            return Err("uri is empty (leave it out for the first device)".into());
        }
        for (key, value) in [
            ("width", self.width),
            ("height", self.height),
            ("fps", self.fps),
        ] {
            if let Some(v) = value
                && (v == 0 || c_int::try_from(v).is_err())
            {
                return Err(format!("{key} must be a positive integer, got {v}"));
            }
        }
        if !(self.playback_speed.is_finite() && self.playback_speed > 0.0) {
            return Err(format!(
                "playback_speed must be a positive number, got {}",
                self.playback_speed
            ));
        }
        if self.stall_timeout_ms == 0 {
            return Err("stall_timeout_ms must be positive".into());
        }
        if self.pool_frames == 0 {
            return Err("pool_frames must be positive".into());
        }
        Ok(())
    }
}

/// OpenNI's device list, as `uri` values for [`OpenNi2Config`].
pub fn list_devices() -> Result<Vec<DeviceInfo>, DeviceError> {
    let label = "openni2";
    OpenNi::get()
        .and_then(|openni| openni.device_list())
        .map_err(|e| {
            openni_error(label, e, |reason| DeviceError::NotFound {
                device: label.into(),
                reason,
            })
        })
}

/// Maps an OpenNI failure to the device contract: OpenNI failing to start at all is a
/// configuration error (its drivers are missing); anything else is what `other` says.
fn openni_error(
    label: &str,
    error: ffi::OniError,
    other: impl FnOnce(String) -> DeviceError,
) -> DeviceError {
    if !error.is_initialisation() {
        return other(error.to_string());
    }
    let hint = if error.message.contains("Found no files matching") {
        " (OpenNI2 loads drivers named lib*.so; on Debian the links come with libopenni2-dev, \
         or set Repository in /etc/openni2/OpenNI.ini to a directory holding them)"
    } else {
        ""
    };
    DeviceError::Config {
        device: label.to_owned(),
        reason: format!("cannot initialise OpenNI2: {error}{hint}"),
    }
}

/// An open device with its started streams, in the order of `kinds`.
#[derive(Debug)]
struct Session {
    device: DeviceHandle,
    streams: Vec<StreamId>,
    kinds: Vec<StreamKind>,
    frames: FrameReceiver,
    /// Frames in the recording per stream, when playing a file once.
    playback_frames: Vec<Option<u32>>,
}

impl Session {
    fn open(config: &OpenNi2Config, kinds: &[StreamKind]) -> Result<Session, DeviceError> {
        let label = config.label();
        let config_error = |reason: String| DeviceError::Config {
            device: label.clone(),
            reason,
        };
        let not_found = |reason: String| DeviceError::NotFound {
            device: label.clone(),
            reason,
        };
        let openni = OpenNi::get().map_err(|e| config_error(e.to_string()))?;
        let device = match config.recording_path() {
            Some(path) => {
                // A recording that is not there (yet) may appear, like a device being plugged
                // in; one that is there but unreadable never becomes readable.
                let path = std::fs::canonicalize(path)
                    .map_err(|e| not_found(format!("recording {}: {e}", path.display())))?;
                let uri = path.to_str().ok_or_else(|| {
                    config_error(format!("recording path {} is not UTF-8", path.display()))
                })?;
                openni.open(Some(uri)).map_err(|e| {
                    openni_error(&label, e, |reason| {
                        config_error(format!(
                            "{} is not a readable OpenNI recording: {reason}",
                            path.display()
                        ))
                    })
                })?
            }
            None => openni.open(config.uri.as_deref()).map_err(|e| {
                openni_error(&label, e, |reason| {
                    let known = openni
                        .device_list()
                        .map(|list| list.into_iter().map(|d| d.uri).collect::<Vec<_>>())
                        .unwrap_or_default();
                    not_found(format!("{reason}; OpenNI enumerates {known:?}"))
                })
            })?,
        };
        let info = device.info().clone();
        let playback = device.is_playback();

        let mut streams = Vec::with_capacity(kinds.len());
        for &kind in kinds {
            let sensor = sensor_type(kind);
            let modes = device
                .sensor_modes(sensor)
                .map_err(|e| not_found(format!("cannot list the {kind} modes: {e}")))?
                .ok_or_else(|| config_error(format!("the device has no {kind} sensor")))?;
            let stream = device
                .create_stream(sensor)
                .map_err(|e| not_found(format!("cannot create the {kind} stream: {e}")))?;
            configure_mode(&device, stream, kind, config, &modes).map_err(&config_error)?;
            match device.is_mirroring_supported(stream) {
                Ok(true) => {
                    if let Err(error) = device.set_mirroring(stream, false) {
                        tracing::warn!(device = %label, stream = %kind, %error, "cannot turn mirroring off");
                    }
                }
                _ => {
                    tracing::debug!(device = %label, stream = %kind, "driver has no mirroring property");
                }
            }
            streams.push(stream);
        }

        if kinds.contains(&StreamKind::Depth)
            && kinds.contains(&StreamKind::Color)
            && config.registration
        {
            if !device.is_registration_supported().unwrap_or(false) {
                tracing::info!(device = %label, "device cannot register depth to colour; depth stays in its own camera");
            } else if let Err(error) = device.set_registration_depth_to_color() {
                tracing::warn!(device = %label, %error, "device refused depth-to-colour registration; depth stays in its own camera");
            } else {
                tracing::debug!(device = %label, "depth registered to the colour camera");
            }
        }

        let mut playback_frames = vec![None; kinds.len()];
        if playback {
            // Before any stream starts: OniFile's reader thread begins with the first one.
            if let Err(error) = device.set_playback_repeat(config.loop_playback) {
                tracing::warn!(device = %label, %error, "cannot set playback repeat");
            }
            if let Err(error) = device.set_playback_speed(config.playback_speed) {
                tracing::warn!(device = %label, %error, "cannot set playback speed");
            }
            if !config.loop_playback {
                for (count, &stream) in playback_frames.iter_mut().zip(&streams) {
                    *count = device.number_of_frames(stream).ok().filter(|&n| n > 0);
                }
            }
        }

        let frames = device
            .start(&streams)
            .map_err(|e| not_found(format!("cannot start streaming: {e}")))?;
        let modes: Vec<String> = streams
            .iter()
            .zip(kinds)
            .map(|(&s, k)| match device.video_mode(s) {
                Ok(m) => format!("{k} {}", describe_mode(&m)),
                Err(_) => format!("{k} (mode unknown)"),
            })
            .collect();
        tracing::info!(
            device = %label, uri = %info.uri, vendor = %info.vendor, name = %info.name,
            playback, ?modes, "OpenNI2 device open"
        );
        Ok(Session {
            device,
            streams,
            kinds: kinds.to_vec(),
            frames,
            playback_frames,
        })
    }

    /// Which of `kinds` a frame belongs to.
    fn lane_of(&self, frame: &RawFrame) -> Option<usize> {
        self.streams.iter().position(|&s| s == frame.stream)
    }
}

fn sensor_type(kind: StreamKind) -> SensorType {
    match kind {
        StreamKind::Color => SensorType::Color,
        _ => SensorType::Depth,
    }
}

fn describe_mode(mode: &VideoMode) -> String {
    format!(
        "{}x{}@{} {}",
        mode.resolution_x,
        mode.resolution_y,
        mode.fps,
        pixel_format::name(mode.pixel_format)
    )
}

/// Sets the stream's video mode to what `config` asks for (fields left out keep the current
/// value). A mode equal to the current one is not set again: some drivers (DummyDevice) offer
/// exactly one mode and refuse `VIDEO_MODE` writes altogether.
fn configure_mode(
    device: &DeviceHandle,
    stream: StreamId,
    kind: StreamKind,
    config: &OpenNi2Config,
    supported: &[VideoMode],
) -> Result<(), String> {
    let current = device
        .video_mode(stream)
        .map_err(|e| format!("cannot read the {kind} video mode: {e}"))?;
    let as_int = |v: Option<u32>, fallback: c_int| {
        v.and_then(|v| c_int::try_from(v).ok()).unwrap_or(fallback)
    };
    let format = match kind {
        StreamKind::Color => pixel_format::RGB888,
        _ => match config.depth_format {
            Some(format) => format.oni(),
            None if matches!(
                current.pixel_format,
                pixel_format::DEPTH_1_MM | pixel_format::DEPTH_100_UM
            ) =>
            {
                current.pixel_format
            }
            None => pixel_format::DEPTH_1_MM,
        },
    };
    let wanted = VideoMode {
        pixel_format: format,
        resolution_x: as_int(config.width, current.resolution_x),
        resolution_y: as_int(config.height, current.resolution_y),
        fps: as_int(config.fps, current.fps),
    };
    if wanted == current {
        return Ok(());
    }
    if !supported.contains(&wanted) {
        let listed: Vec<String> = supported.iter().map(describe_mode).collect();
        return Err(format!(
            "the {kind} sensor does not support {}; it supports {}",
            describe_mode(&wanted),
            if listed.is_empty() {
                "no listed mode".to_owned()
            } else {
                listed.join(", ")
            }
        ));
    }
    device
        .set_video_mode(stream, wanted)
        .map_err(|e| format!("cannot set the {kind} mode {}: {e}", describe_mode(&wanted)))
}

/// Turns OpenNI frame indices into the device's `seq`: the index itself, continued (not
/// restarted) when the index jumps back — a looping recording or a reopened device starts again
/// at 1 — so consumers never see `seq` go backwards.
#[derive(Debug, Default, Clone)]
struct SeqTracker {
    last_index: Option<i64>,
    offset: u64,
    last_seq: u64,
}

impl SeqTracker {
    /// The frame's `seq` and how many frames the index says were skipped before it.
    fn next(&mut self, index: i64) -> (u64, u64) {
        let index = index.max(0);
        let as_u64 = index.unsigned_abs();
        let missed = match self.last_index {
            Some(last) if index > last => (index - last - 1).unsigned_abs(),
            Some(_) => {
                self.offset = self.last_seq + 1 - as_u64;
                0
            }
            None => 0,
        };
        self.last_index = Some(index);
        self.last_seq = self.offset + as_u64;
        (self.last_seq, missed)
    }
}

/// Copies an OpenNI frame (rows `stride` bytes apart) into `out` as the relight pixel format
/// `kind` carries.
fn convert_frame(
    kind: StreamKind,
    format: c_int,
    width: i32,
    height: i32,
    stride: i32,
    data: &[u8],
    out: &mut Image,
) -> Result<(), String> {
    let (target, bytes_per_pixel) = match (kind, format) {
        (StreamKind::Depth, pixel_format::DEPTH_1_MM) => (PixelFormat::DepthU16Mm, 2),
        (StreamKind::Depth, pixel_format::DEPTH_100_UM) => (PixelFormat::DepthF32M, 2),
        (StreamKind::Color, pixel_format::RGB888) => (PixelFormat::Rgb8, 3),
        _ => {
            return Err(format!(
                "{kind} frame in {} is not supported",
                pixel_format::name(format)
            ));
        }
    };
    let (Ok(w), Ok(h), Ok(stride)) = (
        u32::try_from(width),
        u32::try_from(height),
        usize::try_from(stride),
    ) else {
        return Err(format!("frame size {width}x{height}, stride {stride}"));
    };
    if w == 0 || h == 0 {
        return Err(format!("empty frame {w}x{h}"));
    }
    let row_bytes = w as usize * bytes_per_pixel;
    let stride = if stride == 0 { row_bytes } else { stride };
    let needed = stride * (h as usize - 1) + row_bytes;
    if stride < row_bytes || data.len() < needed {
        return Err(format!(
            "{w}x{h} frame with stride {stride} needs {needed} bytes, got {}",
            data.len()
        ));
    }
    out.reshape(w, h, target);
    let rows = (0..h as usize).map(|y| &data[y * stride..y * stride + row_bytes]);
    match target {
        PixelFormat::DepthU16Mm => {
            let Some(dst) = out.as_u16_mut() else {
                return Err("depth image storage is not 16-bit".into());
            };
            for (dst_row, src_row) in dst.chunks_exact_mut(w as usize).zip(rows) {
                for (d, s) in dst_row.iter_mut().zip(src_row.chunks_exact(2)) {
                    *d = u16::from_ne_bytes([s[0], s[1]]);
                }
            }
        }
        PixelFormat::DepthF32M => {
            let Some(dst) = out.as_f32_mut() else {
                return Err("depth image storage is not f32".into());
            };
            for (dst_row, src_row) in dst.chunks_exact_mut(w as usize).zip(rows) {
                for (d, s) in dst_row.iter_mut().zip(src_row.chunks_exact(2)) {
                    *d = f32::from(u16::from_ne_bytes([s[0], s[1]])) * 1e-4;
                }
            }
        }
        _ => {
            let Some(dst) = out.as_u8_mut() else {
                return Err("colour image storage is not 8-bit".into());
            };
            for (dst_row, src_row) in dst.chunks_exact_mut(row_bytes).zip(rows) {
                dst_row.copy_from_slice(src_row);
            }
        }
    }
    Ok(())
}

/// Per-stream publishing state, kept across reopenings so `seq` keeps increasing.
#[derive(Debug)]
struct Lane {
    kind: StreamKind,
    pool: FramePool<Image>,
    seq: SeqTracker,
}

/// An OpenNI2 device (or `.oni` playback) as a relight [`Device`].
#[derive(Debug)]
pub struct OpenNi2Device {
    config: OpenNi2Config,
    label: String,
    lanes: Vec<Lane>,
    session: Option<Session>,
}

impl OpenNi2Device {
    /// Checks the configuration for the requested `streams` (depth, color or both); the device
    /// itself is opened by [`Device::open`].
    pub fn new(config: OpenNi2Config, streams: &[StreamKind]) -> Result<Self, DeviceError> {
        let label = config.label();
        let mut kinds = streams.to_vec();
        kinds.sort();
        kinds.dedup();
        config
            .validate(&kinds)
            .map_err(|reason| DeviceError::Config {
                device: label.clone(),
                reason,
            })?;
        let lanes = kinds
            .iter()
            .map(|&kind| Lane {
                kind,
                pool: FramePool::new(config.pool_frames),
                seq: SeqTracker::default(),
            })
            .collect();
        Ok(Self {
            config,
            label,
            lanes,
            session: None,
        })
    }

    /// The device OpenNI opened (its URI, vendor, name), while open.
    pub fn info(&self) -> Option<&DeviceInfo> {
        self.session.as_ref().map(|s| s.device.info())
    }

    fn lost(&self, reason: String) -> DeviceError {
        DeviceError::Disconnected {
            device: self.label.clone(),
            reason,
        }
    }
}

impl Device for OpenNi2Device {
    fn backend(&self) -> &'static str {
        "openni2"
    }

    fn streams(&self) -> Vec<StreamKind> {
        self.lanes.iter().map(|l| l.kind).collect()
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        self.session = None;
        let kinds = self.streams();
        self.session = Some(Session::open(&self.config, &kinds)?);
        Ok(())
    }

    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        let Some(mut session) = self.session.take() else {
            return Err(self.lost("run called on a closed device".into()));
        };
        let result = self.capture(&mut session, ctx);
        self.session = Some(session);
        result
    }

    fn close(&mut self) {
        self.session = None;
    }
}

impl OpenNi2Device {
    fn capture(
        &mut self,
        session: &mut Session,
        ctx: &DeviceContext,
    ) -> Result<RunEnd, DeviceError> {
        let stall_timeout = Duration::from_millis(self.config.stall_timeout_ms);
        let mut last_frame = Instant::now();
        let mut last_index = vec![None::<i64>; session.streams.len()];
        loop {
            if ctx.should_stop() {
                return Ok(RunEnd::StopRequested);
            }
            if let Some(reason) = session.device.events().lost() {
                return Err(self.lost(reason.into()));
            }
            let played_out =
                session
                    .playback_frames
                    .iter()
                    .zip(&last_index)
                    .all(|(total, last)| match (total, last) {
                        (Some(total), Some(last)) => *last >= i64::from(*total),
                        _ => false,
                    });
            if played_out || session.device.events().end_of_file() {
                // OniFile says so after raising its last frame; the OpenNI thread may still be
                // handing that frame over.
                while let Ok(Some(frame)) = session.frames.recv_timeout(END_DRAIN) {
                    self.publish(session, frame, ctx);
                }
                return Ok(RunEnd::EndOfStream);
            }
            match session.frames.recv_timeout(POLL) {
                Ok(Some(frame)) => {
                    if let Some((lane, index)) = self.publish(session, frame, ctx) {
                        last_index[lane] = Some(index);
                    }
                    last_frame = Instant::now();
                }
                Ok(None) => {}
                Err(ffi::StreamsClosed) => {
                    return Err(self.lost("OpenNI closed the streams".into()));
                }
            }
            if last_frame.elapsed() > stall_timeout {
                return Err(self.lost(format!(
                    "no frame for {} ms",
                    last_frame.elapsed().as_millis()
                )));
            }
        }
    }

    /// Publishes `frame` on its stream and gives its buffer back; returns the stream's lane
    /// and OpenNI's frame index.
    fn publish(
        &mut self,
        session: &Session,
        frame: RawFrame,
        ctx: &DeviceContext,
    ) -> Option<(usize, i64)> {
        let label = &self.label;
        let i = session.lane_of(&frame)?;
        let lane = self.lanes.get_mut(i)?;
        debug_assert_eq!(Some(&lane.kind), session.kinds.get(i));
        let index = frame.index;
        let (seq, missed) = lane.seq.next(index);
        if missed > 0 {
            tracing::debug!(device = %label, stream = %lane.kind, missed, index, "frame index gap");
            for _ in 0..missed.min(MAX_GAP_DROPS) {
                ctx.count_drop();
            }
        }
        let published = match lane.pool.acquire() {
            None => {
                tracing::trace!(device = %label, stream = %lane.kind, "frame pool exhausted; frame dropped");
                None
            }
            Some(mut slot) => match convert_frame(
                lane.kind,
                frame.pixel_format,
                frame.width,
                frame.height,
                frame.stride,
                &frame.data,
                &mut slot.payload,
            ) {
                Err(reason) => {
                    tracing::trace!(device = %label, stream = %lane.kind, %reason, "dropped a bad frame");
                    None
                }
                Ok(()) => {
                    slot.seq = seq;
                    slot.stamp =
                        Timestamp::new(frame.timestamp_us.saturating_mul(1000), frame.host_ns);
                    let shared = slot.share();
                    Some(match lane.kind {
                        StreamKind::Color => StreamMessage::Color(shared),
                        _ => StreamMessage::Depth(shared),
                    })
                }
            },
        };
        session.frames.recycle(frame);
        match published {
            Some(msg) => ctx.publish(msg),
            None => ctx.count_drop(),
        }
        Some((i, index))
    }
}

/// What [`record_oni`] wrote, as OpenNI reads the file back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordingSummary {
    pub path: PathBuf,
    /// Frames per recorded stream (`ONI_STREAM_PROPERTY_NUMBER_OF_FRAMES` of the file).
    pub frames: Vec<(StreamKind, u32)>,
}

impl RecordingSummary {
    pub fn frames(&self, kind: StreamKind) -> Option<u32> {
        self.frames
            .iter()
            .find(|(k, _)| *k == kind)
            .map(|&(_, n)| n)
    }
}

/// Records `streams` of the device `config` names into the `.oni` file `out` with OpenNI's
/// recorder (lossless: 16z for depth, uncompressed colour), until every stream has delivered
/// `frames` frames after the recorder started. OpenNI's recorder takes every frame the driver
/// raises while it runs, so a stream may hold a frame more than this reader saw; the summary
/// reports what the file holds. Streams of devices without a cropping property get the one
/// OpenNI's player needs to play them (see `oni_file`).
///
/// OpenNI's recorder starts on its own thread; frames count only once its start records are in
/// the file, and those already on their way then are let pass, so the file holds at least
/// `frames` frames of every stream (a few more when the driver raised some meanwhile).
///
/// Debian's OpenNI2 leaves one hazard here: the recorder's thread logs OpenNI errors when the
/// device lacks a property it records (DummyDevice lacks most), which puts the thread in the
/// error logger's per-thread map (see `ffi`), and a later new OpenNI-internal thread doing the
/// same probes it after it ended. One recording per process is safe.
pub fn record_oni(
    config: &OpenNi2Config,
    streams: &[StreamKind],
    out: &Path,
    frames: u32,
) -> Result<RecordingSummary, DeviceError> {
    let label = config.label();
    let config_error = |reason: String| DeviceError::Config {
        device: label.clone(),
        reason,
    };
    let mut kinds = streams.to_vec();
    kinds.sort();
    kinds.dedup();
    config.validate(&kinds).map_err(&config_error)?;
    if frames == 0 {
        return Err(config_error("record at least one frame".into()));
    }
    let out_str = out
        .to_str()
        .ok_or_else(|| config_error(format!("output path {} is not UTF-8", out.display())))?;
    let stall_timeout = Duration::from_millis(config.stall_timeout_ms);
    let lost = |reason: String| DeviceError::Disconnected {
        device: label.clone(),
        reason,
    };

    let session = Session::open(config, &kinds)?;
    // Start recording once every stream delivers, so no stream's first frames are cut.
    let mut seen = vec![0u32; kinds.len()];
    read_until(&session, &mut seen, 1, stall_timeout).map_err(&lost)?;
    session
        .device
        .start_recording(out_str)
        .map_err(|e| config_error(format!("cannot record to {}: {e}", out.display())))?;
    wait_for_recorder(out, kinds.len()).map_err(&config_error)?;
    // Frames raised before the recorder ran may still be on their way; they do not count.
    let settled = Instant::now() + RECORDER_SETTLE;
    while let Some(left) = settled.checked_duration_since(Instant::now()) {
        if let Ok(Some(frame)) = session.frames.recv_timeout(left) {
            session.frames.recycle(frame);
        }
    }
    let mut recorded = vec![0u32; kinds.len()];
    let result = read_until(&session, &mut recorded, frames, stall_timeout);
    // Closing the recorder writes the seek tables and closes the file.
    let stopped = session.device.stop_recording();
    drop(session);
    result.map_err(&lost)?;
    stopped.map_err(|e| config_error(format!("closing {}: {e}", out.display())))?;
    let repaired = oni_file::repair_recording(out)
        .map_err(|e| config_error(format!("cannot repair the recording: {e}")))?;
    if repaired > 0 {
        tracing::debug!(
            path = %out.display(), streams = repaired,
            "added the cropping property OpenNI's player needs and its recorder left out"
        );
    }

    // Read back what the file holds.
    let openni = OpenNi::get().map_err(|e| config_error(e.to_string()))?;
    let playback = openni
        .open(Some(out_str))
        .map_err(|e| config_error(format!("cannot reopen {}: {e}", out.display())))?;
    let mut counts = Vec::with_capacity(kinds.len());
    for &kind in &kinds {
        let n = playback
            .create_stream(sensor_type(kind))
            .and_then(|stream| playback.number_of_frames(stream))
            .map_err(|e| config_error(format!("{}: {kind} frame count: {e}", out.display())))?;
        counts.push((kind, n));
    }
    Ok(RecordingSummary {
        path: out.to_path_buf(),
        frames: counts,
    })
}

/// Waits until OpenNI's recorder, which starts on its own thread, has begun all `streams` of
/// the file it writes (it takes frames only from then on).
fn wait_for_recorder(out: &Path, streams: usize) -> Result<(), String> {
    let deadline = Instant::now() + RECORDER_START_TIMEOUT;
    loop {
        let bytes = std::fs::read(out).map_err(|e| format!("{}: {e}", out.display()))?;
        if oni_file::started_streams(&bytes) >= streams {
            return Ok(());
        }
        if Instant::now() > deadline {
            return Err(format!(
                "OpenNI's recorder did not start {} within {} ms",
                out.display(),
                RECORDER_START_TIMEOUT.as_millis()
            ));
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Reads and discards frames until every stream has delivered `target` of them.
fn read_until(
    session: &Session,
    counts: &mut [u32],
    target: u32,
    stall_timeout: Duration,
) -> Result<(), String> {
    let mut last_frame = Instant::now();
    while counts.iter().any(|&n| n < target) {
        match session.frames.recv_timeout(POLL) {
            Ok(Some(frame)) => {
                if let Some(n) = session.lane_of(&frame).and_then(|i| counts.get_mut(i)) {
                    *n += 1;
                }
                session.frames.recycle(frame);
                last_frame = Instant::now();
            }
            Ok(None) => {}
            Err(ffi::StreamsClosed) => return Err("OpenNI closed the streams".into()),
        }
        if last_frame.elapsed() > stall_timeout {
            return Err(format!(
                "no frame for {} ms",
                last_frame.elapsed().as_millis()
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seq_follows_the_index_and_counts_gaps() {
        let mut seq = SeqTracker::default();
        assert_eq!(seq.next(1), (1, 0));
        assert_eq!(seq.next(2), (2, 0));
        assert_eq!(seq.next(5), (5, 2), "indices 3 and 4 were lost");
        assert_eq!(seq.next(6), (6, 0));
    }

    #[test]
    fn seq_continues_when_the_index_restarts() {
        let mut seq = SeqTracker::default();
        for i in 1..=3 {
            seq.next(i);
        }
        // A looping recording or a reopened device counts from 1 again.
        assert_eq!(seq.next(1), (4, 0));
        assert_eq!(seq.next(2), (5, 0));
        assert_eq!(seq.next(4), (7, 1));
        // A restart at a later index than 1 (a device that resumes its counter) also continues.
        assert_eq!(seq.next(3), (8, 0));
    }

    #[test]
    fn depth_100_um_becomes_metres_and_stride_padding_is_skipped() {
        // 2 × 2 pixels, rows padded to 6 bytes.
        let raw: [u16; 2 * 3] = [10_000, 2_345, 0xFFFF, 0, 15_000, 0xFFFF];
        let bytes: Vec<u8> = raw.iter().flat_map(|v| v.to_ne_bytes()).collect();
        let mut image = Image::default();
        convert_frame(
            StreamKind::Depth,
            pixel_format::DEPTH_100_UM,
            2,
            2,
            6,
            &bytes,
            &mut image,
        )
        .unwrap();
        assert_eq!(image.format(), PixelFormat::DepthF32M);
        let depth_m = image.as_f32().unwrap();
        let expected = [1.0, 0.2345, 0.0, 1.5];
        for (got, want) in depth_m.iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
    }

    #[test]
    fn depth_1_mm_and_rgb888_are_copied_exactly() {
        let raw: [u16; 3] = [1000, 0, 65_535];
        let bytes: Vec<u8> = raw.iter().flat_map(|v| v.to_ne_bytes()).collect();
        let mut image = Image::default();
        convert_frame(
            StreamKind::Depth,
            pixel_format::DEPTH_1_MM,
            3,
            1,
            6,
            &bytes,
            &mut image,
        )
        .unwrap();
        assert_eq!(image.format(), PixelFormat::DepthU16Mm);
        assert_eq!(image.as_u16().unwrap(), &raw);

        let rgb = [1, 2, 3, 4, 5, 6, 99, 7, 8, 9, 10, 11, 12, 99];
        convert_frame(
            StreamKind::Color,
            pixel_format::RGB888,
            2,
            2,
            7,
            &rgb,
            &mut image,
        )
        .unwrap();
        assert_eq!(image.format(), PixelFormat::Rgb8);
        assert_eq!(
            image.as_u8().unwrap(),
            &[1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]
        );
    }

    #[test]
    fn short_or_foreign_frames_are_refused() {
        let mut image = Image::default();
        let short = convert_frame(
            StreamKind::Depth,
            pixel_format::DEPTH_1_MM,
            4,
            4,
            8,
            &[0; 20],
            &mut image,
        );
        assert!(short.unwrap_err().contains("needs 32 bytes"));
        let shift = convert_frame(
            StreamKind::Depth,
            pixel_format::SHIFT_9_2,
            1,
            1,
            2,
            &[0; 2],
            &mut image,
        );
        assert!(shift.unwrap_err().contains("SHIFT_9_2"));
        let swapped = convert_frame(
            StreamKind::Color,
            pixel_format::DEPTH_1_MM,
            1,
            1,
            2,
            &[0; 2],
            &mut image,
        );
        assert!(swapped.is_err());
    }

    #[test]
    fn config_rejects_what_can_never_work() {
        let config = OpenNi2Config::default();
        assert!(config.validate(&[StreamKind::Probe]).is_err());
        assert!(config.validate(&[]).is_err());
        for bad in [
            OpenNi2Config {
                playback_speed: 0.0,
                ..OpenNi2Config::default()
            },
            OpenNi2Config {
                width: Some(0),
                ..OpenNi2Config::default()
            },
            OpenNi2Config {
                uri: Some(String::new()),
                ..OpenNi2Config::default()
            },
        ] {
            assert!(bad.validate(&[StreamKind::Depth]).is_err(), "{bad:?}");
        }
        assert!(
            config
                .validate(&[StreamKind::Depth, StreamKind::Color])
                .is_ok()
        );
    }
}
