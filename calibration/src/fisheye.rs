//! Fish-eye intrinsics: `cv::fisheye::calibrate` (Kannala & Brandt, "A generic camera model
//! and calibration method for conventional, wide-angle, and fish-eye lenses", PAMI 2006:
//! θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)), with flags `CALIB_RECOMPUTE_EXTRINSIC |
//! CALIB_CHECK_COND | CALIB_FIX_SKEW`. relight's [`KannalaBrandt`] is the same model with the same
//! coefficients (θ from `atan2`, which equals OpenCV's `atan(r)` in front of the lens; checked
//! against `fisheye::projectPoints` in the tests), so OpenCV's K and D carry over as they are.
//!
//! # Failure modes caught, with an explanation instead of a silent bad result
//!
//! - **A view that breaks the optimisation.** `CALIB_CHECK_COND` makes OpenCV stop at a view
//!   whose pose Jacobian is ill-conditioned (a target too small, too oblique, or with nearly
//!   collinear corners) and name it ("Ill-conditioned matrix for input array N"); that view is
//!   set aside and the calibration re-run (when OpenCV names none, an assertion in
//!   `InitExtrinsics`, each view is left out in turn to find the culprit). Views near the rim
//!   are often ill-conditioned only under OpenCV's crude starting guess, so the central views
//!   are calibrated first and all views fitted from that result; set-aside views get a second
//!   try, and one that still fails is dropped with a message.
//! - **Too few corners near the rim.** The distortion polynomial is only measured out to the
//!   largest angle any corner was seen at; beyond it, it is extrapolated. The corners' angles
//!   off the optical axis are histogrammed, and the calibration is refused when they do not
//!   reach `rim_coverage` of the field (OpenCV's fish-eye model ends at 90°, so of at most 90°).
//! - **Non-monotonic θ_d(θ).** A fit whose θ_d stops increasing inside the field folds the rim
//!   back onto the image: refused.
//! - Outlier views (RMS > `outlier_factor` × the median) are reported and dropped with a re-run,
//!   as for the pinhole.

use glam::DVec3;
use opencv::calib3d;
use opencv::core::{Mat, Size, Vector};
use opencv::prelude::*;
use relight_core::camera::{CameraModel, KannalaBrandt};

use crate::detect::{Detection, common_size};
use crate::error::CalibrationError;
use crate::intrinsics::{
    DroppedView, OutlierView, ViewFit, criteria, cv_points, find_outliers, mat_values,
    pose_from_mats, reprojection_rms_px, usable_views,
};
use crate::synth::fisheye_field_rad;

/// Options of [`calibrate_fisheye`].
#[derive(Debug, Clone, PartialEq)]
pub struct FisheyeSettings {
    /// A view is an outlier when its RMS exceeds this many times the median view RMS …
    pub outlier_factor: f64,
    /// … and this many pixels.
    pub outlier_floor_px: f64,
    /// Drop outlier views and calibrate again (once).
    pub drop_outliers: bool,
    /// Fewest views to calibrate from.
    pub min_views: usize,
    /// Views with fewer points are skipped.
    pub min_points_per_view: usize,
    /// The lens's full field of view, degrees (185 for relight's light probe). θ_d must
    /// increase over all of it. `None`: the field the image shows (its edge midpoints).
    pub field_of_view_deg: Option<f64>,
    /// Corners must reach this fraction of the half field (at most 90°, OpenCV's limit);
    /// 0 disables the check.
    pub rim_coverage: f64,
    /// Most views dropped as ill-conditioned before giving up.
    pub max_ill_conditioned: usize,
}

impl Default for FisheyeSettings {
    fn default() -> Self {
        Self {
            outlier_factor: 3.0,
            outlier_floor_px: 0.3,
            drop_outliers: true,
            min_views: 6,
            min_points_per_view: 8,
            field_of_view_deg: None,
            rim_coverage: 0.85,
            max_ill_conditioned: 3,
        }
    }
}

/// The `fisheye::calibrate` flags used.
pub const FISHEYE_FLAGS: i32 = calib3d::Fisheye_CALIB_RECOMPUTE_EXTRINSIC
    | calib3d::Fisheye_CALIB_CHECK_COND
    | calib3d::Fisheye_CALIB_FIX_SKEW;

