//! ArUco square markers through OpenCV's ArUco module.
//!
//! In OpenCV 4.6 (Debian's `libopencv-contrib-dev`) ArUco is the contrib module `cv::aruco`
//! (`detectMarkers`, `getPredefinedDictionary`, `DetectorParameters`); from 4.7 on it moved to
//! `objdetect` as `ArucoDetector`. Detection is Garrido-Jurado et al., "Automatic generation and
//! detection of highly reliable fiducial markers under occlusion", Pattern Recognition 47(6), 2014:
//! adaptive threshold, contour polygons, perspective removal, bit extraction with Otsu, and
//! lookup in the dictionary with up to `maxCorrectionBits × errorCorrectionRate` flipped bits.
//!
//! # Dictionaries
//!
//! The predefined dictionaries of OpenCV 4.6 (`DICT_*` in `opencv2/aruco/dictionary.hpp`), named
//! without the prefix in lower case: `4x4_50` … `7x7_1000`, `aruco_original`, `apriltag_16h5`,
//! `apriltag_25h9`, `apriltag_36h10`, `apriltag_36h11`. OpenCV 4.6 has **no ARToolKit-compatible
//! dictionary**: ARToolKit's matrix-code markers (`AR_MATRIX_CODE_3x3` …) and its template
//! patterns are not in the list, and `DICT_ARUCO_MIP_36h12` (ArUco 3's recommended set) only
//! arrived in OpenCV 4.8. ARToolKit-style trackers are served here by the ArUco and AprilTag
//! sets, which are square markers of the same construction (black border, binary payload).
//!
//! # Output
//!
//! Detections are [`MarkerDetection`](relight_core::MarkerDetection)s with relight's conventions (see `relight_core::stream`):
//! corners counter-clockwise from the marker's lower-left as printed (OpenCV reports them
//! clockwise from the top-left, so the order is reversed), and `camera_from_marker` from the
//! marker frame (origin at the centre, +x right and +y up as printed, +z out of the print) to the
//! glTF camera frame (+y up, −z forward), as the simulated rig writes its `MarkerTruth`.
//! AprilTag dictionaries report the AprilTag family name (`tag36h11`), so a board tracked by
//! either backend carries the same family and IDs; the others report `aruco_<name>`.
//!
//! # AprilTag orientation
//!
//! OpenCV 4's `DICT_APRILTAG_*` codes are stored rotated by 180° against the AprilTag library
//! and its official images (`AprilRobotics/apriltag-imgs`): `drawMarker` draws them upside
//! down, and on a real AprilTag print `detectMarkers` reports its "top-left" corner at the
//! print's bottom-right (opencv/opencv-python#1195; fixed only for OpenCV 5 by opencv/opencv
//! PR #28823). This backend undoes it for those dictionaries: corners and pose refer to the tag
//! as printed by the AprilTag tools (and by the simulator), and
//! [`Dictionary::tag_bitmap`] returns the official orientation.
//!
//! # Corners
//!
//! OpenCV finds each marker's quad and refines its corners locally (`cornerSubPix`, here with a
//! window scaled to the marker's cells as OpenCV 4.8 does, not 4.6's fixed one). By default
//! ([`CornerRefinement::Edges`]) the corners are then replaced by the intersections of lines
//! fitted to sub-pixel edge points along the middle of each side, on the camera's undistorted
//! image plane (`aruco/edges.rs`): blur does not bias them, a lens does not bend them, and nothing at a
//! corner moves them. The same fit verifies every marker whatever the refinement
//! (`verify_corners`): a side that is not one straight edge, or a corner away from where its
//! sides meet (a fingertip over it), drops the marker — not reported beats a confidently wrong
//! pose.
//!
//! # Pose
//!
//! The pose comes from the shared square-marker solver ([`super::pose`]): the corners go through
//! the rig's [`CameraModel`] (pinhole or fish-eye), so both marker backends report the same pose
//! and the same reprojection RMS for the same corners. OpenCV's `estimatePoseSingleMarkers`
//! is not used: it only knows the Brown–Conrady model.

use std::fmt;

use glam::{DVec2, Vec2};
use opencv::core::{
    Mat, Point2f, Ptr, Size, TermCriteria, TermCriteria_Type, ToInputArray, Vec3b, Vector,
};
use opencv::prelude::*;
use opencv::{aruco, imgproc};
use relight_core::camera::CameraModel;
use relight_core::{Image, MarkerSet, PixelFormat};
use serde::Deserialize;

mod edges;

use self::edges::{GreyView, fit_sides};
use super::board::{Board, BoardConfig, BoardError};
use super::device::MarkerDevice;
use super::one_euro::OneEuroConfig;
use super::pose::{PoseSettings, estimate_square_pose};
use super::render::TagBitmap;
use super::{TagSizeOverride, TagSizes};
use crate::device::DeviceError;
use crate::sources::MarkerTracker;

/// Name of this backend in device errors and logs.
pub const BACKEND: &str = "aruco";

/// A predefined dictionary of OpenCV 4.6's ArUco module.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(try_from = "String")]
pub enum ArucoDictionary {
    Aruco4x4_50,
    Aruco4x4_100,
    Aruco4x4_250,
    Aruco4x4_1000,
    Aruco5x5_50,
    Aruco5x5_100,
    Aruco5x5_250,
    Aruco5x5_1000,
    Aruco6x6_50,
    Aruco6x6_100,
    Aruco6x6_250,
    Aruco6x6_1000,
    Aruco7x7_50,
    Aruco7x7_100,
    Aruco7x7_250,
    Aruco7x7_1000,
    ArucoOriginal,
    AprilTag16h5,
    AprilTag25h9,
    AprilTag36h10,
    AprilTag36h11,
}

