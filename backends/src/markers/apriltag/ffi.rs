//! libapriltag 3 (Debian `libapriltag-dev`): hand-written declarations of the parts of
//! `apriltag.h`, `common/{image_u8,zarray,matd}.h`, `tag36h11.h` and `tagStandard41h12.h` the
//! tracker uses ([`sys`]), and the safe wrappers around them. All `unsafe` of the AprilTag
//! backend lives in this module.

#![allow(unsafe_code)]

/// Raw C declarations. Structs the library allocates and we only read through pointers
/// ([`sys::Detector`]) are declared up to the last field we touch; the C struct continues
/// beyond. Offsets are checked at compile time against the C headers' layout on 64-bit targets.
pub mod sys {
    use std::ffi::{c_char, c_int, c_uint, c_void};

    /// `image_u8_t`: 8-bit image, row `y` at `buf + y * stride`.
    #[repr(C)]
    #[derive(Debug)]
    pub struct ImageU8 {
        pub width: i32,
        pub height: i32,
        pub stride: i32,
        pub buf: *mut u8,
    }

    /// `zarray_t`: a growable array of `size` elements of `el_sz` bytes at `data`.
    #[repr(C)]
    #[derive(Debug)]
    pub struct ZArray {
        pub el_sz: usize,
        pub size: c_int,
        pub alloc: c_int,
        pub data: *mut c_char,
    }

    /// `matd_t`: a row-major `nrows × ncols` matrix of doubles stored right after the header.
    #[repr(C)]
    #[derive(Debug)]
    pub struct Matd {
        pub nrows: c_uint,
        pub ncols: c_uint,
        pub data: [f64; 0],
    }

    /// `apriltag_family_t`.
    #[repr(C)]
    #[derive(Debug)]
    pub struct Family {
        pub ncodes: u32,
        pub codes: *mut u64,
        pub width_at_border: c_int,
        pub total_width: c_int,
        pub reversed_border: bool,
        pub nbits: u32,
        pub bit_x: *mut u32,
        pub bit_y: *mut u32,
        pub h: u32,
        pub name: *mut c_char,
        pub impl_: *mut c_void,
    }

    /// `struct apriltag_quad_thresh_params`.
    #[repr(C)]
    #[derive(Debug)]
    pub struct QuadThreshParams {
        pub min_cluster_pixels: c_int,
        pub max_nmaxima: c_int,
        pub critical_rad: f32,
        pub cos_critical_rad: f32,
        pub max_line_fit_mse: f32,
        pub min_white_black_diff: c_int,
        pub deglitch: c_int,
    }

    /// The leading fields of `apriltag_detector_t` (the C struct continues with profiling, the
    /// family list, the worker pool and a mutex); only ever used behind the pointer
    /// `apriltag_detector_create` returns.
    #[repr(C)]
    #[derive(Debug)]
    pub struct Detector {
        pub nthreads: c_int,
        pub quad_decimate: f32,
        pub quad_sigma: f32,
        pub refine_edges: bool,
        pub decode_sharpening: f64,
        pub debug: bool,
        pub qtp: QuadThreshParams,
    }

    /// `apriltag_detection_t`.
    #[repr(C)]
    #[derive(Debug)]
    pub struct Detection {
        pub family: *mut Family,
        pub id: c_int,
        pub hamming: c_int,
        pub decision_margin: f32,
        /// Tag coordinates ([−1, 1]², y down as printed) → pixels.
        pub h: *mut Matd,
        pub c: [f64; 2],
        pub p: [[f64; 2]; 4],
    }

    #[cfg(target_pointer_width = "64")]
    const _: () = {
        use std::mem::{offset_of, size_of};
        assert!(offset_of!(ImageU8, buf) == 16);
        assert!(offset_of!(ZArray, data) == 16);
        assert!(offset_of!(Matd, data) == 8);
        assert!(offset_of!(Family, width_at_border) == 16);
        assert!(offset_of!(Family, reversed_border) == 24);
        assert!(offset_of!(Family, bit_x) == 32);
        assert!(offset_of!(Family, impl_) == 64);
        assert!(offset_of!(Detector, decode_sharpening) == 16);
        assert!(offset_of!(Detector, qtp) == 28);
        assert!(size_of::<QuadThreshParams>() == 28);
        assert!(offset_of!(Detection, decision_margin) == 16);
        assert!(offset_of!(Detection, h) == 24);
        assert!(offset_of!(Detection, p) == 48);
        assert!(size_of::<Detection>() == 112);
    };

