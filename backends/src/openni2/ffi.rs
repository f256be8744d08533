//! OpenNI2's C API (`OniCAPI.h`, `OniCTypes.h`, `OniCEnums.h`, `OniCProperties.h` of Debian's
//! libopenni2-dev 2.2.0.33), written by hand, and a safe client for it.
//!
//! Every OpenNI call runs on one thread that lives as long as the process (the "OpenNI
//! thread"), which also pumps frames of every started stream to the devices' channels. Two
//! reasons, both OpenNI's:
//! - OpenNI2 has one global context (`oniInitialize` / `oniShutdown`). The OpenNI thread counts
//!   its users (open devices): the first initialises OpenNI, the last shuts it down, so two
//!   devices, or two tests, in one process never pull the context from under each other.
//! - Debian's libOpenNI2 keeps one error buffer per calling thread and, whenever a thread calls
//!   it for the first time, drops the buffers of threads that no longer exist, probing each
//!   with `pthread_kill(id, 0)` (`xnl::ErrorLogger::getBuffer` with `xnOSDoesThreadExistByID`,
//!   XnErrorLogger.cpp, here compiled in its per-thread-map variant). Probing a joined thread
//!   whose stack glibc has unmapped is a use after free: a device thread that called OpenNI,
//!   ended, and was followed by a new calling thread crashed this process in `oniInitialize`
//!   (SIGSEGV in `__pthread_kill_implementation`, on an unmapped thread descriptor). Calling
//!   from one thread that never ends keeps our threads out of that map.

#![allow(unsafe_code)]

use std::cell::Cell;
use std::ffi::{CStr, CString, c_char, c_int, c_void};
use std::fmt;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::ptr::{self, NonNull};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, TrySendError};
use relight_core::frame::host_now_ns;

mod sys {
    use std::ffi::{c_char, c_int, c_void};

    pub type OniStatus = c_int;
    pub type OniBool = c_int;

    pub const ONI_STATUS_OK: OniStatus = 0;
    pub const ONI_STATUS_ERROR: OniStatus = 1;
    pub const ONI_STATUS_NOT_IMPLEMENTED: OniStatus = 2;
    pub const ONI_STATUS_NOT_SUPPORTED: OniStatus = 3;
    pub const ONI_STATUS_BAD_PARAMETER: OniStatus = 4;
    pub const ONI_STATUS_OUT_OF_FLOW: OniStatus = 5;
    pub const ONI_STATUS_NO_DEVICE: OniStatus = 6;
    pub const ONI_STATUS_TIME_OUT: OniStatus = 102;

    /// `ONI_CREATE_API_VERSION(2, 2)` (OniVersion.h).
    pub const ONI_API_VERSION: c_int = 2 * 1000 + 2;
    /// `ONI_MAX_STR` (OniCTypes.h).
    pub const ONI_MAX_STR: usize = 256;

    #[repr(C)]
    #[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
    pub struct OniVideoMode {
        pub pixel_format: c_int,
        pub resolution_x: c_int,
        pub resolution_y: c_int,
        pub fps: c_int,
    }

    #[repr(C)]
    pub struct OniSensorInfo {
        pub sensor_type: c_int,
        pub num_supported_video_modes: c_int,
        pub supported_video_modes: *mut OniVideoMode,
    }

    #[repr(C)]
    pub struct OniDeviceInfo {
        pub uri: [c_char; ONI_MAX_STR],
        pub vendor: [c_char; ONI_MAX_STR],
        pub name: [c_char; ONI_MAX_STR],
        pub usb_vendor_id: u16,
        pub usb_product_id: u16,
    }

    #[repr(C)]
    pub struct OniFrame {
        pub data_size: c_int,
        pub data: *mut c_void,
        pub sensor_type: c_int,
        /// Microseconds on the device clock.
        pub timestamp: u64,
        pub frame_index: c_int,
        pub width: c_int,
        pub height: c_int,
        pub video_mode: OniVideoMode,
        pub cropping_enabled: OniBool,
        pub crop_origin_x: c_int,
        pub crop_origin_y: c_int,
        pub stride: c_int,
    }

    pub type OniDeviceInfoCallback = extern "C" fn(info: *const OniDeviceInfo, cookie: *mut c_void);
    pub type OniDeviceStateCallback =
        extern "C" fn(info: *const OniDeviceInfo, state: c_int, cookie: *mut c_void);

    #[repr(C)]
    pub struct OniDeviceCallbacks {
        pub device_connected: Option<OniDeviceInfoCallback>,
        pub device_disconnected: Option<OniDeviceInfoCallback>,
        pub device_state_changed: Option<OniDeviceStateCallback>,
    }

    /// `_OniDevice`, `_OniStream`, `_OniRecorder`, `OniCallbackHandleImpl`: opaque.
    #[repr(C)]
    pub struct OniDevice {
        _opaque: [u8; 0],
    }
    #[repr(C)]
    pub struct OniStream {
        _opaque: [u8; 0],
    }
    #[repr(C)]
    pub struct OniRecorder {
        _opaque: [u8; 0],
    }
    #[repr(C)]
    pub struct OniCallbackHandleImpl {
        _opaque: [u8; 0],
    }

    pub type OniDeviceHandle = *mut OniDevice;
    pub type OniStreamHandle = *mut OniStream;
    pub type OniRecorderHandle = *mut OniRecorder;
    pub type OniCallbackHandle = *mut OniCallbackHandleImpl;

