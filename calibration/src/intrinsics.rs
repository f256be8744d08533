//! Pinhole intrinsics with Brown–Conrady distortion: `cv::calibrateCamera` (Zhang, "A Flexible
//! New Technique for Camera Calibration", PAMI 2000: closed-form start from the views'
//! homographies, then Levenberg–Marquardt on the reprojection error over all views).
//!
//! # Flags
//!
//! By default every parameter of relight's [`Pinhole`] is estimated: fx, fy, cx, cy and
//! k1, k2, p1, p2, k3 (OpenCV's 5-coefficient model; flags 0). [`PinholeSettings`] can fix
//! k3 (`CALIB_FIX_K3`: lenses with little distortion, or few views near the corners, where
//! k3 over-fits), zero the tangential terms (`CALIB_ZERO_TANGENT_DIST`) or fix fx/fy
//! (`CALIB_FIX_ASPECT_RATIO`).
//!
//! # Reports
//!
//! The overall and per-view reprojection RMS, each view's pose, the intrinsics' standard
//! deviations, and the outlier views (RMS above `outlier_factor` × the median and above
//! `outlier_floor_px`), which are dropped and the calibration re-run once when
//! `drop_outliers` is set. A fit whose distortion folds back inside the image (the polynomial
//! stops increasing before the corners: over-fitting k3 without corner views) is refused.

use glam::{DVec2, DVec3};
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;
use relight_core::camera::{CameraModel, Pinhole};

use crate::detect::{Detection, common_size};
use crate::error::CalibrationError;
use crate::rigid::Rigid;

/// Options of [`calibrate_pinhole`].
#[derive(Debug, Clone, PartialEq)]
pub struct PinholeSettings {
    /// Keep k3 at zero (`CALIB_FIX_K3`).
    pub fix_k3: bool,
    /// Keep p1, p2 at zero (`CALIB_ZERO_TANGENT_DIST`).
    pub zero_tangential: bool,
    /// Keep fx / fy at 1 (`CALIB_FIX_ASPECT_RATIO`).
    pub fix_aspect_ratio: bool,
    /// A view is an outlier when its RMS exceeds this many times the median view RMS …
    pub outlier_factor: f64,
    /// … and this many pixels (views that all fit to a few hundredths of a pixel are fine).
    pub outlier_floor_px: f64,
    /// Drop outlier views and calibrate again (once).
    pub drop_outliers: bool,
    /// Fewest views to calibrate from.
    pub min_views: usize,
    /// Views with fewer points are skipped (a homography needs 4; fewer than 8 are easily
    /// near-collinear).
    pub min_points_per_view: usize,
}

impl Default for PinholeSettings {
    fn default() -> Self {
        Self {
            fix_k3: false,
            zero_tangential: false,
            fix_aspect_ratio: false,
            outlier_factor: 3.0,
            outlier_floor_px: 0.3,
            drop_outliers: true,
            min_views: 6,
            min_points_per_view: 8,
        }
    }
}

impl PinholeSettings {
    /// OpenCV's `calibrateCamera` flags for these settings.
    pub fn flags(&self) -> i32 {
        let mut flags = 0;
        if self.fix_k3 {
            flags |= calib3d::CALIB_FIX_K3;
        }
        if self.zero_tangential {
            flags |= calib3d::CALIB_ZERO_TANGENT_DIST;
        }
        if self.fix_aspect_ratio {
            flags |= calib3d::CALIB_FIX_ASPECT_RATIO;
        }
        flags
    }
}

/// How well one view fits the calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewFit {
    pub view: String,
    pub points: usize,
    pub rms_px: f64,
    /// The target's pose in this view (optical frame).
    pub camera_from_target: Rigid,
}

/// A view whose reprojection RMS stands out.
#[derive(Debug, Clone, PartialEq)]
pub struct OutlierView {
    pub view: String,
    pub rms_px: f64,
    /// The threshold it exceeded (factor × median, at least the floor).
    pub threshold_px: f64,
}

/// A view left out of the final fit, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct DroppedView {
    pub view: String,
    pub reason: String,
}

/// One standard deviation of each estimated intrinsic (zero for a fixed one).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PinholeStdDev {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

