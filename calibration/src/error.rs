//! Typed errors of the geometric calibration: each says what went wrong and what to do about it.

use relight_core::PixelFormat;
use relight_core::camera::CameraError;

/// Why a geometric calibration step failed.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    #[error("invalid target: {0}")]
    InvalidTarget(String),
    #[error("{what} needs the `opencv` feature of relight-calibrate")]
    NeedsOpenCv { what: &'static str },
    #[error("unknown marker dictionary `{0}` (expected e.g. `tag36h11`, `aruco_4x4_50`)")]
    UnknownDictionary(String),
    #[error("no {target} detected in `{view}`")]
    NoTargetDetected { view: String, target: String },
    #[error("`{view}` is {format:?}; detection needs Mono8 or Rgb8")]
    UnsupportedFormat { view: String, format: PixelFormat },
    #[error(
        "{found} usable views, {what} needs at least {minimum}; take more views of the target \
         (tilted, in every part of the image)"
    )]
    TooFewViews {
        what: &'static str,
        found: usize,
        minimum: usize,
    },
    #[error(
        "images differ in size: `{first_view}` is {first_width}x{first_height} but `{view}` is \
         {width}x{height}; calibrate one camera at one resolution"
    )]
    MixedImageSizes {
        first_view: String,
        first_width: u32,
        first_height: u32,
        view: String,
        width: u32,
        height: u32,
    },
    #[error("`{view}`: {found} corners, at least {minimum} needed")]
    TooFewCorners {
        view: String,
        found: usize,
        minimum: usize,
    },
    #[error("ill-conditioned {what}: {hint}")]
    IllConditioned { what: String, hint: String },
    #[error(
        "fish-eye rim not covered: the outermost corner is {max_theta_deg:.1}° off the optical \
         axis, but {required_deg:.1}° is required (field {field_deg:.1}°); distortion beyond \
         that is extrapolated. Add views with the target near the edge of the image circle"
    )]
    RimNotCovered {
        max_theta_deg: f64,
        required_deg: f64,
        field_deg: f64,
    },
    #[error(
        "the fitted fish-eye distortion θ_d(θ) stops increasing at {fold_deg:.1}°, inside the \
         {field_deg:.1}° field: rays beyond it fold back. Add views near the rim, or fix k4"
    )]
    NonMonotonicDistortion { fold_deg: f64, field_deg: f64 },
    #[error("calibration did not converge: {0}")]
    Diverged(String),
    #[error("views do not pair up: {0}")]
    Unpaired(String),
    #[error("camera model: {0}")]
    Camera(#[from] CameraError),
    #[cfg(feature = "opencv")]
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}