impl ArucoDictionary {
    pub const ALL: [ArucoDictionary; 21] = [
        Self::Aruco4x4_50,
        Self::Aruco4x4_100,
        Self::Aruco4x4_250,
        Self::Aruco4x4_1000,
        Self::Aruco5x5_50,
        Self::Aruco5x5_100,
        Self::Aruco5x5_250,
        Self::Aruco5x5_1000,
        Self::Aruco6x6_50,
        Self::Aruco6x6_100,
        Self::Aruco6x6_250,
        Self::Aruco6x6_1000,
        Self::Aruco7x7_50,
        Self::Aruco7x7_100,
        Self::Aruco7x7_250,
        Self::Aruco7x7_1000,
        Self::ArucoOriginal,
        Self::AprilTag16h5,
        Self::AprilTag25h9,
        Self::AprilTag36h10,
        Self::AprilTag36h11,
    ];

    /// The configuration name: OpenCV's `DICT_*` constant without the prefix, in lower case.
    pub fn name(self) -> &'static str {
        match self {
            Self::Aruco4x4_50 => "4x4_50",
            Self::Aruco4x4_100 => "4x4_100",
            Self::Aruco4x4_250 => "4x4_250",
            Self::Aruco4x4_1000 => "4x4_1000",
            Self::Aruco5x5_50 => "5x5_50",
            Self::Aruco5x5_100 => "5x5_100",
            Self::Aruco5x5_250 => "5x5_250",
            Self::Aruco5x5_1000 => "5x5_1000",
            Self::Aruco6x6_50 => "6x6_50",
            Self::Aruco6x6_100 => "6x6_100",
            Self::Aruco6x6_250 => "6x6_250",
            Self::Aruco6x6_1000 => "6x6_1000",
            Self::Aruco7x7_50 => "7x7_50",
            Self::Aruco7x7_100 => "7x7_100",
            Self::Aruco7x7_250 => "7x7_250",
            Self::Aruco7x7_1000 => "7x7_1000",
            Self::ArucoOriginal => "aruco_original",
            Self::AprilTag16h5 => "apriltag_16h5",
            Self::AprilTag25h9 => "apriltag_25h9",
            Self::AprilTag36h10 => "apriltag_36h10",
            Self::AprilTag36h11 => "apriltag_36h11",
        }
    }

    /// Parses a configuration name, case-insensitively, with or without OpenCV's `DICT_` prefix.
    pub fn from_name(name: &str) -> Option<Self> {
        let lower = name.trim().to_ascii_lowercase();
        let bare = lower.strip_prefix("dict_").unwrap_or(&lower);
        Self::ALL.into_iter().find(|d| d.name() == bare)
    }

    /// The family reported in [`MarkerDetection::family`]: the AprilTag library's name for the
    /// AprilTag sets (the same codes and IDs), `aruco_<name>` for the others.
    ///
    /// [`MarkerDetection::family`]: relight_core::MarkerDetection::family
    pub fn family(self) -> &'static str {
        match self {
            Self::Aruco4x4_50 => "aruco_4x4_50",
            Self::Aruco4x4_100 => "aruco_4x4_100",
            Self::Aruco4x4_250 => "aruco_4x4_250",
            Self::Aruco4x4_1000 => "aruco_4x4_1000",
            Self::Aruco5x5_50 => "aruco_5x5_50",
            Self::Aruco5x5_100 => "aruco_5x5_100",
            Self::Aruco5x5_250 => "aruco_5x5_250",
            Self::Aruco5x5_1000 => "aruco_5x5_1000",
            Self::Aruco6x6_50 => "aruco_6x6_50",
            Self::Aruco6x6_100 => "aruco_6x6_100",
            Self::Aruco6x6_250 => "aruco_6x6_250",
            Self::Aruco6x6_1000 => "aruco_6x6_1000",
            Self::Aruco7x7_50 => "aruco_7x7_50",
            Self::Aruco7x7_100 => "aruco_7x7_100",
            Self::Aruco7x7_250 => "aruco_7x7_250",
            Self::Aruco7x7_1000 => "aruco_7x7_1000",
            Self::ArucoOriginal => "aruco_original",
            Self::AprilTag16h5 => "tag16h5",
            Self::AprilTag25h9 => "tag25h9",
            Self::AprilTag36h10 => "tag36h10",
            Self::AprilTag36h11 => "tag36h11",
        }
    }

    /// Quarter turns from the orientation OpenCV 4 stores a code in to the family's official
    /// one: 2 for the AprilTag sets (see the module docs), 0 otherwise.
    pub fn opencv_quarter_turns(self) -> u32 {
        match self {
            Self::AprilTag16h5 | Self::AprilTag25h9 | Self::AprilTag36h10 | Self::AprilTag36h11 => {
                2
            }
            _ => 0,
        }
    }

    fn opencv(self) -> aruco::PREDEFINED_DICTIONARY_NAME {
        use aruco::PREDEFINED_DICTIONARY_NAME as D;
        match self {
            Self::Aruco4x4_50 => D::DICT_4X4_50,
            Self::Aruco4x4_100 => D::DICT_4X4_100,
            Self::Aruco4x4_250 => D::DICT_4X4_250,
            Self::Aruco4x4_1000 => D::DICT_4X4_1000,
            Self::Aruco5x5_50 => D::DICT_5X5_50,
            Self::Aruco5x5_100 => D::DICT_5X5_100,
            Self::Aruco5x5_250 => D::DICT_5X5_250,
            Self::Aruco5x5_1000 => D::DICT_5X5_1000,
            Self::Aruco6x6_50 => D::DICT_6X6_50,
            Self::Aruco6x6_100 => D::DICT_6X6_100,
            Self::Aruco6x6_250 => D::DICT_6X6_250,
            Self::Aruco6x6_1000 => D::DICT_6X6_1000,
            Self::Aruco7x7_50 => D::DICT_7X7_50,
            Self::Aruco7x7_100 => D::DICT_7X7_100,
            Self::Aruco7x7_250 => D::DICT_7X7_250,
            Self::Aruco7x7_1000 => D::DICT_7X7_1000,
            Self::ArucoOriginal => D::DICT_ARUCO_ORIGINAL,
            Self::AprilTag16h5 => D::DICT_APRILTAG_16h5,
            Self::AprilTag25h9 => D::DICT_APRILTAG_25h9,
            Self::AprilTag36h10 => D::DICT_APRILTAG_36h10,
            Self::AprilTag36h11 => D::DICT_APRILTAG_36h11,
        }
    }
}

