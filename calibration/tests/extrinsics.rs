//! Rig extrinsics on synthetic views of known truth: depth ↔ colour registration, the probe's
//! pose in the world, the lamp's light centre. The truth is set up with relight's own frame
//! conventions (glTF camera frames, `Pose`, `optical_from_gl`), independently of the library's
//! conversions, and each test ends with a check that goes through the conventions end to end.
#![cfg(feature = "opencv")]

use std::f32::consts::PI;

use glam::{DVec3, Quat, Vec3};
use relight_calibrate::detect::{Detection, Detector};
use relight_calibrate::extrinsics::{
    LampMarker, calibrate_color_from_depth, locate_lamp_light, locate_probe, observe_lamp,
};
use relight_calibrate::fisheye::{FisheyeSettings, calibrate_fisheye};
use relight_calibrate::intrinsics::{PinholeSettings, calibrate_pinhole};
use relight_calibrate::rigid::Rigid;
use relight_calibrate::synth::{
    PlacedTarget, RenderSettings, Scene, Sphere, SynthCamera, ViewPlan, plan_views,
};
use relight_calibrate::target::{
    AprilGrid, Charuco, Chessboard, Dictionary, Target, TargetGeometry,
};
use relight_core::Pose;
use relight_core::camera::{
    CameraModel, KannalaBrandt, OPTICAL_FROM_GL_ROTATION, Pinhole, optical_from_gl,
};

/// Kinect-like IR (depth) camera.
fn depth_camera() -> Pinhole {
    Pinhole {
        width: 640,
        height: 480,
        fx: 575.0,
        fy: 574.0,
        cx: 317.4,
        cy: 242.1,
        k1: -0.12,
        k2: 0.06,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    }
}

