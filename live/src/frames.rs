//! The frames the live view publishes, and the conversions at its boundary.
//!
//! Poses are glTF-convention inside relight and optical / +z-up where Foxglove reads them; the
//! conversions are [`relight_core::ros_frames`]'s, shared with the recordings. The view
//! publishes:
//!
//! | frame | parent | what |
//! |---|---|---|
//! | `map` | — | the fixed frame, +z up |
//! | `world` | `map` | the board's frame as relight keeps it (+y up): a +90° turn about x |
//! | `color` | `world` | the colour camera, optical convention; images' `frame_id` (as in recordings) |
//! | `board`, `probe` | `world` | from the rig calibration (the probe in optical convention) |
//! | `marker_<id>` | `color` | each marker detected in the frame set |
//! | `light_<n>`, `lamp` | `world` | each light the engine rendered with (the tracked lamp's) |
//! | `virtual_object` | `world` | the virtual object's bounding-box centre |

pub use relight_core::ros_frames::{
    BOARD, LAMP, MAP, WORLD, map_from_world, marker, optical_from, world_from_optical,
};

/// The colour camera, optical convention; named as in the calibration and in recordings.
pub const CAMERA: &str = "color";
pub const PROBE: &str = "probe";
pub const VIRTUAL_OBJECT: &str = "virtual_object";

/// The name of light `index`'s frame.
pub fn light(index: usize) -> String {
    format!("light_{index}")
}
