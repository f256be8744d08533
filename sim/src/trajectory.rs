//! Camera paths of the simulated rig: a tripod (static), an orbit that swings around the virtual
//! object, and a hand-held tremor (smooth, deterministic, a few Hz) on top of either.

use std::f32::consts::TAU;

use glam::{Quat, Vec3};
use relight_core::Pose;

#[derive(Debug, Clone, PartialEq)]
pub enum Trajectory {
    Static(Pose),
    /// On a circle of `radius_m` at `height_m` above `center`, looking at `center`, starting at
    /// azimuth `start_rad` (0: the +Z side, growing towards +X). With `sweep_rad` ≥ π it turns
    /// once per `period_s`; below π it swings to and fro between `start ± sweep_rad`
    /// (`start + sweep · sin(2π t / period)`), as a person walking an arc around a desk does.
    Orbit {
        center: Vec3,
        radius_m: f32,
        height_m: f32,
        period_s: f32,
        start_rad: f32,
        sweep_rad: f32,
    },
    /// `base`'s pose perturbed by a sum of sines (1.3–7.9 Hz, incommensurate, so it never
    /// repeats visibly) with peak translation `amplitude_m` and rotation `amplitude_deg` per
    /// axis.
    Shake {
        base: Box<Trajectory>,
        amplitude_m: f32,
        amplitude_deg: f32,
    },
}

/// Frequencies (Hz) and phases of the shake's three sines per axis.
const SHAKE: [(f32, f32); 3] = [(1.3, 0.0), (3.7, 1.1), (7.9, 2.3)];

fn shake(t_s: f32, axis: usize) -> f32 {
    SHAKE
        .iter()
        .map(|(f, phase)| (TAU * f * t_s + phase + axis as f32 * 0.7).sin())
        .sum::<f32>()
        / SHAKE.len() as f32
}

impl Trajectory {
    /// `world_from_camera` at time `t_s` (camera looks down −Z, +Y up).
    pub fn pose_at(&self, t_s: f32) -> Pose {
        match self {
            Trajectory::Static(pose) => *pose,
            Trajectory::Orbit {
                center,
                radius_m,
                height_m,
                period_s,
                start_rad,
                sweep_rad,
            } => {
                let phase = TAU * t_s / period_s.max(1e-3);
                let angle = if *sweep_rad >= std::f32::consts::PI {
                    start_rad + phase
                } else {
                    start_rad + sweep_rad * phase.sin()
                };
                let eye =
                    *center + Vec3::new(radius_m * angle.sin(), *height_m, radius_m * angle.cos());
                Pose::look_at(eye, *center, Vec3::Y)
            }
            Trajectory::Shake {
                base,
                amplitude_m,
                amplitude_deg,
            } => {
                let base = base.pose_at(t_s);
                let offset = Vec3::new(shake(t_s, 0), shake(t_s, 1), shake(t_s, 2)) * *amplitude_m;
                let a = amplitude_deg.to_radians();
                let wobble = Quat::from_euler(
                    glam::EulerRot::XYZ,
                    a * shake(t_s, 3),
                    a * shake(t_s, 4),
                    a * shake(t_s, 5),
                );
                Pose::new(base.rotation * wobble, base.translation + offset)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orbit_keeps_its_radius_and_looks_at_the_centre() {
        let center = Vec3::new(0.1, 0.2, -0.3);
        let orbit = Trajectory::Orbit {
            center,
            radius_m: 1.5,
            height_m: 0.8,
            period_s: 20.0,
            start_rad: 0.0,
            sweep_rad: TAU,
        };
        for i in 0..40 {
            let pose = orbit.pose_at(i as f32 * 0.5);
            let eye = pose.translation;
            let horizontal = Vec3::new(eye.x - center.x, 0.0, eye.z - center.z).length();
            assert!((horizontal - 1.5).abs() < 1e-4);
            assert!((eye.y - center.y - 0.8).abs() < 1e-5);
            let forward = pose.transform_vector(-Vec3::Z);
            assert!(forward.dot((center - eye).normalize()) > 0.99999);
        }
        assert!((orbit.pose_at(0.0).translation - orbit.pose_at(20.0).translation).length() < 1e-4);
    }

    #[test]
    fn a_partial_orbit_swings_within_its_sweep() {
        let center = Vec3::new(0.0, 0.1, -0.1);
        let swing = Trajectory::Orbit {
            center,
            radius_m: 2.0,
            height_m: 0.7,
            period_s: 8.0,
            start_rad: 0.3,
            sweep_rad: 0.4,
        };
        let mut seen = (f32::INFINITY, f32::NEG_INFINITY);
        for i in 0..400 {
            let eye = swing.pose_at(i as f32 * 0.02).translation - center;
            let azimuth = eye.x.atan2(eye.z);
            assert!((azimuth - 0.3).abs() <= 0.4 + 1e-5, "{azimuth}");
            seen = (seen.0.min(azimuth), seen.1.max(azimuth));
        }
        assert!(
            seen.0 < -0.09 && seen.1 > 0.69,
            "it reaches both ends: {seen:?}"
        );
    }

    #[test]
    fn shake_stays_within_its_amplitude_and_is_smooth() {
        let base = Pose::from_translation(Vec3::new(0.0, 1.0, 2.0));
        let shake = Trajectory::Shake {
            base: Box::new(Trajectory::Static(base)),
            amplitude_m: 0.01,
            amplitude_deg: 0.5,
        };
        let mut previous = shake.pose_at(0.0);
        let mut moved = 0.0f32;
        for i in 1..3000 {
            let pose = shake.pose_at(i as f32 / 300.0);
            let offset = pose.translation - base.translation;
            assert!(offset.abs().max_element() <= 0.01 + 1e-6);
            assert!(
                pose.rotation.angle_between(base.rotation)
                    <= 3f32.sqrt() * 0.5f32.to_radians() + 1e-4
            );
            // Bounded speed: per axis at most amplitude·2π·mean(f) ≈ 0.27 m/s, so under 3 mm
            // per 1/300 s sample over three axes — no jumps.
            let step = (pose.translation - previous.translation).length();
            assert!(step < 3e-3, "{step}");
            moved = moved.max(offset.length());
            previous = pose;
        }
        assert!(moved > 0.005, "it does shake");
    }
}
