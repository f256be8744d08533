//! Pinhole calibration on synthetic views of known truth: chessboard and ChArUco.
#![cfg(feature = "opencv")]

mod support;

use std::time::Instant;

use relight_calibrate::CalibrationError;
use relight_calibrate::detect::{Detection, Detector};
use relight_calibrate::intrinsics::{PinholeSettings, calibrate_pinhole};
use relight_calibrate::synth::{
    Alignment, RenderSettings, SynthCamera, ViewPlan, model_difference, plan_views, with_noise,
};
use relight_calibrate::target::{
    AprilGrid, Charuco, Chessboard, Dictionary, Target, TargetGeometry,
};
use relight_core::camera::{CameraModel, Pinhole};

fn truth() -> Pinhole {
    Pinhole {
        width: 640,
        height: 480,
        fx: 528.0,
        fy: 526.0,
        cx: 323.2,
        cy: 236.9,
        k1: -0.25,
        k2: 0.08,
        p1: 5e-4,
        p2: -3e-4,
        k3: -0.01,
    }
}

fn check(geometry: &TargetGeometry) {
    let camera = truth();
    let found = support::detections(geometry, CameraModel::Pinhole(camera), 18);
    let t = Instant::now();
    let calibration = calibrate_pinhole(&found, &PinholeSettings::default()).unwrap();
    let c = calibration.camera;
    let raw = model_difference(
        &CameraModel::Pinhole(camera),
        &CameraModel::Pinhole(c),
        4.0,
        None,
        Alignment::None,
    );
    let diff = model_difference(
        &CameraModel::Pinhole(camera),
        &CameraModel::Pinhole(c),
        4.0,
        None,
        Alignment::Rotation,
    );
    eprintln!(
        "calibrate {:.2} s; rms {:.4} px; fx {:.3} ({:+.4} %), fy {:.3} ({:+.4} %), cx {:.3} ({:+.3} px), cy {:.3} ({:+.3} px); k {:.4} {:.4} {:.5} {:.5} {:.4}; reprojection over the image max {:.4} px rms {:.4} px at {} after a {:.4}° turn (unaligned max {:.4} px)",
        t.elapsed().as_secs_f64(),
        calibration.rms_px,
        c.fx,
        100.0 * (c.fx / camera.fx - 1.0),
        c.fy,
        100.0 * (c.fy / camera.fy - 1.0),
        c.cx,
        c.cx - camera.cx,
        c.cy,
        c.cy - camera.cy,
        c.k1,
        c.k2,
        c.p1,
        c.p2,
        c.k3,
        diff.max_px,
        diff.rms_px,
        diff.worst_pixel,
        diff.alignment_deg,
        raw.max_px
    );
    assert!((c.fx / camera.fx - 1.0).abs() < 0.005);
    assert!((c.fy / camera.fy - 1.0).abs() < 0.005);
    assert!((c.cx / camera.cx - 1.0).abs() < 0.005);
    assert!((c.cy / camera.cy - 1.0).abs() < 0.005);
    assert!(diff.max_px < 0.1, "{diff:?}");
}

#[test]
fn chessboard_recovers_pinhole_truth() {
    check(&chessboard());
}

#[test]
fn charuco_recovers_pinhole_truth() {
    let geometry = Target::Charuco(Charuco {
        squares_x: 9,
        squares_y: 7,
        square_m: 0.03,
        marker_m: 0.022,
        dictionary: Dictionary::Aruco { bits: 4, count: 50 },
    })
    .geometry()
    .unwrap();
    check(&geometry);
}

/// Perfect detections of planned views with 0.02 px of noise: what a calibration sees without
/// rendering.
fn ideal_views(geometry: &TargetGeometry, camera: &Pinhole, count: usize) -> Vec<Detection> {
    let model = CameraModel::Pinhole(*camera);
    let synth = SynthCamera::new(model, RenderSettings::default()).unwrap();
    plan_views(
        &model,
        geometry,
        &ViewPlan {
            count,
            ..ViewPlan::default()
        },
    )
    .iter()
    .enumerate()
    .map(|(i, pose)| {
        with_noise(
            &synth.ideal_detection(&format!("view-{i:02}.png"), geometry, pose),
            0.02,
            i as u64,
        )
    })
    .collect()
}