impl fmt::Display for ArucoDictionary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl TryFrom<String> for ArucoDictionary {
    type Error = ArucoError;
    fn try_from(name: String) -> Result<Self, ArucoError> {
        Self::from_name(&name).ok_or(ArucoError::UnknownDictionary(name))
    }
}

/// How OpenCV refines the corners of a found quad (`cv::aruco::CornerRefineMethod`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CornerRefinement {
    /// The polygon's vertices as found on the contour: integer pixels, about a pixel inside the
    /// square. Needs `verify_corners = false` (the check would drop every marker).
    None,
    /// `cornerSubPix` on the grey image: the gradient-orthogonality fixed point near each vertex
    /// (Förstner & Gülch 1987), iterated to `corner_refinement_min_accuracy_px`, in a window
    /// scaled to each marker's cell size (OpenCV 4.8's rule, applied here on 4.6). A blurred
    /// corner pulls it into the square by about a third of the blur σ.
    Subpix,
    /// Lines fitted to the contour points of each side, intersected.
    Contour,
    /// `subpix`, then each side's line fitted to sub-pixel edge points along its middle (on the
    /// camera's undistorted image plane) and adjacent lines intersected: AprilTag's edge
    /// refinement on OpenCV's quads. Blur does not move it, nor does an occluder at a corner.
    #[default]
    Edges,
    /// AprilTag 2's quad fitting (Wang & Olson, IROS 2016) on the thresholded image, moved by
    /// −0.5 px to OpenCV's pixel-centre convention.
    Apriltag,
}

impl CornerRefinement {
    fn opencv(self) -> aruco::CornerRefineMethod {
        match self {
            Self::None => aruco::CornerRefineMethod::CORNER_REFINE_NONE,
            Self::Subpix => aruco::CornerRefineMethod::CORNER_REFINE_SUBPIX,
            Self::Contour => aruco::CornerRefineMethod::CORNER_REFINE_CONTOUR,
            Self::Apriltag => aruco::CornerRefineMethod::CORNER_REFINE_APRILTAG,
            Self::Edges => aruco::CornerRefineMethod::CORNER_REFINE_SUBPIX,
        }
    }
}

/// Configuration of the `aruco` marker tracker (the JSON of its TOML section).
///
/// Keys:
/// - `dictionary` (default `"4x4_50"`): a name of [`ArucoDictionary`], e.g. `"5x5_100"`,
///   `"6x6_250"`, `"aruco_original"`, `"apriltag_36h11"` (OpenCV's `DICT_*` in lower case,
///   the prefix optional). There is no ARToolKit dictionary in OpenCV 4.6.
/// - `size_m` (required): edge of a marker's black square in metres (the border included, the
///   white quiet zone not).
/// - `sizes` (default empty): per-ID edge lengths overriding `size_m`, e.g.
///   `sizes = [{ marker_id = 7, size_m = 0.04 }]` for a small lamp marker among board tags.
/// - `corner_refinement` (default `"edges"`): `"edges"`, `"subpix"`, `"contour"`, `"apriltag"`,
///   `"none"` ([`CornerRefinement`]). Measured on rendered 15 cm markers at 0.5–2 m, tilted
///   30–60°, blur σ ≤ 2 px: `edges` 0.01–0.05 px mean corner RMS (0.4 px at 2 m and σ 2 px) for
///   ~4 ms per 640 × 480 frame; `subpix` 0.2–0.7 px (1.4 px at 2 m, σ 2 px), pulled inwards by
///   blur, ~3.5 ms; `apriltag` 0.1–0.4 px but ~110 ms; `contour` ~0.6 px inwards.
/// - `max_correction_bits` (default: OpenCV's, 60 % of the dictionary's maximum): how many
///   flipped payload bits a decoded marker may have; at most the dictionary's
///   `maxCorrectionBits` (⌊(d − 1)/2⌋ for minimum Hamming distance d). 0 accepts exact codes only.
/// - `threshold_window_min_px`, `threshold_window_max_px`, `threshold_window_step_px` (defaults
///   3, 23, 10): the adaptive-threshold window sizes tried.
/// - `threshold_constant` (default 7): subtracted from the local mean in the adaptive threshold.
/// - `min_perimeter_rate`, `max_perimeter_rate` (defaults 0.03, 4.0): a candidate's perimeter
///   relative to the image's larger side.
/// - `corner_refinement_window_px` (default 5), `corner_refinement_relative_window` (default
///   0.3), `corner_refinement_max_iterations` (default 30), `corner_refinement_min_accuracy_px`
///   (default 0.1): `subpix`'s half window (at most the first, else the second times the
///   marker's cell size in pixels), iteration cap and stopping step.
/// - `detect_inverted` (default false): also accept white-on-black markers.
/// - `verify_corners` (default true), `max_edge_rms_px` (default 0.5), `max_corner_shift_px`
///   (default 1.0): fit each side's line as `edges` does and drop markers with a side that is
///   not a straight edge (edge points further from their line than `max_edge_rms_px`, RMS), or,
///   for refinements other than `edges`, with a corner further than `max_corner_shift_px` from
///   where its sides meet — a corner hidden by a finger or a cable, which would otherwise give a
///   confidently wrong pose. Markers need a white margin of at least one cell (as for
///   detection) and all of it inside the image.
/// - `max_reprojection_rms_px` (default 1.0): detections whose pose fit leaves a larger corner
///   RMS are dropped (a quad that is not a flat square seen through the camera model).
/// - `pose` (default `{ corner_sigma_px = 0.2, max_iterations = 50 }`): the shared pose
///   solver's settings ([`PoseSettings`]).
/// - `board` (optional): a rigid board of this dictionary's markers ([`BoardConfig`], its
///   `family` set to this dictionary's family, e.g. `"aruco_4x4_50"`); when given, every frame
///   in which some of its markers are seen also reports one detection for the whole board.
/// - `filter` (default: [`OneEuroConfig`]'s): One-Euro smoothing of each marker's pose, applied
///   by the device ([`aruco_device`]), not by the tracker.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArucoConfig {
    #[serde(default = "default_dictionary")]
    pub dictionary: ArucoDictionary,
    pub size_m: f64,
    #[serde(default)]
    pub sizes: Vec<TagSizeOverride>,
    #[serde(default)]
    pub corner_refinement: CornerRefinement,
    #[serde(default)]
    pub max_correction_bits: Option<u32>,
    #[serde(default = "default_threshold_window_min_px")]
    pub threshold_window_min_px: u32,
    #[serde(default = "default_threshold_window_max_px")]
    pub threshold_window_max_px: u32,
    #[serde(default = "default_threshold_window_step_px")]
    pub threshold_window_step_px: u32,
    #[serde(default = "default_threshold_constant")]
    pub threshold_constant: f64,
    #[serde(default = "default_min_perimeter_rate")]
    pub min_perimeter_rate: f64,
    #[serde(default = "default_max_perimeter_rate")]
    pub max_perimeter_rate: f64,
    #[serde(default = "default_corner_refinement_window_px")]
    pub corner_refinement_window_px: u32,
    #[serde(default = "default_corner_refinement_relative_window")]
    pub corner_refinement_relative_window: f64,
    #[serde(default = "default_corner_refinement_max_iterations")]
    pub corner_refinement_max_iterations: u32,
    #[serde(default = "default_corner_refinement_min_accuracy_px")]
    pub corner_refinement_min_accuracy_px: f64,
    #[serde(default)]
    pub detect_inverted: bool,
    #[serde(default = "default_verify_corners")]
    pub verify_corners: bool,
    #[serde(default = "default_max_edge_rms_px")]
    pub max_edge_rms_px: f64,
    #[serde(default = "default_max_corner_shift_px")]
    pub max_corner_shift_px: f64,
    #[serde(default = "default_max_reprojection_rms_px")]
    pub max_reprojection_rms_px: f64,
    #[serde(default)]
    pub pose: PoseSettings,
    #[serde(default)]
    pub board: Option<BoardConfig>,
    #[serde(default)]
    pub filter: OneEuroConfig,
}

