//! IDS uEye industrial cameras as the fish-eye light probe ([`UeyeProbe`], manual exposure and
//! HDR brackets) or a colour camera ([`UeyeColor`]), through the IDS C API (`libueye_api.so`
//! of the IDS Software Suite, loaded at run time so the daemon builds and runs without it).
//!
//! Opening follows the IDS manual's "freerun with image queue" sequence: `is_InitCamera`,
//! `is_SetDisplayMode(DIB)`, trigger off, `is_SetColorMode` (RGB8 packed, else BGR8, else
//! mono 8), `is_AOI` for the size, `is_SetFrameRate`, auto shutter and auto gain off,
//! `is_SetHardwareGain`, a ring of `is_AllocImageMem` + `is_AddToSequence`,
//! `is_InitImageQueue`, and `is_CaptureVideo`. Each read is `is_WaitForNextImage` →
//! `is_GetImageInfo` (frame number → `seq`, device timestamp in 0.1 µs → `device_ns`) → copy →
//! `is_UnlockSeqBuf`. Exposure goes through `is_Exposure` in ms; frames are tagged with the
//! value the camera reports back. In freerun the camera applies a new exposure one or two
//! frames late, so brackets go through [`ExposureSchedule`].
//!
//! Errors: library absent or too old → `Config` (naming the library); no camera →
//! `NotFound`; a size, colour mode or exposure the camera cannot do → `Config`; a failed
//! transfer (`IS_CAPTURE_STATUS`) → `BadData`; any other failure while streaming (the camera
//! was unplugged: the API frees the handle and calls fail) or no frame for
//! [`UeyeConfig::stall_timeout_ms`] → `Disconnected`.

mod ffi;

use std::sync::Arc;
use std::time::{Duration, Instant};

use relight_core::frame::host_now_ns;
use relight_core::{Frame, Image, ProbeImage, StreamKind, Timestamp};
use serde::Deserialize;

use self::ffi::{Api, CallError, Camera, LockedImage, Wait};
use crate::device::DeviceError;
use crate::exposure_schedule::{ExposureControl, ExposureSchedule};
use crate::pixel_convert::{grey_to_rgb, rgb24_to_rgb};
use crate::sources::{Capture, ColorSource, FrameSource, ProbeSource, SourceDevice};

/// Libraries tried, in order, when the configuration names none.
pub const DEFAULT_LIBRARIES: [&str; 2] = ["libueye_api.so.1", "libueye_api.so"];

/// Exposure used by the probe when the configuration gives none.
pub const DEFAULT_PROBE_EXPOSURE_US: u32 = 10_000;

/// `[probe]` / `[color]` section with `backend = "ueye"`. Every key is optional.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct UeyeConfig {
    /// The uEye API library (a name for the dynamic loader or a path); default
    /// `libueye_api.so.1`, then `libueye_api.so`.
    pub library: Option<String>,
    /// Camera ID as set in the IDS Camera Manager; 0 (default) opens the first free camera.
    pub camera_id: u32,
    /// Area of interest from the sensor's top-left corner, pixels; default: the camera's
    /// current AOI. Give both or neither.
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Frames per second (`is_SetFrameRate`); default: the camera's. The frame period bounds
    /// the longest exposure.
    pub fps: Option<f64>,
    /// Fixed exposure in µs. Probe default: 10 000; colour camera default: none (auto
    /// shutter on).
    pub exposure_us: Option<u32>,
    /// Probe only: exposures (µs) cycled one per kept frame for HDR merging; empty: fixed.
    pub bracket_us: Vec<u32>,
    /// Master gain in percent of the camera's range (0–100, `is_SetHardwareGain`); auto gain
    /// is switched off for the probe. Default: left alone.
    pub gain_percent: Option<u32>,
    /// Frames between writing an exposure and the first frame certainly exposed with it
    /// (default 2). Frames in between are dropped.
    pub exposure_latency_frames: u32,
    /// Image memories in the capture ring (default 4).
    pub buffers: u32,
    /// How long one read waits for a frame before reporting idle, ms (default 200).
    pub frame_timeout_ms: u32,
    /// No frame for this long while capturing counts as a disconnect, ms (default 3000).
    pub stall_timeout_ms: u64,
    /// Frames in flight between this device and its consumers (default 4).
    pub pool_frames: usize,
}