    #[link(name = "apriltag")]
    unsafe extern "C" {
        pub fn apriltag_detector_create() -> *mut Detector;
        pub fn apriltag_detector_add_family_bits(
            td: *mut Detector,
            fam: *mut Family,
            bits_corrected: c_int,
        );
        pub fn apriltag_detector_destroy(td: *mut Detector);
        pub fn apriltag_detector_detect(td: *mut Detector, im_orig: *mut ImageU8) -> *mut ZArray;
        pub fn apriltag_detections_destroy(detections: *mut ZArray);

        pub fn tag36h11_create() -> *mut Family;
        pub fn tag36h11_destroy(tf: *mut Family);
        pub fn tagStandard41h12_create() -> *mut Family;
        pub fn tagStandard41h12_destroy(tf: *mut Family);
    }
}

use std::ffi::c_int;
use std::ptr::NonNull;

use super::Family;

/// A family's code table and bit layout, read from the library's own family struct.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FamilyLayout {
    /// Codes by id, bit `nbits − 1 − i` being data bit `i`.
    pub codes: Vec<u64>,
    /// Cell (column, row) of each data bit, relative to the upper-left cell of the
    /// `width_at_border` square; negative outside it (the data ring of `tagStandard41h12`).
    pub bits: Vec<(i32, i32)>,
    /// Cells across the square whose corners the detector reports.
    pub width_at_border: u32,
    /// Cells across the whole pattern.
    pub total_width: u32,
    /// The detected square is white inside a black ring (`tagStandard41h12`) rather than black
    /// inside a white one (`tag36h11`).
    pub reversed_border: bool,
    /// The family's minimum Hamming distance between codes.
    pub min_hamming: u32,
}

/// A family struct made by the library's `<family>_create`, freed on drop.
#[derive(Debug)]
struct OwnedFamily {
    family: Family,
    raw: NonNull<sys::Family>,
}

impl OwnedFamily {
    fn new(family: Family) -> Option<Self> {
        // SAFETY: the constructors take no arguments and return a heap-allocated family (NULL
        // only when out of memory) that the caller owns and frees with the matching destroy.
        let raw = unsafe {
            match family {
                Family::Tag36h11 => sys::tag36h11_create(),
                Family::TagStandard41h12 => sys::tagStandard41h12_create(),
            }
        };
        NonNull::new(raw).map(|raw| Self { family, raw })
    }

    fn layout(&self) -> Option<FamilyLayout> {
        // SAFETY: `raw` is a live family from `new`; the library fills `codes` with `ncodes`
        // entries and `bit_x`/`bit_y` with `nbits` entries (tag36h11.c, tagStandard41h12.c),
        // checked non-null before use. Nothing else writes them while we read.
        unsafe {
            let family = self.raw.as_ref();
            if family.codes.is_null() || family.bit_x.is_null() || family.bit_y.is_null() {
                return None;
            }
            let codes = std::slice::from_raw_parts(family.codes, family.ncodes as usize).to_vec();
            let bit_x = std::slice::from_raw_parts(family.bit_x, family.nbits as usize);
            let bit_y = std::slice::from_raw_parts(family.bit_y, family.nbits as usize);
            Some(FamilyLayout {
                codes,
                // The library stores negative coordinates in `uint32_t` (two's complement).
                bits: bit_x
                    .iter()
                    .zip(bit_y)
                    .map(|(&x, &y)| (x as i32, y as i32))
                    .collect(),
                width_at_border: u32::try_from(family.width_at_border).ok()?,
                total_width: u32::try_from(family.total_width).ok()?,
                reversed_border: family.reversed_border,
                min_hamming: family.h,
            })
        }
    }
}

impl Drop for OwnedFamily {
    fn drop(&mut self) {
        // SAFETY: `raw` came from the matching create function and is freed exactly once; the
        // detector that referenced it is destroyed before (see `Detector`'s drop order).
        unsafe {
            match self.family {
                Family::Tag36h11 => sys::tag36h11_destroy(self.raw.as_ptr()),
                Family::TagStandard41h12 => sys::tagStandard41h12_destroy(self.raw.as_ptr()),
            }
        }
    }
}

/// The library's own description of a family.
pub fn family_layout(family: Family) -> Option<FamilyLayout> {
    OwnedFamily::new(family)?.layout()
}

/// The detector's tunables (`apriltag_detector_t` fields of the same names).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectorSettings {
    pub nthreads: u32,
    pub quad_decimate: f32,
    pub quad_sigma: f32,
    pub refine_edges: bool,
    pub decode_sharpening: f64,
}