    #[link(name = "OpenNI2")]
    unsafe extern "C" {
        pub fn oniInitialize(api_version: c_int) -> OniStatus;
        pub fn oniShutdown();
        pub fn oniGetDeviceList(devices: *mut *mut OniDeviceInfo, count: *mut c_int) -> OniStatus;
        pub fn oniReleaseDeviceList(devices: *mut OniDeviceInfo) -> OniStatus;
        pub fn oniRegisterDeviceCallbacks(
            callbacks: *mut OniDeviceCallbacks,
            cookie: *mut c_void,
            handle: *mut OniCallbackHandle,
        ) -> OniStatus;
        pub fn oniUnregisterDeviceCallbacks(handle: OniCallbackHandle);
        pub fn oniWaitForAnyStream(
            streams: *mut OniStreamHandle,
            count: c_int,
            ready_index: *mut c_int,
            timeout_ms: c_int,
        ) -> OniStatus;
        pub fn oniGetExtendedError() -> *const c_char;

        pub fn oniDeviceOpen(uri: *const c_char, device: *mut OniDeviceHandle) -> OniStatus;
        pub fn oniDeviceClose(device: OniDeviceHandle) -> OniStatus;
        pub fn oniDeviceGetSensorInfo(
            device: OniDeviceHandle,
            sensor_type: c_int,
        ) -> *const OniSensorInfo;
        pub fn oniDeviceGetInfo(device: OniDeviceHandle, info: *mut OniDeviceInfo) -> OniStatus;
        pub fn oniDeviceCreateStream(
            device: OniDeviceHandle,
            sensor_type: c_int,
            stream: *mut OniStreamHandle,
        ) -> OniStatus;
        pub fn oniDeviceSetProperty(
            device: OniDeviceHandle,
            property: c_int,
            data: *const c_void,
            size: c_int,
        ) -> OniStatus;
        pub fn oniDeviceIsPropertySupported(device: OniDeviceHandle, property: c_int) -> OniBool;
        pub fn oniDeviceIsImageRegistrationModeSupported(
            device: OniDeviceHandle,
            mode: c_int,
        ) -> OniBool;

        pub fn oniStreamDestroy(stream: OniStreamHandle);
        pub fn oniStreamStart(stream: OniStreamHandle) -> OniStatus;
        pub fn oniStreamStop(stream: OniStreamHandle);
        pub fn oniStreamReadFrame(stream: OniStreamHandle, frame: *mut *mut OniFrame) -> OniStatus;
        pub fn oniStreamSetProperty(
            stream: OniStreamHandle,
            property: c_int,
            data: *const c_void,
            size: c_int,
        ) -> OniStatus;
        pub fn oniStreamGetProperty(
            stream: OniStreamHandle,
            property: c_int,
            data: *mut c_void,
            size: *mut c_int,
        ) -> OniStatus;
        pub fn oniStreamIsPropertySupported(stream: OniStreamHandle, property: c_int) -> OniBool;
        pub fn oniFrameRelease(frame: *mut OniFrame);

        pub fn oniCreateRecorder(
            file_name: *const c_char,
            recorder: *mut OniRecorderHandle,
        ) -> OniStatus;
        pub fn oniRecorderAttachStream(
            recorder: OniRecorderHandle,
            stream: OniStreamHandle,
            allow_lossy_compression: OniBool,
        ) -> OniStatus;
        pub fn oniRecorderStart(recorder: OniRecorderHandle) -> OniStatus;
        pub fn oniRecorderStop(recorder: OniRecorderHandle);
        pub fn oniRecorderDestroy(recorder: *mut OniRecorderHandle) -> OniStatus;
    }
}

pub use sys::OniVideoMode as VideoMode;

/// `OniSensorType`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SensorType {
    Color,
    Depth,
}

impl SensorType {
    fn raw(self) -> c_int {
        match self {
            SensorType::Color => 2,
            SensorType::Depth => 3,
        }
    }
}

/// `OniPixelFormat` values this backend names.
pub mod pixel_format {
    use std::ffi::c_int;

    pub const DEPTH_1_MM: c_int = 100;
    pub const DEPTH_100_UM: c_int = 101;
    pub const SHIFT_9_2: c_int = 102;
    pub const SHIFT_9_3: c_int = 103;
    pub const RGB888: c_int = 200;
    pub const YUV422: c_int = 201;
    pub const GRAY8: c_int = 202;
    pub const GRAY16: c_int = 203;
    pub const JPEG: c_int = 204;
    pub const YUYV: c_int = 205;

    /// The header's name without the `ONI_PIXEL_FORMAT_` prefix.
    pub fn name(format: c_int) -> String {
        match format {
            DEPTH_1_MM => "DEPTH_1_MM".into(),
            DEPTH_100_UM => "DEPTH_100_UM".into(),
            SHIFT_9_2 => "SHIFT_9_2".into(),
            SHIFT_9_3 => "SHIFT_9_3".into(),
            RGB888 => "RGB888".into(),
            YUV422 => "YUV422".into(),
            GRAY8 => "GRAY8".into(),
            GRAY16 => "GRAY16".into(),
            JPEG => "JPEG".into(),
            YUYV => "YUYV".into(),
            other => format!("pixel format {other}"),
        }
    }
}

/// Device properties (OniCProperties.h).
const DEVICE_PROPERTY_IMAGE_REGISTRATION: c_int = 5;
const DEVICE_PROPERTY_PLAYBACK_SPEED: c_int = 100;
const DEVICE_PROPERTY_PLAYBACK_REPEAT_ENABLED: c_int = 101;
/// Stream properties (OniCProperties.h).
const STREAM_PROPERTY_VIDEO_MODE: c_int = 3;
const STREAM_PROPERTY_MIRRORING: c_int = 7;
const STREAM_PROPERTY_NUMBER_OF_FRAMES: c_int = 8;
/// `ONI_IMAGE_REGISTRATION_DEPTH_TO_COLOR`.
const IMAGE_REGISTRATION_DEPTH_TO_COLOR: c_int = 1;
/// `OniDeviceState`.
const DEVICE_STATE_ERROR: c_int = 1;
const DEVICE_STATE_NOT_READY: c_int = 2;
const DEVICE_STATE_EOF: c_int = 3;

/// A failed OpenNI call: its status and OpenNI's own explanation (`oniGetExtendedError`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OniError {
    pub call: &'static str,
    pub status: c_int,
    /// `oniGetExtendedError()` right after the call, its tab-indented lines joined by "; ".
    pub message: String,
}

impl OniError {
    /// Reads OpenNI's thread-local error buffer; call right after the failing function, since
    /// every API entry point clears it.
    fn last(call: &'static str, status: c_int) -> Self {
        // SAFETY: oniGetExtendedError returns a pointer to a NUL-terminated thread-local buffer
        // (XnErrorLogger.h) that stays valid until the next OpenNI call on this thread; it is
        // copied out at once.
        let raw = unsafe { sys::oniGetExtendedError() };
        let message = if raw.is_null() {
            String::new()
        } else {
            // SAFETY: non-null and NUL-terminated, see above.
            let text = unsafe { CStr::from_ptr(raw) }.to_string_lossy();
            text.lines()
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .collect::<Vec<_>>()
                .join("; ")
        };
        Self {
            call,
            status,
            message,
        }
    }
}

