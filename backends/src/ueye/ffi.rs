//! The IDS uEye C API (`ueye.h`, IDS Software Suite 4.x), loaded at run time from
//! `libueye_api.so`, and safe wrappers for the calls this backend makes.
//!
//! Prototypes, constants and structure layouts follow `ueye.h` 4.60 for Linux, where `INT` is
//! `int32_t`, `UINT`, `DWORD` and `HIDS` are `uint32_t`, `HWND` is `void*`, and every function is
//! `cdecl` returning `INT` (`IDSEXP`).
#![allow(unsafe_code)]

use std::ffi::{CStr, c_char, c_double, c_void};
use std::fmt;
use std::sync::Arc;

use libloading::Library;

pub type Hids = u32;

// Return codes (ueye.h "Error codes").
pub const IS_NO_SUCCESS: i32 = -1;
pub const IS_SUCCESS: i32 = 0;
pub const IS_INVALID_CAMERA_HANDLE: i32 = 1;
pub const IS_IO_REQUEST_FAILED: i32 = 2;
pub const IS_CANT_OPEN_DEVICE: i32 = 3;
/// What `is_WaitForNextImage` returns for a failed transfer (same value as
/// `IS_CANT_OPEN_DEVICE`; the window message `IS_CAPTURE_STATUS` = 0x0003).
pub const IS_CAPTURE_STATUS: i32 = 3;
pub const IS_CANT_COMMUNICATE_WITH_DRIVER: i32 = 17;
pub const IS_CAMERA_NOT_CONNECTED: i32 = 111;
pub const IS_ALL_DEVICES_BUSY: i32 = 120;
pub const IS_TIMED_OUT: i32 = 122;
pub const IS_NO_HARDWARE_INSTALLED: i32 = 133;
pub const IS_STARTER_FW_UPLOAD_NEEDED: i32 = 184;
pub const IS_DEVICE_BUSY: i32 = 205;

/// `is_InitCamera`: with this flag the API may upload a new starter firmware.
pub const IS_ALLOW_STARTER_FW_UPLOAD: u32 = 0x10000;
pub const IS_IGNORE_PARAMETER: i32 = -1;
pub const IS_DONT_WAIT: i32 = 0x0000;
pub const IS_FORCE_VIDEO_STOP: i32 = 0x4000;
pub const IS_SET_DM_DIB: i32 = 1;
pub const IS_SET_TRIGGER_OFF: i32 = 0x0000;
pub const IS_GET_MASTER_GAIN_FACTOR: i32 = 0x8000;

// Colour modes (ueye.h "pixel formats").
pub const IS_CM_MONO8: i32 = 6;
pub const IS_CM_BGR8_PACKED: i32 = 1;
pub const IS_CM_RGB8_PACKED: i32 = 1 | 0x0080;

// is_AOI commands.
pub const IS_AOI_IMAGE_SET_AOI: u32 = 0x0001;
pub const IS_AOI_IMAGE_GET_AOI: u32 = 0x0002;

// is_Exposure commands; exposure times are in milliseconds (double).
pub const IS_EXPOSURE_CMD_GET_EXPOSURE_RANGE: u32 = 6;
pub const IS_EXPOSURE_CMD_GET_EXPOSURE: u32 = 7;
pub const IS_EXPOSURE_CMD_SET_EXPOSURE: u32 = 12;

// is_SetAutoParameter switches.
pub const IS_SET_ENABLE_AUTO_GAIN: i32 = 0x8800;
pub const IS_SET_ENABLE_AUTO_SHUTTER: i32 = 0x8802;
pub const IS_SET_ENABLE_AUTO_SENSOR_GAIN: i32 = 0x8808;
pub const IS_SET_ENABLE_AUTO_SENSOR_SHUTTER: i32 = 0x8810;

/// `IS_RECT`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IsRect {
    pub x: i32,
    pub y: i32,
    pub width: i32,
    pub height: i32,
}

/// `UEYETIME`: the host's wall-clock time when the driver received the image.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct UeyeTime {
    pub year: u16,
    pub month: u16,
    pub day: u16,
    pub hour: u16,
    pub minute: u16,
    pub second: u16,
    pub milliseconds: u16,
    pub reserved: [u8; 10],
}