/// The quad-fitting thresholds (`apriltag_quad_thresh_params`), read-only.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuadThresholds {
    pub min_cluster_pixels: i32,
    pub max_nmaxima: i32,
    pub max_line_fit_mse: f32,
    pub min_white_black_diff: i32,
}

/// One detection as the library reports it, in the library's pixel convention (pixel `i`
/// spans `[i, i + 1)`, so its centre is at `i + 0.5`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LibDetection {
    pub family: Family,
    pub id: u32,
    pub hamming: u32,
    pub decision_margin: f32,
    /// `p[0..4]`: the tag-frame points (−1, 1), (1, 1), (1, −1), (−1, −1) through `H`.
    pub corners: [[f64; 2]; 4],
    /// `H`, row-major: tag coordinates ([−1, 1]², y down as printed) → pixels.
    pub homography: [f64; 9],
}

/// Why a call into the library gave nothing.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LibraryError {
    #[error("libapriltag could not allocate {0}")]
    OutOfMemory(&'static str),
    #[error("image of {width}×{height} with {len} bytes is not a packed 8-bit image")]
    BadImage { width: u32, height: u32, len: usize },
}

/// An `apriltag_detector_t` with its families; destroyed (detector first) on drop.
#[derive(Debug)]
pub struct Detector {
    raw: NonNull<sys::Detector>,
    /// Declared after `raw` and dropped after the detector is destroyed in `Drop::drop`: the
    /// detector's family list and decode tables point into them.
    families: Vec<OwnedFamily>,
}

// SAFETY: the detector and its families are heap data owned by this value alone; libapriltag
// keeps no thread-local state, and its worker threads (nthreads > 1) finish every task before
// `apriltag_detector_detect` returns, so moving the owner between threads is sound. It is not
// `Sync`: `detect` needs `&mut self`.
unsafe impl Send for Detector {}

impl Detector {
    /// A detector for `families`, correcting up to `bits_corrected` (≤ 3, the library's limit)
    /// bit errors per code.
    pub fn new(
        families: &[Family],
        bits_corrected: u32,
        settings: &DetectorSettings,
    ) -> Result<Self, LibraryError> {
        // SAFETY: no arguments; returns a calloc'd detector with the library's defaults, or
        // NULL when out of memory.
        let raw = NonNull::new(unsafe { sys::apriltag_detector_create() })
            .ok_or(LibraryError::OutOfMemory("a detector"))?;
        let mut detector = Self {
            raw,
            families: Vec::with_capacity(families.len()),
        };
        let bits = c_int::try_from(bits_corrected.min(3)).unwrap_or(0);
        for &family in families {
            let owned = OwnedFamily::new(family).ok_or(LibraryError::OutOfMemory("a family"))?;
            // SAFETY: both pointers are live; the family is kept in `self.families`, which
            // outlives the detector (see the field's comment); 0 ≤ bits ≤ 3 as the library needs.
            unsafe {
                sys::apriltag_detector_add_family_bits(
                    detector.raw.as_ptr(),
                    owned.raw.as_ptr(),
                    bits,
                );
            }
            detector.families.push(owned);
        }
        detector.set_settings(settings);
        Ok(detector)
    }

    pub fn set_settings(&mut self, settings: &DetectorSettings) {
        // SAFETY: `raw` is live and only reachable through `&mut self`; these are plain fields
        // the library reads at the next detect.
        unsafe {
            let detector = self.raw.as_mut();
            detector.nthreads = c_int::try_from(settings.nthreads.max(1)).unwrap_or(1);
            detector.quad_decimate = settings.quad_decimate;
            detector.quad_sigma = settings.quad_sigma;
            detector.refine_edges = settings.refine_edges;
            detector.decode_sharpening = settings.decode_sharpening;
        }
    }

    pub fn settings(&self) -> DetectorSettings {
        // SAFETY: `raw` is live; reading plain fields.
        let detector = unsafe { self.raw.as_ref() };
        DetectorSettings {
            nthreads: u32::try_from(detector.nthreads).unwrap_or(0),
            quad_decimate: detector.quad_decimate,
            quad_sigma: detector.quad_sigma,
            refine_edges: detector.refine_edges,
            decode_sharpening: detector.decode_sharpening,
        }
    }

    pub fn quad_thresholds(&self) -> QuadThresholds {
        // SAFETY: `raw` is live; reading plain fields.
        let qtp = unsafe { &self.raw.as_ref().qtp };
        QuadThresholds {
            min_cluster_pixels: qtp.min_cluster_pixels,
            max_nmaxima: qtp.max_nmaxima,
            max_line_fit_mse: qtp.max_line_fit_mse,
            min_white_black_diff: qtp.min_white_black_diff,
        }
    }

