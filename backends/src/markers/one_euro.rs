//! The One-Euro filter on poses (Casiez, Roussel & Vogel, "1€ Filter: A Simple Speed-based
//! Low-pass Filter for Noisy Input in Interactive Systems", CHI 2012).
//!
//! A first-order low-pass whose cutoff rises with speed: `f_c = f_c,min + β |ẋ̂|`, where `ẋ̂` is
//! the signal's derivative, itself low-passed at a fixed `f_c,d`. At rest the cutoff is low and
//! jitter is removed; in motion it rises and lag shrinks. Each step blends with
//! `α = 1 / (1 + τ / T_e)`, `τ = 1 / (2π f_c)`, `T_e` the time since the previous sample, so
//! irregular frame timing is handled by the timestamps themselves.
//!
//! On a pose: each translation axis is filtered on its own (the paper's per-dimension filter);
//! the rotation is blended by slerp from the filtered rotation towards the new one with the same
//! adaptive `α`, the speed being the length of the low-passed angular velocity vector (the
//! rotation between consecutive raw rotations per second). Filtering the vector rather than its
//! length lets jitter average out at rest, as the signed per-axis derivative does.
//! Like the authors' reference implementation, the raw derivative is taken between consecutive
//! *raw* samples, so on a constant-speed ramp the derivative estimate converges to the speed
//! and the steady lag is `v τ = v / (2π (f_c,min + β v))`.

use glam::{DQuat, DVec3};
use serde::{Deserialize, Serialize};

use super::pose::{DPose, rotation_angle};

/// One-Euro parameters for marker poses (config table `filter`).
///
/// Tuning, after §4 of the paper: with `beta = 0`, lower `min_cutoff_hz` until a still marker
/// no longer jitters; then raise `beta` until a moving marker no longer lags.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OneEuroConfig {
    /// Filter poses at all (default true).
    pub enabled: bool,
    /// `f_c,min`, Hz: the cutoff at rest. The paper starts at 1 Hz; lower removes more jitter
    /// and lags more at low speed.
    pub min_cutoff_hz: f64,
    /// `β` for translation, Hz per m/s: how fast the cutoff rises with speed. 0 is a plain
    /// low-pass. The default (20) gives 11 Hz at 0.5 m/s, a hand moving a marker.
    pub beta: f64,
    /// `β` for rotation, Hz per rad/s. The default (10) gives 11 Hz at 1 rad/s.
    pub beta_rotation: f64,
    /// `f_c,d`, Hz: the cutoff of the derivative estimate (the paper fixes it at 1 Hz).
    pub derivative_cutoff_hz: f64,
    /// A marker unseen for longer than this (s) restarts its filter from its next pose instead
    /// of gliding there from where it was lost.
    pub reset_after_s: f64,
}

impl Default for OneEuroConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            min_cutoff_hz: 1.0,
            beta: 20.0,
            beta_rotation: 10.0,
            derivative_cutoff_hz: 1.0,
            reset_after_s: 0.5,
        }
    }
}

impl OneEuroConfig {
    /// Checks that every parameter is a finite number in its range.
    pub fn validate(&self) -> Result<(), String> {
        let checks = [
            (
                "min_cutoff_hz",
                self.min_cutoff_hz,
                self.min_cutoff_hz > 0.0,
            ),
            ("beta", self.beta, self.beta >= 0.0),
            (
                "beta_rotation",
                self.beta_rotation,
                self.beta_rotation >= 0.0,
            ),
            (
                "derivative_cutoff_hz",
                self.derivative_cutoff_hz,
                self.derivative_cutoff_hz > 0.0,
            ),
            (
                "reset_after_s",
                self.reset_after_s,
                self.reset_after_s > 0.0,
            ),
        ];
        match checks
            .iter()
            .find(|(_, value, in_range)| !(value.is_finite() && *in_range))
        {
            Some((name, value, _)) => Err(format!(
                "filter `{name}` = {value} is out of range (cutoffs and times > 0, betas ≥ 0)"
            )),
            None => Ok(()),
        }
    }
}

