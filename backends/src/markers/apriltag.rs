//! AprilTag tracking with libapriltag 3 (Wang & Olson, "AprilTag 2: Efficient and robust
//! fiducial detection", IROS 2016; Krogius et al., "Flexible Layouts for Fiducial Tags", IROS
//! 2019). Debian package `libapriltag-dev`; feature `apriltag`.
//!
//! The library finds quads and decodes them; the pose comes from [`super::pose`] through the
//! full camera model (libapriltag's own `estimate_tag_pose` assumes an undistorted pinhole).
//!
//! # Conventions of the library, converted here
//!
//! - **Pixels**: libapriltag puts the centre of pixel `i` at `i + 0.5` (its edge points are
//!   `x/2 + 0.5`, decimation maps `(x − 0.5)·d + 0.5`); relight and OpenCV put it at `i`. Corners
//!   and homographies are shifted by −0.5 px.
//! - **Corner order**: `p[i]` is the tag point `(−1, 1), (1, 1), (1, −1), (−1, −1)` through the
//!   detection's homography, whose tag frame has +y *down* as printed (bit rows grow
//!   downwards). That is lower-left, lower-right, upper-right, upper-left as printed, which is
//!   already [`MarkerDetection`]'s order; the integration test checks it against rendered truth.
//! - **Tag size** (`size_m`): the edge of the square whose corners are reported, the
//!   `width_at_border` cells of the family: for `tag36h11` the black square (8 of its 10 cells),
//!   for `tagStandard41h12` the white-bordered square (5 of its 9 cells), as in the AprilTag
//!   documentation.
//!
//! [`MarkerDetection`]: relight_core::MarkerDetection

mod ffi;

use glam::{DMat3, DVec2, DVec3};
use relight_core::camera::CameraModel;
use relight_core::{Image, MarkerDetection, MarkerSet, PixelFormat};
use serde::{Deserialize, Serialize};

pub use ffi::{DetectorSettings, FamilyLayout, QuadThresholds};

use super::board::{Board, BoardConfig, BoardError, BoardFit, corners_f32};
use super::device::MarkerDevice;
use super::one_euro::OneEuroConfig;
use super::pose::{PoseError, PoseFit, PoseSettings, estimate_square_pose};
use super::render::TagBitmap;
use super::{TagSizeOverride, TagSizes};
use crate::device::DeviceError;
use crate::sources::MarkerTracker;

const BACKEND: &str = "apriltag";

/// The tag families this backend detects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Family {
    /// 36-bit codes, minimum Hamming distance 11, 587 ids; the simulator's family.
    #[serde(rename = "tag36h11")]
    Tag36h11,
    /// 41-bit codes, minimum Hamming distance 12, 2115 ids; data also outside the border, so
    /// more bits per printed area.
    #[serde(rename = "tagStandard41h12")]
    TagStandard41h12,
}

impl Family {
    pub const ALL: [Family; 2] = [Family::Tag36h11, Family::TagStandard41h12];

    /// The family's name as libapriltag and [`MarkerDetection::family`] spell it.
    pub fn name(self) -> &'static str {
        match self {
            Family::Tag36h11 => "tag36h11",
            Family::TagStandard41h12 => "tagStandard41h12",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }
}

/// The library's code table and bit layout of `family`; `None` when the library cannot
/// allocate it.
pub fn family_layout(family: Family) -> Option<FamilyLayout> {
    ffi::family_layout(family)
}