/// Corners per 10° band of angle off the optical axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThetaBin {
    pub from_deg: f64,
    pub to_deg: f64,
    pub points: usize,
}

/// Result of [`calibrate_fisheye`].
#[derive(Debug, Clone, PartialEq)]
pub struct FisheyeCalibration {
    pub camera: KannalaBrandt,
    /// RMS reprojection error over all points of the views used (relight's projection).
    pub rms_px: f64,
    /// The views used, in input order.
    pub views: Vec<ViewFit>,
    /// Outliers of the fit before outliers were dropped.
    pub outliers: Vec<OutlierView>,
    /// Views not in the final fit, and why.
    pub dropped: Vec<DroppedView>,
    /// Largest angle off the optical axis at which a corner was seen, degrees: the
    /// distortion is measured up to here and extrapolated beyond.
    pub max_theta_deg: f64,
    /// The half field the checks used, degrees.
    pub field_deg: f64,
    pub theta_histogram: Vec<ThetaBin>,
}

/// Calibrates a fish-eye camera from its detections (one camera, one resolution).
pub fn calibrate_fisheye(
    detections: &[Detection],
    settings: &FisheyeSettings,
) -> Result<FisheyeCalibration, CalibrationError> {
    let (width, height) = common_size(detections)?;
    let (mut views, mut dropped) = usable_views(detections, settings.min_points_per_view);
    let mut fit = fit_dropping_ill_conditioned(&mut views, &mut dropped, width, height, settings)?;
    let outliers = find_outliers(
        &fit.views,
        settings.outlier_factor,
        settings.outlier_floor_px,
    );
    if settings.drop_outliers && !outliers.is_empty() {
        let kept = views.len() - outliers.len();
        if kept >= settings.min_views {
            views.retain(|d| !outliers.iter().any(|o| o.view == d.view));
            dropped.extend(outliers.iter().map(|o| DroppedView {
                view: o.view.clone(),
                reason: format!(
                    "outlier: reprojection RMS {:.3} px > {:.3} px",
                    o.rms_px, o.threshold_px
                ),
            }));
            fit = fit_dropping_ill_conditioned(&mut views, &mut dropped, width, height, settings)?;
        }
    }

    let model = CameraModel::KannalaBrandt(fit.camera);
    let field_rad = match settings.field_of_view_deg {
        Some(full_deg) => (0.5 * full_deg).to_radians(),
        None => fisheye_field_rad(&model),
    };
    check_monotonic(&fit.camera, field_rad.to_degrees())?;
    let thetas: Vec<f64> = views
        .iter()
        .zip(&fit.views)
        .flat_map(|(detection, view)| {
            detection.object_points.iter().map(move |&p| {
                let p: DVec3 = view.camera_from_target.transform_point(p);
                p.truncate().length().atan2(p.z)
            })
        })
        .collect();
    let max_theta = thetas.iter().copied().fold(0.0, f64::max);
    let required = settings.rim_coverage * field_rad.min(std::f64::consts::FRAC_PI_2);
    if max_theta < required {
        return Err(CalibrationError::RimNotCovered {
            max_theta_deg: max_theta.to_degrees(),
            required_deg: required.to_degrees(),
            field_deg: field_rad.to_degrees(),
        });
    }
    let bins = (field_rad.to_degrees() / 10.0).ceil().max(1.0) as usize;
    let mut theta_histogram: Vec<ThetaBin> = (0..bins)
        .map(|i| ThetaBin {
            from_deg: 10.0 * i as f64,
            to_deg: 10.0 * (i + 1) as f64,
            points: 0,
        })
        .collect();
    for theta in &thetas {
        let bin = ((theta.to_degrees() / 10.0) as usize).min(bins - 1);
        theta_histogram[bin].points += 1;
    }
    Ok(FisheyeCalibration {
        camera: fit.camera,
        rms_px: fit.rms_px,
        views: fit.views,
        outliers,
        dropped,
        max_theta_deg: max_theta.to_degrees(),
        field_deg: field_rad.to_degrees(),
        theta_histogram,
    })
}