/// `UEYEIMAGEINFO` (4.x layout, 80 bytes).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct ImageInfo {
    pub flags: u32,
    pub reserved1: [u8; 4],
    /// Camera clock at the end of exposure, in 0.1 µs.
    pub timestamp_device: u64,
    pub timestamp_system: UeyeTime,
    pub io_status: u32,
    pub aoi_index: u16,
    pub aoi_cycle: u16,
    /// Frames the camera has exposed since the capture started (gaps are lost frames).
    pub frame_number: u64,
    pub image_buffers: u32,
    pub image_buffers_in_use: u32,
    pub reserved3: u32,
    pub image_height: u32,
    pub image_width: u32,
    pub host_process_time: u32,
}

const _: () = assert!(size_of::<ImageInfo>() == 80);
const _: () = assert!(size_of::<UeyeTime>() == 24);

type InitCamera = unsafe extern "C" fn(*mut Hids, *mut c_void) -> i32;
type HandleOnly = unsafe extern "C" fn(Hids) -> i32;
type HandleInt = unsafe extern "C" fn(Hids, i32) -> i32;
type Command = unsafe extern "C" fn(Hids, u32, *mut c_void, u32) -> i32;
type SetFrameRate = unsafe extern "C" fn(Hids, c_double, *mut c_double) -> i32;
type SetHardwareGain = unsafe extern "C" fn(Hids, i32, i32, i32, i32) -> i32;
type SetHwGainFactor = unsafe extern "C" fn(Hids, i32, i32) -> i32;
type SetAutoParameter = unsafe extern "C" fn(Hids, i32, *mut c_double, *mut c_double) -> i32;
type AllocImageMem = unsafe extern "C" fn(Hids, i32, i32, i32, *mut *mut c_char, *mut i32) -> i32;
type MemAndId = unsafe extern "C" fn(Hids, *mut c_char, i32) -> i32;
type IdAndMem = unsafe extern "C" fn(Hids, i32, *mut c_char) -> i32;
type InquireImageMem =
    unsafe extern "C" fn(Hids, *mut c_char, i32, *mut i32, *mut i32, *mut i32, *mut i32) -> i32;
type WaitForNextImage = unsafe extern "C" fn(Hids, u32, *mut *mut c_char, *mut i32) -> i32;
type GetImageInfo = unsafe extern "C" fn(Hids, i32, *mut ImageInfo, i32) -> i32;
type GetError = unsafe extern "C" fn(Hids, *mut i32, *mut *mut c_char) -> i32;

/// The loaded library and the entry points this backend uses.
pub struct Api {
    path: String,
    is_init_camera: InitCamera,
    is_exit_camera: HandleOnly,
    is_set_display_mode: HandleInt,
    is_set_color_mode: HandleInt,
    is_set_external_trigger: HandleInt,
    is_aoi: Command,
    is_exposure: Command,
    is_set_frame_rate: SetFrameRate,
    is_set_hardware_gain: SetHardwareGain,
    is_set_hw_gain_factor: SetHwGainFactor,
    is_set_auto_parameter: SetAutoParameter,
    is_alloc_image_mem: AllocImageMem,
    is_free_image_mem: MemAndId,
    is_add_to_sequence: MemAndId,
    is_clear_sequence: HandleOnly,
    is_inquire_image_mem: InquireImageMem,
    is_init_image_queue: HandleInt,
    is_exit_image_queue: HandleOnly,
    is_capture_video: HandleInt,
    is_stop_live_video: HandleInt,
    is_wait_for_next_image: WaitForNextImage,
    is_unlock_seq_buf: IdAndMem,
    is_get_image_info: GetImageInfo,
    is_get_error: GetError,
    /// Keeps the entry points above valid; dropped last.
    _library: Library,
}

impl fmt::Debug for Api {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Api")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

/// Why the library could not be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LoadError {
    #[error("cannot load {0}")]
    Library(String),
    #[error("{path} lacks {symbol} (IDS Software Suite 4.x is required): {error}")]
    Symbol {
        path: String,
        symbol: &'static str,
        error: String,
    },
}

impl Api {
    /// Load the first of `candidates` that loads (names go through the dynamic loader's search,
    /// paths are used as given) and resolve every entry point.
    pub fn load(candidates: &[String]) -> Result<Arc<Api>, LoadError> {
        let mut failures = Vec::new();
        for candidate in candidates {
            // SAFETY: loading runs the library's initialisers. libueye_api has none with
            // preconditions; a library that is not the IDS API is caught by the symbol checks.
            match unsafe { Library::new(candidate.as_str()) } {
                Ok(library) => return Self::resolve(candidate.clone(), library),
                Err(error) => failures.push(format!("{candidate} ({error})")),
            }
        }
        Err(LoadError::Library(failures.join("; ")))
    }