/// The printed cell pattern of tag `id` of `family`, built from the linked library's own
/// family struct exactly as its `apriltag_to_image` draws it: all black, a one-cell white ring
/// (around the black border for normal families, as the border for reversed ones), then the
/// code's set bits white. `None` for an id the family does not have.
pub fn family_bitmap(family: Family, id: u32) -> Option<TagBitmap> {
    let layout = family_layout(family)?;
    let code = *layout.codes.get(id as usize)?;
    let total = layout.total_width;
    let border = layout.width_at_border;
    let mut cells = vec![false; (total * total) as usize];
    let ring = border + if layout.reversed_border { 0 } else { 2 };
    let ring_start = total.checked_sub(ring)? / 2;
    let ring_end = ring_start + ring - 1;
    for row in ring_start..=ring_end {
        for col in ring_start..=ring_end {
            if row == ring_start || row == ring_end || col == ring_start || col == ring_end {
                cells[(row * total + col) as usize] = true;
            }
        }
    }
    let border_start = i64::from((total - border) / 2);
    let nbits = layout.bits.len();
    for (i, &(x, y)) in layout.bits.iter().enumerate() {
        if code & (1u64 << (nbits - 1 - i)) == 0 {
            continue;
        }
        let (col, row) = (border_start + i64::from(x), border_start + i64::from(y));
        if !(0..i64::from(total)).contains(&col) || !(0..i64::from(total)).contains(&row) {
            return None;
        }
        cells[(row * i64::from(total) + col) as usize] = true;
    }
    Some(TagBitmap {
        total_cells: total,
        size_cells: border,
        cells,
    })
}

/// The `[markers]` table with `backend = "apriltag"`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AprilTagConfig {
    /// Families to detect: `tag36h11` (default), `tagStandard41h12`.
    pub families: Vec<Family>,
    /// Edge of a tag's detected square, metres (see the module docs for what that is per
    /// family). Default 0.12, the simulator's board.
    pub size_m: f64,
    /// Tags printed at another size: `[{ marker_id = 7, size_m = 0.05 }]` (any family).
    pub sizes: Vec<TagSizeOverride>,
    /// Quad search on an image decimated by this factor (library default 2; 1 finds smaller
    /// tags, slower). Corners are refined on the full image when `refine_edges` is on.
    pub quad_decimate: f32,
    /// Gaussian blur σ (px) before the quad search; negative sharpens (library default 0).
    pub quad_sigma: f32,
    /// Worker threads of the detector.
    pub nthreads: u32,
    /// Snap quad edges to the strongest gradient of the full-resolution image (sub-pixel
    /// corners; keep on for pose).
    pub refine_edges: bool,
    /// Sharpening of the sampled bits before decoding (library default 0.25).
    pub decode_sharpening: f64,
    /// Most bit errors a detection may have been corrected by (0–2, default 1). The library
    /// builds a decode table for this many errors: about 1 MB (`tag36h11`) and 4 MB
    /// (`tagStandard41h12`) at 1, 36 MB and 170 MB at 2.
    pub max_hamming: u32,
    /// Detections whose decision margin (mean distance of the bits from the black/white
    /// threshold, in grey levels) is below this are rejected as likely false positives.
    pub min_decision_margin: f32,
    /// Detections whose corners do not fit the square tag within this RMS (pixels) are dropped
    /// rather than reported with a wrong pose (an occluded or misfitted corner).
    pub max_reprojection_rms_px: f64,
    /// Pose fitting (`corner_sigma_px`, `max_iterations`).
    pub pose: PoseSettings,
    /// A rigid board of tags to report as one more detection (see [`BoardConfig`]).
    pub board: Option<BoardConfig>,
    /// One-Euro pose smoothing (used by the device, not the tracker).
    pub filter: OneEuroConfig,
}

impl Default for AprilTagConfig {
    fn default() -> Self {
        Self {
            families: vec![Family::Tag36h11],
            size_m: 0.12,
            sizes: Vec::new(),
            quad_decimate: 2.0,
            quad_sigma: 0.0,
            nthreads: 1,
            refine_edges: true,
            decode_sharpening: 0.25,
            max_hamming: 1,
            min_decision_margin: 30.0,
            max_reprojection_rms_px: 1.0,
            pose: PoseSettings::default(),
            board: None,
            filter: OneEuroConfig::default(),
        }
    }
}