fn default_dictionary() -> ArucoDictionary {
    ArucoDictionary::Aruco4x4_50
}
fn default_threshold_window_min_px() -> u32 {
    3
}
fn default_threshold_window_max_px() -> u32 {
    23
}
fn default_threshold_window_step_px() -> u32 {
    10
}
fn default_threshold_constant() -> f64 {
    7.0
}
fn default_min_perimeter_rate() -> f64 {
    0.03
}
fn default_max_perimeter_rate() -> f64 {
    4.0
}
fn default_corner_refinement_window_px() -> u32 {
    5
}
fn default_corner_refinement_relative_window() -> f64 {
    0.3
}
fn default_corner_refinement_max_iterations() -> u32 {
    30
}
fn default_corner_refinement_min_accuracy_px() -> f64 {
    0.1
}
fn default_verify_corners() -> bool {
    true
}
fn default_max_edge_rms_px() -> f64 {
    0.5
}
fn default_max_corner_shift_px() -> f64 {
    1.0
}
fn default_max_reprojection_rms_px() -> f64 {
    1.0
}

impl ArucoConfig {
    /// The defaults for `dictionary` and markers of edge `size_m`.
    pub fn new(dictionary: ArucoDictionary, size_m: f64) -> Self {
        Self {
            dictionary,
            size_m,
            sizes: Vec::new(),
            corner_refinement: CornerRefinement::default(),
            max_correction_bits: None,
            threshold_window_min_px: default_threshold_window_min_px(),
            threshold_window_max_px: default_threshold_window_max_px(),
            threshold_window_step_px: default_threshold_window_step_px(),
            threshold_constant: default_threshold_constant(),
            min_perimeter_rate: default_min_perimeter_rate(),
            max_perimeter_rate: default_max_perimeter_rate(),
            corner_refinement_window_px: default_corner_refinement_window_px(),
            corner_refinement_relative_window: default_corner_refinement_relative_window(),
            corner_refinement_max_iterations: default_corner_refinement_max_iterations(),
            corner_refinement_min_accuracy_px: default_corner_refinement_min_accuracy_px(),
            detect_inverted: false,
            verify_corners: default_verify_corners(),
            max_edge_rms_px: default_max_edge_rms_px(),
            max_corner_shift_px: default_max_corner_shift_px(),
            max_reprojection_rms_px: default_max_reprojection_rms_px(),
            pose: PoseSettings::default(),
            board: None,
            filter: OneEuroConfig::default(),
        }
    }

    /// The marker sizes, checked.
    pub fn tag_sizes(&self) -> Result<TagSizes, ArucoError> {
        TagSizes::new(self.size_m, self.sizes.clone()).map_err(ArucoError::Config)
    }

    fn validate(&self) -> Result<(), ArucoError> {
        let bad = |reason: String| Err(ArucoError::Config(reason));
        self.tag_sizes()?;
        let (min, max, step) = (
            self.threshold_window_min_px,
            self.threshold_window_max_px,
            self.threshold_window_step_px,
        );
        if min < 3 || max < min || step == 0 {
            return bad(format!(
                "threshold windows need 3 ≤ min ≤ max and step > 0, got min {min}, max {max}, \
                 step {step}"
            ));
        }
        if !(positive(self.min_perimeter_rate)
            && positive(self.max_perimeter_rate)
            && self.min_perimeter_rate < self.max_perimeter_rate)
        {
            return bad(format!(
                "perimeter rates need 0 < min < max, got {} and {}",
                self.min_perimeter_rate, self.max_perimeter_rate
            ));
        }
        if self.corner_refinement_window_px == 0
            || self.corner_refinement_max_iterations == 0
            || !positive(self.corner_refinement_min_accuracy_px)
            || !positive(self.corner_refinement_relative_window)
        {
            return bad(
                "corner refinement window, iterations and accuracy must be positive".into(),
            );
        }
        if !(positive(self.max_edge_rms_px) && positive(self.max_corner_shift_px)) {
            return bad(format!(
                "max_edge_rms_px and max_corner_shift_px must be positive, got {} and {}",
                self.max_edge_rms_px, self.max_corner_shift_px
            ));
        }
        if !positive(self.max_reprojection_rms_px) {
            return bad(format!(
                "max_reprojection_rms_px must be positive, got {}",
                self.max_reprojection_rms_px
            ));
        }
        if self.corner_refinement == CornerRefinement::None && self.verify_corners {
            return bad(
                "corner_refinement = \"none\" leaves corners about a pixel off, which \
                 verify_corners would reject every time; set verify_corners = false"
                    .into(),
            );
        }
        if !self.threshold_constant.is_finite() {
            return bad("threshold_constant must be finite".into());
        }
        if !positive(self.pose.corner_sigma_px) || self.pose.max_iterations == 0 {
            return bad(format!(
                "pose.corner_sigma_px and pose.max_iterations must be positive, got {} and {}",
                self.pose.corner_sigma_px, self.pose.max_iterations
            ));
        }
        Ok(())
    }
}