    /// Detects tags in a packed `width × height` 8-bit image, appending to `out`. The library
    /// may blur `luma` in place (with `quad_decimate ≤ 1` and `quad_sigma ≠ 0`), hence `&mut`.
    pub fn detect(
        &mut self,
        luma: &mut [u8],
        width: u32,
        height: u32,
        out: &mut Vec<LibDetection>,
    ) -> Result<(), LibraryError> {
        let bad = LibraryError::BadImage {
            width,
            height,
            len: luma.len(),
        };
        let (Ok(w), Ok(h)) = (i32::try_from(width), i32::try_from(height)) else {
            return Err(bad);
        };
        if w == 0 || h == 0 || luma.len() != width as usize * height as usize {
            return Err(bad);
        }
        // libapriltag 3.3 crashes (SIGSEGV, or SIGFPE at decimation 1.5) when the image it
        // searches for quads has fewer than 3 rows or no columns; nothing smaller than a few
        // 4 × 4 threshold tiles can hold a tag, so such images are answered here.
        let decimate = self.settings().quad_decimate;
        if decimated(width, decimate) < MIN_SEARCH_SIZE
            || decimated(height, decimate) < MIN_SEARCH_SIZE
        {
            return Ok(());
        }
        let mut image = sys::ImageU8 {
            width: w,
            height: h,
            stride: w,
            buf: luma.as_mut_ptr(),
        };
        // SAFETY: the detector is live and exclusively ours; `image` describes `luma` exactly
        // (packed rows, `height` of them), which stays mutably borrowed for the call. The
        // returned array is ours to free.
        let detections =
            NonNull::new(unsafe { sys::apriltag_detector_detect(self.raw.as_ptr(), &mut image) })
                .ok_or(LibraryError::OutOfMemory("the detections"))?;
        // SAFETY: `detections` is a zarray of `size` elements of `el_sz` bytes, each a pointer
        // to an `apriltag_detection_t` (checked: element size and non-null data) that stays
        // valid until `apriltag_detections_destroy`, called once below. `H` is read through the
        // raw pointer it came as, after checking it is a non-null 3 × 3 matrix.
        unsafe {
            let array = detections.as_ref();
            let count = usize::try_from(array.size).unwrap_or(0);
            if array.el_sz == size_of::<*const sys::Detection>() && !array.data.is_null() {
                let items =
                    std::slice::from_raw_parts(array.data as *const *const sys::Detection, count);
                for &item in items {
                    let Some(detection) = item.as_ref() else {
                        continue;
                    };
                    let Some(family) = self
                        .families
                        .iter()
                        .find(|f| std::ptr::eq(f.raw.as_ptr(), detection.family))
                        .map(|f| f.family)
                    else {
                        continue;
                    };
                    let h = detection.h;
                    if h.is_null() || (*h).nrows != 3 || (*h).ncols != 3 {
                        continue;
                    }
                    let data = std::ptr::addr_of!((*h).data) as *const f64;
                    let mut homography = [0.0; 9];
                    homography.copy_from_slice(std::slice::from_raw_parts(data, 9));
                    let (Ok(id), Ok(hamming)) = (
                        u32::try_from(detection.id),
                        u32::try_from(detection.hamming),
                    ) else {
                        continue;
                    };
                    out.push(LibDetection {
                        family,
                        id,
                        hamming,
                        decision_margin: detection.decision_margin,
                        corners: detection.p,
                        homography,
                    });
                }
            }
            sys::apriltag_detections_destroy(detections.as_ptr());
        }
        Ok(())
    }
}

/// Smallest width and height (after decimation) passed to the library: two threshold tiles.
const MIN_SEARCH_SIZE: u32 = 8;

/// Size of the quad-search image along one axis, as `image_u8_decimate` computes it.
fn decimated(size: u32, quad_decimate: f32) -> u32 {
    if quad_decimate <= 1.0 {
        size
    } else if quad_decimate == 1.5 {
        size / 3 * 2
    } else {
        1 + (size - 1) / (quad_decimate as u32).max(1)
    }
}

impl Drop for Detector {
    fn drop(&mut self) {
        // SAFETY: `raw` came from `apriltag_detector_create` and is destroyed exactly once,
        // before the families it references (dropped with `self.families` afterwards).
        unsafe { sys::apriltag_detector_destroy(self.raw.as_ptr()) };
    }
}
