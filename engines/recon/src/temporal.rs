//! Temporal merge of filtered depth: the previous merged depth is warped into the current view
//! and averaged with the current depth where the two agree (Knecht et al., *Reciprocal
//! shading for mixed reality*, C&G 2012, Sec. 4.2).
//!
//! The paper's warp is T_warp = T_prev⁻¹ T_cur with T the cameras' `world_from_camera`, i.e.
//! `previous_from_current`. It is applied as a gather, per current pixel, so that the GPU port
//! needs no scattering: the pixel's point P (from the current depth) is moved into the
//! previous camera, projected, and the previous merged depth is read there (bilinear over the
//! valid neighbours). If that depth is within `reject_sigmas` noise σ of P's depth in the
//! previous camera, the two measure the same surface: the history point (the previous ray
//! scaled to the read depth) is moved back into the current camera and averaged with the
//! current depth, weighted by how many frames it already holds. Otherwise the history is
//! rejected there (something moved, or the surface was occluded) and the pixel restarts from
//! the current depth.
//!
//! Pixels without current depth have no output (a hole stays a hole; history is not used to
//! invent geometry), and their history is dropped.
//!
//! The whole history is dropped — the output is exactly the current depth — on the first frame,
//! when the camera's intrinsics or size change, when the pose is not finite, when the camera
//! moved more than `max_translation_m` or turned more than `max_rotation_rad` since the previous
//! frame (a tracking jump: a warp by a wrong pose smears one view over another), and when fewer
//! than `min_agreement` of the pixels that found history agree with it (the pose is wrong even
//! though it did not jump).

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use relight_core::Pose;
use relight_core::camera::{Pinhole, optical_from_gl};

use crate::depth::{DepthError, DepthMap, DepthNoise, is_valid_depth};
use crate::normals::{PixelRays, point_in_camera};

/// Settings of [`TemporalMerge`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TemporalSettings {
    /// The sensor's noise, for the agreement test.
    pub noise: DepthNoise,
    /// History and current depth agree when they differ by at most this many
    /// [`DepthNoise::sigma_m`] (of a raw measurement, so filtered depth passes easily).
    pub reject_sigmas: f32,
    /// Frames the running mean holds at most; beyond it older frames fade exponentially, so the
    /// merge keeps following slow changes (and the resampling blur of a moving camera stays
    /// bounded).
    pub max_weight: f32,
    /// Camera motion between two frames beyond which the history is dropped.
    pub max_translation_m: f32,
    pub max_rotation_rad: f32,
    /// Share of compared pixels that must agree with the history, or it is dropped.
    pub min_agreement: f32,
}

impl TemporalSettings {
    /// The checks [`TemporalMerge::merge`] makes of its settings.
    pub fn validate(&self) -> Result<(), DepthError> {
        let positive = |v: f32| v.is_finite() && v > 0.0;
        if !(positive(self.reject_sigmas)
            && self.max_weight.is_finite()
            && self.max_weight >= 1.0
            && positive(self.max_translation_m)
            && positive(self.max_rotation_rad)
            && (0.0..=1.0).contains(&self.min_agreement))
        {
            return Err(DepthError::Setting {
                setting: "temporal",
                reason: "needs positive thresholds, max_weight ≥ 1 and min_agreement in [0, 1]",
            });
        }
        self.noise.validate()
    }

    /// Agreement at 3 σ, 16 frames of history; resets beyond 5 cm or 5° per frame (hand-held
    /// motion at 30 fps moves a few mm and a fraction of a degree) or below 80 % agreement. On
    /// a correctly tracked camera under 1 % of the compared pixels disagree (edges, noise); a
    /// pose that stayed put while the camera turned 27° still agrees on about 60 % of a room's
    /// smooth walls, so the threshold sits well above that. Something moving through the view
    /// that covers more than a fifth of it also restarts the merge, which costs a few frames
    /// of averaging, not geometry.
    pub fn kinect_v1(focal_px: f32) -> Self {
        Self {
            noise: DepthNoise::kinect_v1(focal_px),
            reject_sigmas: 3.0,
            max_weight: 16.0,
            max_translation_m: 0.05,
            max_rotation_rad: 5f32.to_radians(),
            min_agreement: 0.8,
        }
    }
}

