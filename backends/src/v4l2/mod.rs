//! V4L2 cameras (UVC webcams, sensors with a V4L2 driver) as the fish-eye light probe
//! ([`V4l2Probe`], with manual exposure and HDR brackets) or as a colour camera
//! ([`V4l2Color`]), through the `v4l` crate's mmap streaming.
//!
//! Opening negotiates the first pixel format of [`V4l2Config::formats`] that the device
//! offers, at the configured size and frame rate, and converts every frame to `Rgb8`
//! ([`crate::pixel_convert`], MJPEG through [`mjpeg`]). Exposure is set through
//! `V4L2_CID_EXPOSURE_AUTO` = manual and `V4L2_CID_EXPOSURE_ABSOLUTE` (units of 100 µs, so
//! exposures are rounded to 100 µs and frames are tagged with the rounded value), gain through
//! `V4L2_CID_AUTOGAIN` = off and `V4L2_CID_GAIN` (driver units). V4L2 applies controls with a
//! latency of one or more frames, so brackets go through [`ExposureSchedule`]: frames of a
//! transition are dropped, and each kept frame carries the exposure certainly in effect.
//!
//! Frames carry the buffer's sequence number (gaps are frames the driver or the settling of a
//! bracket dropped; numbering continues across reconnects) and its timestamp, which uvcvideo
//! and most drivers take from `CLOCK_MONOTONIC` (`V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC`), as
//! `device_ns`.
//!
//! Errors: no device node → `NotFound` (retried: the camera may be plugged in later); a node
//! that is not a V4L2 capture device, no acceptable format, an unreachable size, a missing
//! exposure control, an exposure outside the camera's range, permission denied → `Config`;
//! `ENODEV` (unplugged) or no frame for [`V4l2Config::stall_timeout_ms`] while streaming →
//! `Disconnected`; a buffer the driver flags as corrupt or that does not decode → `BadData`.

mod ffi;
pub mod mjpeg;

use std::fmt::Write as _;
use std::io;
use std::panic::{self, AssertUnwindSafe};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use relight_core::frame::host_now_ns;
use relight_core::{Frame, Image, ProbeImage, StreamKind, Timestamp};
use serde::Deserialize;
use v4l::buffer::{Flags as BufferFlags, Type as BufferType};
use v4l::control::{Control, Value};
use v4l::format::{Colorspace, Quantization};
use v4l::framesize::FrameSizeEnum;
use v4l::io::mmap::Stream;
use v4l::io::traits::{CaptureStream, Stream as _};
use v4l::v4l_sys::{
    V4L2_CAP_STREAMING, V4L2_CAP_VIDEO_CAPTURE, V4L2_CID_AUTOGAIN, V4L2_CID_EXPOSURE_ABSOLUTE,
    V4L2_CID_EXPOSURE_AUTO, V4L2_CID_EXPOSURE_AUTO_PRIORITY, V4L2_CID_GAIN,
    v4l2_exposure_auto_type_V4L2_EXPOSURE_MANUAL,
};
use v4l::video::Capture as _;
use v4l::video::capture::Parameters;
use v4l::{Device, Format, FourCC};

use self::ffi::ControlRange;
use crate::device::DeviceError;
use crate::exposure_schedule::{ExposureControl, ExposureSchedule};
use crate::pixel_convert::{
    BayerPattern, Packed422, YuvEncoding, YuvMatrix, bayer_to_rgb, grey_to_rgb, rgb24_to_rgb,
    yuv422_to_rgb,
};
use crate::sources::{Capture, ColorSource, FrameSource, ProbeSource, SourceDevice};

/// Linux errno values (asm-generic/errno-base.h, errno.h) that decide how an I/O error maps
/// onto the device contract.
mod errno {
    pub const EPERM: i32 = 1;
    pub const ENOENT: i32 = 2;
    pub const EINTR: i32 = 4;
    pub const ENXIO: i32 = 6;
    pub const EACCES: i32 = 13;
    pub const EBUSY: i32 = 16;
    pub const ENODEV: i32 = 19;
    pub const EINVAL: i32 = 22;
    pub const EISDIR: i32 = 21;
    pub const ENOTTY: i32 = 25;
    pub const ERANGE: i32 = 34;
}

/// Exposure used by the probe when the configuration gives none.
pub const DEFAULT_PROBE_EXPOSURE_US: u32 = 10_000;