/// Result of [`calibrate_pinhole`].
#[derive(Debug, Clone, PartialEq)]
pub struct PinholeCalibration {
    pub camera: Pinhole,
    /// RMS reprojection error over all points of the views used.
    pub rms_px: f64,
    /// The views used, in input order.
    pub views: Vec<ViewFit>,
    /// Outliers of the first fit (dropped when `drop_outliers` was set, listed either way).
    pub outliers: Vec<OutlierView>,
    /// Views not in the final fit: too few points, or dropped as outliers.
    pub dropped: Vec<DroppedView>,
    pub std_dev: PinholeStdDev,
    /// The `calibrateCamera` flags used.
    pub flags: i32,
}

/// Calibrates a pinhole camera from its detections (one camera, one resolution).
pub fn calibrate_pinhole(
    detections: &[Detection],
    settings: &PinholeSettings,
) -> Result<PinholeCalibration, CalibrationError> {
    let (width, height) = common_size(detections)?;
    let (usable, mut dropped) = usable_views(detections, settings.min_points_per_view);
    let first = run_calibrate_camera(&usable, width, height, settings)?;
    let outliers = find_outliers(
        &first.views,
        settings.outlier_factor,
        settings.outlier_floor_px,
    );
    let result = if settings.drop_outliers && !outliers.is_empty() {
        let kept: Vec<&Detection> = usable
            .iter()
            .copied()
            .filter(|d| !outliers.iter().any(|o| o.view == d.view))
            .collect();
        if kept.len() >= settings.min_views {
            dropped.extend(outliers.iter().map(|o| DroppedView {
                view: o.view.clone(),
                reason: format!(
                    "outlier: reprojection RMS {:.3} px > {:.3} px",
                    o.rms_px, o.threshold_px
                ),
            }));
            run_calibrate_camera(&kept, width, height, settings)?
        } else {
            first
        }
    } else {
        first
    };
    Ok(PinholeCalibration {
        camera: result.camera,
        rms_px: result.rms_px,
        views: result.views,
        outliers,
        dropped,
        std_dev: result.std_dev,
        flags: settings.flags(),
    })
}

/// Splits off the views with too few points (reported as dropped).
pub(crate) fn usable_views(
    detections: &[Detection],
    min_points: usize,
) -> (Vec<&Detection>, Vec<DroppedView>) {
    let mut usable = Vec::with_capacity(detections.len());
    let mut dropped = Vec::new();
    for detection in detections {
        if detection.len() >= min_points.max(4) {
            usable.push(detection);
        } else {
            dropped.push(DroppedView {
                view: detection.view.clone(),
                reason: format!(
                    "{} points, at least {} needed",
                    detection.len(),
                    min_points.max(4)
                ),
            });
        }
    }
    (usable, dropped)
}

/// Views whose RMS exceeds `factor` × the median view RMS and `floor_px`.
pub(crate) fn find_outliers(views: &[ViewFit], factor: f64, floor_px: f64) -> Vec<OutlierView> {
    let mut rms: Vec<f64> = views
        .iter()
        .map(|v| v.rms_px)
        .filter(|r| r.is_finite())
        .collect();
    if rms.is_empty() {
        return Vec::new();
    }
    rms.sort_by(f64::total_cmp);
    let middle = rms.len() / 2;
    let median = if rms.len() % 2 == 1 {
        rms[middle]
    } else {
        0.5 * (rms[middle - 1] + rms[middle])
    };
    let threshold_px = (factor * median).max(floor_px);
    views
        .iter()
        .filter(|v| v.rms_px.is_nan() || v.rms_px > threshold_px)
        .map(|v| OutlierView {
            view: v.view.clone(),
            rms_px: v.rms_px,
            threshold_px,
        })
        .collect()
}

struct Fit {
    camera: Pinhole,
    rms_px: f64,
    views: Vec<ViewFit>,
    std_dev: PinholeStdDev,
}