/// Why the history was dropped.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ResetReason {
    FirstFrame,
    /// Size or intrinsics differ from the previous frame's.
    CameraChanged,
    NonFinitePose,
    PoseJump {
        translation_m: f32,
        rotation_rad: f32,
    },
    /// Only `agreement` of the compared pixels agreed with the history.
    Disagreement {
        agreement: f32,
    },
}

/// What one merge did, per pixel of the current frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MergeReport {
    /// `Some` when the output is the current depth alone.
    pub reset: Option<ResetReason>,
    /// Averaged with agreeing history.
    pub merged: usize,
    /// History found but rejected (beyond the agreement threshold).
    pub rejected: usize,
    /// Current depth without history there (newly seen, or warped from outside the view).
    pub fresh: usize,
}

#[derive(Debug, Clone)]
struct History {
    depth: DepthMap,
    weight: Vec<f32>,
    world_from_camera: Pose,
    camera: Pinhole,
}

/// Running merge of filtered depth frames; see the module docs.
#[derive(Debug, Clone)]
pub struct TemporalMerge {
    settings: TemporalSettings,
    history: Option<History>,
    report: MergeReport,
    /// The current camera's pixel rays, made once per camera (each is a Newton inversion of
    /// the lens model: a fifth of the merge's time when made every frame).
    rays: Option<PixelRays>,
}

/// Where a point of the current camera lands in the previous camera's image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Landing {
    /// Pixel coordinates (OpenCV convention: pixel centres at integers).
    pub pixel: Vec2,
    /// The point in the previous camera (glTF frame).
    pub point_in_previous: Vec3,
}

/// The warp T_warp = T_prev⁻¹ T_cur of Knecht et al. Sec. 4.2 with the previous camera's
/// intrinsics.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Warp<'a> {
    pub previous_from_current: Pose,
    pub previous_camera: &'a Pinhole,
}

impl Warp<'_> {
    pub fn land(&self, point_in_current: Vec3) -> Option<Landing> {
        let point_in_previous = self.previous_from_current.transform_point(point_in_current);
        let pixel = self
            .previous_camera
            .project(optical_from_gl(point_in_previous.as_dvec3()))
            .filter(|p| self.previous_camera.contains_pixel(*p))?;
        Some(Landing {
            pixel: pixel.as_vec2(),
            point_in_previous,
        })
    }
}

/// Bilinear read of `values` at `pixel` over the neighbours whose depth is valid, weights
/// renormalised; `None` when none of the four is valid.
fn bilinear_valid(depth: &DepthMap, values: &[f32], pixel: Vec2) -> Option<(f32, f32)> {
    let (w, h) = (depth.width as i64, depth.height as i64);
    let x0 = pixel.x.floor();
    let y0 = pixel.y.floor();
    let (fx, fy) = (pixel.x - x0, pixel.y - y0);
    let (x0, y0) = (x0 as i64, y0 as i64);
    let mut weight_sum = 0.0f32;
    let mut depth_sum = 0.0f32;
    let mut value_sum = 0.0f32;
    for (dx, dy, weight) in [
        (0, 0, (1.0 - fx) * (1.0 - fy)),
        (1, 0, fx * (1.0 - fy)),
        (0, 1, (1.0 - fx) * fy),
        (1, 1, fx * fy),
    ] {
        let (x, y) = (x0 + dx, y0 + dy);
        if weight <= 0.0 || x < 0 || y < 0 || x >= w || y >= h {
            continue;
        }
        let i = (y * w + x) as usize;
        let (Some(&z), Some(&v)) = (depth.metres.get(i), values.get(i)) else {
            continue;
        };
        if is_valid_depth(z) {
            weight_sum += weight;
            depth_sum += weight * z;
            value_sum += weight * v;
        }
    }
    (weight_sum > 0.0).then(|| (depth_sum / weight_sum, value_sum / weight_sum))
}

