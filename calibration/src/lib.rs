//! relight-calibrate: calibration of a relight rig.
//!
//! Geometric half: calibration [`target`]s and their [`detect`]ion, [`views`] selection,
//! pinhole ([`intrinsics`]) and fish-eye ([`fisheye`]) intrinsics, and the rig's [`extrinsics`]
//! (depth ↔ colour registration, the probe's pose in the world, the lamp's light centre), with
//! [`synth`]etic views of known truth for tests. Photometric half: the probe's response
//! ([`photometric`]) and [`vignetting`]. Everything that calls OpenCV is behind the `opencv`
//! feature; targets, synthetic views and view selection build without it.

pub mod detect;
pub mod error;
mod linalg;
pub mod rigid;
pub mod synth;
pub mod target;
pub mod views;

#[cfg(feature = "opencv")]
pub mod extrinsics;
#[cfg(feature = "opencv")]
pub mod fisheye;
#[cfg(feature = "opencv")]
pub mod intrinsics;

#[cfg(feature = "opencv")]
pub mod input;
pub mod output;
#[cfg(feature = "opencv")]
pub mod photometric;
pub mod progress;
#[cfg(feature = "opencv")]
pub mod report;
pub mod vignetting;

pub use error::CalibrationError;
pub use rigid::Rigid;
pub use target::{Target, TargetGeometry};
