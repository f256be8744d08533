//! Hand-written bindings to the libfreenect 0.5 C API (`/usr/include/libfreenect.h`, Debian
//! `libfreenect-dev`) and the one safe wrapper the backend uses: a [`Session`] owning a context,
//! one opened camera subdevice and the buffers its frame callbacks copy into.
//!
//! The library is linked at build time (`-lfreenect`, soname `libfreenect.so.0.5`), which is
//! also what lets a process run against fakenect, libfreenect's replay library of the same
//! soname, by putting fakenect's directory on `LD_LIBRARY_PATH` ([`library_is_fakenect`] tells
//! the two apart at run time).

#![allow(unsafe_code)]

use std::ffi::{CStr, CString, c_char, c_int, c_long, c_void};
use std::ptr;
use std::time::Duration;

use relight_core::frame::host_now_ns;

mod sys {
    use std::ffi::{c_char, c_int, c_long, c_void};

    /// `freenect_context` (opaque).
    #[repr(C)]
    pub struct Context {
        _private: [u8; 0],
    }

    /// `freenect_device` (opaque; fakenect hands out a dummy address, never dereference it).
    #[repr(C)]
    pub struct Device {
        _private: [u8; 0],
    }

    /// `freenect_frame_mode`; the anonymous union of video/depth format is an `int32_t`.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct FrameMode {
        pub reserved: u32,
        pub resolution: c_int,
        pub format: i32,
        pub bytes: i32,
        pub width: i16,
        pub height: i16,
        pub data_bits_per_pixel: i8,
        pub padding_bits_per_pixel: i8,
        pub framerate: i8,
        pub is_valid: i8,
    }

    /// `struct timeval` (Linux: `time_t` and `suseconds_t` are `long`).
    #[repr(C)]
    pub struct Timeval {
        pub tv_sec: c_long,
        pub tv_usec: c_long,
    }

    pub type FrameCb = unsafe extern "C" fn(dev: *mut Device, data: *mut c_void, timestamp: u32);
    pub type LogCb = unsafe extern "C" fn(ctx: *mut Context, level: c_int, msg: *const c_char);

    pub const DEVICE_CAMERA: c_int = 0x02;
    pub const LOG_NOTICE: c_int = 3;

    #[link(name = "freenect")]
    unsafe extern "C" {
        pub fn freenect_init(ctx: *mut *mut Context, usb_ctx: *mut c_void) -> c_int;
        pub fn freenect_shutdown(ctx: *mut Context) -> c_int;
        pub fn freenect_set_log_level(ctx: *mut Context, level: c_int);
        pub fn freenect_set_log_callback(ctx: *mut Context, cb: Option<LogCb>);
        pub fn freenect_process_events_timeout(ctx: *mut Context, timeout: *mut Timeval) -> c_int;
        pub fn freenect_num_devices(ctx: *mut Context) -> c_int;
        pub fn freenect_select_subdevices(ctx: *mut Context, subdevs: c_int);
        pub fn freenect_open_device(
            ctx: *mut Context,
            dev: *mut *mut Device,
            index: c_int,
        ) -> c_int;
        pub fn freenect_open_device_by_camera_serial(
            ctx: *mut Context,
            dev: *mut *mut Device,
            camera_serial: *const c_char,
        ) -> c_int;
        pub fn freenect_close_device(dev: *mut Device) -> c_int;
        pub fn freenect_set_user(dev: *mut Device, user: *mut c_void);
        pub fn freenect_get_user(dev: *mut Device) -> *mut c_void;
        pub fn freenect_set_depth_callback(dev: *mut Device, cb: Option<FrameCb>);
        pub fn freenect_set_video_callback(dev: *mut Device, cb: Option<FrameCb>);
        pub fn freenect_start_depth(dev: *mut Device) -> c_int;
        pub fn freenect_start_video(dev: *mut Device) -> c_int;
        pub fn freenect_stop_depth(dev: *mut Device) -> c_int;
        pub fn freenect_stop_video(dev: *mut Device) -> c_int;
        pub fn freenect_get_depth_mode_count() -> c_int;
        pub fn freenect_get_depth_mode(mode_num: c_int) -> FrameMode;
        pub fn freenect_get_video_mode_count() -> c_int;
        pub fn freenect_get_video_mode(mode_num: c_int) -> FrameMode;
        pub fn freenect_set_depth_mode(dev: *mut Device, mode: FrameMode) -> c_int;
        pub fn freenect_set_video_mode(dev: *mut Device, mode: FrameMode) -> c_int;
    }

    // glibc ≥ 2.34 has dlsym in libc itself, which std already links.
    unsafe extern "C" {
        pub fn dlsym(handle: *mut c_void, symbol: *const c_char) -> *mut c_void;
    }
}