/// A finite number above zero (false for NaN).
fn positive(value: f64) -> bool {
    value.is_finite() && value > 0.0
}

/// Why the ArUco tracker cannot be built or cannot process an image.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ArucoError {
    #[error(
        "unknown ArUco dictionary `{0}`; OpenCV 4.6 has 4x4_50 … 7x7_1000, aruco_original, \
         apriltag_16h5, apriltag_25h9, apriltag_36h10, apriltag_36h11 (no ARToolKit set)"
    )]
    UnknownDictionary(String),
    #[error("invalid aruco configuration: {0}")]
    Config(String),
    #[error(
        "max_correction_bits = {requested} exceeds dictionary {dictionary}'s maximum of {maximum}"
    )]
    TooManyCorrectionBits {
        dictionary: ArucoDictionary,
        requested: u32,
        maximum: u32,
    },
    #[error("marker {marker_id} is not in dictionary {dictionary} ({count} markers)")]
    UnknownMarker {
        dictionary: ArucoDictionary,
        marker_id: u32,
        count: u32,
    },
    #[error("image is empty ({width}x{height})")]
    EmptyImage { width: u32, height: u32 },
    #[error("cannot detect markers on a {0:?} image: it needs Rgb8 or Mono8")]
    UnsupportedFormat(PixelFormat),
    #[error("image is {width}x{height} but the camera model is {camera_width}x{camera_height}")]
    CameraMismatch {
        width: u32,
        height: u32,
        camera_width: u32,
        camera_height: u32,
    },
    #[error("OpenCV {operation} failed: {message} (code {code})")]
    OpenCv {
        operation: &'static str,
        code: i32,
        message: String,
    },
}

impl ArucoError {
    fn opencv(operation: &'static str) -> impl FnOnce(opencv::Error) -> ArucoError {
        move |error| ArucoError::OpenCv {
            operation,
            code: error.code,
            message: error.message,
        }
    }
}

/// Configuration problems can never work (`Config`, not retried); a frame the detector cannot
/// take is dropped and counted (`BadData`).
impl From<ArucoError> for DeviceError {
    fn from(error: ArucoError) -> Self {
        let device = BACKEND.to_string();
        let reason = error.to_string();
        match error {
            ArucoError::UnknownDictionary(_)
            | ArucoError::Config(_)
            | ArucoError::TooManyCorrectionBits { .. }
            | ArucoError::UnknownMarker { .. }
            | ArucoError::CameraMismatch { .. } => DeviceError::Config { device, reason },
            ArucoError::EmptyImage { .. }
            | ArucoError::UnsupportedFormat(_)
            | ArucoError::OpenCv { .. } => DeviceError::BadData { device, reason },
        }
    }
}

/// One marker found in an image, before its pose: decoded ID and corners in relight's order
/// (counter-clockwise from the lower-left as printed, pixels in OpenCV's convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArucoCorners {
    pub marker_id: u32,
    pub corners_px: [Vec2; 4],
}

/// An OpenCV ArUco dictionary, loaded.
#[derive(Debug)]
pub struct Dictionary {
    kind: ArucoDictionary,
    inner: Ptr<aruco::Dictionary>,
    count: u32,
}

impl Dictionary {
    pub fn load(kind: ArucoDictionary) -> Result<Self, ArucoError> {
        let inner = aruco::get_predefined_dictionary(kind.opencv())
            .map_err(ArucoError::opencv("getPredefinedDictionary"))?;
        let count = u32::try_from(inner.bytes_list().rows()).unwrap_or(0);
        Ok(Self { kind, inner, count })
    }

    pub fn kind(&self) -> ArucoDictionary {
        self.kind
    }

    /// Payload bits per side (4 for `4x4_*`, 6 for `apriltag_36h11`).
    pub fn bits(&self) -> u32 {
        u32::try_from(self.inner.marker_size()).unwrap_or(0)
    }

    /// Number of markers (IDs `0..count`).
    pub fn count(&self) -> u32 {
        self.count
    }

    /// The dictionary's `maxCorrectionBits`: ⌊(d − 1)/2⌋ for its minimum Hamming distance d.
    pub fn max_correction_bits(&self) -> u32 {
        u32::try_from(self.inner.max_correction_bits()).unwrap_or(0)
    }