fn status_name(status: c_int) -> &'static str {
    match status {
        sys::ONI_STATUS_OK => "OK",
        sys::ONI_STATUS_ERROR => "ERROR",
        sys::ONI_STATUS_NOT_IMPLEMENTED => "NOT_IMPLEMENTED",
        sys::ONI_STATUS_NOT_SUPPORTED => "NOT_SUPPORTED",
        sys::ONI_STATUS_BAD_PARAMETER => "BAD_PARAMETER",
        sys::ONI_STATUS_OUT_OF_FLOW => "OUT_OF_FLOW",
        sys::ONI_STATUS_NO_DEVICE => "NO_DEVICE",
        sys::ONI_STATUS_TIME_OUT => "TIME_OUT",
        _ => "unknown status",
    }
}

impl fmt::Display for OniError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} failed ({})", self.call, status_name(self.status))?;
        if !self.message.is_empty() {
            write!(f, ": {}", self.message)?;
        }
        Ok(())
    }
}

impl std::error::Error for OniError {}

impl OniError {
    /// OpenNI itself could not start (no drivers found, …), as opposed to a device failing.
    pub fn is_initialisation(&self) -> bool {
        self.call == "oniInitialize"
    }
}

fn check(call: &'static str, status: c_int) -> Result<(), OniError> {
    if status == sys::ONI_STATUS_OK {
        Ok(())
    } else {
        Err(OniError::last(call, status))
    }
}

fn c_string(call: &'static str, text: &str) -> Result<CString, OniError> {
    CString::new(text).map_err(|_| OniError {
        call,
        status: sys::ONI_STATUS_BAD_PARAMETER,
        message: format!("{text:?} contains a NUL byte"),
    })
}

fn fixed_str(raw: &[c_char]) -> String {
    let bytes: Vec<u8> = raw
        .iter()
        .take_while(|&&c| c != 0)
        .map(|&c| c as u8)
        .collect();
    String::from_utf8_lossy(&bytes).into_owned()
}

/// What the device callbacks reported about one device URI.
#[derive(Debug, Default)]
pub struct DeviceEvents {
    uri: String,
    disconnected: AtomicBool,
    error: AtomicBool,
    end_of_file: AtomicBool,
}

impl DeviceEvents {
    /// The driver reported the device gone (`deviceDisconnected`) or in error
    /// (`ONI_DEVICE_STATE_ERROR`).
    pub fn lost(&self) -> Option<&'static str> {
        if self.disconnected.load(Ordering::Acquire) {
            Some("OpenNI reported the device disconnected")
        } else if self.error.load(Ordering::Acquire) {
            Some("OpenNI reported the device in error state")
        } else {
            None
        }
    }

    /// A playback device reached the end of its file (`ONI_DEVICE_STATE_EOF`; raised only when
    /// repeat is off).
    pub fn end_of_file(&self) -> bool {
        self.end_of_file.load(Ordering::Acquire)
    }
}

/// Devices whose callbacks are being watched, matched by URI. The callbacks (called on driver
/// threads) only ever touch this static, so one racing with a device closing finds nothing
/// freed.
static WATCHED: Mutex<Vec<Arc<DeviceEvents>>> = Mutex::new(Vec::new());

fn watched_for(info: *const sys::OniDeviceInfo, mut mark: impl FnMut(&DeviceEvents)) {
    if info.is_null() {
        return;
    }
    // SAFETY: OpenNI passes a valid OniDeviceInfo for the duration of the callback.
    let uri = fixed_str(unsafe { &(*info).uri });
    let watched = WATCHED.lock().unwrap_or_else(PoisonError::into_inner);
    for events in watched.iter().filter(|e| e.uri == uri) {
        mark(events);
    }
}

extern "C" fn on_device_disconnected(info: *const sys::OniDeviceInfo, _cookie: *mut c_void) {
    watched_for(info, |e| e.disconnected.store(true, Ordering::Release));
}

extern "C" fn on_device_state_changed(
    info: *const sys::OniDeviceInfo,
    state: c_int,
    _cookie: *mut c_void,
) {
    watched_for(info, |e| match state {
        DEVICE_STATE_ERROR => e.error.store(true, Ordering::Release),
        DEVICE_STATE_EOF => e.end_of_file.store(true, Ordering::Release),
        DEVICE_STATE_NOT_READY => {
            tracing::debug!(uri = %e.uri, "OpenNI reports the device not ready");
        }
        _ => {}
    });
}

/// An entry of OpenNI's device list.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeviceInfo {
    pub uri: String,
    pub vendor: String,
    pub name: String,
    pub usb_vendor_id: u16,
    pub usb_product_id: u16,
}

impl DeviceInfo {
    fn from_raw(raw: &sys::OniDeviceInfo) -> Self {
        Self {
            uri: fixed_str(&raw.uri),
            vendor: fixed_str(&raw.vendor),
            name: fixed_str(&raw.name),
            usb_vendor_id: raw.usb_vendor_id,
            usb_product_id: raw.usb_product_id,
        }
    }
}

/// How long the OpenNI thread waits for frames before it looks at queued calls again (the
/// longest a call waits while streams run).
const PUMP_WAIT_MS: c_int = 10;
/// Pause after a failed wait, so a failing driver is not polled in a busy loop.
const PUMP_ERROR_PAUSE: Duration = Duration::from_millis(10);
/// Frames queued per device; when its consumer is this far behind, newer frames are dropped
/// (and show as gaps in the frame index).
const FRAME_QUEUE: usize = 4;
/// How long a driver thread may take to start running. OpenNI's DummyDevice
/// (`OzStream::threadFunc`) and OniFile (`PlayerDevice::MainLoop`) set their threads' running
/// flags from inside the new thread, so a stop or close that comes first is lost: the thread
/// runs on over a freed object, or the close waits 3 s, cancels it and the process crashes
/// later (reproduced with a playback device closed right after opening: SIGSEGV in most runs).
/// Streams are never stopped, nor playback devices closed, sooner than this after starting.
const THREAD_START_GRACE: Duration = Duration::from_millis(100);

type Job = Box<dyn FnOnce(&mut Hub) + Send>;

thread_local! {
    static ON_OPENNI_THREAD: Cell<bool> = const { Cell::new(false) };
}