/// Why the history must be dropped before a frame of `camera` at `world_from_camera` is merged,
/// given the camera and pose the history was last merged at (`None`: no history yet); `None`
/// when it can be kept. The per-pixel agreement test comes after this.
pub fn reset_reason(
    previous: Option<(&Pinhole, &Pose)>,
    camera: &Pinhole,
    world_from_camera: &Pose,
    settings: &TemporalSettings,
) -> Option<ResetReason> {
    let Some((previous_camera, previous_pose)) = previous else {
        return Some(ResetReason::FirstFrame);
    };
    if previous_camera != camera {
        return Some(ResetReason::CameraChanged);
    }
    let Some((translation_m, rotation_rad)) = motion(previous_pose, world_from_camera) else {
        return Some(ResetReason::NonFinitePose);
    };
    if translation_m > settings.max_translation_m || rotation_rad > settings.max_rotation_rad {
        return Some(ResetReason::PoseJump {
            translation_m,
            rotation_rad,
        });
    }
    None
}

/// Camera motion from `previous` to `current` (`world_from_camera` both): translation (m) and
/// rotation angle (rad); `None` when either pose is not finite.
pub(crate) fn motion(previous: &Pose, current: &Pose) -> Option<(f32, f32)> {
    let finite = |p: &Pose| p.translation.is_finite() && p.rotation.is_finite();
    if !(finite(previous) && finite(current)) {
        return None;
    }
    let translation = (current.translation - previous.translation).length();
    let rotation = previous
        .rotation
        .normalize()
        .angle_between(current.rotation.normalize());
    (translation.is_finite() && rotation.is_finite()).then_some((translation, rotation))
}

enum PixelOutcome {
    Invalid,
    Fresh,
    Merged,
    Rejected,
}

impl TemporalMerge {
    pub fn new(settings: TemporalSettings) -> Self {
        Self {
            settings,
            history: None,
            report: MergeReport::default(),
            rays: None,
        }
    }

    pub fn settings(&self) -> &TemporalSettings {
        &self.settings
    }

    /// Drop the history: the next merge returns its input.
    pub fn reset(&mut self) {
        self.history = None;
    }

    /// What the last [`Self::merge`] did.
    pub fn report(&self) -> &MergeReport {
        &self.report
    }

    /// Frames averaged into each pixel of the last output (0 where it has no depth).
    pub fn weights(&self) -> &[f32] {
        self.history.as_ref().map_or(&[], |h| &h.weight)
    }

    /// Merge the current filtered depth (seen by `camera` at `world_from_camera`, glTF
    /// convention) with the history; returns the merged depth in the current view.
    pub fn merge(
        &mut self,
        current: &DepthMap,
        camera: &Pinhole,
        world_from_camera: &Pose,
    ) -> Result<DepthMap, DepthError> {
        self.settings.validate()?;
        current.check_size("camera", camera.width, camera.height)?;
        if self.rays.as_ref().is_none_or(|r| r.camera != *camera) {
            self.rays = Some(PixelRays::new(camera));
        }
        let merged = match (self.reset_reason(camera, world_from_camera), &self.history) {
            (None, Some(history)) => {
                let rays = self.rays.as_ref().expect("made above");
                let (depth, weight, report) =
                    self.warp_and_merge(current, rays, world_from_camera, history);
                let compared = report.merged + report.rejected;
                let agreement = if compared == 0 {
                    1.0
                } else {
                    report.merged as f32 / compared as f32
                };
                if agreement < self.settings.min_agreement {
                    Self::restart(current, ResetReason::Disagreement { agreement })
                } else {
                    (depth, weight, report)
                }
            }
            (reason, _) => Self::restart(current, reason.unwrap_or(ResetReason::FirstFrame)),
        };
        let (depth, weight, report) = merged;
        self.report = report;
        self.history = Some(History {
            depth: depth.clone(),
            weight,
            world_from_camera: *world_from_camera,
            camera: *camera,
        });
        Ok(depth)
    }