/// A decoded tag with its pose.
#[derive(Debug, Clone, PartialEq)]
pub struct TagObservation {
    pub family: Family,
    pub marker_id: u32,
    pub hamming: u32,
    pub decision_margin: f32,
    /// Corners in relight pixels, [`MarkerDetection`] order.
    pub corners_px: [DVec2; 4],
    /// Tag coordinates ([−1, 1]², y down as printed) → relight pixels.
    pub homography: DMat3,
    pub size_m: f64,
    pub fit: PoseFit,
}

impl TagObservation {
    pub fn detection(&self) -> MarkerDetection {
        self.fit.detection(
            self.family.name(),
            self.marker_id,
            corners_f32(&self.corners_px),
        )
    }
}

/// Why a decoded tag was not reported.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    Hamming(u32),
    DecisionMargin(f32),
    Pose(PoseError),
    Reprojection { rms_px: f64 },
}

#[derive(Debug, Clone, PartialEq)]
pub struct RejectedTag {
    pub family: Family,
    pub marker_id: u32,
    pub corners_px: [DVec2; 4],
    pub reason: Rejection,
}

/// The configured board, when enough of it was seen.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardObservation {
    pub fit: BoardFit,
    pub detection: MarkerDetection,
}

/// Everything one image gave.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Observations {
    pub tags: Vec<TagObservation>,
    pub rejected: Vec<RejectedTag>,
    pub board: Option<BoardObservation>,
}

/// AprilTag detection and pose, a [`MarkerTracker`].
#[derive(Debug)]
pub struct AprilTagTracker {
    detector: ffi::Detector,
    families: Vec<Family>,
    family_label: String,
    sizes: TagSizes,
    max_hamming: u32,
    min_decision_margin: f32,
    max_reprojection_rms_px: f64,
    pose: PoseSettings,
    board: Option<(Family, Board)>,
    luma: Vec<u8>,
    raw: Vec<ffi::LibDetection>,
    observations: Observations,
}

impl AprilTagTracker {
    /// Checks the configuration and creates the library's detector.
    pub fn new(config: &AprilTagConfig) -> Result<Self, DeviceError> {
        let invalid = |reason: String| DeviceError::Config {
            device: BACKEND.into(),
            reason,
        };
        if config.families.is_empty() {
            return Err(invalid("`families` must name at least one family".into()));
        }
        let mut families: Vec<Family> = Vec::with_capacity(config.families.len());
        for family in &config.families {
            if !families.contains(family) {
                families.push(*family);
            }
        }
        let sizes = TagSizes::new(config.size_m, config.sizes.clone()).map_err(invalid)?;
        if config.max_hamming > 2 {
            return Err(invalid(format!(
                "`max_hamming` = {} exceeds 2 (the decode table would take gigabytes)",
                config.max_hamming
            )));
        }
        if !(config.quad_decimate.is_finite() && config.quad_decimate >= 1.0) {
            return Err(invalid(format!(
                "`quad_decimate` must be ≥ 1, got {}",
                config.quad_decimate
            )));
        }
        if !config.quad_sigma.is_finite() || !config.decode_sharpening.is_finite() {
            return Err(invalid(
                "`quad_sigma` and `decode_sharpening` must be numbers".into(),
            ));
        }
        if !(1..=64).contains(&config.nthreads) {
            return Err(invalid(format!(
                "`nthreads` must be 1–64, got {}",
                config.nthreads
            )));
        }
        let rms_ok =
            config.max_reprojection_rms_px.is_finite() && config.max_reprojection_rms_px > 0.0;
        if !(rms_ok && config.min_decision_margin.is_finite()) {
            return Err(invalid(
                "`max_reprojection_rms_px` must be > 0 and `min_decision_margin` a number".into(),
            ));
        }
        if !(config.pose.corner_sigma_px.is_finite() && config.pose.corner_sigma_px > 0.0) {
            return Err(invalid("`pose.corner_sigma_px` must be > 0".into()));
        }
        config.filter.validate().map_err(invalid)?;
        let board = match &config.board {
            None => None,
            Some(board_config) => {
                let board = Board::from_config(board_config)
                    .map_err(|e: BoardError| invalid(e.to_string()))?;
                let family = Family::from_name(board.family())
                    .filter(|f| families.contains(f))
                    .ok_or_else(|| {
                        invalid(format!(
                            "the board's family `{}` is not one of the detected `families`",
                            board.family()
                        ))
                    })?;
                Some((family, board))
            }
        };
        let settings = DetectorSettings {
            nthreads: config.nthreads,
            quad_decimate: config.quad_decimate,
            quad_sigma: config.quad_sigma,
            refine_edges: config.refine_edges,
            decode_sharpening: config.decode_sharpening,
        };
        let detector =
            ffi::Detector::new(&families, config.max_hamming, &settings).map_err(|e| {
                DeviceError::NotFound {
                    device: BACKEND.into(),
                    reason: e.to_string(),
                }
            })?;
        let family_label = families
            .iter()
            .map(|f| f.name())
            .collect::<Vec<_>>()
            .join(",");
        Ok(Self {
            detector,
            families,
            family_label,
            sizes,
            max_hamming: config.max_hamming,
            min_decision_margin: config.min_decision_margin,
            max_reprojection_rms_px: config.max_reprojection_rms_px,
            pose: config.pose,
            board,
            luma: Vec::new(),
            raw: Vec::new(),
            observations: Observations::default(),
        })
    }