/// `[probe]` / `[color]` section with `backend = "v4l2"`. Every key is optional.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct V4l2Config {
    /// Device node, default `/dev/video0`. A stable name such as
    /// `/dev/v4l/by-id/usb-…-video-index0` survives re-plugging into another port.
    pub device: PathBuf,
    /// Frame width in pixels; default: the size the device is set to. When given, the device
    /// must support exactly `width × height` (the error lists the sizes it offers).
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Frames per second to request (`VIDIOC_S_PARM`); default: the device's current rate.
    pub fps: Option<u32>,
    /// Pixel formats in order of preference: `yuyv`, `uyvy`, `mjpeg`, `rgb24`, `bgr24`, `grey`,
    /// `bayer_rggb`, `bayer_bggr`, `bayer_grbg`, `bayer_gbrg` (8-bit). The first one the
    /// device offers is used. Default: uncompressed first, in the order above but `mjpeg` last.
    pub formats: Vec<V4l2PixelFormat>,
    /// Fixed (manual) exposure in µs, rounded to the 100 µs unit of V4L2. Probe default:
    /// 10 000; colour camera default: none (the camera's automatic exposure is left alone).
    pub exposure_us: Option<u32>,
    /// Probe only: exposures (µs) cycled one per kept frame for HDR merging; empty: fixed.
    pub bracket_us: Vec<u32>,
    /// Analogue gain (`V4L2_CID_GAIN`, driver units); setting it turns auto gain off. Default:
    /// left alone. V4L2 gives gain no unit, so probe frames report `gain_db = 0`: keep the gain
    /// fixed for a calibrated HDR session.
    pub gain: Option<i64>,
    /// Frames between writing an exposure and the first frame certainly exposed with it
    /// (default 2: UVC cameras take one to two frames). Frames in between are dropped.
    pub exposure_latency_frames: u32,
    /// Driver buffers for mmap streaming (default 4).
    pub buffers: u32,
    /// How long one read waits for a frame before reporting idle, ms (default 200).
    pub frame_timeout_ms: u64,
    /// No frame for this long while streaming counts as a disconnect, ms (default 3000; raise it
    /// above the frame period for exposures longer than a second). The very first frame after
    /// opening is waited for this long in one read.
    pub stall_timeout_ms: u64,
    /// Frames in flight between this device and its consumers (default 4).
    pub pool_frames: usize,
}

impl Default for V4l2Config {
    fn default() -> Self {
        Self {
            device: PathBuf::from("/dev/video0"),
            width: None,
            height: None,
            fps: None,
            formats: V4l2PixelFormat::DEFAULT_PREFERENCE.to_vec(),
            exposure_us: None,
            bracket_us: Vec::new(),
            gain: None,
            exposure_latency_frames: 2,
            buffers: 4,
            frame_timeout_ms: 200,
            stall_timeout_ms: 3_000,
            pool_frames: 4,
        }
    }
}

/// Camera pixel formats this backend converts (8 bits per sample).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum V4l2PixelFormat {
    Yuyv,
    Uyvy,
    Mjpeg,
    Rgb24,
    Bgr24,
    Grey,
    BayerRggb,
    BayerBggr,
    BayerGrbg,
    BayerGbrg,
}

impl V4l2PixelFormat {
    pub const DEFAULT_PREFERENCE: [V4l2PixelFormat; 10] = [
        V4l2PixelFormat::Yuyv,
        V4l2PixelFormat::Uyvy,
        V4l2PixelFormat::Rgb24,
        V4l2PixelFormat::Bgr24,
        V4l2PixelFormat::BayerRggb,
        V4l2PixelFormat::BayerBggr,
        V4l2PixelFormat::BayerGrbg,
        V4l2PixelFormat::BayerGbrg,
        V4l2PixelFormat::Grey,
        V4l2PixelFormat::Mjpeg,
    ];

    /// The V4L2 fourccs of this format (videodev2.h `V4L2_PIX_FMT_*`).
    pub fn fourccs(self) -> &'static [&'static [u8; 4]] {
        match self {
            V4l2PixelFormat::Yuyv => &[b"YUYV"],
            V4l2PixelFormat::Uyvy => &[b"UYVY"],
            V4l2PixelFormat::Mjpeg => &[b"MJPG", b"JPEG"],
            V4l2PixelFormat::Rgb24 => &[b"RGB3"],
            V4l2PixelFormat::Bgr24 => &[b"BGR3"],
            V4l2PixelFormat::Grey => &[b"GREY"],
            V4l2PixelFormat::BayerRggb => &[b"RGGB"],
            V4l2PixelFormat::BayerBggr => &[b"BA81"],
            V4l2PixelFormat::BayerGrbg => &[b"GRBG"],
            V4l2PixelFormat::BayerGbrg => &[b"GBRG"],
        }
    }

    fn bytes_per_pixel(self) -> usize {
        match self {
            V4l2PixelFormat::Yuyv | V4l2PixelFormat::Uyvy => 2,
            V4l2PixelFormat::Rgb24 | V4l2PixelFormat::Bgr24 => 3,
            V4l2PixelFormat::Mjpeg
            | V4l2PixelFormat::Grey
            | V4l2PixelFormat::BayerRggb
            | V4l2PixelFormat::BayerBggr
            | V4l2PixelFormat::BayerGrbg
            | V4l2PixelFormat::BayerGbrg => 1,
        }
    }
}

fn fourcc_name(fourcc: FourCC) -> String {
    fourcc
        .repr
        .iter()
        .map(|&b| if b.is_ascii_graphic() { b as char } else { '?' })
        .collect()
}

/// The stream as negotiated with the driver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Negotiated {
    pub format: V4l2PixelFormat,
    pub fourcc: [u8; 4],
    pub width: u32,
    pub height: u32,
    /// Bytes per row (`bytesperline`).
    pub stride: usize,
    pub yuv: YuvEncoding,
}