/// Refuses a model whose θ_d(θ) stops increasing inside the half field `field_deg`: past that
/// angle rays fold back onto pixels that belong to other rays.
pub fn check_monotonic(camera: &KannalaBrandt, field_deg: f64) -> Result<(), CalibrationError> {
    let fold = camera.max_theta();
    if fold < field_deg.to_radians() - 1e-9 {
        return Err(CalibrationError::NonMonotonicDistortion {
            fold_deg: fold.to_degrees(),
            field_deg,
        });
    }
    Ok(())
}

struct Fit {
    camera: KannalaBrandt,
    rms_px: f64,
    views: Vec<ViewFit>,
}

/// Runs `fisheye::calibrate` robustly against views that are ill-conditioned only because of
/// a poor starting point. OpenCV starts from an equidistant guess (f = max(w, h) / π, no
/// distortion); under it a target near the rim of a real fish-eye is often ill-conditioned,
/// and one such view derails the whole optimisation. So the most central views (by their
/// points' mean distance from the image centre; a third of them, at least `min_views`, more if
/// too many of those are ill-conditioned) are calibrated first, and every view is then fitted starting from that result
/// (`CALIB_USE_INTRINSIC_GUESS`). A view OpenCV reports as ill-conditioned (or, when it names
/// none, the view whose absence lets it succeed) is set aside and the rest fitted; set-aside
/// views are tried once more from that fit, and those that still fail are dropped with a
/// message (at most `max_ill_conditioned` of them).
fn fit_dropping_ill_conditioned(
    views: &mut Vec<&Detection>,
    dropped: &mut Vec<DroppedView>,
    width: u32,
    height: u32,
    settings: &FisheyeSettings,
) -> Result<Fit, CalibrationError> {
    let minimum = settings.min_views.max(3);
    if views.len() < minimum {
        return Err(CalibrationError::TooFewViews {
            what: "a fish-eye calibration",
            found: views.len(),
            minimum,
        });
    }
    let order: Vec<String> = views.iter().map(|d| d.view.clone()).collect();
    let centre = glam::DVec2::new(f64::from(width) - 1.0, f64::from(height) - 1.0) / 2.0;
    let spread = |d: &Detection| {
        d.image_points
            .iter()
            .map(|p| p.distance(centre))
            .sum::<f64>()
            / d.len().max(1) as f64
    };
    let mut by_centrality = views.clone();
    by_centrality.sort_by(|a, b| spread(a).total_cmp(&spread(b)));
    // The seed grows by the next most central views until enough of it is well-conditioned.
    let mut seed_count = (views.len() / 3).max(minimum).min(views.len());
    let seed_fit = loop {
        let mut seed: Vec<&Detection> = by_centrality[..seed_count].to_vec();
        match fit_setting_aside(&mut seed, width, height, None, minimum) {
            Ok((fit, _)) => break fit,
            Err(error) if seed_count == views.len() => return Err(error),
            Err(_) => seed_count = (seed_count + 2).min(views.len()),
        }
    };

    let mut guess = seed_fit.camera;
    let mut retried = false;
    loop {
        let (fit, set_aside) = fit_setting_aside(views, width, height, Some(&guess), minimum)?;
        if set_aside.is_empty() {
            return Ok(fit);
        }
        if retried {
            if set_aside.len() > settings.max_ill_conditioned {
                let names: Vec<&str> = set_aside.iter().map(|d| d.view.as_str()).collect();
                return Err(CalibrationError::IllConditioned {
                    what: "fish-eye calibration".into(),
                    hint: format!(
                        "views {} each made the optimisation ill-conditioned; retake them with \
                         the target larger in the image, less oblique, and fully in front of the \
                         lens",
                        names.join(", ")
                    ),
                });
            }
            for view in set_aside {
                tracing::warn!(view = %view.view, "fish-eye view dropped: ill-conditioned");
                dropped.push(DroppedView {
                    view: view.view.clone(),
                    reason: "ill-conditioned: OpenCV cannot estimate the target's pose in this \
                             view (CALIB_CHECK_COND); the target is too small, too oblique, or \
                             its corners nearly collinear"
                        .into(),
                });
            }
            return Ok(fit);
        }
        guess = fit.camera;
        retried = true;
        views.extend(set_aside);
        views.sort_by_key(|d| order.iter().position(|v| *v == d.view));
    }
}