fn run_calibrate_camera(
    views: &[&Detection],
    width: u32,
    height: u32,
    settings: &PinholeSettings,
) -> Result<Fit, CalibrationError> {
    if views.len() < settings.min_views.max(3) {
        return Err(CalibrationError::TooFewViews {
            what: "a pinhole calibration",
            found: views.len(),
            minimum: settings.min_views.max(3),
        });
    }
    let (object_points, image_points) = cv_points(views);
    let mut k = Mat::default();
    let mut d = Mat::default();
    let mut rvecs = Vector::<Mat>::new();
    let mut tvecs = Vector::<Mat>::new();
    let mut std_intrinsics = Mat::default();
    let mut std_extrinsics = Mat::default();
    let mut per_view = Mat::default();
    let rms_px = calib3d::calibrate_camera_extended(
        &object_points,
        &image_points,
        Size::new(width as i32, height as i32),
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        &mut std_intrinsics,
        &mut std_extrinsics,
        &mut per_view,
        settings.flags(),
        criteria(100, f64::EPSILON),
    )?;
    let at = |m: &Mat, i: usize| -> Result<f64, CalibrationError> {
        Ok(mat_values(m)?.get(i).copied().unwrap_or(0.0))
    };
    let camera = Pinhole {
        width,
        height,
        fx: *k.at_2d::<f64>(0, 0)?,
        fy: *k.at_2d::<f64>(1, 1)?,
        cx: *k.at_2d::<f64>(0, 2)?,
        cy: *k.at_2d::<f64>(1, 2)?,
        k1: at(&d, 0)?,
        k2: at(&d, 1)?,
        p1: at(&d, 2)?,
        p2: at(&d, 3)?,
        k3: at(&d, 4)?,
    };
    check_pinhole(&camera, rms_px)?;
    let std_dev = PinholeStdDev {
        fx: at(&std_intrinsics, 0)?,
        fy: at(&std_intrinsics, 1)?,
        cx: at(&std_intrinsics, 2)?,
        cy: at(&std_intrinsics, 3)?,
        k1: at(&std_intrinsics, 4)?,
        k2: at(&std_intrinsics, 5)?,
        p1: at(&std_intrinsics, 6)?,
        p2: at(&std_intrinsics, 7)?,
        k3: at(&std_intrinsics, 8)?,
    };
    let per_view = mat_values(&per_view)?;
    let mut fits = Vec::with_capacity(views.len());
    for (index, view) in views.iter().enumerate() {
        fits.push(ViewFit {
            view: view.view.clone(),
            points: view.len(),
            rms_px: per_view.get(index).copied().unwrap_or(f64::NAN),
            camera_from_target: pose_from_mats(&rvecs.get(index)?, &tvecs.get(index)?)?,
        });
    }
    Ok(Fit {
        camera,
        rms_px,
        views: fits,
        std_dev,
    })
}

/// Refuses a non-finite fit, and one whose distortion folds back inside the image.
fn check_pinhole(camera: &Pinhole, rms_px: f64) -> Result<(), CalibrationError> {
    if !rms_px.is_finite() {
        return Err(CalibrationError::Diverged(format!(
            "reprojection RMS is {rms_px}"
        )));
    }
    camera.validate()?;
    let model = CameraModel::Pinhole(*camera);
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let corners = [
        DVec2::new(-0.5, -0.5),
        DVec2::new(w - 0.5, -0.5),
        DVec2::new(-0.5, h - 0.5),
        DVec2::new(w - 0.5, h - 0.5),
    ];
    if let Some(corner) = corners.iter().find(|&&c| model.unproject(c).is_none()) {
        return Err(CalibrationError::IllConditioned {
            what: "pinhole distortion".into(),
            hint: format!(
                "the fitted radial polynomial (k1 {:.4}, k2 {:.4}, k3 {:.4}) folds back before \
                 the image corner {corner}; add views with the target in the image corners, or \
                 fix k3",
                camera.k1, camera.k2, camera.k3
            ),
        });
    }
    Ok(())
}

/// OpenCV termination criteria: at most `count` iterations or a step below `epsilon`.
pub(crate) fn criteria(count: i32, epsilon: f64) -> TermCriteria {
    TermCriteria {
        typ: TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        max_count: count,
        epsilon,
    }
}