/// Convert one raw frame of `negotiated` into `out` (`Rgb8`). `scratch` is reused by MJPEG.
pub fn frame_to_rgb(
    data: &[u8],
    negotiated: &Negotiated,
    scratch: &mut Vec<u8>,
    out: &mut Image,
) -> Result<(), String> {
    let Negotiated {
        format,
        width: w,
        height: h,
        stride,
        yuv,
        ..
    } = *negotiated;
    let bayer = |pattern, out: &mut Image| bayer_to_rgb(data, w, h, stride, pattern, out);
    let result = match format {
        V4l2PixelFormat::Yuyv => yuv422_to_rgb(data, w, h, stride, Packed422::Yuyv, yuv, out),
        V4l2PixelFormat::Uyvy => yuv422_to_rgb(data, w, h, stride, Packed422::Uyvy, yuv, out),
        V4l2PixelFormat::Rgb24 => rgb24_to_rgb(data, w, h, stride, false, out),
        V4l2PixelFormat::Bgr24 => rgb24_to_rgb(data, w, h, stride, true, out),
        V4l2PixelFormat::Grey => grey_to_rgb(data, w, h, stride, out),
        V4l2PixelFormat::BayerRggb => bayer(BayerPattern::Rggb, out),
        V4l2PixelFormat::BayerBggr => bayer(BayerPattern::Bggr, out),
        V4l2PixelFormat::BayerGrbg => bayer(BayerPattern::Grbg, out),
        V4l2PixelFormat::BayerGbrg => bayer(BayerPattern::Gbrg, out),
        V4l2PixelFormat::Mjpeg => {
            return mjpeg::decode_mjpeg(data, w, h, scratch, out).map_err(|e| e.to_string());
        }
    };
    result.map_err(|e| e.to_string())
}

/// Buffer sequence numbers (u32, restarting at 0 on every stream start) → a u64 index that
/// keeps increasing across wraps and reconnects.
#[derive(Debug, Default)]
struct SequenceCounter {
    /// Index given to the first frame of this stream.
    base: u64,
    first_raw: Option<u32>,
    last_raw: u32,
    wraps: u64,
    last: Option<u64>,
}

impl SequenceCounter {
    fn restart(&mut self) {
        self.base = self.last.map_or(0, |last| last + 1);
        self.first_raw = None;
        self.wraps = 0;
    }

    fn next(&mut self, raw: u32) -> u64 {
        match self.first_raw {
            None => self.first_raw = Some(raw),
            Some(_) if raw < self.last_raw => self.wraps += 1,
            Some(_) => {}
        }
        self.last_raw = raw;
        let first = u64::from(self.first_raw.unwrap_or(raw));
        let index = self.base + ((self.wraps << 32) + u64::from(raw)).saturating_sub(first);
        self.last = Some(index);
        index
    }
}

/// An open, streaming device. `stream` is declared first so it is dropped (stopped and
/// unmapped) before the device's file descriptor.
struct OpenStream {
    stream: Stream<'static>,
    device: Device,
    negotiated: Negotiated,
    exposure: Option<ControlRange>,
    last_frame: Instant,
    /// Whether `Stream::next` has queued the buffers and started streaming.
    started: bool,
}

/// `POLLIN` (poll.h): a buffer is ready to dequeue.
const POLLIN: i16 = 0x0001;

/// One dequeued buffer, still in the driver's memory.
struct RawFrame<'a> {
    label: &'a str,
    data: &'a [u8],
    seq: u64,
    device_ns: u64,
    device: &'a Device,
    negotiated: &'a Negotiated,
    exposure: Option<ControlRange>,
    scratch: &'a mut Vec<u8>,
}

impl RawFrame<'_> {
    fn convert_into(&mut self, out: &mut Image) -> Result<(), DeviceError> {
        frame_to_rgb(self.data, self.negotiated, self.scratch, out).map_err(|reason| {
            DeviceError::BadData {
                device: self.label.to_owned(),
                reason,
            }
        })
    }

    fn set_exposure(&self, exposure_us: u32) -> Result<u32, DeviceError> {
        write_exposure(self.label, self.device, self.exposure, exposure_us)
    }
}

/// Write an exposure through `EXPOSURE_ABSOLUTE`; returns the value the driver stores (µs):
/// rounded to its unit and step, clamped to its range.
fn write_exposure(
    label: &str,
    device: &Device,
    range: Option<ControlRange>,
    exposure_us: u32,
) -> Result<u32, DeviceError> {
    let Some(range) = range else {
        return Err(DeviceError::Config {
            device: label.to_owned(),
            reason: "exposure control was not set up".into(),
        });
    };
    let units = range.adjust(exposure_units(exposure_us));
    let applied_us = units_to_us(units);
    if applied_us.abs_diff(exposure_us) >= EXPOSURE_UNIT_US {
        tracing::warn!(
            device = label,
            exposure_us,
            applied_us,
            "exposure outside the camera's range; clamped"
        );
    }
    set_control(device, V4L2_CID_EXPOSURE_ABSOLUTE, units)
        .map_err(|e| stream_error(label, "VIDIOC_S_EXT_CTRLS(EXPOSURE_ABSOLUTE)", &e))?;
    Ok(applied_us)
}

/// `V4L2_CID_EXPOSURE_ABSOLUTE` counts in units of 100 µs.
const EXPOSURE_UNIT_US: u32 = 100;