/// `FREENECT_RESOLUTION_MEDIUM` (640 × 480).
pub(super) const RESOLUTION_MEDIUM: i32 = 1;
/// `freenect_depth_format` values.
pub(super) const DEPTH_11BIT: i32 = 0;
pub(super) const DEPTH_REGISTERED: i32 = 4;
pub(super) const DEPTH_MM: i32 = 5;
/// `FREENECT_VIDEO_RGB`.
pub(super) const VIDEO_RGB: i32 = 0;

/// A frame mode the library offers (`freenect_frame_mode`, the fields the backend reads).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct FrameMode {
    raw: sys::FrameMode,
}

impl FrameMode {
    pub(super) fn resolution(&self) -> i32 {
        self.raw.resolution
    }
    /// `freenect_video_format` or `freenect_depth_format`, as the list it came from says.
    pub(super) fn format(&self) -> i32 {
        self.raw.format
    }
    pub(super) fn bytes(&self) -> usize {
        usize::try_from(self.raw.bytes).unwrap_or(0)
    }
    pub(super) fn width(&self) -> u32 {
        u32::try_from(self.raw.width).unwrap_or(0)
    }
    pub(super) fn height(&self) -> u32 {
        u32::try_from(self.raw.height).unwrap_or(0)
    }
    pub(super) fn framerate(&self) -> u32 {
        u32::try_from(self.raw.framerate).unwrap_or(0)
    }
    pub(super) fn is_valid(&self) -> bool {
        self.raw.is_valid != 0
    }
}

/// The depth modes the linked library offers (`freenect_get_depth_mode`). Enumerating is safe
/// with fakenect too, whose `freenect_find_depth_mode` asserts (aborts) on anything but 11-bit.
pub(super) fn depth_modes() -> Vec<FrameMode> {
    // SAFETY: takes no arguments and reads static tables.
    let count = unsafe { sys::freenect_get_depth_mode_count() };
    (0..count)
        // SAFETY: `i` is below the count the library reported.
        .map(|i| FrameMode {
            raw: unsafe { sys::freenect_get_depth_mode(i) },
        })
        .collect()
}

/// The video modes the linked library offers (`freenect_get_video_mode`).
pub(super) fn video_modes() -> Vec<FrameMode> {
    // SAFETY: takes no arguments and reads static tables.
    let count = unsafe { sys::freenect_get_video_mode_count() };
    (0..count)
        // SAFETY: `i` is below the count the library reported.
        .map(|i| FrameMode {
            raw: unsafe { sys::freenect_get_video_mode(i) },
        })
        .collect()
}

/// Whether the `libfreenect.so.0.5` this process loaded is fakenect, libfreenect's replay
/// library: fakenect does not define `freenect_list_device_attributes`, which every real
/// libfreenect since 0.2 exports.
pub fn library_is_fakenect() -> bool {
    // SAFETY: RTLD_DEFAULT (a null handle on glibc) searches the global scope; the symbol name
    // is a valid NUL-terminated string, and the result is only compared with null.
    let symbol =
        unsafe { sys::dlsym(ptr::null_mut(), c"freenect_list_device_attributes".as_ptr()) };
    symbol.is_null()
}

/// Where one stream's frame callback lands: a copy of the frame, its device timestamp and the
/// host time it arrived.
#[derive(Debug, Default)]
pub(super) struct Landing {
    pub(super) bytes: Vec<u8>,
    /// The Kinect's 32-bit frame timestamp (60 MHz; fakenect: the number in the file name).
    pub(super) ticks: u32,
    pub(super) host_ns: u64,
    /// A frame arrived since the backend last took one.
    pub(super) fresh: bool,
    /// Frames that arrived while the previous one was still fresh (overwritten, never seen).
    pub(super) overwritten: u64,
}

impl Landing {
    fn sized(bytes: usize) -> Self {
        Self {
            bytes: vec![0; bytes],
            ..Self::default()
        }
    }

    /// Copy one frame in. Never panics: the callback runs inside C.
    fn land(&mut self, data: *const c_void, ticks: u32) {
        if data.is_null() {
            return;
        }
        // SAFETY: libfreenect and fakenect hand the callback a frame of the current mode's
        // `bytes` (fakenect copies exactly that many out of the file, which the backend
        // checked beforehand), and `self.bytes` was sized to that mode. Read as bytes: the
        // pointer need not be aligned (fakenect's points just past a PGM header).
        let frame = unsafe { std::slice::from_raw_parts(data.cast::<u8>(), self.bytes.len()) };
        self.bytes.copy_from_slice(frame);
        if self.fresh {
            self.overwritten += 1;
        }
        self.fresh = true;
        self.ticks = ticks;
        self.host_ns = host_now_ns();
    }
}

