//! Coordinate conventions at relight's boundary with ROS and Foxglove.
//!
//! Inside relight every pose is glTF-convention: the world is the marker board's frame with +y
//! up, and a camera looks along its −z with +y up. ROS and Foxglove expect an image's
//! `frame_id` in the optical convention (REP 103/104: +x right, +y down, +z forward) and a fixed
//! frame with +z up (REP 105). Recordings ([`crate::recording`]) and the live view convert with
//! these functions where they write, and nowhere else, and name the frames alike (cameras by
//! their calibration names, `depth`, `color`, `probe`).
//!
//! The camera flip is half a turn about x; it is written out component by component (a sign
//! change and a swap, see [`optical_from`]) so that a pose survives the round trip bit for bit.

use glam::{Quat, Vec3};

use crate::pose::Pose;

/// The fixed frame (+z up).
pub const MAP: &str = "map";
/// The board's (glTF, +y up) world frame.
pub const WORLD: &str = "world";
/// The world-defining marker board.
pub const BOARD: &str = "board";
/// The tracked lamp's light centre.
pub const LAMP: &str = "lamp";

/// The name of marker `id`'s frame.
pub fn marker(id: u32) -> String {
    format!("marker_{id}")
}

/// `map_from_world`: the world's +y (up) becomes the fixed frame's +z.
pub fn map_from_world() -> Pose {
    Pose {
        rotation: Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        translation: Vec3::ZERO,
    }
}

/// `gltf_camera_from_optical`: half a turn about x (+y down becomes +y up, +z forward becomes
/// −z forward). It is its own inverse.
pub fn gltf_camera_from_optical() -> Pose {
    Pose {
        rotation: Quat::from_xyzw(1.0, 0.0, 0.0, 0.0),
        translation: Vec3::ZERO,
    }
}

/// `flip · q` for the flip (1, 0, 0, 0): the Hamilton product reduces to a swap and signs.
fn flip_rotation(q: Quat) -> Quat {
    Quat::from_xyzw(q.w, -q.z, q.y, -q.x)
}

/// `q · flip`.
fn rotation_then_flip(q: Quat) -> Quat {
    Quat::from_xyzw(q.w, q.z, -q.y, -q.x)
}

fn flip_point(p: Vec3) -> Vec3 {
    Vec3::new(p.x, -p.y, -p.z)
}

/// A pose seen from a glTF-convention camera, re-expressed in its optical frame:
/// `optical_from_gltf_camera · camera_from_x`.
pub fn optical_from(camera_from_x: Pose) -> Pose {
    Pose {
        rotation: flip_rotation(camera_from_x.rotation),
        translation: flip_point(camera_from_x.translation),
    }
}

/// The inverse of [`optical_from`]: a pose in a camera's optical frame, in its glTF frame.
pub fn gltf_from(optical_from_x: Pose) -> Pose {
    // The flip is an involution, so the same swap undoes it.
    Pose {
        rotation: inverse_flip_rotation(optical_from_x.rotation),
        translation: flip_point(optical_from_x.translation),
    }
}

/// `flip⁻¹ · q`, where `flip⁻¹ = (−1, 0, 0, 0)`, the same rotation.
fn inverse_flip_rotation(q: Quat) -> Quat {
    Quat::from_xyzw(-q.w, q.z, -q.y, q.x)
}

/// A glTF-convention camera pose as its optical frame's: `world_from_camera · gltf_from_optical`.
pub fn world_from_optical(world_from_camera: Pose) -> Pose {
    Pose {
        rotation: rotation_then_flip(world_from_camera.rotation),
        translation: world_from_camera.translation,
    }
}

/// One camera's pose relative to another, both glTF-convention, as optical frames:
/// `optical_a_from_optical_b = flip · a_from_b · flip`.
pub fn optical_between(a_from_b: Pose) -> Pose {
    let pose = world_from_optical(optical_from(a_from_b));
    // The two flips make −q of an identity-like q; the same rotation, written w ≥ 0.
    if pose.rotation.w < 0.0 {
        Pose {
            rotation: -pose.rotation,
            ..pose
        }
    } else {
        pose
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: Vec3, b: Vec3) -> bool {
        (a - b).length() < 1e-6
    }

    fn sample_pose() -> Pose {
        Pose {
            rotation: Quat::from_euler(glam::EulerRot::YXZ, 0.7, -0.3, 0.2),
            translation: Vec3::new(0.1, 0.5, 1.2),
        }
    }

    #[test]
    fn the_written_out_flips_equal_the_quaternion_products() {
        let pose = sample_pose();
        let flip = gltf_camera_from_optical();
        let by_product = flip * pose;
        let optical = optical_from(pose);
        assert!(optical.rotation.abs_diff_eq(by_product.rotation, 1e-6));
        assert!(close(optical.translation, by_product.translation));
        let by_product = pose * flip;
        let optical = world_from_optical(pose);
        assert!(optical.rotation.abs_diff_eq(by_product.rotation, 1e-6));
        assert!(close(optical.translation, by_product.translation));
        assert_eq!(gltf_from(optical_from(pose)), pose, "bit-exact round trip");
    }

    #[test]
    fn the_optical_frame_looks_where_the_gltf_camera_looks() {
        let world_from_camera = sample_pose();
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
    fn cameras_related_in_gltf_are_related_the_same_as_optical_frames() {
        let a_from_b = sample_pose();
        let point_in_optical_b = Vec3::new(0.2, -0.1, 2.0);
        let via_gltf = optical_from(a_from_b)
            .transform_point(gltf_camera_from_optical().transform_point(point_in_optical_b));
        let direct = optical_between(a_from_b).transform_point(point_in_optical_b);
        assert!(close(via_gltf, direct));
    }

    #[test]
    fn the_world_up_is_the_map_up() {
        assert!(close(map_from_world().transform_point(Vec3::Y), Vec3::Z));
    }
}