fn exposure_units(exposure_us: u32) -> i64 {
    i64::from(exposure_us.saturating_add(EXPOSURE_UNIT_US / 2) / EXPOSURE_UNIT_US)
}

fn units_to_us(units: i64) -> u32 {
    u32::try_from(units.max(0))
        .unwrap_or(u32::MAX / EXPOSURE_UNIT_US)
        .saturating_mul(EXPOSURE_UNIT_US)
}

fn set_control(device: &Device, id: u32, value: i64) -> io::Result<()> {
    device.set_control(Control {
        id,
        value: Value::Integer(value),
    })
}

/// An error while streaming: the device is gone (or wedged) and must be reopened.
fn stream_error(label: &str, what: &str, error: &io::Error) -> DeviceError {
    let reason = match error.raw_os_error() {
        Some(errno::ENODEV | errno::ENXIO) => format!("{what}: device unplugged ({error})"),
        _ => format!("{what}: {error}"),
    };
    DeviceError::Disconnected {
        device: label.to_owned(),
        reason,
    }
}

/// An error while opening: absent or busy devices are retried, the rest cannot work.
fn open_error(label: &str, what: &str, error: &io::Error) -> DeviceError {
    let device = label.to_owned();
    match error.raw_os_error() {
        Some(errno::EACCES | errno::EPERM) => DeviceError::Config {
            device,
            reason: format!(
                "{what}: permission denied ({error}); add the daemon's user to the `video` group"
            ),
        },
        Some(errno::EINVAL | errno::ENOTTY | errno::ERANGE | errno::EISDIR) => {
            DeviceError::Config {
                device,
                reason: format!("{what}: {error}"),
            }
        }
        Some(errno::EBUSY) => DeviceError::NotFound {
            device,
            reason: format!("{what}: device busy, another program is using it ({error})"),
        },
        _ => DeviceError::NotFound {
            device,
            reason: format!("{what}: {error}"),
        },
    }
}

/// The capture half shared by the probe and the colour camera.
struct V4l2Stream {
    config: V4l2Config,
    label: String,
    open: Option<OpenStream>,
    seq: SequenceCounter,
    scratch: Vec<u8>,
}

impl std::fmt::Debug for V4l2Stream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("V4l2Stream")
            .field("label", &self.label)
            .field("negotiated", &self.open.as_ref().map(|o| o.negotiated))
            .finish_non_exhaustive()
    }
}

impl V4l2Stream {
    fn new(config: V4l2Config) -> Result<Self, DeviceError> {
        let label = format!("v4l2 {}", config.device.display());
        let bad = |reason: String| DeviceError::Config {
            device: label.clone(),
            reason,
        };
        if config.device.as_os_str().as_encoded_bytes().contains(&0) {
            return Err(bad("device path contains a NUL byte".into()));
        }
        if config.formats.is_empty() {
            return Err(bad("`formats` is empty".into()));
        }
        if config.width.is_some() != config.height.is_some() {
            return Err(bad("give both `width` and `height`, or neither".into()));
        }
        if config.width == Some(0) || config.height == Some(0) || config.fps == Some(0) {
            return Err(bad("`width`, `height` and `fps` must be positive".into()));
        }
        if config.buffers == 0 || config.pool_frames == 0 {
            return Err(bad("`buffers` and `pool_frames` must be positive".into()));
        }
        if config.frame_timeout_ms == 0 || config.stall_timeout_ms < config.frame_timeout_ms {
            return Err(bad(
                "`frame_timeout_ms` must be positive and at most `stall_timeout_ms`".into(),
            ));
        }
        let exposures = config.exposure_us.iter().chain(&config.bracket_us);
        if let Some(&bad_exposure) = exposures.clone().find(|&&e| e == 0) {
            return Err(bad(format!("exposure {bad_exposure} µs: must be positive")));
        }
        Ok(Self {
            config,
            label,
            open: None,
            seq: SequenceCounter::default(),
            scratch: Vec::new(),
        })
    }

    fn config_error(&self, reason: String) -> DeviceError {
        DeviceError::Config {
            device: self.label.clone(),
            reason,
        }
    }

    /// Open and configure the device; `exposures_us` are the configured exposures to check
    /// against the camera's range (an empty slice leaves exposure alone). The `v4l` crate
    /// panics on some replies it cannot parse (unknown colorspace, field order): such a
    /// driver is reported as a configuration error instead of taking the thread down.
    fn open(&mut self, exposures_us: &[u32]) -> Result<(), DeviceError> {
        self.close();
        let opened = panic::catch_unwind(AssertUnwindSafe(|| self.open_device(exposures_us)))
            .unwrap_or_else(|panic| {
                let what = panic
                    .downcast_ref::<String>()
                    .map(String::as_str)
                    .or_else(|| panic.downcast_ref::<&str>().copied())
                    .unwrap_or("unknown");
                Err(self.config_error(format!("unexpected reply from the driver: {what}")))
            })?;
        tracing::info!(
            device = %self.label,
            format = %String::from_utf8_lossy(&opened.negotiated.fourcc),
            width = opened.negotiated.width,
            height = opened.negotiated.height,
            "V4L2 stream open"
        );
        self.seq.restart();
        self.open = Some(opened);
        Ok(())
    }