/// The frame callbacks' destination, reached through `freenect_get_user`.
#[derive(Debug, Default)]
pub(super) struct Sink {
    pub(super) depth: Landing,
    pub(super) video: Landing,
}

unsafe extern "C" fn on_depth(dev: *mut sys::Device, data: *mut c_void, timestamp: u32) {
    // SAFETY: the user pointer was set by `Session::open` to the session's live `Sink`, which
    // outlives every call that can run this callback (callbacks run inside
    // `freenect_process_events_timeout`, called only through `&mut Session`).
    let sink = unsafe { sys::freenect_get_user(dev) }.cast::<Sink>();
    // SAFETY: as above; no other reference to the sink exists while libfreenect runs.
    if let Some(sink) = unsafe { sink.as_mut() } {
        sink.depth.land(data, timestamp);
    }
}

unsafe extern "C" fn on_video(dev: *mut sys::Device, data: *mut c_void, timestamp: u32) {
    // SAFETY: as in `on_depth`.
    let sink = unsafe { sys::freenect_get_user(dev) }.cast::<Sink>();
    // SAFETY: as in `on_depth`.
    if let Some(sink) = unsafe { sink.as_mut() } {
        sink.video.land(data, timestamp);
    }
}

/// libfreenect's log, routed to `tracing`. Its errors (a missing subdevice, a dead USB stream)
/// come back to the backend as typed errors too, so they are DEBUG here.
unsafe extern "C" fn on_log(_ctx: *mut sys::Context, level: c_int, msg: *const c_char) {
    if msg.is_null() {
        return;
    }
    // SAFETY: libfreenect passes a NUL-terminated message valid for the call.
    let text = unsafe { CStr::from_ptr(msg) }.to_string_lossy();
    let text = text.trim_end();
    match level {
        0 => tracing::warn!(target: "libfreenect", "{text}"),
        1..=3 => tracing::debug!(target: "libfreenect", "{text}"),
        _ => tracing::trace!(target: "libfreenect", "{text}"),
    }
}

/// Which Kinect to open.
#[derive(Debug, Clone)]
pub(super) enum Selector {
    Index(u32),
    Serial(CString),
}