static OPENNI: OnceLock<Result<OpenNi, String>> = OnceLock::new();

/// A handle to the process's OpenNI thread.
#[derive(Clone)]
pub struct OpenNi {
    jobs: Sender<Job>,
}

impl fmt::Debug for OpenNi {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("OpenNi")
    }
}

fn thread_gone(detail: &str) -> OniError {
    OniError {
        call: "the OpenNI thread",
        status: sys::ONI_STATUS_ERROR,
        message: detail.to_owned(),
    }
}

impl OpenNi {
    /// The OpenNI thread, started on first use. OpenNI itself is initialised only while a
    /// device is open.
    pub fn get() -> Result<OpenNi, OniError> {
        OPENNI
            .get_or_init(|| {
                let (jobs, queue) = crossbeam_channel::unbounded::<Job>();
                std::thread::Builder::new()
                    .name("openni2".into())
                    .spawn(move || run_openni_thread(&queue))
                    .map(|_| OpenNi { jobs })
                    .map_err(|e| format!("cannot start the OpenNI thread: {e}"))
            })
            .clone()
            .map_err(|message| thread_gone(&message))
    }

    /// Runs `job` on the OpenNI thread and waits for its result.
    fn call<R: Send + 'static>(
        &self,
        job: impl FnOnce(&mut Hub) -> Result<R, OniError> + Send + 'static,
    ) -> Result<R, OniError> {
        if ON_OPENNI_THREAD.with(Cell::get) {
            return Err(thread_gone(
                "an OpenNI call was made from the OpenNI thread itself",
            ));
        }
        let (reply, result) = crossbeam_channel::bounded(1);
        self.jobs
            .send(Box::new(move |hub: &mut Hub| {
                // The caller may have stopped waiting; nothing to do then.
                let _ = reply.send(job(hub));
            }))
            .map_err(|_| thread_gone("it has ended"))?;
        result
            .recv()
            .map_err(|_| thread_gone("the call failed on it (see the log)"))?
    }

    /// OpenNI's device list (initialising OpenNI for the call if no device is open).
    pub fn device_list(&self) -> Result<Vec<DeviceInfo>, OniError> {
        self.call(|hub| {
            hub.acquire()?;
            let list = hub.device_list();
            hub.release();
            list
        })
    }

    /// Opens `uri`, or the first enumerated device when `None`. OpenNI tries every driver
    /// with an unknown URI, which is how `Dummy` (DummyDevice) and `.oni` paths (OniFile) open.
    pub fn open(&self, uri: Option<&str>) -> Result<DeviceHandle, OniError> {
        let uri = uri.map(str::to_owned);
        let (id, info, events, playback) = self.call(move |hub| hub.open(uri))?;
        Ok(DeviceHandle {
            id,
            openni: self.clone(),
            info,
            events,
            playback,
        })
    }
}

fn run_openni_thread(queue: &Receiver<Job>) {
    ON_OPENNI_THREAD.with(|flag| flag.set(true));
    let mut hub = Hub::new();
    loop {
        let job = if hub.active.is_empty() {
            match queue.recv() {
                Ok(job) => Some(job),
                Err(_) => return,
            }
        } else {
            queue.try_recv().ok()
        };
        match job {
            Some(job) => {
                if catch_unwind(AssertUnwindSafe(|| job(&mut hub))).is_err() {
                    tracing::error!("an OpenNI call panicked; its caller gets an error");
                }
            }
            None => hub.pump(),
        }
    }
}

/// Identifies a stream of a [`DeviceHandle`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct StreamId(u64);

/// A frame copied out of OpenNI by the OpenNI thread.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawFrame {
    pub stream: StreamId,
    /// The driver's frame counter.
    pub index: i64,
    /// Device clock, microseconds.
    pub timestamp_us: u64,
    /// Host clock (ns since the Unix epoch) when OpenNI handed the frame over.
    pub host_ns: u64,
    pub width: i32,
    pub height: i32,
    /// Bytes per row as delivered (may exceed width × bytes per pixel).
    pub stride: i32,
    pub pixel_format: c_int,
    /// The pixel buffer (`dataSize` bytes).
    pub data: Vec<u8>,
}

/// Where the OpenNI thread puts a device's frames, and where their buffers come back.
#[derive(Clone)]
struct FrameSink {
    frames: Sender<RawFrame>,
    spare: Receiver<Vec<u8>>,
}

/// The frames of a device's started streams, oldest first.
#[derive(Debug)]
pub struct FrameReceiver {
    frames: Receiver<RawFrame>,
    spare: Sender<Vec<u8>>,
}

/// The device was closed; no frame will come.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamsClosed;

impl FrameReceiver {
    /// The next frame, `None` after `timeout`.
    pub fn recv_timeout(&self, timeout: Duration) -> Result<Option<RawFrame>, StreamsClosed> {
        match self.frames.recv_timeout(timeout) {
            Ok(frame) => Ok(Some(frame)),
            Err(RecvTimeoutError::Timeout) => Ok(None),
            Err(RecvTimeoutError::Disconnected) => Err(StreamsClosed),
        }
    }

    /// Gives the frame's buffer back to the OpenNI thread, so steady capture allocates nothing.
    pub fn recycle(&self, frame: RawFrame) {
        let _ = self.spare.try_send(frame.data);
    }
}

/// An open OpenNI device; closed (its streams and recorder first) when dropped.
pub struct DeviceHandle {
    id: u64,
    openni: OpenNi,
    info: DeviceInfo,
    events: Arc<DeviceEvents>,
    playback: bool,
}

impl fmt::Debug for DeviceHandle {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("DeviceHandle")
            .field("info", &self.info)
            .field("playback", &self.playback)
            .finish_non_exhaustive()
    }
}