    fn open_device(&self, exposures_us: &[u32]) -> Result<OpenStream, DeviceError> {
        let label = self.label.as_str();
        let config = &self.config;
        let path = config.device.display();
        let device = Device::with_path(&config.device).map_err(|e| match e.raw_os_error() {
            Some(errno::ENOENT | errno::ENODEV | errno::ENXIO) => DeviceError::NotFound {
                device: label.to_owned(),
                reason: format!("no device at {path} ({e})"),
            },
            _ => open_error(label, "open", &e),
        })?;
        let fd = device.handle().fd();
        let caps = ffi::query_caps(fd).map_err(|e| match e.raw_os_error() {
            Some(errno::ENOTTY | errno::EINVAL) => self.config_error(format!(
                "{path} is not a V4L2 device (VIDIOC_QUERYCAP: {e})"
            )),
            _ => open_error(label, "VIDIOC_QUERYCAP", &e),
        })?;
        if caps.caps & V4L2_CAP_VIDEO_CAPTURE == 0 {
            return Err(self.config_error(format!(
                "{path} ({}, {}) is not a single-planar video capture node (a metadata or \
                 output node of the same camera?)",
                caps.card, caps.driver
            )));
        }
        if caps.caps & V4L2_CAP_STREAMING == 0 {
            return Err(self.config_error(format!(
                "{path} ({}) does not support streaming I/O",
                caps.card
            )));
        }

        let offered: Vec<FourCC> = device
            .enum_formats()
            .map_err(|e| open_error(label, "VIDIOC_ENUM_FMT", &e))?
            .into_iter()
            .map(|d| d.fourcc)
            .collect();
        let choice = config.formats.iter().find_map(|&format| {
            format
                .fourccs()
                .iter()
                .map(|cc| FourCC::new(cc))
                .find(|cc| offered.contains(cc))
                .map(|cc| (format, cc))
        });
        let Some((format, fourcc)) = choice else {
            let offered: Vec<String> = offered.into_iter().map(fourcc_name).collect();
            return Err(self.config_error(format!(
                "{path} offers {} but `formats` allows only {:?}",
                if offered.is_empty() {
                    "no formats".to_owned()
                } else {
                    offered.join(", ")
                },
                config.formats
            )));
        };

        let current = device
            .format()
            .map_err(|e| open_error(label, "VIDIOC_G_FMT", &e))?;
        let (width, height) = (
            config.width.unwrap_or(current.width),
            config.height.unwrap_or(current.height),
        );
        let actual = device
            .set_format(&Format::new(width, height, fourcc))
            .map_err(|e| open_error(label, "VIDIOC_S_FMT", &e))?;
        if actual.fourcc != fourcc {
            return Err(self.config_error(format!(
                "asked for {}, the driver set {}",
                fourcc_name(fourcc),
                fourcc_name(actual.fourcc)
            )));
        }
        if (actual.width, actual.height) != (width, height) {
            let mut sizes = String::new();
            for size in device.enum_framesizes(fourcc).unwrap_or_default() {
                let _ = match size.size {
                    FrameSizeEnum::Discrete(d) => write!(sizes, " {}×{}", d.width, d.height),
                    FrameSizeEnum::Stepwise(s) => write!(
                        sizes,
                        " {}–{}×{}–{} (steps {}×{})",
                        s.min_width,
                        s.max_width,
                        s.min_height,
                        s.max_height,
                        s.step_width,
                        s.step_height
                    ),
                };
            }
            return Err(self.config_error(format!(
                "{} {width}×{height} is not available (driver chose {}×{}); sizes offered:{sizes}",
                fourcc_name(fourcc),
                actual.width,
                actual.height
            )));
        }
        let packed_row = actual.width as usize * format.bytes_per_pixel();
        let stride = match actual.stride as usize {
            0 => packed_row,
            s => s,
        };
        let yuv = YuvEncoding {
            matrix: if matches!(actual.colorspace, Colorspace::Rec709) {
                YuvMatrix::Bt709
            } else {
                YuvMatrix::Bt601
            },
            limited_range: match actual.quantization {
                Quantization::FullRange => false,
                Quantization::LimitedRange => true,
                Quantization::Default => !matches!(actual.colorspace, Colorspace::JPEG),
            },
        };

        if let Some(fps) = config.fps {
            match device.set_params(&Parameters::with_fps(fps)) {
                Ok(params) => {
                    let interval = params.interval;
                    let actual_fps =
                        f64::from(interval.denominator) / f64::from(interval.numerator.max(1));
                    if (actual_fps - f64::from(fps)).abs() > 0.01 * f64::from(fps) {
                        tracing::warn!(device = label, fps, actual_fps, "frame rate not available");
                    }
                }
                Err(e) => {
                    tracing::warn!(device = label, fps, error = %e, "cannot set the frame rate")
                }
            }
        }

        let exposure = if exposures_us.is_empty() {
            None
        } else {
            Some(self.setup_exposure(&device, exposures_us)?)
        };
        if let Some(gain) = config.gain {
            self.setup_gain(&device, gain)?;
        }

        let mut stream = Stream::with_buffers(&device, BufferType::VideoCapture, config.buffers)
            .map_err(|e| open_error(label, "VIDIOC_REQBUFS (mmap)", &e))?;
        // See `next_frame`: the stream's own wait only covers the first frame.
        stream.set_timeout(Duration::from_millis(config.stall_timeout_ms));
        Ok(OpenStream {
            stream,
            device,
            negotiated: Negotiated {
                format,
                fourcc: fourcc.repr,
                width: actual.width,
                height: actual.height,
                stride,
                yuv,
            },
            exposure,
            last_frame: Instant::now(),
            started: false,
        })
    }

