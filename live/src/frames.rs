//! The frames the live view publishes, and the conversions at its boundary.
//!
//! Inside relight every pose is glTF-convention: the world is the marker board's frame with +y
//! up, and a camera looks along its −z with +y up. Foxglove and ROS expect an image's
//! `frame_id` in the optical convention (REP 103/104: +x right, +y down, +z forward) and a
//! fixed frame with +z up (REP 105). So the view publishes:
//!
//! | frame | parent | what |
//! |---|---|---|
//! | `map` | — | the fixed frame, +z up |
//! | `world` | `map` | the board's frame as relight keeps it (+y up): a +90° turn about x |
//! | `camera` | `world` | the colour camera, optical convention; images' `frame_id` |
//! | `board`, `probe` | `world` | from the rig calibration (the probe in optical convention) |
//! | `marker_<id>` | `camera` | each marker detected in the frame set |
//! | `light_<n>`, `lamp` | `world` | each light the engine rendered with (the tracked lamp's) |
//! | `virtual_object` | `world` | the virtual object's bounding-box centre |

use glam::{Quat, Vec3};
use relight_core::Pose;

/// The fixed frame (+z up).
pub const MAP: &str = "map";
/// The board's (glTF, +y up) world frame.
pub const WORLD: &str = "world";
/// The colour camera, optical convention.
pub const CAMERA: &str = "camera";
pub const BOARD: &str = "board";
pub const PROBE: &str = "probe";
pub const LAMP: &str = "lamp";
pub const VIRTUAL_OBJECT: &str = "virtual_object";

/// `map_from_world`: the world's +y (up) becomes the map's +z.
pub fn map_from_world() -> Pose {
    Pose {
        rotation: Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        translation: Vec3::ZERO,
    }
}

/// `gltf_camera_from_optical`: half a turn about x (+y down becomes +y up, +z forward
/// becomes −z forward).
pub fn gltf_camera_from_optical() -> Pose {
    Pose {
        rotation: Quat::from_xyzw(1.0, 0.0, 0.0, 0.0),
        translation: Vec3::ZERO,
    }
}

/// A glTF-convention camera pose as its optical frame's: `world_from_camera · gltf_from_optical`.
pub fn world_from_optical(world_from_camera: Pose) -> Pose {
    world_from_camera * gltf_camera_from_optical()
}

/// A pose seen from a glTF-convention camera, re-expressed in its optical frame.
pub fn optical_from(camera_from_x: Pose) -> Pose {
    gltf_camera_from_optical().inverse() * camera_from_x
}

/// The name of marker `id`'s frame.
pub fn marker(id: u32) -> String {
    format!("marker_{id}")
}

/// The name of light `index`'s frame.
pub fn light(index: usize) -> String {
    format!("light_{index}")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: Vec3, b: Vec3) -> bool {
        (a - b).length() < 1e-6
    }

    #[test]
    fn the_optical_frame_looks_where_the_gltf_camera_looks() {
        let world_from_camera = Pose {
            rotation: Quat::from_rotation_y(0.7),
            translation: Vec3::new(0.1, 0.5, 1.2),
        };
        let optical = world_from_optical(world_from_camera);
        // +z forward in the optical frame is −z in the glTF camera's.
        let ahead_optical = optical.transform_point(Vec3::Z) - optical.translation;
        let ahead_gltf =
            world_from_camera.transform_point(-Vec3::Z) - world_from_camera.translation;
        assert!(close(ahead_optical, ahead_gltf));
        // +y down in the optical frame is −y in the glTF camera's.
        let down_optical = optical.transform_point(Vec3::Y) - optical.translation;
        let down_gltf = world_from_camera.transform_point(-Vec3::Y) - world_from_camera.translation;
        assert!(close(down_optical, down_gltf));
        assert!(close(optical.translation, world_from_camera.translation));
    }

    #[test]
    fn a_marker_in_front_of_the_camera_has_positive_optical_z() {
        // 1.86 m in front of a glTF camera is z = −1.86.
        let camera_from_marker = Pose {
            rotation: Quat::IDENTITY,
            translation: Vec3::new(0.0, 0.0, -1.86),
        };
        let optical = optical_from(camera_from_marker);
        assert!(close(optical.translation, Vec3::new(0.0, 0.0, 1.86)));
    }

    #[test]
    fn the_world_up_is_the_map_up() {
        assert!(close(map_from_world().transform_point(Vec3::Y), Vec3::Z));
    }
}