    /// Marker `marker_id` as OpenCV draws it (`Dictionary::drawMarker` with one pixel per cell
    /// and a one-cell black border), so a rendered marker is exactly what the detector decodes;
    /// AprilTag codes turned to their official orientation (see the module docs).
    /// The bitmap has no quiet zone: the tag's size is the whole black square (print it with a
    /// white margin of at least one cell, e.g. [`PlanarTexture::tag`] with `margin_cells ≥ 1`).
    ///
    /// [`PlanarTexture::tag`]: super::render::PlanarTexture::tag
    pub fn tag_bitmap(&self, marker_id: u32) -> Result<TagBitmap, ArucoError> {
        let unknown = ArucoError::UnknownMarker {
            dictionary: self.kind,
            marker_id,
            count: self.count,
        };
        let id = i32::try_from(marker_id).map_err(|_| unknown.clone())?;
        if marker_id >= self.count {
            return Err(unknown);
        }
        let side = self.bits() + 2;
        let mut drawn = Mat::default();
        self.inner
            .draw_marker(id, to_i32(side)?, &mut drawn, 1)
            .map_err(ArucoError::opencv("drawMarker"))?;
        let bytes = drawn
            .data_bytes()
            .map_err(ArucoError::opencv("drawMarker"))?;
        if bytes.len() != (side * side) as usize {
            return Err(ArucoError::OpenCv {
                operation: "drawMarker",
                code: 0,
                message: format!("drew {} bytes for {side}×{side} cells", bytes.len()),
            });
        }
        let mut cells: Vec<bool> = bytes.iter().map(|&b| b >= 128).collect();
        for _ in 0..self.kind.opencv_quarter_turns() {
            cells = rotate_clockwise(&cells, side as usize);
        }
        Ok(TagBitmap {
            total_cells: side,
            size_cells: side,
            cells,
        })
    }
}

/// OpenCV's port of AprilTag 2's quad fitting (`CORNER_REFINE_APRILTAG`) reports corners half a
/// pixel right of and below the true ones (measured on rendered markers: +0.47 px mean in x and
/// y, with or without blur), as if pixel (x, y) covered [x, x + 1) × [y, y + 1) where OpenCV and
/// relight centre it on (x, y).
const APRILTAG_QUAD_PIXEL_OFFSET: f32 = 0.5;

/// `cornerSubPix` settings of the `subpix` refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
struct SubpixWindow {
    max_window_px: i32,
    relative_window: f64,
    max_iterations: i32,
    min_accuracy_px: f64,
}

/// Thresholds of `verify_corners`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Verification {
    enabled: bool,
    max_edge_rms_px: f64,
    max_corner_shift_px: f64,
}

/// OpenCV's marker detector with relight's corner order: no pose.
#[derive(Debug)]
pub struct ArucoDetector {
    dictionary: Dictionary,
    parameters: Ptr<aruco::DetectorParameters>,
    refinement: CornerRefinement,
    subpix: SubpixWindow,
    verify: Verification,
    gray: Mat,
    corners: Vector<Vector<Point2f>>,
    ids: Vector<i32>,
    rejected: Vector<Vector<Point2f>>,
}

impl ArucoDetector {
    pub fn new(config: &ArucoConfig) -> Result<Self, ArucoError> {
        config.validate()?;
        let dictionary = Dictionary::load(config.dictionary)?;
        let mut parameters = aruco::DetectorParameters::create()
            .map_err(ArucoError::opencv("DetectorParameters"))?;
        let maximum = dictionary.max_correction_bits();
        if let Some(requested) = config.max_correction_bits {
            if requested > maximum {
                return Err(ArucoError::TooManyCorrectionBits {
                    dictionary: config.dictionary,
                    requested,
                    maximum,
                });
            }
            // OpenCV accepts up to `maxCorrectionBits × errorCorrectionRate` flipped bits
            // (`Dictionary::identify`), truncated to an integer.
            let rate = if maximum == 0 {
                0.0
            } else {
                (f64::from(requested) + 0.5) / f64::from(maximum)
            };
            parameters.set_error_correction_rate(rate.min(1.0));
        }
        // `subpix` runs after detection with a per-marker window (see `detect_on`).
        let opencv_refinement = match config.corner_refinement {
            CornerRefinement::Subpix | CornerRefinement::Edges => CornerRefinement::None,
            other => other,
        };
        parameters.set_corner_refinement_method(opencv_refinement.opencv() as i32);
        parameters.set_adaptive_thresh_win_size_min(to_i32(config.threshold_window_min_px)?);
        parameters.set_adaptive_thresh_win_size_max(to_i32(config.threshold_window_max_px)?);
        parameters.set_adaptive_thresh_win_size_step(to_i32(config.threshold_window_step_px)?);
        parameters.set_adaptive_thresh_constant(config.threshold_constant);
        parameters.set_min_marker_perimeter_rate(config.min_perimeter_rate);
        parameters.set_max_marker_perimeter_rate(config.max_perimeter_rate);
        parameters.set_corner_refinement_win_size(to_i32(config.corner_refinement_window_px)?);
        parameters
            .set_corner_refinement_max_iterations(to_i32(config.corner_refinement_max_iterations)?);
        parameters.set_corner_refinement_min_accuracy(config.corner_refinement_min_accuracy_px);
        parameters.set_detect_inverted_marker(config.detect_inverted);
        Ok(Self {
            dictionary,
            parameters,
            refinement: config.corner_refinement,
            verify: Verification {
                enabled: config.verify_corners,
                max_edge_rms_px: config.max_edge_rms_px,
                max_corner_shift_px: config.max_corner_shift_px,
            },
            subpix: SubpixWindow {
                max_window_px: to_i32(config.corner_refinement_window_px)?,
                relative_window: config.corner_refinement_relative_window,
                max_iterations: to_i32(config.corner_refinement_max_iterations)?,
                min_accuracy_px: config.corner_refinement_min_accuracy_px,
            },
            gray: Mat::default(),
            corners: Vector::new(),
            ids: Vector::new(),
            rejected: Vector::new(),
        })
    }

    pub fn dictionary(&self) -> &Dictionary {
        &self.dictionary
    }

    /// The 8-bit pixels of an image markers can be detected on.
    fn pixels(image: &Image) -> Result<&[u8], ArucoError> {
        let (width, height) = (image.width(), image.height());
        if width == 0 || height == 0 {
            return Err(ArucoError::EmptyImage { width, height });
        }
        match (image.format(), image.as_u8()) {
            (PixelFormat::Rgb8 | PixelFormat::Mono8, Some(bytes)) => Ok(bytes),
            (format, _) => Err(ArucoError::UnsupportedFormat(format)),
        }
    }