impl DeviceHandle {
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }

    pub fn events(&self) -> &DeviceEvents {
        &self.events
    }

    /// Whether this plays a recording (it has `ONI_DEVICE_PROPERTY_PLAYBACK_SPEED`).
    pub fn is_playback(&self) -> bool {
        self.playback
    }

    /// The video modes the device lists for `sensor`, or `None` when it has no such sensor.
    pub fn sensor_modes(&self, sensor: SensorType) -> Result<Option<Vec<VideoMode>>, OniError> {
        let id = self.id;
        self.openni.call(move |hub| hub.sensor_modes(id, sensor))
    }

    pub fn create_stream(&self, sensor: SensorType) -> Result<StreamId, OniError> {
        let id = self.id;
        self.openni.call(move |hub| hub.create_stream(id, sensor))
    }

    pub fn video_mode(&self, stream: StreamId) -> Result<VideoMode, OniError> {
        self.openni.call(move |hub| {
            let mut mode = VideoMode::default();
            hub.get_stream_property(
                stream,
                "oniStreamGetProperty(VIDEO_MODE)",
                STREAM_PROPERTY_VIDEO_MODE,
                &mut mode,
            )?;
            Ok(mode)
        })
    }

    pub fn set_video_mode(&self, stream: StreamId, mode: VideoMode) -> Result<(), OniError> {
        self.openni.call(move |hub| {
            hub.set_stream_property(
                stream,
                "oniStreamSetProperty(VIDEO_MODE)",
                STREAM_PROPERTY_VIDEO_MODE,
                &mode,
            )
        })
    }

    pub fn is_mirroring_supported(&self, stream: StreamId) -> Result<bool, OniError> {
        self.openni.call(move |hub| {
            let handle = hub.stream(stream)?.handle;
            // SAFETY: a live stream handle.
            Ok(unsafe {
                sys::oniStreamIsPropertySupported(handle.as_ptr(), STREAM_PROPERTY_MIRRORING)
            } != 0)
        })
    }

    pub fn set_mirroring(&self, stream: StreamId, mirror: bool) -> Result<(), OniError> {
        let value: sys::OniBool = mirror.into();
        self.openni.call(move |hub| {
            hub.set_stream_property(
                stream,
                "oniStreamSetProperty(MIRRORING)",
                STREAM_PROPERTY_MIRRORING,
                &value,
            )
        })
    }

    /// Frames in the recording, for playback streams (`ONI_STREAM_PROPERTY_NUMBER_OF_FRAMES`).
    pub fn number_of_frames(&self, stream: StreamId) -> Result<u32, OniError> {
        self.openni.call(move |hub| {
            let mut frames: c_int = 0;
            hub.get_stream_property(
                stream,
                "oniStreamGetProperty(NUMBER_OF_FRAMES)",
                STREAM_PROPERTY_NUMBER_OF_FRAMES,
                &mut frames,
            )?;
            Ok(u32::try_from(frames).unwrap_or(0))
        })
    }

    pub fn is_registration_supported(&self) -> Result<bool, OniError> {
        let id = self.id;
        self.openni.call(move |hub| {
            let handle = hub.device(id)?.handle;
            // SAFETY: a live device handle.
            Ok(unsafe {
                sys::oniDeviceIsImageRegistrationModeSupported(
                    handle.as_ptr(),
                    IMAGE_REGISTRATION_DEPTH_TO_COLOR,
                )
            } != 0)
        })
    }

    /// Maps depth pixels onto the colour camera (`ONI_IMAGE_REGISTRATION_DEPTH_TO_COLOR`).
    pub fn set_registration_depth_to_color(&self) -> Result<(), OniError> {
        let id = self.id;
        self.openni.call(move |hub| {
            hub.set_device_property(
                id,
                "oniDeviceSetProperty(IMAGE_REGISTRATION)",
                DEVICE_PROPERTY_IMAGE_REGISTRATION,
                &IMAGE_REGISTRATION_DEPTH_TO_COLOR,
            )
        })
    }

    /// Playback speed as a multiple of recorded time (`ONI_DEVICE_PROPERTY_PLAYBACK_SPEED`).
    pub fn set_playback_speed(&self, speed: f32) -> Result<(), OniError> {
        let id = self.id;
        self.openni.call(move |hub| {
            hub.set_device_property(
                id,
                "oniDeviceSetProperty(PLAYBACK_SPEED)",
                DEVICE_PROPERTY_PLAYBACK_SPEED,
                &speed,
            )
        })
    }

    /// Rewind at end of file (`ONI_DEVICE_PROPERTY_PLAYBACK_REPEAT_ENABLED`; OniFile's default
    /// is on).
    pub fn set_playback_repeat(&self, repeat: bool) -> Result<(), OniError> {
        let id = self.id;
        let value: sys::OniBool = repeat.into();
        self.openni.call(move |hub| {
            hub.set_device_property(
                id,
                "oniDeviceSetProperty(PLAYBACK_REPEAT_ENABLED)",
                DEVICE_PROPERTY_PLAYBACK_REPEAT_ENABLED,
                &value,
            )
        })
    }

    /// Starts `streams`; their frames arrive, oldest first, on the returned receiver.
    pub fn start(&self, streams: &[StreamId]) -> Result<FrameReceiver, OniError> {
        let (frames_tx, frames) = crossbeam_channel::bounded(FRAME_QUEUE);
        let (spare, spare_rx) = crossbeam_channel::bounded(FRAME_QUEUE + 2);
        let sink = FrameSink {
            frames: frames_tx,
            spare: spare_rx,
        };
        let streams = streams.to_vec();
        self.openni.call(move |hub| hub.start(&streams, &sink))?;
        Ok(FrameReceiver { frames, spare })
    }

    /// Records every stream of this device into the `.oni` file `path` with OpenNI's recorder
    /// (lossless: 16z for depth, uncompressed colour), from now until
    /// [`DeviceHandle::stop_recording`].
    pub fn start_recording(&self, path: &str) -> Result<(), OniError> {
        let id = self.id;
        let path = c_string("oniCreateRecorder", path)?;
        self.openni.call(move |hub| hub.start_recording(id, &path))
    }

    /// Stops recording and closes the file (seek tables written).
    pub fn stop_recording(&self) -> Result<(), OniError> {
        let id = self.id;
        self.openni.call(move |hub| {
            hub.stop_recording(id);
            Ok(())
        })
    }
}

impl Drop for DeviceHandle {
    fn drop(&mut self) {
        let id = self.id;
        if let Err(error) = self.openni.call(move |hub| {
            hub.close(id);
            Ok(())
        }) {
            tracing::warn!(%error, uri = %self.info.uri, "closing the OpenNI device");
        }
    }
}

struct DeviceEntry {
    id: u64,
    handle: NonNull<sys::OniDevice>,
    events: Arc<DeviceEvents>,
    opened_at: Instant,
    playback: bool,
}