    /// Manual exposure: `EXPOSURE_AUTO` = manual, `EXPOSURE_AUTO_PRIORITY` off (the camera may
    /// not stretch frames to fit the exposure, which would change the control latency), and
    /// every configured exposure within the range of `EXPOSURE_ABSOLUTE`.
    fn setup_exposure(
        &self,
        device: &Device,
        exposures_us: &[u32],
    ) -> Result<ControlRange, DeviceError> {
        let label = self.label.as_str();
        let fd = device.handle().fd();
        let query = |id| {
            ffi::query_control(fd, id).map_err(|e| open_error(label, "VIDIOC_QUERY_EXT_CTRL", &e))
        };
        let set = |id, value, what| {
            set_control(device, id, value).map_err(|e| open_error(label, what, &e))
        };
        if query(V4L2_CID_EXPOSURE_AUTO)?.is_some() {
            set(
                V4L2_CID_EXPOSURE_AUTO,
                i64::from(v4l2_exposure_auto_type_V4L2_EXPOSURE_MANUAL),
                "set EXPOSURE_AUTO = manual",
            )?;
        }
        if query(V4L2_CID_EXPOSURE_AUTO_PRIORITY)?.is_some() {
            set(
                V4L2_CID_EXPOSURE_AUTO_PRIORITY,
                0,
                "set EXPOSURE_AUTO_PRIORITY = 0",
            )?;
        }
        let Some(range) = query(V4L2_CID_EXPOSURE_ABSOLUTE)? else {
            return Err(self.config_error(
                "the camera has no writable V4L2_CID_EXPOSURE_ABSOLUTE control, so its exposure \
                 cannot be set"
                    .into(),
            ));
        };
        for &exposure_us in exposures_us {
            if !range.contains(exposure_units(exposure_us)) {
                return Err(self.config_error(format!(
                    "exposure {exposure_us} µs is outside the camera's range {}–{} µs",
                    units_to_us(range.min),
                    units_to_us(range.max)
                )));
            }
        }
        Ok(range)
    }

    fn setup_gain(&self, device: &Device, gain: i64) -> Result<(), DeviceError> {
        let label = self.label.as_str();
        let fd = device.handle().fd();
        let query = |id| {
            ffi::query_control(fd, id).map_err(|e| open_error(label, "VIDIOC_QUERY_EXT_CTRL", &e))
        };
        if query(V4L2_CID_AUTOGAIN)?.is_some() {
            set_control(device, V4L2_CID_AUTOGAIN, 0)
                .map_err(|e| open_error(label, "set AUTOGAIN = 0", &e))?;
        }
        let Some(range) = query(V4L2_CID_GAIN)? else {
            return Err(self.config_error(
                "`gain` is set but the camera has no writable V4L2_CID_GAIN".into(),
            ));
        };
        if !range.contains(gain) {
            return Err(self.config_error(format!(
                "gain {gain} is outside the camera's range {}–{}",
                range.min, range.max
            )));
        }
        set_control(device, V4L2_CID_GAIN, gain).map_err(|e| open_error(label, "set GAIN", &e))
    }

    /// Write an exposure before streaming starts (or on a colour camera, once).
    fn set_exposure(&self, exposure_us: u32) -> Result<u32, DeviceError> {
        let Some(open) = self.open.as_ref() else {
            return Err(DeviceError::Disconnected {
                device: self.label.clone(),
                reason: "not open".into(),
            });
        };
        write_exposure(&self.label, &open.device, open.exposure, exposure_us).map_err(|e| match e {
            DeviceError::Disconnected { device, reason } => {
                DeviceError::NotFound { device, reason }
            }
            other => other,
        })
    }