impl Default for UeyeConfig {
    fn default() -> Self {
        Self {
            library: None,
            camera_id: 0,
            width: None,
            height: None,
            fps: None,
            exposure_us: None,
            bracket_us: Vec::new(),
            gain_percent: None,
            exposure_latency_frames: 2,
            buffers: 4,
            frame_timeout_ms: 200,
            stall_timeout_ms: 3_000,
            pool_frames: 4,
        }
    }
}

/// Pixel layout of the image memories.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UeyeLayout {
    Rgb8,
    Bgr8,
    Mono8,
}

impl UeyeLayout {
    const PREFERENCE: [(UeyeLayout, i32, i32); 3] = [
        (UeyeLayout::Rgb8, ffi::IS_CM_RGB8_PACKED, 24),
        (UeyeLayout::Bgr8, ffi::IS_CM_BGR8_PACKED, 24),
        (UeyeLayout::Mono8, ffi::IS_CM_MONO8, 8),
    ];
}

/// The capture as set up on the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UeyeSetup {
    pub layout: UeyeLayout,
    pub width: u32,
    pub height: u32,
    /// Bytes per line of the image memories.
    pub pitch: usize,
    /// Master gain as reported by the camera, dB.
    pub gain_db: f32,
}

/// Camera frame numbers → an index that keeps increasing across reconnects (the camera
/// restarts its count when opened).
#[derive(Debug, Default)]
struct FrameCounter {
    base: u64,
    first: Option<u64>,
    last: Option<u64>,
}

impl FrameCounter {
    fn restart(&mut self) {
        self.base = self.last.map_or(0, |last| last + 1);
        self.first = None;
    }

    fn next(&mut self, frame_number: u64) -> u64 {
        let first = *self.first.get_or_insert(frame_number);
        let index = self.base + frame_number.saturating_sub(first);
        self.last = Some(self.last.map_or(index, |last| last.max(index)));
        index
    }
}

/// Codes that mean the camera (or its driver daemon) is not reachable now.
fn camera_absent(code: i32) -> bool {
    matches!(
        code,
        ffi::IS_NO_SUCCESS
            | ffi::IS_INVALID_CAMERA_HANDLE
            | ffi::IS_IO_REQUEST_FAILED
            | ffi::IS_CANT_OPEN_DEVICE
            | ffi::IS_CANT_COMMUNICATE_WITH_DRIVER
            | ffi::IS_CAMERA_NOT_CONNECTED
            | ffi::IS_ALL_DEVICES_BUSY
            | ffi::IS_NO_HARDWARE_INSTALLED
            | ffi::IS_DEVICE_BUSY
    )
}

struct OpenCamera {
    camera: Camera,
    setup: UeyeSetup,
    last_frame: Instant,
}

/// The capture half shared by the probe and the colour camera.
struct UeyeStream {
    config: UeyeConfig,
    label: String,
    api: Option<Arc<Api>>,
    open: Option<OpenCamera>,
    frames: FrameCounter,
}

impl std::fmt::Debug for UeyeStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UeyeStream")
            .field("label", &self.label)
            .field("api", &self.api)
            .field("setup", &self.open.as_ref().map(|o| o.setup))
            .finish_non_exhaustive()
    }
}

impl UeyeStream {
    fn new(config: UeyeConfig) -> Result<Self, DeviceError> {
        let label = format!("ueye camera {}", config.camera_id);
        let bad = |reason: String| DeviceError::Config {
            device: label.clone(),
            reason,
        };
        if config.width.is_some() != config.height.is_some() {
            return Err(bad("give both `width` and `height`, or neither".into()));
        }
        let too_large = |v: Option<u32>| v.is_some_and(|v| v == 0 || i32::try_from(v).is_err());
        if too_large(config.width) || too_large(config.height) {
            return Err(bad(
                "`width` and `height` must be positive pixel counts".into()
            ));
        }
        if config
            .fps
            .is_some_and(|fps| !(fps.is_finite() && fps > 0.0))
        {
            return Err(bad("`fps` must be a positive number".into()));
        }
        if config.gain_percent.is_some_and(|g| g > 100) {
            return Err(bad("`gain_percent` must be within 0–100".into()));
        }
        if config.buffers < 2 || config.pool_frames == 0 {
            return Err(bad(
                "`buffers` must be at least 2 and `pool_frames` positive".into(),
            ));
        }
        if config.frame_timeout_ms == 0
            || config.stall_timeout_ms < u64::from(config.frame_timeout_ms)
        {
            return Err(bad(
                "`frame_timeout_ms` must be positive and at most `stall_timeout_ms`".into(),
            ));
        }
        let exposures = config.exposure_us.iter().chain(&config.bracket_us);
        if exposures.clone().any(|&e| e == 0) {
            return Err(bad("exposures must be positive".into()));
        }
        Ok(Self {
            config,
            label,
            api: None,
            open: None,
            frames: FrameCounter::default(),
        })
    }