    pub fn families(&self) -> &[Family] {
        &self.families
    }

    /// The library detector's settings as it holds them.
    pub fn detector_settings(&self) -> DetectorSettings {
        self.detector.settings()
    }

    /// The library's quad thresholds (left at its defaults).
    pub fn quad_thresholds(&self) -> QuadThresholds {
        self.detector.quad_thresholds()
    }

    /// Detects, decodes and fits every tag in `image` (`Rgb8`, converted to luma, or `Mono8`)
    /// seen by `camera`, whose resolution must be the image's.
    pub fn observe(
        &mut self,
        image: &Image,
        camera: &CameraModel,
    ) -> Result<&Observations, DeviceError> {
        let (width, height) = (image.width(), image.height());
        if (camera.width(), camera.height()) != (width, height) {
            return Err(DeviceError::Config {
                device: BACKEND.into(),
                reason: format!(
                    "image is {width}×{height}, camera calibrated at {}×{}",
                    camera.width(),
                    camera.height()
                ),
            });
        }
        to_luma(image, &mut self.luma)?;
        self.raw.clear();
        self.detector
            .detect(&mut self.luma, width, height, &mut self.raw)
            .map_err(|e| DeviceError::BadData {
                device: BACKEND.into(),
                reason: e.to_string(),
            })?;
        let observations = &mut self.observations;
        observations.tags.clear();
        observations.rejected.clear();
        observations.board = None;
        for raw in &self.raw {
            // libapriltag's pixel centres are at +0.5.
            let corners_px = raw.corners.map(|[x, y]| DVec2::new(x - 0.5, y - 0.5));
            let reject = |reason| RejectedTag {
                family: raw.family,
                marker_id: raw.id,
                corners_px,
                reason,
            };
            if raw.hamming > self.max_hamming {
                observations
                    .rejected
                    .push(reject(Rejection::Hamming(raw.hamming)));
                continue;
            }
            if raw.decision_margin < self.min_decision_margin {
                observations
                    .rejected
                    .push(reject(Rejection::DecisionMargin(raw.decision_margin)));
                continue;
            }
            let size_m = self.sizes.size_m(raw.id);
            let fit = match estimate_square_pose(&corners_px, size_m, camera, &self.pose) {
                Ok(fit) => fit,
                Err(error) => {
                    observations.rejected.push(reject(Rejection::Pose(error)));
                    continue;
                }
            };
            if fit.reprojection_rms_px > self.max_reprojection_rms_px {
                observations.rejected.push(reject(Rejection::Reprojection {
                    rms_px: fit.reprojection_rms_px,
                }));
                continue;
            }
            let h = raw.homography;
            let to_relight = DMat3::from_cols(DVec3::X, DVec3::Y, DVec3::new(-0.5, -0.5, 1.0));
            let homography = to_relight
                * DMat3::from_cols(
                    DVec3::new(h[0], h[3], h[6]),
                    DVec3::new(h[1], h[4], h[7]),
                    DVec3::new(h[2], h[5], h[8]),
                );
            observations.tags.push(TagObservation {
                family: raw.family,
                marker_id: raw.id,
                hamming: raw.hamming,
                decision_margin: raw.decision_margin,
                corners_px,
                homography,
                size_m,
                fit,
            });
        }
        if let Some((family, board)) = &self.board {
            let seen: Vec<(u32, [DVec2; 4])> = observations
                .tags
                .iter()
                .filter(|tag| tag.family == *family)
                .map(|tag| (tag.marker_id, tag.corners_px))
                .collect();
            match board.estimate(&seen, camera, &self.pose) {
                Ok(fit) => {
                    let used: Vec<DVec2> = seen
                        .iter()
                        .filter(|(id, _)| fit.tags_used.contains(id))
                        .flat_map(|(_, corners)| *corners)
                        .collect();
                    let detection = board.detection(&fit, &used, camera);
                    observations.board = Some(BoardObservation { fit, detection });
                }
                Err(BoardError::NoTags) => {}
                Err(error) => tracing::trace!(%error, "board pose failed"),
            }
        }
        Ok(&self.observations)
    }
}