    fn resolve(path: String, library: Library) -> Result<Arc<Api>, LoadError> {
        macro_rules! symbol {
            ($name:literal) => {
                // SAFETY: the function-pointer type given at each use is the prototype of this
                // symbol in ueye.h; the pointer is copied out and stays valid while `library`,
                // stored in the same `Api`, is loaded.
                match unsafe { library.get($name) } {
                    Ok(symbol) => *symbol,
                    Err(error) => {
                        return Err(LoadError::Symbol {
                            path,
                            symbol: $name,
                            error: error.to_string(),
                        });
                    }
                }
            };
        }
        Ok(Arc::new(Api {
            is_init_camera: symbol!("is_InitCamera"),
            is_exit_camera: symbol!("is_ExitCamera"),
            is_set_display_mode: symbol!("is_SetDisplayMode"),
            is_set_color_mode: symbol!("is_SetColorMode"),
            is_set_external_trigger: symbol!("is_SetExternalTrigger"),
            is_aoi: symbol!("is_AOI"),
            is_exposure: symbol!("is_Exposure"),
            is_set_frame_rate: symbol!("is_SetFrameRate"),
            is_set_hardware_gain: symbol!("is_SetHardwareGain"),
            is_set_hw_gain_factor: symbol!("is_SetHWGainFactor"),
            is_set_auto_parameter: symbol!("is_SetAutoParameter"),
            is_alloc_image_mem: symbol!("is_AllocImageMem"),
            is_free_image_mem: symbol!("is_FreeImageMem"),
            is_add_to_sequence: symbol!("is_AddToSequence"),
            is_clear_sequence: symbol!("is_ClearSequence"),
            is_inquire_image_mem: symbol!("is_InquireImageMem"),
            is_init_image_queue: symbol!("is_InitImageQueue"),
            is_exit_image_queue: symbol!("is_ExitImageQueue"),
            is_capture_video: symbol!("is_CaptureVideo"),
            is_stop_live_video: symbol!("is_StopLiveVideo"),
            is_wait_for_next_image: symbol!("is_WaitForNextImage"),
            is_unlock_seq_buf: symbol!("is_UnlockSeqBuf"),
            is_get_image_info: symbol!("is_GetImageInfo"),
            is_get_error: symbol!("is_GetError"),
            path,
            _library: library,
        }))
    }

    pub fn path(&self) -> &str {
        &self.path
    }
}

/// A failed API call: the function, its return code and the driver's error text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CallError {
    pub function: &'static str,
    pub code: i32,
    pub message: String,
}

impl fmt::Display for CallError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} returned {}", self.function, self.code)?;
        if !self.message.is_empty() {
            write!(f, " ({})", self.message)?;
        }
        Ok(())
    }
}

/// One image memory allocated by `is_AllocImageMem`, `pitch × height` bytes.
#[derive(Debug)]
struct ImageMem {
    ptr: *mut c_char,
    id: i32,
    len: usize,
}

/// An open camera (`is_InitCamera` … `is_ExitCamera`), with its ring of image memories.
#[derive(Debug)]
pub struct Camera {
    api: Arc<Api>,
    hcam: Hids,
    ring: Vec<ImageMem>,
    queue: bool,
    live: bool,
}

// SAFETY: `ring` holds pointers to image memories that the uEye API allocated for this camera;
// they are only dereferenced through `&mut Camera` (one thread at a time), and the uEye API
// may be called from any thread.
unsafe impl Send for Camera {}

/// A frame held in the ring until dropped (`is_UnlockSeqBuf`).
#[derive(Debug)]
pub struct LockedImage<'a> {
    camera: &'a Camera,
    mem: usize,
    pub info: ImageInfo,
}

impl<'a> LockedImage<'a> {
    /// The camera the image belongs to (to write controls while it is held).
    pub fn camera(&self) -> &'a Camera {
        self.camera
    }

    /// The whole image memory, `pitch × height` bytes.
    pub fn data(&self) -> &[u8] {
        let mem = &self.camera.ring[self.mem];
        // SAFETY: `mem.ptr` is one of this camera's image memories, allocated with `len` bytes
        // (pitch × height as reported by is_InquireImageMem); while locked, the driver does not
        // write to it, and it is freed only in `Camera::drop`, which cannot run while this
        // borrow of the camera lives.
        unsafe { std::slice::from_raw_parts(mem.ptr.cast::<u8>(), mem.len) }
    }
}