    fn config_error(&self, reason: String) -> DeviceError {
        DeviceError::Config {
            device: self.label.clone(),
            reason,
        }
    }

    /// A failed call while opening: an absent camera is retried, anything else cannot work.
    fn open_error(&self, error: &CallError) -> DeviceError {
        if camera_absent(error.code) {
            DeviceError::NotFound {
                device: self.label.clone(),
                reason: error.to_string(),
            }
        } else {
            self.config_error(error.to_string())
        }
    }

    /// Load the library once; it stays loaded across reconnects.
    fn api(&mut self) -> Result<Arc<Api>, DeviceError> {
        if let Some(api) = &self.api {
            return Ok(api.clone());
        }
        let candidates: Vec<String> = match &self.config.library {
            Some(library) => vec![library.clone()],
            None => DEFAULT_LIBRARIES.iter().map(|s| (*s).to_owned()).collect(),
        };
        let api = Api::load(&candidates).map_err(|e| {
            self.config_error(format!(
                "{e}; install the IDS Software Suite or set `library` to libueye_api.so's path"
            ))
        })?;
        tracing::debug!(library = api.path(), "uEye API loaded");
        self.api = Some(api.clone());
        Ok(api)
    }

    /// Open and configure the camera, ready to capture; `exposures_us` are the configured
    /// exposures, checked against the camera's range (empty: exposure left alone).
    fn open(&mut self, exposures_us: &[u32], manual_exposure: bool) -> Result<(), DeviceError> {
        self.close();
        let api = self.api()?;
        let mut camera =
            Camera::init(api, self.config.camera_id).map_err(|e| self.open_error(&e))?;
        let setup = self.configure(&mut camera, exposures_us, manual_exposure)?;
        tracing::info!(device = %self.label, ?setup, "uEye camera open");
        self.frames.restart();
        self.open = Some(OpenCamera {
            camera,
            setup,
            last_frame: Instant::now(),
        });
        Ok(())
    }

    fn configure(
        &self,
        camera: &mut Camera,
        exposures_us: &[u32],
        manual_exposure: bool,
    ) -> Result<UeyeSetup, DeviceError> {
        let config = &self.config;
        let fail = |e: CallError| self.open_error(&e);
        camera.set_display_mode_dib().map_err(fail)?;
        camera.set_trigger_off().map_err(fail)?;
        let mut chosen = None;
        for (layout, mode, bits) in UeyeLayout::PREFERENCE {
            match camera.set_color_mode(mode) {
                Ok(()) => {
                    chosen = Some((layout, bits));
                    break;
                }
                Err(e) if camera_absent(e.code) => return Err(fail(e)),
                Err(e) => {
                    tracing::debug!(device = %self.label, ?layout, error = %e, "colour mode refused")
                }
            }
        }
        let Some((layout, bits)) = chosen else {
            return Err(self.config_error(
                "the camera takes none of the RGB8, BGR8 and mono 8 colour modes".into(),
            ));
        };
        if let (Some(width), Some(height)) = (config.width, config.height) {
            // Both fit in i32, checked in `new`.
            camera.set_aoi(width as i32, height as i32).map_err(|e| {
                if camera_absent(e.code) {
                    fail(e)
                } else {
                    self.config_error(format!("AOI {width}×{height}: {e}"))
                }
            })?;
        }
        let aoi = camera.get_aoi().map_err(fail)?;
        let (Ok(width), Ok(height)) = (u32::try_from(aoi.width), u32::try_from(aoi.height)) else {
            return Err(self.config_error(format!("the camera reports an AOI of {aoi:?}")));
        };
        if width == 0 || height == 0 {
            return Err(self.config_error(format!("the camera reports an AOI of {aoi:?}")));
        }
        if let Some(fps) = config.fps {
            let actual = camera.set_frame_rate(fps).map_err(fail)?;
            if (actual - fps).abs() > 0.01 * fps {
                tracing::warn!(device = %self.label, fps, actual, "frame rate not available");
            }
        }
        if manual_exposure {
            camera
                .set_auto(ffi::IS_SET_ENABLE_AUTO_SHUTTER, false)
                .map_err(fail)?;
            camera
                .set_auto(ffi::IS_SET_ENABLE_AUTO_GAIN, false)
                .map_err(fail)?;
            // Sensor-side automatics exist on some models only.
            for parameter in [
                ffi::IS_SET_ENABLE_AUTO_SENSOR_SHUTTER,
                ffi::IS_SET_ENABLE_AUTO_SENSOR_GAIN,
            ] {
                if let Err(e) = camera.set_auto(parameter, false) {
                    tracing::debug!(device = %self.label, error = %e, "no sensor automatic to switch off");
                }
            }
        } else if exposures_us.is_empty() {
            camera
                .set_auto(ffi::IS_SET_ENABLE_AUTO_SHUTTER, true)
                .map_err(fail)?;
        }
        if let Some(percent) = config.gain_percent {
            // At most 100, checked in `new`.
            camera.set_master_gain(percent as i32).map_err(fail)?;
        }
        let gain_db = (20.0 * camera.master_gain_factor().log10()) as f32;
        if !exposures_us.is_empty() {
            let [min_ms, max_ms, increment_ms] = camera.exposure_range_ms().map_err(fail)?;
            let slack = increment_ms.max(0.0) / 2.0;
            for &exposure_us in exposures_us {
                let ms = f64::from(exposure_us) / 1_000.0;
                if ms < min_ms - slack || ms > max_ms + slack {
                    return Err(self.config_error(format!(
                        "exposure {exposure_us} µs is outside the camera's range \
                         {:.0}–{:.0} µs at this frame rate",
                        min_ms * 1_000.0,
                        max_ms * 1_000.0
                    )));
                }
            }
        }
        let buffers = self.config.buffers as usize;
        let pitch = camera
            .start_ring(width as i32, height as i32, bits, buffers)
            .map_err(fail)?;
        Ok(UeyeSetup {
            layout,
            width,
            height,
            pitch,
            gain_db,
        })
    }