    /// Finds the markers of the dictionary in an `Rgb8` or `Mono8` image, replacing `out`.
    ///
    /// A `Mono8` image is handed to OpenCV as it is, without a copy; an `Rgb8` one is converted
    /// to grey (Rec. 601 weights, in RGB order — OpenCV's own conversion would assume BGR) into a
    /// buffer kept between calls. `lens` is the camera that took the image: with it, side lines
    /// are fitted on its undistorted image plane (without, in pixels, where distortion bends
    /// long sides).
    pub fn detect(
        &mut self,
        image: &Image,
        lens: Option<&CameraModel>,
        out: &mut Vec<ArucoCorners>,
    ) -> Result<(), ArucoError> {
        out.clear();
        let bytes = Self::pixels(image)?;
        let (rows, cols) = (to_i32(image.height())?, to_i32(image.width())?);
        let wrap = ArucoError::opencv("Mat from image");
        if image.format() == PixelFormat::Mono8 {
            let gray = Mat::new_rows_cols_with_bytes::<u8>(rows, cols, bytes).map_err(wrap)?;
            self.detect_on(&gray)?;
        } else {
            let rgb = Mat::new_rows_cols_with_bytes::<Vec3b>(rows, cols, bytes).map_err(wrap)?;
            imgproc::cvt_color(&rgb, &mut self.gray, imgproc::COLOR_RGB2GRAY, 0)
                .map_err(ArucoError::opencv("cvtColor"))?;
            let gray = std::mem::take(&mut self.gray);
            let result = self.detect_on(&gray);
            self.gray = gray;
            result?;
        }
        let turns = self.dictionary.kind.opencv_quarter_turns() as usize;
        let shift = match self.refinement {
            CornerRefinement::Apriltag => APRILTAG_QUAD_PIXEL_OFFSET,
            _ => 0.0,
        };
        for (id, quad) in self.ids.iter().zip(self.corners.iter()) {
            let (Ok(marker_id), 4) = (u32::try_from(id), quad.len()) else {
                continue;
            };
            let mut corners_px = [Vec2::ZERO; 4];
            // OpenCV: clockwise from the top-left of its stored code; relight: counter-clockwise
            // from the bottom-left as printed, i.e. the same cycle reversed, then shifted by
            // the turn between OpenCV's stored code and the official print.
            for (k, corner) in corners_px.iter_mut().enumerate() {
                let index = (3 - k + turns) % 4;
                let p = quad.get(index).map_err(ArucoError::opencv("corners"))?;
                *corner = Vec2::new(p.x, p.y) - shift;
            }
            if corners_px.iter().all(|c| c.is_finite()) {
                out.push(ArucoCorners {
                    marker_id,
                    corners_px,
                });
            }
        }
        if self.verify.enabled || self.refinement == CornerRefinement::Edges {
            let grey = match image.format() {
                PixelFormat::Mono8 => bytes,
                _ => self
                    .gray
                    .data_bytes()
                    .map_err(ArucoError::opencv("grey image"))?,
            };
            let view = GreyView {
                pixels: grey,
                width: image.width() as usize,
                height: image.height() as usize,
            };
            let cells = self.dictionary.bits() + 2;
            let refine = self.refinement == CornerRefinement::Edges;
            let verify = self.verify;
            out.retain_mut(|marker| {
                let Some(fit) = fit_sides(&view, &marker.corners_px, cells, lens) else {
                    tracing::trace!(marker_id = marker.marker_id, "no straight sides found");
                    return !verify.enabled;
                };
                if verify.enabled && fit.max_side_rms_px > verify.max_edge_rms_px {
                    tracing::trace!(
                        marker_id = marker.marker_id,
                        rms_px = fit.max_side_rms_px,
                        "marker dropped: a side is not a straight edge"
                    );
                    return false;
                }
                if refine {
                    marker.corners_px = fit.corners_px;
                } else if verify.enabled && fit.max_corner_shift_px > verify.max_corner_shift_px {
                    tracing::trace!(
                        marker_id = marker.marker_id,
                        shift_px = fit.max_corner_shift_px,
                        "marker dropped: a corner is off its sides' lines"
                    );
                    return false;
                }
                true
            });
        }
        Ok(())
    }

    /// `detectMarkers` on the grey image, then, for `subpix`, `cornerSubPix` per marker with a
    /// window scaled to the marker's cells: OpenCV 4.6 uses one fixed window for every marker,
    /// which on a small or steeply tilted marker reaches over the data cells next to the
    /// border and pulls the corner off by pixels. OpenCV 4.8 added the same rule
    /// (`relativeCornerRefinmentWinSize`): half-window = min(`corner_refinement_window_px`,
    /// round(`corner_refinement_relative_window` × mean cell size)), at least 1.
    fn detect_on(&mut self, gray: &impl ToInputArray) -> Result<(), ArucoError> {
        aruco::detect_markers(
            gray,
            &self.dictionary.inner,
            &mut self.corners,
            &mut self.ids,
            &self.parameters,
            &mut self.rejected,
        )
        .map_err(ArucoError::opencv("detectMarkers"))?;
        if !matches!(
            self.refinement,
            CornerRefinement::Subpix | CornerRefinement::Edges
        ) {
            return Ok(());
        }
        let criteria = TermCriteria::new(
            TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
            self.subpix.max_iterations,
            self.subpix.min_accuracy_px,
        )
        .map_err(ArucoError::opencv("TermCriteria"))?;
        let cells = f64::from(self.dictionary.bits() + 2);
        let mut refined = Vector::<Vector<Point2f>>::with_capacity(self.corners.len());
        for mut quad in self.corners.iter() {
            let perimeter_px: f64 = (0..quad.len())
                .filter_map(|i| Some((quad.get(i).ok()?, quad.get((i + 1) % quad.len()).ok()?)))
                .map(|(a, b)| (a - b).norm())
                .sum();
            let cell_px = perimeter_px / (4.0 * cells);
            let half_window = ((self.subpix.relative_window * cell_px).round() as i32)
                .clamp(1, self.subpix.max_window_px);
            imgproc::corner_sub_pix(
                gray,
                &mut quad,
                Size::new(half_window, half_window),
                Size::new(-1, -1),
                criteria,
            )
            .map_err(ArucoError::opencv("cornerSubPix"))?;
            refined.push(quad);
        }
        self.corners = refined;
        Ok(())
    }
}