/// Fits `views`, removing (and returning) each view OpenCV reports as ill-conditioned until the
/// fit succeeds.
fn fit_setting_aside<'a>(
    views: &mut Vec<&'a Detection>,
    width: u32,
    height: u32,
    guess: Option<&KannalaBrandt>,
    minimum: usize,
) -> Result<(Fit, Vec<&'a Detection>), CalibrationError> {
    let mut set_aside = Vec::new();
    loop {
        if views.len() < minimum {
            return Err(CalibrationError::IllConditioned {
                what: "fish-eye calibration".into(),
                hint: format!(
                    "{} views are ill-conditioned and only {} remain; take more views with the \
                     target large in the image and near its centre",
                    set_aside.len(),
                    views.len()
                ),
            });
        }
        let error = match run_fisheye_calibrate(views, width, height, guess) {
            Ok(fit) => return Ok((fit, set_aside)),
            Err(CalibrationError::OpenCv(error)) if is_conditioning_failure(&error) => error,
            Err(error) => return Err(error),
        };
        let culprit = match named_view(&error.message).filter(|&i| i < views.len()) {
            Some(index) => Some(index),
            None => (0..views.len()).find(|&skip| {
                let rest: Vec<&Detection> = views
                    .iter()
                    .enumerate()
                    .filter(|&(i, _)| i != skip)
                    .map(|(_, d)| *d)
                    .collect();
                run_fisheye_calibrate(&rest, width, height, guess).is_ok()
            }),
        };
        let Some(index) = culprit else {
            return Err(CalibrationError::IllConditioned {
                what: "fish-eye calibration".into(),
                hint: format!(
                    "OpenCV: {}; no single view is to blame: take views with the target larger \
                     in the image and less oblique",
                    error.message
                ),
            });
        };
        set_aside.push(views.remove(index));
    }
}

/// Whether OpenCV gave up on a view's conditioning rather than on the input.
fn is_conditioning_failure(error: &opencv::Error) -> bool {
    let message = &error.message;
    message.contains("CALIB_CHECK_COND")
        || message.contains("Ill-conditioned")
        || message.contains("InitExtrinsics")
        || message.contains("norm_u1")
}

/// The view OpenCV names in "… Ill-conditioned matrix for input array N".
fn named_view(message: &str) -> Option<usize> {
    const MARKER: &str = "input array ";
    let at = message.find(MARKER)? + MARKER.len();
    let digits: String = message[at..]
        .chars()
        .take_while(char::is_ascii_digit)
        .collect();
    digits.parse().ok()
}