/// The smoothing factor of a first-order low-pass with cutoff `cutoff_hz` sampled after `dt_s`.
pub fn smoothing_factor(cutoff_hz: f64, dt_s: f64) -> f64 {
    let tau = 1.0 / (std::f64::consts::TAU * cutoff_hz);
    1.0 / (1.0 + tau / dt_s)
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct State {
    time_ns: u64,
    raw: DPose,
    filtered: DPose,
    /// Low-passed per-axis velocity, m/s.
    velocity: DVec3,
    /// Low-passed angular velocity (world-frame rotation vector per second), rad/s.
    angular_velocity: DVec3,
}

/// A One-Euro filter on one marker's pose.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseFilter {
    config: OneEuroConfig,
    state: Option<State>,
}

impl PoseFilter {
    pub fn new(config: OneEuroConfig) -> Self {
        Self {
            config,
            state: None,
        }
    }

    pub fn config(&self) -> &OneEuroConfig {
        &self.config
    }

    /// Forget the history: the next pose passes unfiltered.
    pub fn reset(&mut self) {
        self.state = None;
    }

    /// Time of the last sample, ns.
    pub fn last_time_ns(&self) -> Option<u64> {
        self.state.map(|s| s.time_ns)
    }

    /// The filtered pose for a sample taken at `time_ns`. The first sample, one after a gap
    /// longer than `reset_after_s`, one whose time does not advance, or any sample when the
    /// filter is disabled passes through unchanged (and restarts the history).
    pub fn filter(&mut self, time_ns: u64, pose: &DPose) -> DPose {
        let config = self.config;
        let previous = match self.state {
            Some(previous) if config.enabled && time_ns > previous.time_ns => previous,
            _ => return self.restart(time_ns, pose),
        };
        let dt_s = (time_ns - previous.time_ns) as f64 * 1e-9;
        if dt_s > config.reset_after_s {
            return self.restart(time_ns, pose);
        }
        let alpha_d = smoothing_factor(config.derivative_cutoff_hz, dt_s);

        let raw_velocity = (pose.translation - previous.raw.translation) / dt_s;
        let velocity = previous.velocity + (raw_velocity - previous.velocity) * alpha_d;
        let alpha = (velocity.abs() * config.beta + DVec3::splat(config.min_cutoff_hz))
            .to_array()
            .map(|cutoff| smoothing_factor(cutoff, dt_s));
        let translation = previous.filtered.translation
            + (pose.translation - previous.filtered.translation) * DVec3::from_array(alpha);

        let raw_angular_velocity =
            rotation_vector(pose.rotation * previous.raw.rotation.inverse()) / dt_s;
        let angular_velocity = previous.angular_velocity
            + (raw_angular_velocity - previous.angular_velocity) * alpha_d;
        let alpha_rotation = smoothing_factor(
            config.min_cutoff_hz + config.beta_rotation * angular_velocity.length(),
            dt_s,
        );
        let target = shortest_arc_to(previous.filtered.rotation, pose.rotation);
        let rotation = previous.filtered.rotation.slerp(target, alpha_rotation);

        let filtered = DPose::new(rotation, translation);
        self.state = Some(State {
            time_ns,
            raw: *pose,
            filtered,
            velocity,
            angular_velocity,
        });
        filtered
    }

    fn restart(&mut self, time_ns: u64, pose: &DPose) -> DPose {
        self.state = Some(State {
            time_ns,
            raw: *pose,
            filtered: *pose,
            velocity: DVec3::ZERO,
            angular_velocity: DVec3::ZERO,
        });
        *pose
    }
}

/// The rotation vector (axis × angle, angle in [0, π]) of a rotation.
fn rotation_vector(rotation: DQuat) -> DVec3 {
    let rotation = if rotation.w < 0.0 {
        -rotation
    } else {
        rotation
    };
    let sin_half = rotation.xyz().length();
    if sin_half < 1e-300 {
        return DVec3::ZERO;
    }
    rotation.xyz() / sin_half * rotation_angle(rotation)
}