/// Packed luma of an `Rgb8` (BT.601 weights, as libapriltag's own RGB loaders) or `Mono8`
/// image.
fn to_luma(image: &Image, luma: &mut Vec<u8>) -> Result<(), DeviceError> {
    let bad = |reason: String| DeviceError::BadData {
        device: BACKEND.into(),
        reason,
    };
    let pixels = image.as_u8().ok_or_else(|| {
        bad(format!(
            "{:?} image, expected rgb8 or mono8",
            image.format()
        ))
    })?;
    luma.clear();
    match image.format() {
        PixelFormat::Mono8 => luma.extend_from_slice(pixels),
        PixelFormat::Rgb8 => luma.extend(pixels.chunks_exact(3).map(|rgb| {
            let y = 77 * u32::from(rgb[0]) + 150 * u32::from(rgb[1]) + 29 * u32::from(rgb[2]);
            ((y + 128) >> 8) as u8
        })),
        other => return Err(bad(format!("{other:?} image, expected rgb8 or mono8"))),
    }
    if luma.len() != image.pixel_count() {
        return Err(bad("image buffer does not match its size".into()));
    }
    Ok(())
}

impl MarkerTracker for AprilTagTracker {
    fn family(&self) -> &str {
        &self.family_label
    }

    fn detect(
        &mut self,
        image: &Image,
        camera: &CameraModel,
        out: &mut MarkerSet,
    ) -> Result<(), DeviceError> {
        let observations = self.observe(image, camera)?;
        out.detections.clear();
        out.detections
            .extend(observations.tags.iter().map(TagObservation::detection));
        if let Some(board) = &observations.board {
            out.detections.push(board.detection.clone());
        }
        Ok(())
    }
}

/// The `[markers]` device of the daemon: an AprilTag tracker on the colour stream, with the
/// rig calibration's colour camera and the config's filter.
pub fn apriltag_device(
    config: &AprilTagConfig,
    colour_camera: CameraModel,
) -> Result<MarkerDevice<AprilTagTracker>, DeviceError> {
    MarkerDevice::new(
        BACKEND,
        AprilTagTracker::new(config)?,
        colour_camera,
        config.filter,
    )
}