impl Drop for LockedImage<'_> {
    fn drop(&mut self) {
        let mem = &self.camera.ring[self.mem];
        let api = &self.camera.api;
        // SAFETY: prototype per ueye.h; `mem.ptr` is the locked image memory of this camera.
        let code =
            unsafe { (api.is_unlock_seq_buf)(self.camera.hcam, IS_IGNORE_PARAMETER, mem.ptr) };
        if code != IS_SUCCESS {
            tracing::debug!(code, "is_UnlockSeqBuf failed");
        }
    }
}

/// What one wait gave.
#[derive(Debug)]
pub enum Wait<'a> {
    Image(LockedImage<'a>),
    TimedOut,
}

impl Camera {
    /// `is_InitCamera` for camera ID `camera_id` (0: the first free camera). When the camera
    /// needs a new starter firmware, retries once allowing the upload, as the IDS manual
    /// advises.
    pub fn init(api: Arc<Api>, camera_id: u32) -> Result<Camera, CallError> {
        let mut hcam = camera_id;
        // SAFETY: prototype per ueye.h; `hcam` is a live local, HWND may be null on Linux.
        let mut code = unsafe { (api.is_init_camera)(&raw mut hcam, std::ptr::null_mut()) };
        if code == IS_STARTER_FW_UPLOAD_NEEDED {
            hcam = camera_id | IS_ALLOW_STARTER_FW_UPLOAD;
            // SAFETY: as above.
            code = unsafe { (api.is_init_camera)(&raw mut hcam, std::ptr::null_mut()) };
        }
        if code != IS_SUCCESS {
            return Err(CallError {
                function: "is_InitCamera",
                code,
                message: error_text(&api, 0),
            });
        }
        Ok(Camera {
            api,
            hcam,
            ring: Vec::new(),
            queue: false,
            live: false,
        })
    }

    fn check(&self, function: &'static str, code: i32) -> Result<(), CallError> {
        if code == IS_SUCCESS {
            Ok(())
        } else {
            Err(CallError {
                function,
                code,
                message: error_text(&self.api, self.hcam),
            })
        }
    }

    pub fn set_display_mode_dib(&mut self) -> Result<(), CallError> {
        // SAFETY: prototype per ueye.h; plain integer arguments.
        let code = unsafe { (self.api.is_set_display_mode)(self.hcam, IS_SET_DM_DIB) };
        self.check("is_SetDisplayMode", code)
    }

    pub fn set_trigger_off(&mut self) -> Result<(), CallError> {
        // SAFETY: prototype per ueye.h; plain integer arguments.
        let code = unsafe { (self.api.is_set_external_trigger)(self.hcam, IS_SET_TRIGGER_OFF) };
        self.check("is_SetExternalTrigger", code)
    }

    pub fn set_color_mode(&mut self, mode: i32) -> Result<(), CallError> {
        // SAFETY: prototype per ueye.h; plain integer arguments.
        let code = unsafe { (self.api.is_set_color_mode)(self.hcam, mode) };
        self.check("is_SetColorMode", code)
    }

    fn aoi(&mut self, command: u32, rect: &mut IsRect) -> Result<(), CallError> {
        // SAFETY: prototype per ueye.h; is_AOI reads or writes one IS_RECT of the given size.
        let code = unsafe {
            (self.api.is_aoi)(
                self.hcam,
                command,
                std::ptr::from_mut(rect).cast(),
                size_of::<IsRect>() as u32,
            )
        };
        self.check("is_AOI", code)
    }

    pub fn set_aoi(&mut self, width: i32, height: i32) -> Result<(), CallError> {
        let mut rect = IsRect {
            x: 0,
            y: 0,
            width,
            height,
        };
        self.aoi(IS_AOI_IMAGE_SET_AOI, &mut rect)
    }

    pub fn get_aoi(&mut self) -> Result<IsRect, CallError> {
        let mut rect = IsRect::default();
        self.aoi(IS_AOI_IMAGE_GET_AOI, &mut rect)?;
        Ok(rect)
    }

    /// Returns the frame rate the camera set.
    pub fn set_frame_rate(&mut self, fps: f64) -> Result<f64, CallError> {
        let mut actual = 0.0;
        // SAFETY: prototype per ueye.h; `actual` is a live local the call writes.
        let code = unsafe { (self.api.is_set_frame_rate)(self.hcam, fps, &raw mut actual) };
        self.check("is_SetFrameRate", code)?;
        Ok(actual)
    }

