//! The simulator's own frames through the real libapriltag: a board the rig renders is found
//! where the rig's marker truth says, within the corner budget of its path-traced print.

#![cfg(feature = "apriltag")]

use glam::{Quat, Vec3};
use relight_backends::markers::apriltag::{AprilTagConfig, AprilTagTracker};
use relight_backends::sources::MarkerTracker;
use relight_core::camera::CameraModel;
use relight_core::light::Light;
use relight_core::scene::{Material, Scene, SceneCamera};
use relight_core::{MarkerSet, Pose, StreamMessage};
use relight_reference::shapes::quad;
use relight_sim::markers::MarkerBoard;
use relight_sim::rig::{SimRig, SimSettings};

fn focal_px(camera: &CameraModel) -> f64 {
    camera.intrinsics().x_axis.x
}

/// A diffuse floor under a point light, for the simulator.
fn floor_scene() -> Scene {
    Scene {
        name: "floor".into(),
        meshes: vec![quad(
            "floor",
            Vec3::ZERO,
            Vec3::X * 4.0,
            -Vec3::Z * 4.0,
            0,
            false,
        )],
        materials: vec![Material {
            name: "floor".into(),
            albedo: Vec3::splat(0.6),
            specular: Vec3::ZERO,
            shininess: 0.0,
            emission: Vec3::ZERO,
        }],
        camera: SceneCamera {
            world_from_camera: Pose::look_at(
                Vec3::new(0.0, 0.8, 0.4),
                Vec3::new(0.0, 0.0, -0.2),
                Vec3::Y,
            ),
            yfov_rad: 0.7,
            width: 320,
            height: 240,
        },
        lights: vec![Light::Point {
            position_in_world: Vec3::new(0.0, 2.0, 0.5),
            intensity: Vec3::splat(4.0),
        }],
        environment: None,
        environment_lights: Vec::new(),
        shadow_proxy: None,
        surface_revision: None,
    }
}

#[test]
fn detections_match_the_simulators_truth_on_its_own_frames() {
    let scene = floor_scene();
    let board = MarkerBoard {
        first_id: 4,
        cols: 2,
        rows: 2,
        tag_size_m: 0.15,
        gap_m: 0.04,
        world_from_board: Pose::new(
            Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2) * Quat::from_rotation_z(0.3),
            Vec3::new(0.05, 0.0, -0.2),
        ),
        white_albedo: 0.8,
        black_albedo: 0.04,
    };
    let rig = SimRig::new(
        &scene,
        SimSettings {
            width: 320,
            height: 240,
            frames: 1,
            color_spp: 4,
            board: Some(board),
            ..SimSettings::default()
        },
    )
    .unwrap()
    .metered();
    let frame = rig.frame(0);
    let colour = frame.messages.iter().find_map(|m| match m {
        StreamMessage::Color(f) => Some(f.payload.clone()),
        _ => None,
    });
    let truth = frame.messages.iter().find_map(|m| match m {
        StreamMessage::Markers(f) => Some(f.payload.clone()),
        _ => None,
    });
    let (Some(colour), Some(truth)) = (colour, truth) else {
        panic!("the rig renders colour and markers");
    };
    assert_eq!(truth.detections.len(), 4);
    let camera = CameraModel::Pinhole(*rig.camera());
    let mut tracker = AprilTagTracker::new(&AprilTagConfig {
        size_m: 0.15,
        quad_decimate: 1.0,
        ..AprilTagConfig::default()
    })
    .unwrap();
    let mut found = MarkerSet::default();
    tracker.detect(&colour, &camera, &mut found).unwrap();
    assert_eq!(
        found.detections.len(),
        4,
        "{:?}",
        tracker.observe(&colour, &camera).unwrap().rejected
    );
    let f = focal_px(&camera);
    for expected in &truth.detections {
        let detected = found
            .detections
            .iter()
            .find(|d| d.marker_id == expected.marker_id)
            .unwrap();
        assert_eq!(detected.family, expected.family);
        // The sim path-traces 4 spp with 4 × 4 supersampled print: a looser corner budget.
        for (a, b) in detected.corners_px.iter().zip(&expected.corners_px) {
            assert!(
                (*a - *b).length() < 0.6,
                "tag {}: {a} vs {b}",
                expected.marker_id
            );
        }
        let distance = f64::from(expected.camera_from_marker.translation.length());
        let closed_form = distance * distance * 0.6 / (f * 0.15);
        let error = (detected.camera_from_marker.translation
            - expected.camera_from_marker.translation)
            .length();
        assert!(
            f64::from(error) < 3.0 * closed_form,
            "tag {}: {error} m",
            expected.marker_id
        );
        let angle = detected
            .camera_from_marker
            .rotation
            .angle_between(expected.camera_from_marker.rotation);
        assert!(
            angle.to_degrees() < 5.0,
            "tag {}: {}°",
            expected.marker_id,
            angle.to_degrees()
        );
    }
}
