//! Rigid transforms in f64 for the calibration maths, and the one place where OpenCV's frames
//! meet relight's.
//!
//! OpenCV reports every camera pose in the camera's *optical* frame (+X right, +Y down, +Z out of
//! the lens) and every target point in the target's own frame (see [`crate::target`]). relight
//! stores poses between cameras in the glTF camera frame (+Y up, −Z forward; see
//! `relight_core::camera`), so a transform between two optical frames `X` becomes
//! `G · X · G` with `G` = [`OPTICAL_FROM_GL`] (a 180° turn about X, its own inverse).

use std::ops::Mul;

use glam::{DQuat, DVec3};
use relight_core::Pose;

/// `point_in_a = a_from_b * point_in_b`: rotation then translation, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rigid {
    pub rotation: DQuat,
    pub translation: DVec3,
}

/// `point_in_optical = OPTICAL_FROM_GL * point_in_gl` (and the other way round: it is its own
/// inverse).
pub const OPTICAL_FROM_GL: Rigid = Rigid {
    rotation: DQuat::from_xyzw(1.0, 0.0, 0.0, 0.0),
    translation: DVec3::ZERO,
};

impl Default for Rigid {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Rigid {
    pub const IDENTITY: Rigid = Rigid {
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
    };

    pub fn new(rotation: DQuat, translation: DVec3) -> Self {
        Self {
            rotation: rotation.normalize(),
            translation,
        }
    }

    /// From OpenCV's rotation vector (Rodrigues: axis × angle) and translation, as returned by
    /// `solvePnP` and `calibrateCamera`: `camera_from_target`.
    pub fn from_rvec_tvec(rvec: [f64; 3], tvec: [f64; 3]) -> Self {
        Self::new(
            DQuat::from_scaled_axis(DVec3::from(rvec)),
            DVec3::from(tvec),
        )
    }

    /// The rotation as OpenCV's rotation vector (angle in [0, π]).
    pub fn rvec(&self) -> [f64; 3] {
        let q = if self.rotation.w < 0.0 {
            -self.rotation
        } else {
            self.rotation
        };
        q.to_scaled_axis().to_array()
    }

    pub fn tvec(&self) -> [f64; 3] {
        self.translation.to_array()
    }

    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        Self {
            rotation,
            translation: -(rotation * self.translation),
        }
    }

    pub fn transform_point(&self, point: DVec3) -> DVec3 {
        self.rotation * point + self.translation
    }

    pub fn transform_vector(&self, vector: DVec3) -> DVec3 {
        self.rotation * vector
    }

    pub fn from_pose(pose: &Pose) -> Self {
        Self::new(pose.rotation.as_dquat(), pose.translation.as_dvec3())
    }

    pub fn to_pose(&self) -> Pose {
        Pose::new(self.rotation.as_quat(), self.translation.as_vec3())
    }

    /// Angle of the rotation that takes `self`'s orientation to `other`'s, degrees.
    pub fn rotation_error_deg(&self, other: &Rigid) -> f64 {
        self.rotation.angle_between(other.rotation).to_degrees()
    }

    /// Distance between the translations, metres.
    pub fn translation_error_m(&self, other: &Rigid) -> f64 {
        self.translation.distance(other.translation)
    }

    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite()
    }
}

/// `a_from_c = a_from_b * b_from_c`.
impl Mul for Rigid {
    type Output = Rigid;
    fn mul(self, rhs: Rigid) -> Rigid {
        Rigid::new(
            self.rotation * rhs.rotation,
            self.rotation * rhs.translation + self.translation,
        )
    }
}

/// A transform between two cameras' optical frames, expressed between their glTF frames:
/// `a_gl_from_b_gl = gl_from_optical · a_optical_from_b_optical · optical_from_gl`.
pub fn gl_from_optical_pair(a_optical_from_b_optical: &Rigid) -> Rigid {
    OPTICAL_FROM_GL * *a_optical_from_b_optical * OPTICAL_FROM_GL
}

/// A camera's pose in some frame `w` from OpenCV's `camera_from_target` and the target's place
/// in `w`: `w_from_camera_gl = w_from_target · target_from_camera_optical · optical_from_gl`.
pub fn frame_from_camera_gl(w_from_target: &Rigid, camera_optical_from_target: &Rigid) -> Rigid {
    *w_from_target * camera_optical_from_target.inverse() * OPTICAL_FROM_GL
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::camera::{OPTICAL_FROM_GL_ROTATION, optical_from_gl};

    #[test]
    fn rvec_round_trip_and_opencv_rodrigues_convention() {
        // 90° about +Z takes +X to +Y (OpenCV's Rodrigues is a right-handed axis-angle).
        let quarter = Rigid::from_rvec_tvec([0.0, 0.0, std::f64::consts::FRAC_PI_2], [0.0; 3]);
        assert!(quarter.transform_vector(DVec3::X).distance(DVec3::Y) < 1e-12);
        let pose = Rigid::from_rvec_tvec([0.3, -1.2, 2.0], [0.1, 0.2, 0.3]);
        let back = Rigid::from_rvec_tvec(pose.rvec(), pose.tvec());
        assert!(back.rotation_error_deg(&pose) < 1e-9);
        assert!((pose * pose.inverse()).translation.length() < 1e-12);
    }

    #[test]
    fn optical_from_gl_matches_core() {
        let p = DVec3::new(0.3, -0.4, 2.0);
        assert!(
            OPTICAL_FROM_GL
                .transform_point(p)
                .distance(optical_from_gl(p))
                < 1e-15
        );
        assert_eq!(OPTICAL_FROM_GL.rotation.as_quat(), OPTICAL_FROM_GL_ROTATION);
        // Between two optical frames related by a pure translation along +X (a baseline to
        // the right), the glTF frames are related by the same translation.
        let b = Rigid::new(DQuat::IDENTITY, DVec3::new(-0.025, 0.0, 0.0));
        let gl = gl_from_optical_pair(&b);
        assert!(gl.translation.distance(DVec3::new(-0.025, 0.0, 0.0)) < 1e-15);
        // A translation along the optical axis becomes one along −Z.
        let forward = Rigid::new(DQuat::IDENTITY, DVec3::new(0.0, 0.1, 0.5));
        let gl = gl_from_optical_pair(&forward);
        assert!(gl.translation.distance(DVec3::new(0.0, -0.1, -0.5)) < 1e-15);
    }
}