/// `to` or `−to`, whichever is nearer `from` (the same rotation; slerp then takes the short way).
fn shortest_arc_to(from: DQuat, to: DQuat) -> DQuat {
    if from.dot(to) < 0.0 { -to } else { to }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rand_pcg::Pcg64Mcg;

    const FPS: f64 = 30.0;

    fn time_ns(frame: u32) -> u64 {
        (f64::from(frame) / FPS * 1e9).round() as u64
    }

    /// RMS of the filtered minus the true translation and rotation over frames `from..`.
    fn jitter(config: OneEuroConfig, frames: u32, from: u32) -> ((f64, f64), (f64, f64)) {
        let truth = DPose::new(DQuat::from_rotation_y(0.7), DVec3::new(0.1, -0.2, -1.5));
        let mut filter = PoseFilter::new(config);
        let mut rng = Pcg64Mcg::seed_from_u64(3);
        // Jitter of a tag's pose at ~1 m: 2 mm per axis, 0.5° about a random axis.
        let translation_noise = Normal::new(0.0, 0.002).unwrap();
        let axis_noise = Normal::new(0.0, 0.5f64.to_radians()).unwrap();
        let (mut raw_t, mut raw_r, mut out_t, mut out_r) = (0.0, 0.0, 0.0, 0.0);
        for i in 0..frames {
            let noisy = DPose::new(
                DQuat::from_scaled_axis(DVec3::new(
                    axis_noise.sample(&mut rng),
                    axis_noise.sample(&mut rng),
                    axis_noise.sample(&mut rng),
                )) * truth.rotation,
                truth.translation
                    + DVec3::new(
                        translation_noise.sample(&mut rng),
                        translation_noise.sample(&mut rng),
                        translation_noise.sample(&mut rng),
                    ),
            );
            let filtered = filter.filter(time_ns(i), &noisy);
            if i >= from {
                raw_t += noisy.translation.distance_squared(truth.translation);
                raw_r += noisy.angle_to(&truth).powi(2);
                out_t += filtered.translation.distance_squared(truth.translation);
                out_r += filtered.angle_to(&truth).powi(2);
            }
        }
        ((raw_t.sqrt(), out_t.sqrt()), (raw_r.sqrt(), out_r.sqrt()))
    }

    #[test]
    fn jitter_on_a_still_pose_drops_by_the_low_pass_factor() {
        // β = 0 is a plain exponential smoother: output variance α / (2 − α) of the input's.
        let plain = OneEuroConfig {
            beta: 0.0,
            beta_rotation: 0.0,
            ..OneEuroConfig::default()
        };
        let alpha = smoothing_factor(plain.min_cutoff_hz, 1.0 / FPS);
        let expected = (alpha / (2.0 - alpha)).sqrt();
        let ((raw_t, out_t), (raw_r, out_r)) = jitter(plain, 3000, 30);
        let (ratio_t, ratio_r) = (out_t / raw_t, out_r / raw_r);
        assert!(
            (ratio_t / expected - 1.0).abs() < 0.1,
            "{ratio_t} vs {expected}"
        );
        assert!(
            (ratio_r / expected - 1.0).abs() < 0.1,
            "{ratio_r} vs {expected}"
        );
        // The default β lets noise-induced speed open the cutoff a little; most jitter still goes.
        let ((raw_t, out_t), (raw_r, out_r)) = jitter(OneEuroConfig::default(), 3000, 30);
        assert!(
            out_t / raw_t < 0.6,
            "translation jitter ratio {}",
            out_t / raw_t
        );
        assert!(
            out_r / raw_r < 0.6,
            "rotation jitter ratio {}",
            out_r / raw_r
        );
        assert!(out_t / raw_t > expected && out_r / raw_r > expected);
    }

    #[test]
    fn a_ramp_is_followed_with_the_derived_lag() {
        let config = OneEuroConfig::default();
        let speed = 0.5; // m/s along x
        let angular_speed = 1.0; // rad/s about z
        let mut filter = PoseFilter::new(config);
        let pose_at = |i: u32| {
            let t = f64::from(i) / FPS;
            DPose::new(
                DQuat::from_rotation_z(angular_speed * t),
                DVec3::new(speed * t, 0.2, -1.0),
            )
        };
        let mut last = (DPose::IDENTITY, DPose::IDENTITY);
        for i in 0..120 {
            last = (filter.filter(time_ns(i), &pose_at(i)), pose_at(i));
        }
        let (filtered, truth) = last;
        // Steady state of exponential smoothing on a ramp: lag = v τ, τ = 1 / (2π f_c), with the
        // derivative converged to v so f_c = f_c,min + β v.
        let lag_bound =
            |v: f64, beta: f64| v / (std::f64::consts::TAU * (config.min_cutoff_hz + beta * v));
        let lag = truth.translation.x - filtered.translation.x;
        assert!(
            (lag / lag_bound(speed, config.beta) - 1.0).abs() < 0.02,
            "lag {lag} m vs {}",
            lag_bound(speed, config.beta)
        );
        assert!((filtered.translation.y - 0.2).abs() < 1e-12);
        let angular_lag = filtered.angle_to(&truth);
        let angular_bound = lag_bound(angular_speed, config.beta_rotation);
        assert!(
            (angular_lag / angular_bound - 1.0).abs() < 0.02,
            "{angular_lag} rad vs {angular_bound}"
        );
        // A plain low-pass at the same minimum cutoff lags (1 + β v / f_c,min) times more.
        assert!(lag * 5.0 < lag_bound(speed, 0.0));
    }

    #[test]
    fn a_step_is_followed_faster_than_the_resting_cutoff_allows() {
        let config = OneEuroConfig::default();
        let step = 0.2;
        let mut filter = PoseFilter::new(config);
        let mut plain = PoseFilter::new(OneEuroConfig {
            beta: 0.0,
            ..config
        });
        let before = DPose::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, -1.0));
        let after = DPose::new(DQuat::IDENTITY, DVec3::new(step, 0.0, -1.0));
        for i in 0..30 {
            filter.filter(time_ns(i), &before);
            plain.filter(time_ns(i), &before);
        }
        let alpha_min = smoothing_factor(config.min_cutoff_hz, 1.0 / FPS);
        for k in 1..=10u32 {
            let i = 29 + k;
            let error = step - filter.filter(time_ns(i), &after).translation.x;
            let plain_error = step - plain.filter(time_ns(i), &after).translation.x;
            // Every step blends at least α(f_c,min) of the way: error ≤ D (1 − α_min)^k.
            let bound = step * (1.0 - alpha_min).powi(k as i32);
            assert!(error <= bound + 1e-12, "frame {k}: {error} > {bound}");
            assert!((plain_error - bound).abs() < 1e-9);
            if k == 5 {
                assert!(error < 0.5 * plain_error, "{error} vs {plain_error}");
            }
        }
    }

    #[test]
    fn gaps_and_disabled_filters_pass_poses_through() {
        let config = OneEuroConfig::default();
        let mut filter = PoseFilter::new(config);
        let a = DPose::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, -1.0));
        let b = DPose::new(DQuat::from_rotation_x(1.0), DVec3::new(0.3, 0.0, -1.0));
        filter.filter(0, &a);
        assert_ne!(filter.filter(time_ns(1), &b), b);
        // Lost for a second: restart at the new pose.
        assert_eq!(filter.filter(time_ns(40), &a), a);
        // Time going backwards (a replay looped): restart.
        assert_eq!(filter.filter(time_ns(2), &b), b);
        let mut off = PoseFilter::new(OneEuroConfig {
            enabled: false,
            ..config
        });
        off.filter(0, &a);
        assert_eq!(off.filter(time_ns(1), &b), b);
        assert!(OneEuroConfig::default().validate().is_ok());
        assert!(
            OneEuroConfig {
                min_cutoff_hz: 0.0,
                ..config
            }
            .validate()
            .is_err()
        );
        assert!(
            OneEuroConfig {
                beta: f64::NAN,
                ..config
            }
            .validate()
            .is_err()
        );
    }
}