    /// Dequeue the next buffer: `None` when none arrived within the frame timeout.
    fn next_frame(&mut self) -> Result<Option<RawFrame<'_>>, DeviceError> {
        let label = self.label.as_str();
        let Some(open) = self.open.as_mut() else {
            return Err(DeviceError::Disconnected {
                device: label.to_owned(),
                reason: "read before open".into(),
            });
        };
        let OpenStream {
            stream,
            device,
            negotiated,
            exposure,
            last_frame,
            started,
        } = open;
        let stall = Duration::from_millis(self.config.stall_timeout_ms);
        let stalled = |last_frame: &Instant| DeviceError::Disconnected {
            device: label.to_owned(),
            reason: format!("no frame for {} ms", last_frame.elapsed().as_millis()),
        };
        // `Stream::next` re-queues the buffer it returned last before waiting; when its wait
        // times out, the next call queues that buffer a second time and fails (EINVAL). So
        // once streaming, wait here and call `next` only when a buffer is ready. The first
        // call, which queues the buffers and starts the stream, waits up to the stall timeout.
        if *started {
            let timeout_ms = i32::try_from(self.config.frame_timeout_ms).unwrap_or(i32::MAX);
            match device.handle().poll(POLLIN, timeout_ms) {
                Ok(0) if last_frame.elapsed() > stall => return Err(stalled(last_frame)),
                Ok(0) => return Ok(None),
                Ok(_) => {}
                Err(e) if e.raw_os_error() == Some(errno::EINTR) => return Ok(None),
                Err(e) => return Err(stream_error(label, "poll", &e)),
            }
        }
        *started = true;
        let (data, meta) = match CaptureStream::next(stream) {
            Ok(buffer) => buffer,
            Err(e) if e.kind() == io::ErrorKind::TimedOut => return Err(stalled(last_frame)),
            Err(e) => return Err(stream_error(label, "VIDIOC_DQBUF", &e)),
        };
        *last_frame = Instant::now();
        let seq = self.seq.next(meta.sequence);
        let bad = |reason: String| DeviceError::BadData {
            device: label.to_owned(),
            reason,
        };
        if meta.flags.contains(BufferFlags::ERROR) {
            return Err(bad(format!(
                "frame {seq}: the driver flagged the buffer as corrupt"
            )));
        }
        let used = meta.bytesused as usize;
        if used == 0 || used > data.len() {
            return Err(bad(format!(
                "frame {seq}: {used} bytes used of a {}-byte buffer",
                data.len()
            )));
        }
        let timestamp = meta.timestamp;
        let device_ns = u64::try_from(timestamp.sec)
            .unwrap_or(0)
            .saturating_mul(1_000_000_000)
            .saturating_add(
                u64::try_from(timestamp.usec)
                    .unwrap_or(0)
                    .saturating_mul(1_000),
            );
        Ok(Some(RawFrame {
            label,
            data: &data[..used],
            seq,
            device_ns,
            device,
            negotiated,
            exposure: *exposure,
            scratch: &mut self.scratch,
        }))
    }

    fn negotiated(&self) -> Option<Negotiated> {
        self.open.as_ref().map(|o| o.negotiated)
    }

    /// Stop streaming and close. `v4l`'s stream panics on drop when `VIDIOC_STREAMOFF` fails
    /// for any reason but `ENODEV`; in that case its buffers (and the descriptor) are leaked
    /// instead, which a reconnect survives.
    fn close(&mut self) {
        let Some(OpenStream { mut stream, .. }) = self.open.take() else {
            return;
        };
        match stream.stop() {
            Ok(()) => {}
            Err(e) if e.raw_os_error() == Some(errno::ENODEV) => {}
            Err(e) => {
                tracing::error!(device = %self.label, error = %e, "VIDIOC_STREAMOFF failed; leaking the stream's buffers");
                std::mem::forget(stream);
            }
        }
    }
}

/// The fish-eye light probe on a V4L2 camera.
#[derive(Debug)]
pub struct V4l2Probe {
    stream: V4l2Stream,
    control: ExposureControl,
    seen_generation: u64,
    schedule: ExposureSchedule,
}

impl V4l2Probe {
    /// Check the configuration; nothing is opened until [`FrameSource::open`].
    pub fn new(config: V4l2Config) -> Result<Self, DeviceError> {
        let exposure_us = config.exposure_us.unwrap_or(DEFAULT_PROBE_EXPOSURE_US);
        let control = ExposureControl::new(exposure_us);
        if !config.bracket_us.is_empty() {
            control.set_bracketing(&config.bracket_us);
        }
        let schedule = ExposureSchedule::new(config.exposure_latency_frames, exposure_us);
        Ok(Self {
            stream: V4l2Stream::new(config)?,
            control,
            seen_generation: u64::MAX,
            schedule,
        })
    }

    /// Wrapped for a [`crate::DeviceRunner`].
    pub fn into_device(self) -> SourceDevice<Self> {
        let pool_frames = self.stream.config.pool_frames;
        SourceDevice::new(self, pool_frames)
    }

    /// A handle that changes the exposure or bracket while the probe runs on its thread.
    pub fn exposure_control(&self) -> ExposureControl {
        self.control.clone()
    }

    /// The stream as negotiated (after a successful open).
    pub fn negotiated(&self) -> Option<Negotiated> {
        self.stream.negotiated()
    }

    fn configured_exposures(&self) -> Vec<u32> {
        let config = &self.stream.config;
        let mut exposures = config.bracket_us.clone();
        exposures.push(config.exposure_us.unwrap_or(DEFAULT_PROBE_EXPOSURE_US));
        exposures
    }
}

fn check_exposures(device: &str, exposures_us: &[u32]) -> Result<(), DeviceError> {
    if exposures_us.contains(&0) {
        return Err(DeviceError::Config {
            device: device.to_owned(),
            reason: format!("exposures must be positive, got {exposures_us:?}"),
        });
    }
    Ok(())
}

impl FrameSource for V4l2Probe {
    type Payload = ProbeImage;