    /// Write an exposure; returns the camera's read-back value in µs.
    fn set_exposure(&self, exposure_us: u32) -> Result<u32, DeviceError> {
        let Some(open) = self.open.as_ref() else {
            return Err(DeviceError::NotFound {
                device: self.label.clone(),
                reason: "not open".into(),
            });
        };
        write_exposure(&open.camera, exposure_us).map_err(|e| self.open_error(&e))
    }

    fn start_capture(&mut self) -> Result<(), DeviceError> {
        let Some(open) = self.open.as_mut() else {
            return Err(DeviceError::NotFound {
                device: self.label.clone(),
                reason: "not open".into(),
            });
        };
        let result = open.camera.capture_video();
        open.last_frame = Instant::now();
        result.map_err(|e| self.open_error(&e))
    }

    fn setup(&self) -> Option<UeyeSetup> {
        self.open.as_ref().map(|o| o.setup)
    }

    /// Wait for the next image and hand it to `use_frame` while it is locked in the ring.
    fn next_frame<T>(
        &mut self,
        use_frame: impl FnOnce(RawFrame<'_>) -> Result<T, DeviceError>,
    ) -> Result<Option<T>, DeviceError> {
        let label = self.label.as_str();
        let Some(open) = self.open.as_mut() else {
            return Err(DeviceError::Disconnected {
                device: label.to_owned(),
                reason: "read before open".into(),
            });
        };
        let timeout_ms = self.config.frame_timeout_ms;
        let stall = Duration::from_millis(self.config.stall_timeout_ms);
        let setup = open.setup;
        let last_frame = &mut open.last_frame;
        match open.camera.wait_for_next_image(timeout_ms) {
            Ok(Wait::Image(locked)) => {
                *last_frame = Instant::now();
                let seq = self.frames.next(locked.info.frame_number);
                use_frame(RawFrame {
                    label,
                    locked,
                    setup,
                    seq,
                })
                .map(Some)
            }
            Ok(Wait::TimedOut) => {
                let waited = last_frame.elapsed();
                if waited > stall {
                    return Err(DeviceError::Disconnected {
                        device: label.to_owned(),
                        reason: format!("no frame for {} ms", waited.as_millis()),
                    });
                }
                Ok(None)
            }
            Err(e) if e.code == ffi::IS_CAPTURE_STATUS => {
                *last_frame = Instant::now();
                Err(DeviceError::BadData {
                    device: label.to_owned(),
                    reason: e.to_string(),
                })
            }
            Err(e) => Err(DeviceError::Disconnected {
                device: label.to_owned(),
                reason: e.to_string(),
            }),
        }
    }

    fn close(&mut self) {
        // Dropping the camera stops the capture, frees the ring and exits the camera.
        self.open = None;
    }
}

fn write_exposure(camera: &Camera, exposure_us: u32) -> Result<u32, CallError> {
    let applied_ms = camera.set_exposure_ms(f64::from(exposure_us) / 1_000.0)?;
    Ok((applied_ms * 1_000.0)
        .round()
        .clamp(0.0, f64::from(u32::MAX)) as u32)
}

/// One image, locked in the ring until this is dropped.
struct RawFrame<'a> {
    label: &'a str,
    locked: LockedImage<'a>,
    setup: UeyeSetup,
    seq: u64,
}