fn run_fisheye_calibrate(
    views: &[&Detection],
    width: u32,
    height: u32,
    guess: Option<&KannalaBrandt>,
) -> Result<Fit, CalibrationError> {
    let (object_points, image_points) = cv_points(views);
    let (mut k, mut d, flags) = match guess {
        Some(g) => (
            Mat::from_slice_2d(&[[g.fx, 0.0, g.cx], [0.0, g.fy, g.cy], [0.0, 0.0, 1.0]])?,
            Mat::from_slice(&[g.k1, g.k2, g.k3, g.k4])?.try_clone()?,
            FISHEYE_FLAGS | calib3d::Fisheye_CALIB_USE_INTRINSIC_GUESS,
        ),
        None => (Mat::default(), Mat::default(), FISHEYE_FLAGS),
    };
    let mut rvecs = Vector::<Mat>::new();
    let mut tvecs = Vector::<Mat>::new();
    calib3d::calibrate(
        &object_points,
        &image_points,
        Size::new(width as i32, height as i32),
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        flags,
        criteria(200, 1e-12),
    )?;
    let d = mat_values(&d)?;
    let coefficient = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let camera = KannalaBrandt {
        width,
        height,
        fx: *k.at_2d::<f64>(0, 0)?,
        fy: *k.at_2d::<f64>(1, 1)?,
        cx: *k.at_2d::<f64>(0, 2)?,
        cy: *k.at_2d::<f64>(1, 2)?,
        k1: coefficient(0),
        k2: coefficient(1),
        k3: coefficient(2),
        k4: coefficient(3),
    };
    camera.validate()?;
    let model = CameraModel::KannalaBrandt(camera);
    let mut fits = Vec::with_capacity(views.len());
    let mut sum_sq = 0.0;
    let mut count = 0usize;
    for (index, view) in views.iter().enumerate() {
        let camera_from_target = pose_from_mats(&rvecs.get(index)?, &tvecs.get(index)?)?;
        let rms_px = reprojection_rms_px(&model, view, &camera_from_target);
        sum_sq += rms_px * rms_px * view.len() as f64;
        count += view.len();
        fits.push(ViewFit {
            view: view.view.clone(),
            points: view.len(),
            rms_px,
            camera_from_target,
        });
    }
    let rms_px = (sum_sq / count.max(1) as f64).sqrt();
    if !rms_px.is_finite() {
        return Err(CalibrationError::Diverged(format!(
            "fish-eye reprojection RMS is {rms_px}"
        )));
    }
    Ok(Fit {
        camera,
        rms_px,
        views: fits,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rigid::Rigid;
    use glam::{DQuat, DVec2};
    use opencv::core::{Point2d, Point3d};

    #[test]
    fn folding_distortion_is_refused_inside_the_field() {
        let camera = KannalaBrandt {
            width: 640,
            height: 480,
            fx: 150.0,
            fy: 150.0,
            cx: 319.5,
            cy: 239.5,
            k1: -0.2,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        };
        // dθ_d/dθ = 1 − 0.6 θ² vanishes at θ = 74.0°.
        let err = check_monotonic(&camera, 92.5).unwrap_err();
        let CalibrationError::NonMonotonicDistortion { fold_deg, .. } = err else {
            panic!("{err}");
        };
        assert!((fold_deg - (1.0f64 / 0.6).sqrt().to_degrees()).abs() < 1e-6);
        assert!(check_monotonic(&camera, 70.0).is_ok());
    }

    #[test]
    fn opencv_names_the_ill_conditioned_view() {
        let message = "OpenCV(4.6.0) fisheye.cpp:1449: error: (-3:Internal error) \
                       CALIB_CHECK_COND - Ill-conditioned matrix for input array 5 in function \
                       'CalibrateExtrinsics'";
        assert_eq!(named_view(message), Some(5));
        assert_eq!(
            named_view("(-215:Assertion failed) fabs(norm_u1) > 0"),
            None
        );
    }

    /// relight's Kannala–Brandt projection is OpenCV's `fisheye::projectPoints` (same θ, same
    /// coefficients), out to 89° off the axis.
    #[test]
    fn relight_projection_matches_opencv_fisheye() {
        let camera = KannalaBrandt {
            width: 640,
            height: 480,
            fx: 150.0,
            fy: 149.0,
            cx: 321.0,
            cy: 238.5,
            k1: -0.012,
            k2: 0.006,
            k3: -0.0021,
            k4: 0.0004,
        };
        let pose = Rigid::new(
            DQuat::from_scaled_axis(DVec3::new(0.1, -0.2, 0.05)),
            DVec3::new(0.02, -0.01, 0.1),
        );
        let mut points = Vector::<Point3d>::new();
        let mut expected = Vec::new();
        for i in 0..40 {
            let theta = (89.0 * i as f64 / 39.0).to_radians();
            let phi = 0.7 * i as f64;
            let direction = DVec3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            );
            let in_camera = direction * (0.3 + 0.01 * i as f64);
            let in_target = pose.inverse().transform_point(in_camera);
            points.push(Point3d::new(in_target.x, in_target.y, in_target.z));
            expected.push(camera.project(in_camera).unwrap());
        }
        let k = Mat::from_slice_2d(&[
            [camera.fx, 0.0, camera.cx],
            [0.0, camera.fy, camera.cy],
            [0.0, 0.0, 1.0],
        ])
        .unwrap();
        let d = Mat::from_slice(&[camera.k1, camera.k2, camera.k3, camera.k4])
            .unwrap()
            .try_clone()
            .unwrap();
        let rvec = Mat::from_slice(&pose.rvec()).unwrap().try_clone().unwrap();
        let tvec = Mat::from_slice(&pose.tvec()).unwrap().try_clone().unwrap();
        let mut projected = Vector::<Point2d>::new();
        calib3d::fisheye_project_points_vec_def(&points, &mut projected, &rvec, &tvec, &k, &d)
            .unwrap();
        for (p, e) in projected.iter().zip(&expected) {
            let p = DVec2::new(p.x, p.y);
            assert!(p.distance(*e) < 1e-6, "OpenCV {p} relight {e}");
        }
    }
}