    pub fn set_auto(&mut self, parameter: i32, enable: bool) -> Result<(), CallError> {
        let mut value = if enable { 1.0 } else { 0.0 };
        let mut unused = 0.0;
        // SAFETY: prototype per ueye.h; both pointers are live locals.
        let code = unsafe {
            (self.api.is_set_auto_parameter)(self.hcam, parameter, &raw mut value, &raw mut unused)
        };
        self.check("is_SetAutoParameter", code)
    }

    /// Master gain in percent of the range (0–100).
    pub fn set_master_gain(&mut self, percent: i32) -> Result<(), CallError> {
        let ignore = IS_IGNORE_PARAMETER;
        // SAFETY: prototype per ueye.h; plain integer arguments.
        let code =
            unsafe { (self.api.is_set_hardware_gain)(self.hcam, percent, ignore, ignore, ignore) };
        self.check("is_SetHardwareGain", code)
    }

    /// The master gain as an amplification factor (is_SetHWGainFactor reports it × 100).
    pub fn master_gain_factor(&mut self) -> f64 {
        // SAFETY: prototype per ueye.h; plain integer arguments; returns the factor × 100.
        let factor =
            unsafe { (self.api.is_set_hw_gain_factor)(self.hcam, IS_GET_MASTER_GAIN_FACTOR, 0) };
        f64::from(factor.max(100)) / 100.0
    }

    fn exposure(&self, command: u32, values: &mut [f64]) -> Result<(), CallError> {
        // SAFETY: prototype per ueye.h; the command reads or writes `values.len()` doubles, the
        // size passed.
        let code = unsafe {
            (self.api.is_exposure)(
                self.hcam,
                command,
                values.as_mut_ptr().cast(),
                size_of_val(values) as u32,
            )
        };
        self.check("is_Exposure", code)
    }

    /// (min, max, increment) of the exposure time in ms, at the current frame rate.
    pub fn exposure_range_ms(&mut self) -> Result<[f64; 3], CallError> {
        let mut range = [0.0; 3];
        self.exposure(IS_EXPOSURE_CMD_GET_EXPOSURE_RANGE, &mut range)?;
        Ok(range)
    }

    /// Set the exposure time; returns the exposure the camera applied (read back), in ms.
    pub fn set_exposure_ms(&self, exposure_ms: f64) -> Result<f64, CallError> {
        self.exposure(IS_EXPOSURE_CMD_SET_EXPOSURE, &mut [exposure_ms])?;
        let mut actual = [0.0];
        self.exposure(IS_EXPOSURE_CMD_GET_EXPOSURE, &mut actual)?;
        Ok(actual[0])
    }

    /// Allocate `count` image memories for `width × height` at `bits_per_pixel`, add them to
    /// the capture sequence and start the image queue. Returns the line pitch in bytes.
    pub fn start_ring(
        &mut self,
        width: i32,
        height: i32,
        bits_per_pixel: i32,
        count: usize,
    ) -> Result<usize, CallError> {
        let mut pitch = 0usize;
        for _ in 0..count {
            let mut ptr: *mut c_char = std::ptr::null_mut();
            let mut id = 0;
            // SAFETY: prototype per ueye.h; the call writes a pointer and an ID to the locals.
            let code = unsafe {
                (self.api.is_alloc_image_mem)(
                    self.hcam,
                    width,
                    height,
                    bits_per_pixel,
                    &raw mut ptr,
                    &raw mut id,
                )
            };
            self.check("is_AllocImageMem", code)?;
            if ptr.is_null() {
                return Err(CallError {
                    function: "is_AllocImageMem",
                    code: IS_NO_SUCCESS,
                    message: "returned a null image memory".into(),
                });
            }
            let (mut w, mut h, mut bits, mut line) = (0, 0, 0, 0);
            // SAFETY: prototype per ueye.h; `ptr`/`id` were just allocated; the outputs are
            // live locals.
            let code = unsafe {
                (self.api.is_inquire_image_mem)(
                    self.hcam,
                    ptr,
                    id,
                    &raw mut w,
                    &raw mut h,
                    &raw mut bits,
                    &raw mut line,
                )
            };
            let len = usize::try_from(line).unwrap_or(0) * usize::try_from(h).unwrap_or(0);
            // Recorded before checking so that `Drop` frees it whatever happens next.
            self.ring.push(ImageMem { ptr, id, len });
            self.check("is_InquireImageMem", code)?;
            if (w, h, bits) != (width, height, bits_per_pixel) || line < width * bits_per_pixel / 8
            {
                return Err(CallError {
                    function: "is_InquireImageMem",
                    code: IS_NO_SUCCESS,
                    message: format!(
                        "memory is {w}×{h} at {bits} bits, pitch {line}; asked for {width}×{height} at {bits_per_pixel}"
                    ),
                });
            }
            pitch = line as usize;
            // SAFETY: prototype per ueye.h; `ptr`/`id` are this camera's image memory.
            let code = unsafe { (self.api.is_add_to_sequence)(self.hcam, ptr, id) };
            self.check("is_AddToSequence", code)?;
        }
        // SAFETY: prototype per ueye.h; mode 0 is the only defined mode.
        let code = unsafe { (self.api.is_init_image_queue)(self.hcam, 0) };
        self.check("is_InitImageQueue", code)?;
        self.queue = true;
        Ok(pitch)
    }

