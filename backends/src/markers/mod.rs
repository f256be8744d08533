//! Square-marker tracking (AprilTag, ArUco): shared pose estimation and filtering.
//!
//! A detector backend (`apriltag`, `aruco`, each behind its feature) finds tags and their four
//! corners in an image; everything after that is shared and pure Rust:
//!
//! - [`pose`]: a marker's (or a board's) pose from its corners through the full camera model:
//!   IPPE initialisation (both planar solutions), Levenberg–Marquardt refinement of the pixel
//!   reprojection error, and a covariance → 1-σ pose error estimate.
//! - [`board`]: rigid boards of several tags, solved jointly from every visible corner.
//! - [`one_euro`]: the One-Euro filter (Casiez et al. 2012) on poses, per marker.
//! - [`device`]: [`device::MarkerDevice`], which runs any [`MarkerTracker`] on the colour stream
//!   of the bus and publishes filtered [`MarkerSet`]s.
//! - [`render`]: a small planar-texture renderer (supersampled, blur, noise, occlusion) that the
//!   detector tests use to produce images with known truth.
//!
//! # Frames and corner order
//!
//! [`MarkerDetection::camera_from_marker`] uses relight's camera convention, the glTF one (+X
//! right, +Y up, the camera looks down −Z), exactly like the simulator's ground truth
//! (`camera_from_world * world_from_marker`). The marker frame has its origin at the tag's
//! centre, +x right and +y up as printed, +z out of the print. Corners are reported
//! counter-clockwise from the tag's lower-left as printed (lower-left, lower-right, upper-right,
//! upper-left), which is [`pose::square_corners_in_marker`] projected into the image. The pose
//! maths itself works in the OpenCV optical frame of [`relight_core::camera`].
//!
//! [`MarkerTracker`]: crate::sources::MarkerTracker
//! [`MarkerSet`]: relight_core::MarkerSet
//! [`MarkerDetection::camera_from_marker`]: relight_core::MarkerDetection::camera_from_marker

#[cfg(feature = "apriltag")]
pub mod apriltag;
#[cfg(feature = "opencv")]
pub mod aruco;
pub mod board;
pub mod device;
pub mod one_euro;
pub mod pose;
pub mod render;
pub mod tag36h11;

use serde::{Deserialize, Serialize};

/// A tag whose printed size differs from the tracker's default `size_m`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TagSizeOverride {
    pub marker_id: u32,
    /// Edge of the tag's detected square, metres.
    pub size_m: f64,
}

/// Tag sizes: one default and optional per-id overrides (config keys `size_m` and `sizes`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TagSizes {
    pub default_m: f64,
    pub overrides: Vec<TagSizeOverride>,
}

impl TagSizes {
    /// Checks that every size is a positive finite number and no id is listed twice.
    pub fn new(default_m: f64, overrides: Vec<TagSizeOverride>) -> Result<Self, String> {
        let positive = |size: f64| size.is_finite() && size > 0.0;
        if !positive(default_m) {
            return Err(format!(
                "`size_m` must be a positive number of metres, got {default_m}"
            ));
        }
        for (i, entry) in overrides.iter().enumerate() {
            if !positive(entry.size_m) {
                return Err(format!(
                    "`sizes`: marker {} has size {} m; sizes must be positive",
                    entry.marker_id, entry.size_m
                ));
            }
            if overrides[..i]
                .iter()
                .any(|other| other.marker_id == entry.marker_id)
            {
                return Err(format!("`sizes`: marker {} listed twice", entry.marker_id));
            }
        }
        Ok(Self {
            default_m,
            overrides,
        })
    }

    /// Size of the tag with this id, metres.
    pub fn size_m(&self, marker_id: u32) -> f64 {
        self.overrides
            .iter()
            .find(|entry| entry.marker_id == marker_id)
            .map_or(self.default_m, |entry| entry.size_m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_win_over_the_default_size() {
        let sizes = TagSizes::new(
            0.12,
            vec![TagSizeOverride {
                marker_id: 7,
                size_m: 0.05,
            }],
        )
        .unwrap();
        assert_eq!(sizes.size_m(7), 0.05);
        assert_eq!(sizes.size_m(8), 0.12);
        assert!(TagSizes::new(0.0, vec![]).is_err());
        assert!(TagSizes::new(f64::NAN, vec![]).is_err());
        let twice = TagSizeOverride {
            marker_id: 1,
            size_m: 0.1,
        };
        assert!(TagSizes::new(0.1, vec![twice, twice]).is_err());
    }
}
