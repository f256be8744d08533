//! Fish-eye calibration on synthetic views of known truth: chessboard and ChArUco.
#![cfg(feature = "opencv")]

mod support;

use std::time::Instant;

use relight_calibrate::CalibrationError;
use relight_calibrate::detect::Detection;
use relight_calibrate::fisheye::{FisheyeSettings, calibrate_fisheye};
use relight_calibrate::synth::{
    Alignment, RenderSettings, SynthCamera, ViewPlan, model_difference, plan_views, with_noise,
};
use relight_calibrate::target::{Charuco, Chessboard, Dictionary, Target, TargetGeometry};
use relight_core::camera::{CameraModel, KannalaBrandt};

/// A 185° circular fish-eye like relight's light probe, on a 640 × 480 sensor.
fn truth() -> KannalaBrandt {
    KannalaBrandt {
        width: 640,
        height: 480,
        fx: 144.0,
        fy: 144.3,
        cx: 320.8,
        cy: 238.7,
        k1: -0.01,
        k2: 0.005,
        k3: -0.002,
        k4: 0.0005,
    }
}

fn check(geometry: &TargetGeometry) {
    let camera = truth();
    let found = support::detections(geometry, CameraModel::KannalaBrandt(camera), 20);
    let t = Instant::now();
    let settings = FisheyeSettings {
        field_of_view_deg: Some(185.0),
        ..FisheyeSettings::default()
    };
    let calibration = calibrate_fisheye(&found, &settings).unwrap();
    let c = calibration.camera;
    // Over the measured field and over the lens's whole 185° field (extrapolated past the
    // largest angle a corner was seen at).
    let measured = model_difference(
        &CameraModel::KannalaBrandt(camera),
        &CameraModel::KannalaBrandt(c),
        4.0,
        Some(calibration.max_theta_deg.to_radians()),
        Alignment::Rotation,
    );
    let diff = model_difference(
        &CameraModel::KannalaBrandt(camera),
        &CameraModel::KannalaBrandt(c),
        4.0,
        Some(92.5f64.to_radians()),
        Alignment::Rotation,
    );
    eprintln!(
        "calibrate {:.2} s; rms {:.4} px; max θ {:.1}°; dropped {:?}; fx {:.3} ({:+.4} %), fy {:.3} ({:+.4} %), cx {:.3} ({:+.3} px), cy {:.3} ({:+.3} px); k {:.5} {:.5} {:.5} {:.5}; reprojection up to {:.1}° max {:.4} px; over the 185° field max {:.4} px rms {:.4} px at {} after a {:.4}° turn",
        t.elapsed().as_secs_f64(),
        calibration.rms_px,
        calibration.max_theta_deg,
        calibration.dropped,
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
        c.k3,
        c.k4,
        calibration.max_theta_deg,
        measured.max_px,
        diff.max_px,
        diff.rms_px,
        diff.worst_pixel,
        diff.alignment_deg
    );
    assert!((c.fx / camera.fx - 1.0).abs() < 0.005);
    assert!((c.fy / camera.fy - 1.0).abs() < 0.005);
    assert!((c.cx / camera.cx - 1.0).abs() < 0.005);
    assert!((c.cy / camera.cy - 1.0).abs() < 0.005);
    assert!(diff.max_px < 0.1, "{diff:?}");
}

#[test]
fn chessboard_recovers_fisheye_truth() {
    check(&chessboard());
}

#[test]
fn charuco_recovers_fisheye_truth() {
    // Few, large squares: a fish-eye shows a target small, and ChArUco corners need room
    // between the markers to be located well.
    let geometry = Target::Charuco(Charuco {
        squares_x: 7,
        squares_y: 5,
        square_m: 0.05,
        marker_m: 0.03,
        dictionary: Dictionary::Aruco { bits: 4, count: 50 },
    })
    .geometry()
    .unwrap();
    check(&geometry);
}

/// Perfect detections of planned views with 0.02 px of noise.
fn ideal_views(geometry: &TargetGeometry, plan: &ViewPlan) -> Vec<Detection> {
    let model = CameraModel::KannalaBrandt(truth());
    let synth = SynthCamera::new(model, RenderSettings::default()).unwrap();
    plan_views(&model, geometry, plan)
        .iter()
        .enumerate()
        .map(|(i, pose)| {
            with_noise(
                &synth.ideal_detection(&format!("probe-{i:02}.png"), geometry, pose),
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
fn views_that_stay_near_the_centre_leave_the_rim_uncovered() {
    let views = ideal_views(
        &chessboard(),
        &ViewPlan {
            max_theta_deg: 45.0,
            ..ViewPlan::default()
        },
    );
    let settings = FisheyeSettings {
        field_of_view_deg: Some(185.0),
        ..FisheyeSettings::default()
    };
    let err = calibrate_fisheye(&views, &settings).unwrap_err();
    let CalibrationError::RimNotCovered {
        max_theta_deg,
        required_deg,
        ..
    } = err
    else {
        panic!("{err}");
    };
    assert!(max_theta_deg <= 45.0 && required_deg > 75.0, "{err}");
    assert!(
        err.to_string().contains("edge of the image circle"),
        "{err}"
    );
    // Asked for less, the same views calibrate.
    let relaxed = FisheyeSettings {
        rim_coverage: 0.0,
        ..settings
    };
    assert!(calibrate_fisheye(&views, &relaxed).is_ok());
}

#[test]
fn an_ill_conditioned_view_is_dropped_by_name() {
    let mut views = ideal_views(&chessboard(), &ViewPlan::default());
    // A view in which only one row of corners was found: collinear points fix no pose.
    let mut row = views[7].clone();
    row.view = "one-row.png".into();
    let keep: Vec<usize> = (0..row.len()).filter(|&i| row.ids[i] < 9).collect();
    row.ids = keep.iter().map(|&i| row.ids[i]).collect();
    row.image_points = keep.iter().map(|&i| row.image_points[i]).collect();
    row.object_points = keep.iter().map(|&i| row.object_points[i]).collect();
    views.insert(3, row);
    let calibration = calibrate_fisheye(
        &views,
        &FisheyeSettings {
            field_of_view_deg: Some(185.0),
            ..FisheyeSettings::default()
        },
    )
    .unwrap();
    let dropped: Vec<String> = calibration
        .dropped
        .iter()
        .map(|d| format!("{}: {}", d.view, d.reason))
        .collect();
    assert!(
        dropped
            .iter()
            .any(|d| d.starts_with("one-row.png: ill-conditioned")),
        "{dropped:?}"
    );
    assert_eq!(calibration.views.len(), views.len() - 1);
    // The rest calibrate as if the view had never been there (over the field the corners
    // reach: these views carry 0.02 px of noise, which the extrapolation to the rim amplifies).
    let diff = model_difference(
        &CameraModel::KannalaBrandt(truth()),
        &CameraModel::KannalaBrandt(calibration.camera),
        8.0,
        Some(calibration.max_theta_deg.to_radians()),
        Alignment::Rotation,
    );
    assert!(diff.max_px < 0.1, "{diff:?}");
}