    fn backend(&self) -> &'static str {
        "v4l2"
    }

    fn stream(&self) -> StreamKind {
        StreamKind::Probe
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        let exposures = self.configured_exposures();
        self.stream.open(&exposures)?;
        self.seen_generation = u64::MAX;
        let plan = self
            .control
            .plan_if_changed(&mut self.seen_generation)
            .unwrap_or_default();
        self.schedule.set_plan(&plan);
        let stream = &self.stream;
        self.schedule.start(|us| stream.set_exposure(us))
    }

    fn read(&mut self, frame: &mut Frame<ProbeImage>) -> Result<Capture, DeviceError> {
        if let Some(plan) = self.control.plan_if_changed(&mut self.seen_generation) {
            self.schedule.set_plan(&plan);
        }
        let Some(mut raw) = self.stream.next_frame()? else {
            return Ok(Capture::Idle);
        };
        let Some(exposure_us) = self.schedule.on_frame(raw.seq, |us| raw.set_exposure(us))? else {
            tracing::trace!(seq = raw.seq, "exposure settling; frame dropped");
            return Ok(Capture::Idle);
        };
        raw.convert_into(&mut frame.payload.image)?;
        frame.payload.exposure_us = exposure_us;
        frame.payload.gain_db = 0.0;
        frame.seq = raw.seq;
        frame.stamp = Timestamp::new(raw.device_ns, host_now_ns());
        Ok(Capture::Frame)
    }

    fn close(&mut self) {
        self.stream.close();
    }
}

impl ProbeSource for V4l2Probe {
    fn set_exposure_us(&mut self, exposure_us: u32) -> Result<(), DeviceError> {
        check_exposures(&self.stream.label, &[exposure_us])?;
        self.control.set_exposure_us(exposure_us);
        Ok(())
    }

    fn set_bracketing(&mut self, exposures_us: &[u32]) -> Result<(), DeviceError> {
        check_exposures(&self.stream.label, exposures_us)?;
        self.control.set_bracketing(exposures_us);
        Ok(())
    }
}

/// A colour camera on V4L2: every frame, converted to `Rgb8`.
#[derive(Debug)]
pub struct V4l2Color {
    stream: V4l2Stream,
}

impl V4l2Color {
    /// Check the configuration (a colour camera takes no bracket); nothing is opened yet.
    pub fn new(config: V4l2Config) -> Result<Self, DeviceError> {
        let stream = V4l2Stream::new(config)?;
        if !stream.config.bracket_us.is_empty() {
            return Err(stream.config_error("`bracket_us` is for the probe only".into()));
        }
        Ok(Self { stream })
    }

    pub fn into_device(self) -> SourceDevice<Self> {
        let pool_frames = self.stream.config.pool_frames;
        SourceDevice::new(self, pool_frames)
    }

    pub fn negotiated(&self) -> Option<Negotiated> {
        self.stream.negotiated()
    }
}

impl FrameSource for V4l2Color {
    type Payload = Image;

    fn backend(&self) -> &'static str {
        "v4l2"
    }

    fn stream(&self) -> StreamKind {
        StreamKind::Color
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        let exposure: Vec<u32> = self.stream.config.exposure_us.into_iter().collect();
        self.stream.open(&exposure)?;
        if let Some(&exposure_us) = exposure.first() {
            self.stream.set_exposure(exposure_us)?;
        }
        Ok(())
    }

    fn read(&mut self, frame: &mut Frame<Image>) -> Result<Capture, DeviceError> {
        let Some(mut raw) = self.stream.next_frame()? else {
            return Ok(Capture::Idle);
        };
        raw.convert_into(&mut frame.payload)?;
        frame.seq = raw.seq;
        frame.stamp = Timestamp::new(raw.device_ns, host_now_ns());
        Ok(Capture::Frame)
    }

    fn close(&mut self) {
        self.stream.close();
    }
}

impl ColorSource for V4l2Color {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequence_numbers_continue_across_wraps_and_restarts() {
        let mut seq = SequenceCounter::default();
        seq.restart();
        assert_eq!(seq.next(7), 0);
        assert_eq!(seq.next(9), 2, "a gap stays a gap");
        assert_eq!(seq.next(u32::MAX), u64::from(u32::MAX) - 7);
        assert_eq!(seq.next(0), u64::from(u32::MAX) - 6, "wrapped");
        seq.restart();
        assert_eq!(
            seq.next(0),
            u64::from(u32::MAX) - 5,
            "a reconnect continues"
        );
        assert_eq!(seq.next(1), u64::from(u32::MAX) - 4);
    }

    #[test]
    fn exposures_round_to_the_100_us_unit_and_the_control_step() {
        assert_eq!(exposure_units(250), 3);
        assert_eq!(exposure_units(249), 2);
        assert_eq!(exposure_units(16_000), 160);
        let range = ControlRange {
            min: 3,
            max: 2047,
            step: 4,
            default: 250,
        };
        assert_eq!(range.adjust(2), 3);
        assert_eq!(range.adjust(9), 11);
        assert_eq!(range.adjust(10), 11);
        assert_eq!(range.adjust(9999), 2047);
        assert_eq!(units_to_us(range.adjust(exposure_units(1_000))), 1_100);
    }
}
