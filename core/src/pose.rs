//! Rigid transforms. Name them by the frames they connect, read right to left:
//! `point_in_world = world_from_camera * point_in_camera`.

use std::ops::Mul;

use glam::{Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// A rigid transform (rotation then translation), metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub rotation: Quat,
    pub translation: Vec3,
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Pose {
    pub const IDENTITY: Pose = Pose {
        rotation: Quat::IDENTITY,
        translation: Vec3::ZERO,
    };

    pub fn new(rotation: Quat, translation: Vec3) -> Self {
        Self {
            rotation: rotation.normalize(),
            translation,
        }
    }

    pub fn from_translation(translation: Vec3) -> Self {
        Self::new(Quat::IDENTITY, translation)
    }

    /// A camera pose at `eye` looking at `target` (camera looks down −Z, +Y up): `world_from_camera`.
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let camera_from_world = Mat4::look_at_rh(eye, target, up);
        let (_, rotation, translation) =
            camera_from_world.inverse().to_scale_rotation_translation();
        Self::new(rotation, translation)
    }

    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        Self {
            rotation,
            translation: -(rotation * self.translation),
        }
    }

    pub fn transform_point(&self, point: Vec3) -> Vec3 {
        self.rotation * point + self.translation
    }

    pub fn transform_vector(&self, vector: Vec3) -> Vec3 {
        self.rotation * vector
    }

    pub fn to_mat4(&self) -> Mat4 {
        Mat4::from_rotation_translation(self.rotation, self.translation)
    }

    /// Interpolate (slerp + lerp) between two poses, t ∈ [0, 1].
    pub fn interpolate(&self, other: &Pose, t: f32) -> Pose {
        Pose::new(
            self.rotation.slerp(other.rotation, t),
            self.translation.lerp(other.translation, t),
        )
    }
}

/// `a_from_c = a_from_b * b_from_c`.
impl Mul for Pose {
    type Output = Pose;
    fn mul(self, rhs: Pose) -> Pose {
        Pose::new(
            self.rotation * rhs.rotation,
            self.rotation * rhs.translation + self.translation,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_composes_to_identity() {
        let world_from_camera = Pose::new(
            Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0),
            Vec3::new(1.0, -2.0, 0.5),
        );
        let p = Vec3::new(0.2, 0.4, -3.0);
        let back = (world_from_camera.inverse() * world_from_camera).transform_point(p);
        assert!((back - p).length() < 1e-5);
    }

    #[test]
    fn look_at_points_minus_z_at_target() {
        let world_from_camera = Pose::look_at(Vec3::new(0.0, 1.0, 2.0), Vec3::ZERO, Vec3::Y);
        let forward_in_world = world_from_camera.transform_vector(-Vec3::Z);
        assert!((forward_in_world - Vec3::new(0.0, -1.0, -2.0).normalize()).length() < 1e-5);
    }
}