fn color_camera() -> Pinhole {
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

fn probe_camera() -> KannalaBrandt {
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

/// `optical_from_gl` as a relight pose.
fn optical_from_gl_pose() -> Pose {
    Pose::new(OPTICAL_FROM_GL_ROTATION, Vec3::ZERO)
}

fn to_rigid(pose: &Pose) -> Rigid {
    Rigid::from_pose(pose)
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

fn charuco(squares_x: u32, squares_y: u32, square_m: f64, marker_m: f64) -> TargetGeometry {
    Target::Charuco(Charuco {
        squares_x,
        squares_y,
        square_m,
        marker_m,
        dictionary: Dictionary::Aruco { bits: 4, count: 50 },
    })
    .geometry()
    .unwrap()
}

/// Position and orientation errors between two relight poses, millimetres and degrees (in f64:
/// f32's `acos` cannot resolve angles below ~0.02°).
fn pose_error(a: &Pose, b: &Pose) -> (f64, f64) {
    let (a, b) = (to_rigid(a), to_rigid(b));
    (a.translation_error_m(&b) * 1000.0, a.rotation_error_deg(&b))
}

fn depth_to_color(geometry: &TargetGeometry) {
    // The colour camera 2.5 cm to the depth camera's left as the rig looks (its −X), slightly
    // turned: glTF frames, as RigCalibration stores it.
    let truth = Pose::new(
        Quat::from_euler(
            glam::EulerRot::XYZ,
            0.4f32.to_radians(),
            -0.6f32.to_radians(),
            0.3f32.to_radians(),
        ),
        Vec3::new(-0.025, 0.0012, 0.0008),
    );
    let color_optical_from_depth_optical =
        to_rigid(&(optical_from_gl_pose() * truth * optical_from_gl_pose()));
    let (depth, color) = (depth_camera(), color_camera());
    let depth_synth =
        SynthCamera::new(CameraModel::Pinhole(depth), RenderSettings::default()).unwrap();
    let color_synth = SynthCamera::new(
        CameraModel::Pinhole(color),
        RenderSettings {
            format: relight_core::PixelFormat::Rgb8,
            ..RenderSettings::default()
        },
    )
    .unwrap();
    let poses = plan_views(
        &CameraModel::Pinhole(depth),
        geometry,
        &ViewPlan {
            count: 16,
            ..ViewPlan::default()
        },
    );
    let detector = Detector::new(geometry).unwrap();
    let mut pairs: Vec<(Detection, Detection)> = Vec::new();
    for (i, depth_from_target) in poses.iter().enumerate() {
        let color_from_target = color_optical_from_depth_optical * *depth_from_target;
        let ir = depth_synth.render_target(geometry, depth_from_target);
        let rgb = color_synth.render_target(geometry, &color_from_target);
        let (Ok(in_depth), Ok(in_color)) = (
            detector.detect(&format!("ir-{i:02}.png"), &ir),
            detector.detect(&format!("rgb-{i:02}.png"), &rgb),
        ) else {
            continue;
        };
        pairs.push((in_depth, in_color));
    }
    let depth_views: Vec<Detection> = pairs.iter().map(|(d, _)| d.clone()).collect();
    let color_views: Vec<Detection> = pairs.iter().map(|(_, c)| c.clone()).collect();
    let depth_fit = calibrate_pinhole(&depth_views, &PinholeSettings::default()).unwrap();
    let color_fit = calibrate_pinhole(&color_views, &PinholeSettings::default()).unwrap();
    let stereo = calibrate_color_from_depth(&depth_fit.camera, &color_fit.camera, &pairs).unwrap();
    let (mm, deg) = pose_error(&stereo.color_from_depth, &truth);
    eprintln!(
        "{}: {} pairs, stereo RMS {:.4} px; colour_from_depth off by {mm:.3} mm, {deg:.4}°",
        geometry.target().describe(),
        stereo.pairs.len(),
        stereo.rms_px
    );
    assert!(stereo.pairs.len() >= 8, "{}", stereo.pairs.len());
    assert!(mm < 2.0 && deg < 0.2, "{mm} mm, {deg}°");

    // End to end: a point 0.8 m in front of the depth camera (glTF: −Z), moved into the colour
    // camera with the calibration, lands on the colour pixel where the truth puts it.
    let point_in_depth = Vec3::new(0.12, -0.07, -0.8);
    let pixel_of = |pose: &Pose| {
        let point_in_color = pose.transform_point(point_in_depth);
        CameraModel::Pinhole(color)
            .project(optical_from_gl(point_in_color.as_dvec3()))
            .unwrap()
    };
    let miss = pixel_of(&stereo.color_from_depth).distance(pixel_of(&truth));
    assert!(miss < 0.3, "{miss} px");
}

#[test]
fn chessboard_registers_depth_to_color() {
    depth_to_color(&chessboard());
}

#[test]
fn charuco_registers_depth_to_color() {
    depth_to_color(&charuco(9, 7, 0.03, 0.022));
}

/// The world board's frame as relight documents it, built here from the target's points: origin
/// at their centre, +X along the rows, +Y up the print (against the target frame's +Y), +Z out
/// of the print.
fn documented_world_from_target(geometry: &TargetGeometry) -> Pose {
    let (lo, hi) = geometry.points().iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let centre = (0.5 * (lo + hi)).as_vec3();
    let flip = Quat::from_rotation_x(PI);
    Pose::new(flip, -(flip * centre))
}

fn probe_in_world(geometry: &TargetGeometry) {
    let camera = probe_camera();
    let model = CameraModel::KannalaBrandt(camera);
    // Intrinsics first, from planned views.
    let synth = SynthCamera::new(model, RenderSettings::default()).unwrap();
    let detector = Detector::new(geometry).unwrap();
    let views: Vec<Detection> = plan_views(&model, geometry, &ViewPlan::default())
        .iter()
        .enumerate()
        .filter_map(|(i, pose)| {
            detector
                .detect(
                    &format!("probe-{i:02}"),
                    &synth.render_target(geometry, pose),
                )
                .ok()
        })
        .collect();
    let intrinsics = calibrate_fisheye(
        &views,
        &FisheyeSettings {
            field_of_view_deg: Some(185.0),
            ..FisheyeSettings::default()
        },
    )
    .unwrap();

    // The probe mounted 0.3 m above the board, looking past it: the board is ~35° off its
    // axis. World = the board's frame (+Z up out of the print).
    let world_from_target = documented_world_from_target(geometry);
    let world_from_target_lib = geometry.world_from_target().to_pose();
    let (mm, deg) = pose_error(&world_from_target, &world_from_target_lib);
    assert!(
        mm < 1e-3 && deg < 1e-3,
        "board frame differs: {mm} mm {deg}°"
    );
    let truth = Pose::look_at(
        Vec3::new(0.1, -0.15, 0.3),
        Vec3::new(-0.25, 0.25, -0.05),
        Vec3::Z,
    );
    let probe_optical_from_target =
        to_rigid(&(optical_from_gl_pose() * truth.inverse() * world_from_target));
    let image = synth.render_target(geometry, &probe_optical_from_target);
    let detection = detector.detect("probe-in-rig", &image).unwrap();
    let located = locate_probe(
        &CameraModel::KannalaBrandt(intrinsics.camera),
        geometry,
        &[detection],
    )
    .unwrap();
    let (mm, deg) = pose_error(&located.world_from_probe, &truth);
    eprintln!(
        "{}: probe located from {} points, RMS {:.4} px: off by {mm:.3} mm, {deg:.4}°",
        geometry.target().describe(),
        located.points,
        located.rms_px
    );
    assert!(located.points >= 16, "{} points", located.points);
    assert!(mm < 2.0 && deg < 0.2, "{mm} mm, {deg}°");

    // End to end: a point on the table, seen from the located probe through relight's glTF
    // convention, lands where the truth puts it.
    let point_in_world = Vec3::new(0.3, 0.25, 0.0);
    let pixel_of = |world_from_probe: &Pose| {
        let in_probe = world_from_probe.inverse().transform_point(point_in_world);
        model.project(optical_from_gl(in_probe.as_dvec3())).unwrap()
    };
    let miss = pixel_of(&located.world_from_probe).distance(pixel_of(&truth));
    assert!(miss < 0.3, "{miss} px");
}

#[test]
fn chessboard_locates_the_probe_in_the_world() {
    probe_in_world(&chessboard());
}

#[test]
fn charuco_locates_the_probe_in_the_world() {
    probe_in_world(&charuco(7, 5, 0.05, 0.03));
}

#[test]
fn lamp_light_centre_from_turned_lamp() {
    let camera = CameraModel::Pinhole(color_camera());
    let marker = LampMarker {
        dictionary: Dictionary::AprilTag36h11,
        marker_id: 7,
        size_m: 0.06,
    };
    // The printed marker: a one-tag grid whose board frame is relight's marker frame.
    let print = Target::AprilGrid(AprilGrid {
        cols: 1,
        rows: 1,
        tag_m: marker.size_m,
        spacing_m: 0.015,
        first_id: marker.marker_id,
    })
    .geometry()
    .unwrap();
    let marker_from_print = print.world_from_target();
    for (k, corner) in marker.corners_in_marker().iter().enumerate() {
        let printed = marker_from_print.transform_point(print.point(4 * 7 + k as u32).unwrap());
        assert!(printed.distance(*corner) < 1e-12, "corner {k}");
    }
    // The bulb: 8.5 cm above the tag's centre and 3.5 cm in front of the print.
    let light_in_marker = DVec3::new(0.015, 0.085, 0.035);
    let synth = SynthCamera::new(camera, RenderSettings::default()).unwrap();
    // Facing the camera is a half turn about X (marker +Y up in the image, +Z towards the
    // camera); then the lamp is turned in the hand.
    let facing = glam::DQuat::from_rotation_x(std::f64::consts::PI);
    let turns_deg = [
        (0.0, 0.0, 0.0),
        (30.0, 0.0, 10.0),
        (-30.0, 5.0, -10.0),
        (0.0, 35.0, 0.0),
        (5.0, -35.0, 20.0),
        (25.0, 25.0, -15.0),
        (-25.0, -25.0, 30.0),
        (-20.0, 30.0, -30.0),
    ];
    let mut observations = Vec::new();
    for (i, &(about_x, about_y, about_z)) in turns_deg.iter().enumerate() {
        let turn = glam::DQuat::from_euler(
            glam::EulerRot::XYZ,
            f64::to_radians(about_x),
            f64::to_radians(about_y),
            f64::to_radians(about_z),
        );
        let offset = DVec3::new(
            0.05 * (i as f64 * 1.3).sin(),
            0.04 * (i as f64 * 0.7).cos(),
            0.5,
        );
        let camera_from_marker = Rigid::new(facing * turn, offset);
        let bulb = Sphere {
            centre_in_camera: camera_from_marker.transform_point(light_in_marker),
            radius_m: 0.012,
            radiance: 3.0,
        };
        let image = synth.render(&Scene {
            targets: vec![PlacedTarget {
                geometry: &print,
                camera_from_target: camera_from_marker * marker_from_print,
            }],
            spheres: vec![bulb],
        });
        observations
            .push(observe_lamp(&camera, &marker, &format!("lamp-{i}"), &image, 250).unwrap());
    }
    let lamp = locate_lamp_light(&camera, &observations).unwrap();
    let error_mm = lamp.light_in_marker.distance(light_in_marker) * 1000.0;
    eprintln!(
        "lamp: light centre off by {error_mm:.3} mm; ray residual RMS {:.3} mm; lamp turned over {:.1}°",
        lamp.rms_m * 1000.0,
        lamp.spread_deg
    );
    assert!(error_mm < 2.0, "{error_mm} mm");

    // End to end: with a tracker's world_from_marker, the light sits where the truth puts it.
    let world_from_marker = Pose::new(Quat::from_rotation_y(0.7), Vec3::new(0.4, 0.9, -0.2));
    let light_in_world = (world_from_marker * lamp.lamp_marker_from_light).translation;
    let truth_in_world = world_from_marker.transform_point(light_in_marker.as_vec3());
    assert!((light_in_world - truth_in_world).length() < 0.002);
}