impl RawFrame<'_> {
    fn device_ns(&self) -> u64 {
        self.locked.info.timestamp_device.saturating_mul(100)
    }

    fn set_exposure(&self, exposure_us: u32) -> Result<u32, DeviceError> {
        write_exposure(self.locked.camera(), exposure_us).map_err(|e| DeviceError::Disconnected {
            device: self.label.to_owned(),
            reason: e.to_string(),
        })
    }

    fn convert_into(&self, out: &mut Image) -> Result<(), DeviceError> {
        let UeyeSetup {
            layout,
            width,
            height,
            pitch,
            ..
        } = self.setup;
        let info = &self.locked.info;
        let bad = |reason: String| DeviceError::BadData {
            device: self.label.to_owned(),
            reason,
        };
        if (info.image_width, info.image_height) != (0, 0)
            && (info.image_width, info.image_height) != (width, height)
        {
            return Err(bad(format!(
                "image is {}×{}, the ring was set up for {width}×{height}",
                info.image_width, info.image_height
            )));
        }
        let data = self.locked.data();
        match layout {
            UeyeLayout::Rgb8 => rgb24_to_rgb(data, width, height, pitch, false, out),
            UeyeLayout::Bgr8 => rgb24_to_rgb(data, width, height, pitch, true, out),
            UeyeLayout::Mono8 => grey_to_rgb(data, width, height, pitch, out),
        }
        .map_err(|e| bad(e.to_string()))
    }
}

/// The fish-eye light probe on a uEye camera.
#[derive(Debug)]
pub struct UeyeProbe {
    stream: UeyeStream,
    control: ExposureControl,
    seen_generation: u64,
    schedule: ExposureSchedule,
}