/// Object and image points of the views as OpenCV wants them (f32: 1e-7 relative, far below
/// any detector's accuracy).
pub(crate) fn cv_points(
    views: &[&Detection],
) -> (Vector<Vector<Point3f>>, Vector<Vector<Point2f>>) {
    let mut object_points = Vector::<Vector<Point3f>>::new();
    let mut image_points = Vector::<Vector<Point2f>>::new();
    for view in views {
        object_points.push(
            view.object_points
                .iter()
                .map(|p| Point3f::new(p.x as f32, p.y as f32, p.z as f32))
                .collect(),
        );
        image_points.push(
            view.image_points
                .iter()
                .map(|p| Point2f::new(p.x as f32, p.y as f32))
                .collect(),
        );
    }
    (object_points, image_points)
}

/// Every element of a continuous `f64` matrix, row-major.
pub(crate) fn mat_values(mat: &Mat) -> Result<Vec<f64>, CalibrationError> {
    if mat.empty() {
        return Ok(Vec::new());
    }
    let mat = if mat.is_continuous() {
        mat.try_clone()?
    } else {
        let mut copy = Mat::default();
        mat.copy_to(&mut copy)?;
        copy
    };
    Ok(mat.data_typed::<f64>()?.to_vec())
}

/// `camera_from_target` from OpenCV's rotation and translation vectors.
pub(crate) fn pose_from_mats(rvec: &Mat, tvec: &Mat) -> Result<Rigid, CalibrationError> {
    let r = mat_values(rvec)?;
    let t = mat_values(tvec)?;
    if r.len() != 3 || t.len() != 3 {
        return Err(CalibrationError::Diverged(format!(
            "OpenCV returned a pose with {} + {} values",
            r.len(),
            t.len()
        )));
    }
    Ok(Rigid::from_rvec_tvec(
        [r[0], r[1], r[2]],
        [t[0], t[1], t[2]],
    ))
}

/// RMS distance between a view's points and their projection through `camera` at the view's
/// pose: the reprojection error as relight's own model computes it.
pub fn reprojection_rms_px(
    camera: &CameraModel,
    detection: &Detection,
    camera_from_target: &Rigid,
) -> f64 {
    let mut sum_sq = 0.0;
    for (object, image) in detection.object_points.iter().zip(&detection.image_points) {
        let p: DVec3 = camera_from_target.transform_point(*object);
        sum_sq += match camera.project(p) {
            Some(pixel) => pixel.distance_squared(*image),
            None => f64::INFINITY,
        };
    }
    (sum_sq / detection.len().max(1) as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fit(view: &str, rms_px: f64) -> ViewFit {
        ViewFit {
            view: view.into(),
            points: 10,
            rms_px,
            camera_from_target: Rigid::IDENTITY,
        }
    }

    #[test]
    fn outliers_stand_out_from_the_median_and_the_floor() {
        let views = [fit("a", 0.2), fit("b", 0.25), fit("c", 0.22), fit("d", 1.4)];
        let outliers = find_outliers(&views, 3.0, 0.3);
        assert_eq!(outliers.len(), 1);
        assert_eq!(outliers[0].view, "d");
        // Median of 0.2, 0.22, 0.25, 1.4 is 0.235.
        assert!((outliers[0].threshold_px - 0.705).abs() < 1e-12);
        // All views fit to hundredths of a pixel: nothing is an outlier.
        let tight = [fit("a", 0.01), fit("b", 0.012), fit("c", 0.05)];
        assert!(find_outliers(&tight, 3.0, 0.3).is_empty());
        // A NaN RMS is an outlier.
        let broken = [fit("a", 0.2), fit("b", f64::NAN), fit("c", 0.2)];
        assert_eq!(find_outliers(&broken, 3.0, 0.3).len(), 1);
    }

    #[test]
    fn flags_follow_the_settings() {
        assert_eq!(PinholeSettings::default().flags(), 0);
        let settings = PinholeSettings {
            fix_k3: true,
            zero_tangential: true,
            ..PinholeSettings::default()
        };
        assert_eq!(
            settings.flags(),
            calib3d::CALIB_FIX_K3 | calib3d::CALIB_ZERO_TANGENT_DIST
        );
    }
}