    /// Start continuous (freerun) capture into the ring.
    pub fn capture_video(&mut self) -> Result<(), CallError> {
        // SAFETY: prototype per ueye.h; plain integer arguments.
        let code = unsafe { (self.api.is_capture_video)(self.hcam, IS_DONT_WAIT) };
        self.check("is_CaptureVideo", code)?;
        self.live = true;
        Ok(())
    }

    /// Wait up to `timeout_ms` for the next image of the queue.
    pub fn wait_for_next_image(&mut self, timeout_ms: u32) -> Result<Wait<'_>, CallError> {
        let mut ptr: *mut c_char = std::ptr::null_mut();
        let mut id = 0;
        // SAFETY: prototype per ueye.h; the outputs are live locals.
        let code = unsafe {
            (self.api.is_wait_for_next_image)(self.hcam, timeout_ms, &raw mut ptr, &raw mut id)
        };
        if code == IS_TIMED_OUT {
            return Ok(Wait::TimedOut);
        }
        self.check("is_WaitForNextImage", code)?;
        let Some(mem) = self.ring.iter().position(|m| m.id == id && m.ptr == ptr) else {
            return Err(CallError {
                function: "is_WaitForNextImage",
                code: IS_NO_SUCCESS,
                message: format!("returned image memory {id}, which is not in this camera's ring"),
            });
        };
        let mut info = ImageInfo::default();
        // SAFETY: prototype per ueye.h; writes at most `size_of::<ImageInfo>()` bytes to `info`.
        let code = unsafe {
            (self.api.is_get_image_info)(
                self.hcam,
                id,
                &raw mut info,
                size_of::<ImageInfo>() as i32,
            )
        };
        let locked = LockedImage {
            camera: &*self,
            mem,
            info,
        };
        // Unlocked (by drop) even when the info cannot be read.
        locked.camera.check("is_GetImageInfo", code)?;
        Ok(Wait::Image(locked))
    }
}

impl Drop for Camera {
    /// Stop, free the ring and close, in the order of the IDS manual. Failures (a camera that
    /// is already gone) are logged only.
    fn drop(&mut self) {
        let api = self.api.clone();
        let hcam = self.hcam;
        let log = |function: &str, code: i32| {
            if code != IS_SUCCESS {
                tracing::debug!(function, code, "uEye cleanup call failed");
            }
        };
        // SAFETY (all calls below): prototypes per ueye.h; `hcam` is this camera and every
        // pointer/ID pair in `ring` came from is_AllocImageMem for it.
        unsafe {
            if self.live {
                log(
                    "is_StopLiveVideo",
                    (api.is_stop_live_video)(hcam, IS_FORCE_VIDEO_STOP),
                );
            }
            if self.queue {
                log("is_ExitImageQueue", (api.is_exit_image_queue)(hcam));
            }
            if !self.ring.is_empty() {
                log("is_ClearSequence", (api.is_clear_sequence)(hcam));
            }
            for mem in self.ring.drain(..) {
                log(
                    "is_FreeImageMem",
                    (api.is_free_image_mem)(hcam, mem.ptr, mem.id),
                );
            }
            log("is_ExitCamera", (api.is_exit_camera)(hcam));
        }
    }
}

/// The driver's text for the last error on `hcam` (0: errors not tied to a camera).
fn error_text(api: &Api, hcam: Hids) -> String {
    let mut code = 0;
    let mut text: *mut c_char = std::ptr::null_mut();
    // SAFETY: prototype per ueye.h; the outputs are live locals; the returned string belongs to
    // the library and is copied out at once.
    unsafe {
        if (api.is_get_error)(hcam, &raw mut code, &raw mut text) != IS_SUCCESS || text.is_null() {
            return String::new();
        }
        CStr::from_ptr(text).to_string_lossy().into_owned()
    }
}
