//! A rig's calibration: every camera's intrinsics and the transforms between them.
//!
//! Written by `relight-calibrate` as one TOML file per rig, loaded by `relightd`, and embedded
//! verbatim in every recording so a recording can be replayed without the rig.

use serde::{Deserialize, Serialize};

use crate::camera::CameraModel;
use crate::pose::Pose;

/// Calibration of one rig. Every field is optional so a partial rig (depth only) still loads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigCalibration {
    /// Free-form rig name, e.g. `lab-desk-1`.
    #[serde(default)]
    pub name: String,
    pub depth: Option<CameraModel>,
    pub color: Option<CameraModel>,
    pub probe: Option<CameraModel>,
    /// Registration of the depth sensor: `point_in_color = color_from_depth * point_in_depth`.
    #[serde(default)]
    pub color_from_depth: Pose,
    /// The fish-eye probe's pose in the world (marker board) frame.
    #[serde(default)]
    pub world_from_probe: Pose,
    /// The world-defining marker board's pose in the world frame. The board on the table defines
    /// the world (identity: the board's frame is the world's); a lab that keeps another world
    /// frame, such as a simulator's scene, puts the board there.
    #[serde(default)]
    pub world_from_board: Pose,
    /// The printed layout of that board, so a recording can be tracked without the rig's
    /// configuration.
    #[serde(default)]
    pub board: Option<BoardLayout>,
    /// The lamp's light centre in its marker's frame.
    #[serde(default)]
    pub lamp_marker_from_light: Pose,
    /// The probe's inverse response, 256 entries mapping 8-bit value → relative linear radiance.
    #[serde(default)]
    pub probe_response: Vec<f32>,
    /// Radiance, W/(m²·sr), per unit of the inverse response per second of exposure: the
    /// probe's absolute scale, which turns merged HDR values into radiance (1: relative units).
    #[serde(default = "unit_scale")]
    pub probe_radiance_scale: f32,
    /// The probe's vignetting `[a1, a2, a3]` of `V(r) = 1 + a1 r² + a2 r⁴ + a3 r⁶` about its
    /// model's principal point (`relight-calibrate vignetting`); empty: none measured.
    #[serde(default)]
    pub probe_vignetting: Vec<f32>,
    /// The colour camera's inverse response, 256 entries mapping 8-bit value → relative linear
    /// exposure (sRGB decoding for a camera that writes sRGB); empty: not measured, and the real
    /// surfaces' albedo cannot be measured either.
    #[serde(default)]
    pub color_response: Vec<f32>,
    /// Radiance, W/(m²·sr), per unit of the colour camera's inverse response at the exposure it
    /// is locked to for the session (1: relative units).
    #[serde(default = "unit_scale")]
    pub color_radiance_scale: f32,
}

/// A printed grid of square tags with consecutive ids, left to right from the top row; the board
/// frame has its origin at the grid's centre, the tags in its x–y plane (+x right, +y up as
/// printed) and +z out of the print.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardLayout {
    /// Tag family, e.g. `tag36h11`.
    pub family: String,
    pub first_id: u32,
    pub cols: u32,
    pub rows: u32,
    /// Edge of each tag's detected square, metres.
    pub tag_size_m: f64,
    /// Between neighbouring tags' squares, metres.
    pub gap_m: f64,
}

fn unit_scale() -> f32 {
    1.0
}

#[derive(Debug, thiserror::Error)]
pub enum RigCalibrationError {
    #[error("calibration TOML: {0}")]
    Parse(#[from] toml::de::Error),
    #[error("calibration to TOML: {0}")]
    Serialize(#[from] toml::ser::Error),
}

impl Default for RigCalibration {
    fn default() -> Self {
        Self {
            name: String::new(),
            depth: None,
            color: None,
            probe: None,
            color_from_depth: Pose::default(),
            world_from_probe: Pose::default(),
            world_from_board: Pose::default(),
            board: None,
            lamp_marker_from_light: Pose::default(),
            probe_response: Vec::new(),
            probe_radiance_scale: 1.0,
            probe_vignetting: Vec::new(),
            color_response: Vec::new(),
            color_radiance_scale: 1.0,
        }
    }
}

impl RigCalibration {
    pub fn from_toml(text: &str) -> Result<Self, RigCalibrationError> {
        Ok(toml::from_str(text)?)
    }

    pub fn to_toml(&self) -> Result<String, RigCalibrationError> {
        Ok(toml::to_string_pretty(self)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Pinhole;

    #[test]
    fn toml_round_trip() {
        let rig = RigCalibration {
            name: "desk".into(),
            depth: Some(CameraModel::Pinhole(Pinhole {
                width: 320,
                height: 240,
                fx: 285.0,
                fy: 285.0,
                cx: 160.0,
                cy: 120.0,
                k1: 0.01,
                k2: 0.0,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0,
            })),
            probe_response: vec![0.5; 4],
            ..Default::default()
        };
        let text = rig.to_toml().unwrap();
        assert_eq!(RigCalibration::from_toml(&text).unwrap(), rig);
    }
}