fn chessboard() -> TargetGeometry {
    Target::Chessboard(Chessboard {
        inner_cols: 9,
        inner_rows: 6,
        square_m: 0.03,
    })
    .geometry()
    .unwrap()
}

#[test]
fn outlier_view_is_reported_and_dropped() {
    let camera = truth();
    let mut views = ideal_views(&chessboard(), &camera, 12);
    // One view whose corners are 1 px off (a mis-detection, a moved target).
    views[5] = with_noise(&views[5], 1.0, 99);
    views[5].view = "shaken.png".into();
    let calibration = calibrate_pinhole(&views, &PinholeSettings::default()).unwrap();
    assert_eq!(calibration.outliers.len(), 1, "{:?}", calibration.outliers);
    assert_eq!(calibration.outliers[0].view, "shaken.png");
    assert!(
        calibration
            .dropped
            .iter()
            .any(|d| d.view == "shaken.png" && d.reason.contains("outlier"))
    );
    assert_eq!(calibration.views.len(), 11);
    assert!(calibration.rms_px < 0.05, "{}", calibration.rms_px);
    // Kept, the view spoils the fit.
    let kept = calibrate_pinhole(
        &views,
        &PinholeSettings {
            drop_outliers: false,
            ..PinholeSettings::default()
        },
    )
    .unwrap();
    assert_eq!(kept.views.len(), 12);
    assert!(kept.rms_px > 3.0 * calibration.rms_px);
}

#[test]
fn too_few_views_and_mixed_sizes_are_refused_by_name() {
    let camera = truth();
    let views = ideal_views(&chessboard(), &camera, 4);
    let err = calibrate_pinhole(&views, &PinholeSettings::default()).unwrap_err();
    assert!(
        matches!(
            err,
            CalibrationError::TooFewViews {
                found: 4,
                minimum: 6,
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("at least 6"), "{err}");

    let mut views = ideal_views(&chessboard(), &camera, 8);
    views[3].width = 1280;
    views[3].height = 960;
    let err = calibrate_pinhole(&views, &PinholeSettings::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("view-00.png")
            && err.contains("640x480")
            && err.contains("view-03.png")
            && err.contains("1280x960"),
        "{err}"
    );
}

#[test]
fn april_grid_corners_are_found_where_the_truth_puts_them() {
    let geometry = Target::AprilGrid(AprilGrid {
        cols: 5,
        rows: 4,
        tag_m: 0.045,
        spacing_m: 0.015,
        first_id: 0,
    })
    .geometry()
    .unwrap();
    let camera = CameraModel::Pinhole(truth());
    let synth = SynthCamera::new(camera, RenderSettings::default()).unwrap();
    let detector = Detector::new(&geometry).unwrap();
    let poses = plan_views(
        &camera,
        &geometry,
        &ViewPlan {
            count: 6,
            ..ViewPlan::default()
        },
    );
    let (mut sum_sq, mut found, mut visible) = (0.0, 0usize, 0usize);
    for (i, pose) in poses.iter().enumerate() {
        let image = synth.render_target(&geometry, pose);
        let detection = detector.detect(&format!("grid-{i}"), &image).unwrap();
        let truth = synth.visible_points(&geometry, pose);
        visible += truth.len();
        for (id, pixel) in detection.ids.iter().zip(&detection.image_points) {
            let (_, expected) = truth
                .iter()
                .find(|(t, _)| t == id)
                .unwrap_or_else(|| panic!("grid-{i}: id {id} is not in view"));
            sum_sq += pixel.distance_squared(*expected);
            found += 1;
        }
    }
    let rms = (sum_sq / found as f64).sqrt();
    eprintln!("AprilTag grid: {found} of {visible} corners, RMS {rms:.4} px from the truth");
    assert!(found * 10 >= visible * 7, "{found} of {visible}");
    assert!(rms < 0.1, "{rms}");
}
