//! Camera models: pinhole with Brown–Conrady distortion, and Kannala–Brandt fish-eye.
//!
//! Pixel coordinates have their origin at the top-left pixel's corner... (see `project`).

use serde::{Deserialize, Serialize};

/// Pinhole camera with Brown–Conrady (OpenCV 5-parameter) distortion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pinhole {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub p1: f64,
    #[serde(default)]
    pub p2: f64,
    #[serde(default)]
    pub k3: f64,
}

/// Kannala–Brandt fish-eye model (OpenCV `fisheye`): θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct KannalaBrandt {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub k3: f64,
    #[serde(default)]
    pub k4: f64,
}

/// Either camera model, tagged by `model = "pinhole" | "kannala_brandt"` in TOML/JSON.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case")]
pub enum CameraModel {
    Pinhole(Pinhole),
    KannalaBrandt(KannalaBrandt),
}