/// Why a session could not be opened.
#[derive(Debug)]
pub(super) enum OpenError {
    /// `freenect_init` failed (libusb could not start).
    Init(i32),
    /// No such device, or it could not be claimed; `devices` is how many libfreenect sees.
    Open { code: i32, devices: i32 },
    /// The device refused a frame mode.
    Mode { stream: &'static str, code: i32 },
    /// A stream would not start.
    Start { stream: &'static str, code: i32 },
}

/// One opened Kinect camera: context, device, and the streams started on it. Dropping it
/// stops the streams, closes the device and shuts the context down.
#[derive(Debug)]
pub(super) struct Session {
    ctx: *mut sys::Context,
    dev: *mut sys::Device,
    /// From `Box::into_raw`; freed in `Drop` after the device is closed.
    sink: *mut Sink,
    depth: Option<FrameMode>,
    video: Option<FrameMode>,
    streaming: bool,
}

// SAFETY: a libfreenect context is single-threaded, not thread-bound: the session owns its
// context, device and sink exclusively and every call goes through `&mut self`, so moving it
// to the runner's thread between calls is sound.
unsafe impl Send for Session {}

impl Session {
    /// Init a context (camera subdevice only: tilt motor and LED stay untouched), open the
    /// device, set the modes, install the callbacks and start the requested streams.
    pub(super) fn open(
        selector: &Selector,
        depth: Option<FrameMode>,
        video: Option<FrameMode>,
    ) -> Result<Session, OpenError> {
        let mut ctx = ptr::null_mut();
        // SAFETY: `ctx` is a valid out-pointer; a null USB context lets libfreenect make one.
        let code = unsafe { sys::freenect_init(&mut ctx, ptr::null_mut()) };
        if code < 0 || ctx.is_null() {
            return Err(OpenError::Init(code));
        }
        // SAFETY: `ctx` is the live context just created; `on_log` matches `freenect_log_cb`.
        unsafe {
            sys::freenect_set_log_callback(ctx, Some(on_log));
            sys::freenect_set_log_level(ctx, sys::LOG_NOTICE);
            sys::freenect_select_subdevices(ctx, sys::DEVICE_CAMERA);
        }
        let sink = Box::into_raw(Box::new(Sink {
            depth: Landing::sized(depth.map_or(0, |m| m.bytes())),
            video: Landing::sized(video.map_or(0, |m| m.bytes())),
        }));
        // From here on `Drop` releases whatever has been acquired.
        let mut session = Session {
            ctx,
            dev: ptr::null_mut(),
            sink,
            depth,
            video,
            streaming: false,
        };
        let mut dev = ptr::null_mut();
        let code = match selector {
            // SAFETY: live context, valid out-pointer.
            Selector::Index(index) => unsafe {
                sys::freenect_open_device(ctx, &mut dev, c_int::try_from(*index).unwrap_or(-1))
            },
            // SAFETY: live context, valid out-pointer, NUL-terminated serial.
            Selector::Serial(serial) => unsafe {
                sys::freenect_open_device_by_camera_serial(ctx, &mut dev, serial.as_ptr())
            },
        };
        if code < 0 || dev.is_null() {
            // SAFETY: live context.
            let devices = unsafe { sys::freenect_num_devices(ctx) };
            return Err(OpenError::Open { code, devices });
        }
        session.dev = dev;
        // SAFETY: live device; the sink outlives it (freed in `Drop` after the close).
        unsafe { sys::freenect_set_user(dev, sink.cast()) };
        if let Some(mode) = depth {
            // SAFETY: live device; `mode` came from the library's own table.
            let code = unsafe { sys::freenect_set_depth_mode(dev, mode.raw) };
            if code < 0 {
                return Err(OpenError::Mode {
                    stream: "depth",
                    code,
                });
            }
            // SAFETY: live device; `on_depth` matches `freenect_depth_cb`.
            unsafe { sys::freenect_set_depth_callback(dev, Some(on_depth)) };
        }
        if let Some(mode) = video {
            // SAFETY: live device; `mode` came from the library's own table.
            let code = unsafe { sys::freenect_set_video_mode(dev, mode.raw) };
            if code < 0 {
                return Err(OpenError::Mode {
                    stream: "video",
                    code,
                });
            }
            // SAFETY: live device; `on_video` matches `freenect_video_cb`.
            unsafe { sys::freenect_set_video_callback(dev, Some(on_video)) };
        }
        session.set_streaming(true)?;
        Ok(session)
    }

    /// Start (or stop) the configured streams. Stopping and starting again is how a broken
    /// fakenect frame is skipped: fakenect reads a line without touching its pixels when no
    /// stream of that kind runs.
    pub(super) fn set_streaming(&mut self, on: bool) -> Result<(), OpenError> {
        if on == self.streaming {
            return Ok(());
        }
        let dev = self.dev;
        let streams: [(
            &'static str,
            bool,
            unsafe extern "C" fn(*mut sys::Device) -> c_int,
        ); 2] = [
            (
                "depth",
                self.depth.is_some(),
                if on {
                    sys::freenect_start_depth
                } else {
                    sys::freenect_stop_depth
                },
            ),
            (
                "video",
                self.video.is_some(),
                if on {
                    sys::freenect_start_video
                } else {
                    sys::freenect_stop_video
                },
            ),
        ];
        for (stream, wanted, call) in streams {
            if !wanted {
                continue;
            }
            // SAFETY: `dev` is the live device; the callbacks and user data are installed.
            let code = unsafe { call(dev) };
            if code < 0 && on {
                // Leave `streaming` set so that `Drop` stops whatever did start.
                self.streaming = true;
                return Err(OpenError::Start { stream, code });
            }
        }
        self.streaming = on;
        Ok(())
    }

    /// Let libfreenect handle USB events (fakenect: play one line of the dump) for up to
    /// `timeout`; frame callbacks fill the sink. libfreenect's return code: negative on error.
    pub(super) fn process_events(&mut self, timeout: Duration) -> i32 {
        let mut tv = sys::Timeval {
            tv_sec: c_long::try_from(timeout.as_secs()).unwrap_or(c_long::MAX),
            // Below 10⁶: fits any `long`.
            tv_usec: timeout.subsec_micros() as c_long,
        };
        // SAFETY: live context and a valid timeval; callbacks reach the sink through the
        // user pointer while no Rust reference to it is held (`&mut self` is not used here).
        unsafe { sys::freenect_process_events_timeout(self.ctx, &mut tv) }
    }

    /// The frames landed so far.
    pub(super) fn sink(&mut self) -> &mut Sink {
        // SAFETY: `sink` is the live box from `open`; `&mut self` excludes callbacks (they only
        // run inside `process_events`) and other references.
        unsafe { &mut *self.sink }
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        if !self.dev.is_null() {
            if self.streaming {
                // SAFETY: live device whose streams were started.
                unsafe {
                    if self.depth.is_some() {
                        sys::freenect_stop_depth(self.dev);
                    }
                    if self.video.is_some() {
                        sys::freenect_stop_video(self.dev);
                    }
                }
            }
            // SAFETY: live device, closed once.
            unsafe { sys::freenect_close_device(self.dev) };
        }
        // SAFETY: live context, shut down once, after its device is closed.
        unsafe { sys::freenect_shutdown(self.ctx) };
        // SAFETY: from `Box::into_raw` in `open`; no callback can run any more.
        drop(unsafe { Box::from_raw(self.sink) });
    }
}