impl UeyeProbe {
    /// Check the configuration; the library and the camera are opened in
    /// [`FrameSource::open`].
    pub fn new(config: UeyeConfig) -> Result<Self, DeviceError> {
        let exposure_us = config.exposure_us.unwrap_or(DEFAULT_PROBE_EXPOSURE_US);
        let control = ExposureControl::new(exposure_us);
        if !config.bracket_us.is_empty() {
            control.set_bracketing(&config.bracket_us);
        }
        let schedule = ExposureSchedule::new(config.exposure_latency_frames, exposure_us);
        Ok(Self {
            stream: UeyeStream::new(config)?,
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

    /// The capture as set up (after a successful open).
    pub fn setup(&self) -> Option<UeyeSetup> {
        self.stream.setup()
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

impl FrameSource for UeyeProbe {
    type Payload = ProbeImage;

    fn backend(&self) -> &'static str {
        "ueye"
    }

    fn stream(&self) -> StreamKind {
        StreamKind::Probe
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        let config = &self.stream.config;
        let mut exposures = config.bracket_us.clone();
        exposures.push(config.exposure_us.unwrap_or(DEFAULT_PROBE_EXPOSURE_US));
        self.stream.open(&exposures, true)?;
        self.seen_generation = u64::MAX;
        if let Some(plan) = self.control.plan_if_changed(&mut self.seen_generation) {
            self.schedule.set_plan(&plan);
        }
        let stream = &self.stream;
        self.schedule.start(|us| stream.set_exposure(us))?;
        self.stream.start_capture()
    }

    fn read(&mut self, frame: &mut Frame<ProbeImage>) -> Result<Capture, DeviceError> {
        if let Some(plan) = self.control.plan_if_changed(&mut self.seen_generation) {
            self.schedule.set_plan(&plan);
        }
        let schedule = &mut self.schedule;
        let captured = self.stream.next_frame(|raw| {
            let Some(exposure_us) = schedule.on_frame(raw.seq, |us| raw.set_exposure(us))? else {
                tracing::trace!(seq = raw.seq, "exposure settling; frame dropped");
                return Ok(false);
            };
            raw.convert_into(&mut frame.payload.image)?;
            frame.payload.exposure_us = exposure_us;
            frame.payload.gain_db = raw.setup.gain_db;
            frame.seq = raw.seq;
            frame.stamp = Timestamp::new(raw.device_ns(), host_now_ns());
            Ok(true)
        })?;
        Ok(match captured {
            Some(true) => Capture::Frame,
            _ => Capture::Idle,
        })
    }

    fn close(&mut self) {
        self.stream.close();
    }
}

impl ProbeSource for UeyeProbe {
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

/// A colour camera on uEye: every frame, as `Rgb8`.
#[derive(Debug)]
pub struct UeyeColor {
    stream: UeyeStream,
}

impl UeyeColor {
    /// Check the configuration (a colour camera takes no bracket); nothing is opened yet.
    pub fn new(config: UeyeConfig) -> Result<Self, DeviceError> {
        let stream = UeyeStream::new(config)?;
        if !stream.config.bracket_us.is_empty() {
            return Err(stream.config_error("`bracket_us` is for the probe only".into()));
        }
        Ok(Self { stream })
    }

    pub fn into_device(self) -> SourceDevice<Self> {
        let pool_frames = self.stream.config.pool_frames;
        SourceDevice::new(self, pool_frames)
    }

    pub fn setup(&self) -> Option<UeyeSetup> {
        self.stream.setup()
    }
}

impl FrameSource for UeyeColor {
    type Payload = Image;

    fn backend(&self) -> &'static str {
        "ueye"
    }

    fn stream(&self) -> StreamKind {
        StreamKind::Color
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        let exposure: Vec<u32> = self.stream.config.exposure_us.into_iter().collect();
        self.stream.open(&exposure, !exposure.is_empty())?;
        if let Some(&exposure_us) = exposure.first() {
            self.stream.set_exposure(exposure_us)?;
        }
        self.stream.start_capture()
    }

    fn read(&mut self, frame: &mut Frame<Image>) -> Result<Capture, DeviceError> {
        let captured = self.stream.next_frame(|raw| {
            raw.convert_into(&mut frame.payload)?;
            frame.seq = raw.seq;
            frame.stamp = Timestamp::new(raw.device_ns(), host_now_ns());
            Ok(())
        })?;
        Ok(match captured {
            Some(()) => Capture::Frame,
            None => Capture::Idle,
        })
    }

    fn close(&mut self) {
        self.stream.close();
    }
}

impl ColorSource for UeyeColor {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_numbers_continue_across_reconnects() {
        let mut frames = FrameCounter::default();
        frames.restart();
        assert_eq!(frames.next(500), 0);
        assert_eq!(frames.next(503), 3);
        frames.restart();
        assert_eq!(frames.next(1), 4);
        assert_eq!(frames.next(2), 5);
    }

    #[test]
    fn a_missing_library_is_a_configuration_error_naming_it() {
        let mut probe = UeyeProbe::new(UeyeConfig {
            library: Some("/nonexistent/libueye_api.so".into()),
            ..UeyeConfig::default()
        })
        .unwrap();
        match probe.open() {
            Err(DeviceError::Config { reason, .. }) => {
                assert!(reason.contains("/nonexistent/libueye_api.so"), "{reason}");
            }
            other => panic!("expected a configuration error, got {other:?}"),
        }
    }

    #[test]
    fn bad_configurations_are_refused_up_front() {
        let refused =
            |config: UeyeConfig| matches!(UeyeProbe::new(config), Err(DeviceError::Config { .. }));
        assert!(refused(UeyeConfig {
            width: Some(640),
            ..UeyeConfig::default()
        }));
        assert!(refused(UeyeConfig {
            gain_percent: Some(101),
            ..UeyeConfig::default()
        }));
        assert!(refused(UeyeConfig {
            bracket_us: vec![100, 0],
            ..UeyeConfig::default()
        }));
        assert!(refused(UeyeConfig {
            fps: Some(f64::NAN),
            ..UeyeConfig::default()
        }));
        assert!(matches!(
            UeyeColor::new(UeyeConfig {
                bracket_us: vec![100],
                ..UeyeConfig::default()
            }),
            Err(DeviceError::Config { .. })
        ));
    }
}