    fn reset_reason(&self, camera: &Pinhole, world_from_camera: &Pose) -> Option<ResetReason> {
        reset_reason(
            self.history
                .as_ref()
                .map(|h| (&h.camera, &h.world_from_camera)),
            camera,
            world_from_camera,
            &self.settings,
        )
    }

    /// The current depth alone (invalid values cleaned to 0), weight 1 where valid.
    fn restart(current: &DepthMap, reason: ResetReason) -> (DepthMap, Vec<f32>, MergeReport) {
        let metres: Vec<f32> = current
            .metres
            .iter()
            .map(|&z| if is_valid_depth(z) { z } else { 0.0 })
            .collect();
        let weight: Vec<f32> = metres
            .iter()
            .map(|&z| if z > 0.0 { 1.0 } else { 0.0 })
            .collect();
        let report = MergeReport {
            reset: Some(reason),
            fresh: weight.iter().filter(|w| **w > 0.0).count(),
            ..MergeReport::default()
        };
        let depth = DepthMap {
            width: current.width,
            height: current.height,
            metres,
        };
        (depth, weight, report)
    }

    fn warp_and_merge(
        &self,
        current: &DepthMap,
        rays: &PixelRays,
        world_from_camera: &Pose,
        history: &History,
    ) -> (DepthMap, Vec<f32>, MergeReport) {
        let warp = Warp {
            previous_from_current: history.world_from_camera.inverse() * *world_from_camera,
            previous_camera: &history.camera,
        };
        let current_from_previous = warp.previous_from_current.inverse();
        let settings = &self.settings;
        let per_pixel: Vec<(f32, f32, PixelOutcome)> = (0..current.pixel_count())
            .into_par_iter()
            .map(|i| {
                let z = current.metres[i];
                let Some(point) = is_valid_depth(z)
                    .then(|| rays.get(i).map(|ray| point_in_camera(ray, z)))
                    .flatten()
                else {
                    return (0.0, 0.0, PixelOutcome::Invalid);
                };
                let Some(landing) = warp.land(point) else {
                    return (z, 1.0, PixelOutcome::Fresh);
                };
                let Some((history_z, history_weight)) =
                    bilinear_valid(&history.depth, &history.weight, landing.pixel)
                else {
                    return (z, 1.0, PixelOutcome::Fresh);
                };
                let predicted_z = -landing.point_in_previous.z;
                let limit = settings.reject_sigmas * settings.noise.sigma_m(predicted_z);
                if (history_z - predicted_z).abs() > limit || predicted_z <= 0.0 {
                    return (z, 1.0, PixelOutcome::Rejected);
                }
                // The previous surface point on the previous camera's ray through P.
                let history_point = landing.point_in_previous * (history_z / predicted_z);
                let history_in_current = -current_from_previous.transform_point(history_point).z;
                if !is_valid_depth(history_in_current) {
                    return (z, 1.0, PixelOutcome::Rejected);
                }
                let w = history_weight.clamp(0.0, settings.max_weight - 1.0);
                let merged = (w * history_in_current + z) / (w + 1.0);
                (merged, w + 1.0, PixelOutcome::Merged)
            })
            .collect();
        let mut report = MergeReport::default();
        let mut metres = Vec::with_capacity(per_pixel.len());
        let mut weight = Vec::with_capacity(per_pixel.len());
        for (z, w, outcome) in per_pixel {
            match outcome {
                PixelOutcome::Invalid => {}
                PixelOutcome::Fresh => report.fresh += 1,
                PixelOutcome::Merged => report.merged += 1,
                PixelOutcome::Rejected => report.rejected += 1,
            }
            metres.push(z);
            weight.push(w);
        }
        let depth = DepthMap {
            width: current.width,
            height: current.height,
            metres,
        };
        (depth, weight, report)
    }
}