/// A square row-major grid of `side × side` cells turned a quarter clockwise.
fn rotate_clockwise(cells: &[bool], side: usize) -> Vec<bool> {
    (0..side * side)
        .map(|i| {
            let (row, col) = (i / side, i % side);
            cells[(side - 1 - col) * side + row]
        })
        .collect()
}

fn to_i32(value: u32) -> Result<i32, ArucoError> {
    i32::try_from(value)
        .map_err(|_| ArucoError::Config(format!("{value} does not fit OpenCV's int")))
}

/// The `aruco` marker tracker: OpenCV's detection, the shared pose solver, optionally a board.
#[derive(Debug)]
pub struct ArucoTracker {
    detector: ArucoDetector,
    sizes: TagSizes,
    pose: PoseSettings,
    max_reprojection_rms_px: f64,
    board: Option<Board>,
    found: Vec<ArucoCorners>,
    board_corners: Vec<(u32, [DVec2; 4])>,
}

impl ArucoTracker {
    /// Loads the dictionary and checks the configuration; every error here is permanent.
    pub fn new(config: &ArucoConfig) -> Result<Self, ArucoError> {
        let detector = ArucoDetector::new(config)?;
        let board = match &config.board {
            Some(board_config) => {
                let board = Board::from_config(board_config)
                    .map_err(|e| ArucoError::Config(e.to_string()))?;
                let family = config.dictionary.family();
                if board.family() != family {
                    return Err(ArucoError::Config(format!(
                        "board `{}` is of family `{}` but the dictionary is `{family}`",
                        board.name(),
                        board.family()
                    )));
                }
                let count = detector.dictionary().count();
                if let Some(tag) = board.tags().iter().find(|t| t.marker_id >= count) {
                    return Err(ArucoError::UnknownMarker {
                        dictionary: config.dictionary,
                        marker_id: tag.marker_id,
                        count,
                    });
                }
                Some(board)
            }
            None => None,
        };
        Ok(Self {
            detector,
            sizes: config.tag_sizes()?,
            pose: config.pose,
            max_reprojection_rms_px: config.max_reprojection_rms_px,
            board,
            found: Vec::new(),
            board_corners: Vec::new(),
        })
    }

    pub fn detector(&self) -> &ArucoDetector {
        &self.detector
    }

    pub fn board(&self) -> Option<&Board> {
        self.board.as_ref()
    }

    /// Markers (and the board) in `image`, replacing `out`. A marker whose pose cannot be fitted
    /// or fits worse than `max_reprojection_rms_px` is left out: not reported beats a wrong pose.
    pub fn track(
        &mut self,
        image: &Image,
        camera: &CameraModel,
        out: &mut MarkerSet,
    ) -> Result<(), ArucoError> {
        out.detections.clear();
        ArucoDetector::pixels(image)?;
        if (image.width(), image.height()) != (camera.width(), camera.height()) {
            return Err(ArucoError::CameraMismatch {
                width: image.width(),
                height: image.height(),
                camera_width: camera.width(),
                camera_height: camera.height(),
            });
        }
        self.detector.detect(image, Some(camera), &mut self.found)?;
        let family = self.detector.dictionary().kind().family();
        self.board_corners.clear();
        for found in &self.found {
            let corners_px = found.corners_px.map(|c| c.as_dvec2());
            self.board_corners.push((found.marker_id, corners_px));
            let size_m = self.sizes.size_m(found.marker_id);
            match estimate_square_pose(&corners_px, size_m, camera, &self.pose) {
                Ok(fit) if fit.reprojection_rms_px <= self.max_reprojection_rms_px => out
                    .detections
                    .push(fit.detection(family, found.marker_id, found.corners_px)),
                Ok(fit) => tracing::trace!(
                    marker_id = found.marker_id,
                    rms_px = fit.reprojection_rms_px,
                    "marker dropped: its corners do not fit a square"
                ),
                Err(error) => {
                    tracing::trace!(marker_id = found.marker_id, %error, "marker dropped: no pose");
                }
            }
        }
        if let Some(board) = &self.board {
            match board.estimate(&self.board_corners, camera, &self.pose) {
                Ok(fit) if fit.fit.reprojection_rms_px <= self.max_reprojection_rms_px => {
                    let used: Vec<DVec2> = self
                        .board_corners
                        .iter()
                        .filter(|(id, _)| fit.tags_used.contains(id))
                        .flat_map(|(_, corners)| *corners)
                        .collect();
                    out.detections.push(board.detection(&fit, &used, camera));
                }
                Ok(fit) => tracing::trace!(
                    rms_px = fit.fit.reprojection_rms_px,
                    "board dropped: its corners do not fit the layout"
                ),
                Err(BoardError::NoTags) => {}
                Err(error) => tracing::trace!(%error, "board dropped: no pose"),
            }
        }
        Ok(())
    }
}

impl MarkerTracker for ArucoTracker {
    fn family(&self) -> &str {
        self.detector.dictionary().kind().family()
    }

    fn detect(
        &mut self,
        image: &Image,
        camera: &CameraModel,
        out: &mut MarkerSet,
    ) -> Result<(), DeviceError> {
        Ok(self.track(image, camera, out)?)
    }
}

/// The daemon's `[markers]` device with `backend = "aruco"`: the tracker on the colour stream,
/// posed with the rig calibration's colour camera, smoothed by the config's filter. Every error
/// here is a configuration error (not retried).
pub fn aruco_device(
    config: &ArucoConfig,
    colour_camera: CameraModel,
) -> Result<MarkerDevice<ArucoTracker>, DeviceError> {
    let tracker = ArucoTracker::new(config).map_err(|error| DeviceError::Config {
        device: BACKEND.into(),
        reason: error.to_string(),
    })?;
    MarkerDevice::new(BACKEND, tracker, colour_camera, config.filter)
}