struct StreamEntry {
    id: u64,
    device: u64,
    handle: NonNull<sys::OniStream>,
    started_at: Option<Instant>,
    /// Longest time the driver may still deliver after `oniStreamStop` (1.5 frame periods).
    settle: Duration,
    sink: Option<FrameSink>,
}

struct RecorderEntry {
    device: u64,
    handle: sys::OniRecorderHandle,
}

/// OpenNI's state, owned by the OpenNI thread.
struct Hub {
    /// Open devices; OpenNI is initialised while this is positive.
    users: usize,
    callbacks: sys::OniCallbackHandle,
    next_id: u64,
    devices: Vec<DeviceEntry>,
    streams: Vec<StreamEntry>,
    recorders: Vec<RecorderEntry>,
    /// The started streams, as oniWaitForAnyStream takes them, and their ids.
    active: Vec<sys::OniStreamHandle>,
    active_ids: Vec<u64>,
}

fn sleep_until(deadline: Instant) {
    let now = Instant::now();
    if deadline > now {
        std::thread::sleep(deadline - now);
    }
}

impl Hub {
    fn new() -> Self {
        Self {
            users: 0,
            callbacks: ptr::null_mut(),
            next_id: 1,
            devices: Vec::new(),
            streams: Vec::new(),
            recorders: Vec::new(),
            active: Vec::new(),
            active_ids: Vec::new(),
        }
    }

    fn acquire(&mut self) -> Result<(), OniError> {
        if self.users == 0 {
            // SAFETY: OpenNI is not initialised (no user), and only this thread calls it.
            let status = unsafe { sys::oniInitialize(sys::ONI_API_VERSION) };
            if status != sys::ONI_STATUS_OK {
                let error = OniError::last("oniInitialize", status);
                // OpenNI counts initialisations itself; balance the failed one.
                // SAFETY: shutting down after a failed initialise only unwinds its counter.
                unsafe { sys::oniShutdown() };
                return Err(error);
            }
            let mut callbacks = sys::OniDeviceCallbacks {
                device_connected: None,
                device_disconnected: Some(on_device_disconnected),
                device_state_changed: Some(on_device_state_changed),
            };
            let mut handle: sys::OniCallbackHandle = ptr::null_mut();
            // SAFETY: OpenNI copies the function pointers out of `callbacks` during the call;
            // the functions are 'static and the cookie is unused.
            let status = unsafe {
                sys::oniRegisterDeviceCallbacks(&mut callbacks, ptr::null_mut(), &mut handle)
            };
            if status != sys::ONI_STATUS_OK {
                tracing::warn!(
                    error = %OniError::last("oniRegisterDeviceCallbacks", status),
                    "OpenNI device events unavailable; relying on frame timeouts"
                );
                handle = ptr::null_mut();
            }
            self.callbacks = handle;
        }
        self.users += 1;
        Ok(())
    }

    fn release(&mut self) {
        self.users = self.users.saturating_sub(1);
        if self.users == 0 {
            if !self.callbacks.is_null() {
                // SAFETY: the handle came from oniRegisterDeviceCallbacks of this
                // initialisation.
                unsafe { sys::oniUnregisterDeviceCallbacks(self.callbacks) };
                self.callbacks = ptr::null_mut();
            }
            // SAFETY: the last user is gone: every device, stream and recorder is destroyed.
            unsafe { sys::oniShutdown() };
        }
    }

    fn next_id(&mut self) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        id
    }

    fn device(&self, id: u64) -> Result<&DeviceEntry, OniError> {
        self.devices
            .iter()
            .find(|d| d.id == id)
            .ok_or_else(|| thread_gone("the device is closed"))
    }

    fn stream(&self, id: StreamId) -> Result<&StreamEntry, OniError> {
        self.streams
            .iter()
            .find(|s| s.id == id.0)
            .ok_or_else(|| thread_gone("the stream is closed"))
    }

    fn device_list(&mut self) -> Result<Vec<DeviceInfo>, OniError> {
        let mut list: *mut sys::OniDeviceInfo = ptr::null_mut();
        let mut count: c_int = 0;
        // SAFETY: out-pointers to locals; OpenNI allocates the array.
        check("oniGetDeviceList", unsafe {
            sys::oniGetDeviceList(&mut list, &mut count)
        })?;
        let devices = match usize::try_from(count) {
            Ok(count) if count > 0 && !list.is_null() => {
                // SAFETY: OpenNI returned `count` contiguous OniDeviceInfo at `list`.
                unsafe { std::slice::from_raw_parts(list, count) }
                    .iter()
                    .map(DeviceInfo::from_raw)
                    .collect()
            }
            _ => Vec::new(),
        };
        if !list.is_null() {
            // SAFETY: the array came from oniGetDeviceList and is released once.
            unsafe { sys::oniReleaseDeviceList(list) };
        }
        Ok(devices)
    }

    fn open(
        &mut self,
        uri: Option<String>,
    ) -> Result<(u64, DeviceInfo, Arc<DeviceEvents>, bool), OniError> {
        self.acquire()?;
        match self.open_acquired(uri) {
            Ok(opened) => Ok(opened),
            Err(error) => {
                self.release();
                Err(error)
            }
        }
    }

    fn open_acquired(
        &mut self,
        uri: Option<String>,
    ) -> Result<(u64, DeviceInfo, Arc<DeviceEvents>, bool), OniError> {
        let uri = match uri {
            Some(uri) => uri,
            None => match self.device_list()?.into_iter().next() {
                Some(first) => first.uri,
                None => {
                    return Err(OniError {
                        call: "oniGetDeviceList",
                        status: sys::ONI_STATUS_NO_DEVICE,
                        message: "no device connected".into(),
                    });
                }
            },
        };
        let c_uri = c_string("oniDeviceOpen", &uri)?;
        let mut raw: sys::OniDeviceHandle = ptr::null_mut();
        // SAFETY: a NUL-terminated string and an out-pointer to a local.
        check("oniDeviceOpen", unsafe {
            sys::oniDeviceOpen(c_uri.as_ptr(), &mut raw)
        })?;
        let handle = NonNull::new(raw).ok_or_else(|| OniError {
            call: "oniDeviceOpen",
            status: sys::ONI_STATUS_ERROR,
            message: "returned no handle".into(),
        })?;
        let opened_at = Instant::now();
        let mut raw_info = std::mem::MaybeUninit::<sys::OniDeviceInfo>::zeroed();
        // SAFETY: a live handle; OpenNI copies a whole OniDeviceInfo into the buffer.
        let info_status = unsafe { sys::oniDeviceGetInfo(handle.as_ptr(), raw_info.as_mut_ptr()) };
        let info = if info_status == sys::ONI_STATUS_OK {
            // SAFETY: zero-initialised, then filled by OpenNI: a valid OniDeviceInfo.
            DeviceInfo::from_raw(unsafe { raw_info.assume_init_ref() })
        } else {
            DeviceInfo {
                uri: uri.clone(),
                vendor: String::new(),
                name: String::new(),
                usb_vendor_id: 0,
                usb_product_id: 0,
            }
        };
        // SAFETY: a live handle.
        let playback = unsafe {
            sys::oniDeviceIsPropertySupported(handle.as_ptr(), DEVICE_PROPERTY_PLAYBACK_SPEED)
        } != 0;
        let events = Arc::new(DeviceEvents {
            uri: info.uri.clone(),
            ..DeviceEvents::default()
        });
        WATCHED
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(events.clone());
        let id = self.next_id();
        self.devices.push(DeviceEntry {
            id,
            handle,
            events: events.clone(),
            opened_at,
            playback,
        });
        Ok((id, info, events, playback))
    }

    fn sensor_modes(
        &self,
        device: u64,
        sensor: SensorType,
    ) -> Result<Option<Vec<VideoMode>>, OniError> {
        let handle = self.device(device)?.handle;
        // SAFETY: a live handle; the returned pointer is owned by the device and read at once.
        let info = unsafe { sys::oniDeviceGetSensorInfo(handle.as_ptr(), sensor.raw()) };
        // SAFETY: non-null pointers from OpenNI point to a live OniSensorInfo.
        let Some(info) = (unsafe { info.as_ref() }) else {
            return Ok(None);
        };
        let modes = match usize::try_from(info.num_supported_video_modes) {
            Ok(n) if n > 0 && !info.supported_video_modes.is_null() => {
                // SAFETY: the sensor info points to `num_supported_video_modes` modes.
                unsafe { std::slice::from_raw_parts(info.supported_video_modes, n) }.to_vec()
            }
            _ => Vec::new(),
        };
        Ok(Some(modes))
    }

    fn create_stream(&mut self, device: u64, sensor: SensorType) -> Result<StreamId, OniError> {
        let device_handle = self.device(device)?.handle;
        let mut raw: sys::OniStreamHandle = ptr::null_mut();
        // SAFETY: a live device handle and an out-pointer to a local.
        check("oniDeviceCreateStream", unsafe {
            sys::oniDeviceCreateStream(device_handle.as_ptr(), sensor.raw(), &mut raw)
        })?;
        let handle = NonNull::new(raw).ok_or_else(|| OniError {
            call: "oniDeviceCreateStream",
            status: sys::ONI_STATUS_ERROR,
            message: "returned no handle".into(),
        })?;
        let id = self.next_id();
        self.streams.push(StreamEntry {
            id,
            device,
            handle,
            started_at: None,
            settle: Duration::ZERO,
            sink: None,
        });
        Ok(StreamId(id))
    }

    fn set_device_property<T>(
        &self,
        device: u64,
        call: &'static str,
        property: c_int,
        value: &T,
    ) -> Result<(), OniError> {
        let handle = self.device(device)?.handle;
        // SAFETY: a live handle; `value` points to size_of::<T>() readable bytes of the type
        // the header documents for `property`.
        check(call, unsafe {
            sys::oniDeviceSetProperty(
                handle.as_ptr(),
                property,
                ptr::from_ref(value).cast(),
                size_of::<T>() as c_int,
            )
        })
    }

    fn set_stream_property<T>(
        &self,
        stream: StreamId,
        call: &'static str,
        property: c_int,
        value: &T,
    ) -> Result<(), OniError> {
        let handle = self.stream(stream)?.handle;
        // SAFETY: a live handle; `value` points to size_of::<T>() readable bytes of the type
        // the header documents for `property`.
        check(call, unsafe {
            sys::oniStreamSetProperty(
                handle.as_ptr(),
                property,
                ptr::from_ref(value).cast(),
                size_of::<T>() as c_int,
            )
        })
    }

    fn get_stream_property<T>(
        &self,
        stream: StreamId,
        call: &'static str,
        property: c_int,
        value: &mut T,
    ) -> Result<(), OniError> {
        let handle = self.stream(stream)?.handle;
        let mut size = size_of::<T>() as c_int;
        // SAFETY: a live handle; `value` points to size_of::<T>() writable bytes of the type
        // the header documents for `property`, and OpenNI checks `size` against it.
        check(call, unsafe {
            sys::oniStreamGetProperty(
                handle.as_ptr(),
                property,
                ptr::from_mut(value).cast(),
                &mut size,
            )
        })
    }

    fn start(&mut self, streams: &[StreamId], sink: &FrameSink) -> Result<(), OniError> {
        for &stream in streams {
            let mut mode = VideoMode::default();
            let settle = match self.get_stream_property(
                stream,
                "oniStreamGetProperty(VIDEO_MODE)",
                STREAM_PROPERTY_VIDEO_MODE,
                &mut mode,
            ) {
                Ok(()) if mode.fps > 0 => Duration::from_secs_f64(1.5 / f64::from(mode.fps))
                    .min(Duration::from_millis(250)),
                _ => Duration::from_millis(100),
            };
            let handle = self.stream(stream)?.handle;
            // SAFETY: a live stream handle.
            check("oniStreamStart", unsafe {
                sys::oniStreamStart(handle.as_ptr())
            })?;
            if let Some(entry) = self.streams.iter_mut().find(|s| s.id == stream.0) {
                entry.started_at = Some(Instant::now());
                entry.settle = settle;
                entry.sink = Some(sink.clone());
            }
            self.active.push(handle.as_ptr());
            self.active_ids.push(stream.0);
        }
        Ok(())
    }

    /// Waits briefly for a frame on any started stream and hands it to its device.
    fn pump(&mut self) {
        let mut ready: c_int = -1;
        let count = c_int::try_from(self.active.len()).unwrap_or(c_int::MAX);
        // SAFETY: `active` holds live handles of started streams; `ready` is a local.
        let status = unsafe {
            sys::oniWaitForAnyStream(self.active.as_mut_ptr(), count, &mut ready, PUMP_WAIT_MS)
        };
        match status {
            sys::ONI_STATUS_OK => {}
            sys::ONI_STATUS_TIME_OUT => return,
            status => {
                tracing::trace!(error = %OniError::last("oniWaitForAnyStream", status), "waiting for frames");
                std::thread::sleep(PUMP_ERROR_PAUSE);
                return;
            }
        }
        let Some(&stream_id) = usize::try_from(ready)
            .ok()
            .and_then(|i| self.active_ids.get(i))
        else {
            return;
        };
        let Some(entry) = self.streams.iter().find(|s| s.id == stream_id) else {
            return;
        };
        let host_ns = host_now_ns();
        let mut frame: *mut sys::OniFrame = ptr::null_mut();
        // SAFETY: a live, started stream with a frame waiting; an out-pointer to a local.
        let status = unsafe { sys::oniStreamReadFrame(entry.handle.as_ptr(), &mut frame) };
        if status != sys::ONI_STATUS_OK || frame.is_null() {
            tracing::trace!(error = %OniError::last("oniStreamReadFrame", status), "reading a frame");
            return;
        }
        // SAFETY: OpenNI returned a valid frame, valid until oniFrameRelease below.
        let raw = unsafe { &*frame };
        if let Some(sink) = &entry.sink {
            let mut data = sink.spare.try_recv().unwrap_or_default();
            data.clear();
            if let Ok(len) = usize::try_from(raw.data_size)
                && len > 0
                && !raw.data.is_null()
            {
                // SAFETY: the frame holds `dataSize` bytes at `data` until released.
                data.extend_from_slice(unsafe {
                    std::slice::from_raw_parts(raw.data.cast::<u8>(), len)
                });
            }
            let copied = RawFrame {
                stream: StreamId(stream_id),
                index: i64::from(raw.frame_index),
                timestamp_us: raw.timestamp,
                host_ns,
                width: raw.width,
                height: raw.height,
                stride: raw.stride,
                pixel_format: raw.video_mode.pixel_format,
                data,
            };
            if let Err(TrySendError::Full(_)) = sink.frames.try_send(copied) {
                tracing::trace!("consumer behind; frame dropped");
            }
        }
        // SAFETY: the frame came from oniStreamReadFrame and is released once.
        unsafe { sys::oniFrameRelease(frame) };
    }

    fn start_recording(&mut self, device: u64, path: &CStr) -> Result<(), OniError> {
        self.device(device)?;
        let mut handle: sys::OniRecorderHandle = ptr::null_mut();
        // SAFETY: a NUL-terminated path and an out-pointer to a local.
        check("oniCreateRecorder", unsafe {
            sys::oniCreateRecorder(path.as_ptr(), &mut handle)
        })?;
        if handle.is_null() {
            return Err(OniError {
                call: "oniCreateRecorder",
                status: sys::ONI_STATUS_ERROR,
                message: "returned no handle".into(),
            });
        }
        self.recorders.push(RecorderEntry { device, handle });
        let streams: Vec<_> = self
            .streams
            .iter()
            .filter(|s| s.device == device)
            .map(|s| s.handle)
            .collect();
        for stream in streams {
            // SAFETY: live recorder and stream handles; no lossy compression.
            let status = unsafe { sys::oniRecorderAttachStream(handle, stream.as_ptr(), 0) };
            if let Err(error) = check("oniRecorderAttachStream", status) {
                self.stop_recording(device);
                return Err(error);
            }
        }
        // SAFETY: a live recorder handle.
        if let Err(error) = check("oniRecorderStart", unsafe { sys::oniRecorderStart(handle) }) {
            self.stop_recording(device);
            return Err(error);
        }
        Ok(())
    }

    fn stop_recording(&mut self, device: u64) {
        let (mine, others) = std::mem::take(&mut self.recorders)
            .into_iter()
            .partition(|r| r.device == device);
        self.recorders = others;
        for mut recorder in mine {
            // SAFETY: a live recorder handle; stopped, then destroyed once (which detaches
            // the streams, writes the seek tables and closes the file; OpenNI nulls the
            // handle).
            unsafe { sys::oniRecorderStop(recorder.handle) };
            // SAFETY: see above.
            let status = unsafe { sys::oniRecorderDestroy(&mut recorder.handle) };
            if status != sys::ONI_STATUS_OK {
                tracing::warn!(error = %OniError::last("oniRecorderDestroy", status), "closing recorder");
            }
        }
    }

    fn close(&mut self, device: u64) {
        self.stop_recording(device);
        let (mine, others): (Vec<_>, Vec<_>) = std::mem::take(&mut self.streams)
            .into_iter()
            .partition(|s| s.device == device);
        self.streams = others;
        let mut settle = Duration::ZERO;
        for stream in &mine {
            if let Some(started_at) = stream.started_at {
                sleep_until(started_at + THREAD_START_GRACE);
                // SAFETY: a live, started stream handle.
                unsafe { sys::oniStreamStop(stream.handle.as_ptr()) };
                settle = settle.max(stream.settle);
            }
        }
        // Some drivers stop lazily: DummyDevice only clears a flag that its frame thread checks
        // once per frame period (OzStream::stop), and the thread uses the stream until then.
        std::thread::sleep(settle);
        for stream in mine {
            // SAFETY: a live handle, destroyed once; its frames were all released (pump).
            unsafe { sys::oniStreamDestroy(stream.handle.as_ptr()) };
        }
        self.active.clear();
        self.active_ids.clear();
        for stream in self.streams.iter().filter(|s| s.started_at.is_some()) {
            self.active.push(stream.handle.as_ptr());
            self.active_ids.push(stream.id);
        }

        let Some(position) = self.devices.iter().position(|d| d.id == device) else {
            return;
        };
        let entry = self.devices.swap_remove(position);
        if entry.playback {
            sleep_until(entry.opened_at + THREAD_START_GRACE);
        }
        WATCHED
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .retain(|e| !Arc::ptr_eq(e, &entry.events));
        // SAFETY: a live handle whose streams and recorders are destroyed; closed once.
        let status = unsafe { sys::oniDeviceClose(entry.handle.as_ptr()) };
        if status != sys::ONI_STATUS_OK {
            tracing::debug!(error = %OniError::last("oniDeviceClose", status), "closing device");
        }
        self.release();
    }
}
