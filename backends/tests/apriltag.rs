//! The AprilTag backend through the real libapriltag, on images rendered with known truth:
//! corner order and pixel convention, pose accuracy per distance × blur (both families, tilted
//! tags, noise), boards with occlusion, a fish-eye camera, bad input, and the marker device on
//! the bus with its One-Euro filter. The simulator's own frames are checked against this detector
//! in `relight-sim` (`sim/tests/apriltag.rs`).
//!
//! Tolerances come from the corner accuracy: a corner budget σ_c per blur level is asserted on
//! the detected corners, and pose errors must stay within 3 σ of what that corner noise gives
//! through the pose Jacobian (`PoseFit` covariance, checked against Monte Carlo in the unit
//! tests) and within 3 × the closed form `z² σ_c / (f s)` of a square of size `s` at depth `z`.
//! Run with `--nocapture` for the table of errors.

#![cfg(feature = "apriltag")]

use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{DQuat, DVec2, DVec3, Quat, Vec3};
use relight_backends::DeviceError;
use relight_backends::device::{Backoff, DeviceRunner};
use relight_backends::markers::apriltag::{
    AprilTagConfig, AprilTagTracker, Family, Observations, Rejection, apriltag_device,
    family_bitmap, family_layout,
};
use relight_backends::markers::board::{Board, BoardConfig};
use relight_backends::markers::one_euro::OneEuroConfig;
use relight_backends::markers::pose::{
    DPose, PoseFit, PoseSettings, estimate_square_pose, square_corners_in_marker,
};
use relight_backends::markers::render::{
    Occluder, PlanarTexture, RenderSettings, Surface, TagBitmap, project_points, render,
};
use relight_backends::sources::MarkerTracker;
use relight_core::bus::Bus;
use relight_core::camera::{CameraModel, KannalaBrandt, Pinhole};
use relight_core::rig::BoardLayout;
use relight_core::{Frame, Image, MarkerSet, PixelFormat, Pose, StreamMessage, Timestamp};

const TAG_SIZE_M: f64 = 0.12;
const WHITE: f32 = 0.9;
const BLACK: f32 = 0.08;

/// A Kinect-class colour camera with mild barrel distortion.
fn camera() -> CameraModel {
    CameraModel::Pinhole(Pinhole {
        width: 640,
        height: 480,
        fx: 525.0,
        fy: 525.0,
        cx: 319.5,
        cy: 239.5,
        k1: -0.05,
        k2: 0.01,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    })
}

fn focal_px(camera: &CameraModel) -> f64 {
    camera.intrinsics().x_axis.x
}

fn tag_surface(family: Family, id: u32, size_m: f64, camera_from_marker: DPose) -> Surface {
    let bitmap = family_bitmap(family, id).expect("id in the family");
    Surface {
        camera_from_surface: camera_from_marker,
        texture: PlanarTexture::tag(&bitmap, size_m, 1, WHITE, BLACK),
    }
}

fn tracker(families: &[Family]) -> AprilTagTracker {
    AprilTagTracker::new(&AprilTagConfig {
        families: families.to_vec(),
        size_m: TAG_SIZE_M,
        ..AprilTagConfig::default()
    })
    .unwrap()
}

/// A tag pose `distance_m` ahead, tilted by `tilt_deg` about an in-plane axis at `axis_deg`,
/// turned by `spin_rad` in its plane, offset sideways.
fn tilted(distance_m: f64, tilt_deg: f64, axis_deg: f64, spin_rad: f64, offset: DVec2) -> DPose {
    let axis = DVec3::new(
        axis_deg.to_radians().cos(),
        axis_deg.to_radians().sin(),
        0.0,
    );
    DPose::new(
        DQuat::from_axis_angle(axis, tilt_deg.to_radians()) * DQuat::from_rotation_z(spin_rad),
        offset.extend(-distance_m),
    )
}

fn corner_rms_px(found: &[DVec2; 4], truth: &[DVec2]) -> f64 {
    (found
        .iter()
        .zip(truth)
        .map(|(a, b)| a.distance_squared(*b))
        .sum::<f64>()
        / 4.0)
        .sqrt()
}

/// Corner accuracy budget (1 σ per coordinate, px) of libapriltag's refined edges: ~0.2 px on
/// sharp images; a blur of σ px lets a neighbouring cell's edge pull the border's by up to
/// ~0.3 σ once the (foreshortened) cell is within 2 σ.
fn corner_budget_px(blur_sigma_px: f64) -> f64 {
    0.2 + 0.3 * blur_sigma_px
}

/// 1-σ translation (m) and rotation (°) errors the fit's geometry gives for corner noise
/// `sigma_px` (the covariance scales with σ²).
fn predicted(fit: &PoseFit, sigma_px: f64) -> (f64, f64) {
    let scale = sigma_px / fit.sigma_px;
    (
        fit.translation_sigma_m() * scale,
        fit.rotation_sigma_deg() * scale,
    )
}

#[test]
fn family_tables_match_the_printed_codes_and_the_library() {
    for id in 0..32 {
        assert_eq!(
            family_bitmap(Family::Tag36h11, id),
            TagBitmap::tag36h11(id),
            "tag36h11 id {id}"
        );
    }
    let t36 = family_layout(Family::Tag36h11).unwrap();
    assert_eq!(
        (t36.codes.len(), t36.bits.len(), t36.min_hamming),
        (587, 36, 11)
    );
    assert_eq!((t36.width_at_border, t36.total_width), (8, 10));
    assert!(!t36.reversed_border);
    let t41 = family_layout(Family::TagStandard41h12).unwrap();
    assert_eq!(
        (t41.codes.len(), t41.bits.len(), t41.min_hamming),
        (2115, 41, 12)
    );
    assert_eq!((t41.width_at_border, t41.total_width), (5, 9));
    assert!(t41.reversed_border);
    // tagStandard41h12 carries data outside its border square: 32 bits in the outer ring.
    assert_eq!(
        t41.bits
            .iter()
            .filter(|(x, y)| *x < 0 || *y < 0 || *x > 4 || *y > 4)
            .count(),
        32
    );
    let bitmap = family_bitmap(Family::TagStandard41h12, 0).unwrap();
    // The white ring is the detected square's border; the ring outside it is black.
    assert!((2..7).all(|k| bitmap.white_at(k, 2) && bitmap.white_at(2, k)));
    assert!((1..8).all(|k| !bitmap.white_at(k, 1) && !bitmap.white_at(1, k)));
    assert_eq!(family_bitmap(Family::Tag36h11, 587), None);
    assert_eq!(
        Family::from_name("tagStandard41h12"),
        Some(Family::TagStandard41h12)
    );
}

#[test]
fn detector_struct_layout_reads_the_library_defaults() {
    // Values set by `apriltag_detector_create`, read through our declaration of its struct.
    let tracker = tracker(&[Family::Tag36h11]);
    let thresholds = tracker.quad_thresholds();
    assert_eq!(thresholds.min_cluster_pixels, 5);
    assert_eq!(thresholds.max_nmaxima, 10);
    assert_eq!(thresholds.max_line_fit_mse, 10.0);
    assert_eq!(thresholds.min_white_black_diff, 5);
    let settings = tracker.detector_settings();
    assert_eq!(settings.quad_decimate, 2.0);
    assert_eq!(settings.nthreads, 1);
    assert!(settings.refine_edges);
    assert_eq!(settings.decode_sharpening, 0.25);
    let other = AprilTagTracker::new(&AprilTagConfig {
        quad_decimate: 1.5,
        quad_sigma: 0.8,
        nthreads: 2,
        refine_edges: false,
        decode_sharpening: 0.5,
        ..AprilTagConfig::default()
    })
    .unwrap();
    let settings = other.detector_settings();
    assert_eq!(
        (
            settings.quad_decimate,
            settings.quad_sigma,
            settings.nthreads
        ),
        (1.5, 0.8, 2)
    );
    assert!(!settings.refine_edges && settings.decode_sharpening == 0.5);
}

#[test]
fn corners_follow_marker_detection_order_and_pixel_centres() {
    let camera = camera();
    for family in Family::ALL {
        let mut tracker = tracker(&[family]);
        let mut mean_error = DVec2::ZERO;
        let mut count = 0.0;
        for (k, spin_deg) in [0.0f64, 90.0, 180.0, 270.0, 20.0, 135.0].iter().enumerate() {
            let pose = tilted(
                0.6,
                25.0,
                40.0 * k as f64,
                spin_deg.to_radians(),
                DVec2::new(0.02, -0.01),
            );
            let image = render(
                &camera,
                &[tag_surface(family, 5, TAG_SIZE_M, pose)],
                &[],
                &RenderSettings {
                    seed: k as u64,
                    noise_sigma: 1.0,
                    ..RenderSettings::default()
                },
            )
            .unwrap();
            let truth =
                project_points(&camera, &pose, &square_corners_in_marker(TAG_SIZE_M)).unwrap();
            let observations = tracker.observe(&image, &camera).unwrap();
            let [tag] = observations.tags.as_slice() else {
                panic!("{family:?} spin {spin_deg}: {:?}", observations.rejected);
            };
            assert_eq!(tag.marker_id, 5);
            for (found, expected) in tag.corners_px.iter().zip(&truth) {
                // Each corner is the truth corner of the same index (the order), with no
                // half-pixel offset (the convention).
                assert!(
                    found.distance(*expected) < 0.3,
                    "{family:?} spin {spin_deg}: {found} vs {expected}"
                );
                mean_error += *found - *expected;
                count += 1.0;
            }
            // The homography maps the tag's (−1, 1) to the lower-left corner, like p[0].
            let h = tag.homography * DVec3::new(-1.0, 1.0, 1.0);
            assert!((h.truncate() / h.z).distance(tag.corners_px[0]) < 1e-6);
            let detection = tag.detection();
            assert_eq!(detection.family, family.name());
            assert!(
                detection.corners_px[2]
                    .as_dvec2()
                    .distance(tag.corners_px[2])
                    < 1e-3
            );
        }
        let mean_error = mean_error / count;
        assert!(
            mean_error.length() < 0.05,
            "{family:?}: mean corner offset {mean_error}"
        );
    }
}

#[test]
fn pose_error_per_distance_and_blur_stays_within_the_corner_budget() {
    let camera = camera();
    let f = focal_px(&camera);
    let distances = [0.5, 1.0, 2.0];
    let blurs = [0.0, 1.0, 2.0];
    let tilts = [30.0, 45.0, 60.0];
    let mut table = String::new();
    for family in Family::ALL {
        let mut tracker = tracker(&[family]);
        let size_cells = f64::from(family_bitmap(family, 0).unwrap().size_cells);
        table += &format!(
            "\n{:<17}| σ_blur px | found | t err mm (max) | rot err ° (max) | corner rms px | z²σc/(f·s) mm\n",
            family.name()
        );
        for &distance in &distances {
            for &blur in &blurs {
                let budget = corner_budget_px(blur);
                let (mut t_errs, mut r_errs, mut corner_sq) = (Vec::new(), Vec::new(), 0.0);
                for (k, &tilt) in tilts.iter().enumerate() {
                    let pose = tilted(
                        distance,
                        tilt,
                        40.0 + 120.0 * k as f64,
                        0.2 + 0.5 * k as f64,
                        DVec2::new(0.03 * distance * (k as f64 - 1.0), 0.02 * distance),
                    );
                    let image = render(
                        &camera,
                        &[tag_surface(family, 3, TAG_SIZE_M, pose)],
                        &[],
                        &RenderSettings {
                            blur_sigma_px: blur,
                            noise_sigma: 2.0,
                            supersampling: 3,
                            seed: 10 + k as u64,
                            ..RenderSettings::default()
                        },
                    )
                    .unwrap();
                    let truth =
                        project_points(&camera, &pose, &square_corners_in_marker(TAG_SIZE_M))
                            .unwrap();
                    // Decoding needs a cell's contrast to survive the blur: required when the
                    // smallest projected cell is at least 2 σ_blur + 1.5 px.
                    let min_edge_px = (0..4)
                        .map(|i| truth[i].distance(truth[(i + 1) % 4]))
                        .fold(f64::INFINITY, f64::min);
                    let required = min_edge_px / size_cells >= 2.0 * blur + 1.5;
                    let observations = tracker.observe(&image, &camera).unwrap();
                    let Some(tag) = observations.tags.iter().find(|t| t.marker_id == 3) else {
                        assert!(
                            !required,
                            "{family:?} at {distance} m, blur {blur}, tilt {tilt}: lost ({:?})",
                            observations.rejected
                        );
                        continue;
                    };
                    assert_eq!(observations.tags.len(), 1, "no false positives");
                    let rms = corner_rms_px(&tag.corners_px, &truth);
                    assert!(
                        rms <= budget,
                        "{family:?} at {distance} m, blur {blur}, tilt {tilt}: corners {rms} px"
                    );
                    let estimate = tag.fit.camera_from_object();
                    let t_err = estimate.translation.distance(pose.translation);
                    let r_err = estimate.angle_to(&pose).to_degrees();
                    let (t_sigma, r_sigma) = predicted(&tag.fit, budget);
                    let closed_form = distance * distance * budget / (f * TAG_SIZE_M);
                    assert!(
                        t_err <= 3.0 * t_sigma && t_err <= 3.0 * closed_form,
                        "{family:?} at {distance} m, blur {blur}, tilt {tilt}: {t_err} m vs σ {t_sigma}, {closed_form}"
                    );
                    assert!(
                        r_err <= 3.0 * r_sigma,
                        "{family:?} at {distance} m, blur {blur}, tilt {tilt}: {r_err}° vs σ {r_sigma}"
                    );
                    corner_sq += rms * rms;
                    t_errs.push(t_err * 1e3);
                    r_errs.push(r_err);
                }
                let n = t_errs.len();
                let closed_form_mm = distance * distance * budget / (f * TAG_SIZE_M) * 1e3;
                let found = format!("{n}/{}", tilts.len());
                if n == 0 {
                    table += &format!(
                        "  z = {distance:.1} m       | {blur:9.0} | {found:<5} | {:>15} | {:>15} | {:>13} | {closed_form_mm:13.2}\n",
                        "lost", "lost", "-"
                    );
                    continue;
                }
                let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
                let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
                table += &format!(
                    "  z = {distance:.1} m       | {blur:9.0} | {found:<5} | {:6.2} ({:6.2}) | {:6.3} ({:6.3}) | {:13.3} | {closed_form_mm:13.2}\n",
                    mean(&t_errs),
                    max(&t_errs),
                    mean(&r_errs),
                    max(&r_errs),
                    (corner_sq / n as f64).sqrt(),
                );
            }
        }
    }
    println!(
        "AprilTag pose error vs truth, {} px camera f = {f} px, {TAG_SIZE_M} m tags tilted {tilts:?}°, noise σ 2 DN:{table}",
        camera.width()
    );
}

/// The demo board (2 × 2 tag36h11, 12 cm tags, 3 cm gaps) as the detector lays it out (the
/// simulator's truth follows the same layout: `relight-sim`'s marker tests), placed in the world.
struct PlacedBoard {
    board: Board,
    world_from_board: Pose,
}

fn demo_board(world_from_board: Pose) -> PlacedBoard {
    let board = Board::from_layout(&BoardLayout {
        family: "tag36h11".into(),
        first_id: 0,
        cols: 2,
        rows: 2,
        tag_size_m: TAG_SIZE_M,
        gap_m: 0.03,
    })
    .unwrap();
    PlacedBoard {
        board,
        world_from_board,
    }
}

/// Surfaces of the board's tags and their true `camera_from_marker`,
/// `camera_from_world · world_from_board · board_from_marker`.
fn board_scene(
    placed: &PlacedBoard,
    world_from_camera: &Pose,
) -> (Vec<Surface>, Vec<(u32, DPose)>) {
    let camera_from_board = world_from_camera.inverse() * placed.world_from_board;
    placed
        .board
        .tags()
        .iter()
        .map(|tag| {
            let camera_from_marker = DPose::from_pose(&(camera_from_board * tag.board_from_marker));
            (
                tag_surface(
                    Family::Tag36h11,
                    tag.marker_id,
                    tag.size_m,
                    camera_from_marker,
                ),
                (tag.marker_id, camera_from_marker),
            )
        })
        .unzip()
}

fn board_tracker() -> AprilTagTracker {
    AprilTagTracker::new(&AprilTagConfig {
        board: Some(BoardConfig::Grid {
            name: "board".into(),
            family: "tag36h11".into(),
            first_id: 0,
            cols: 2,
            rows: 2,
            tag_size_m: TAG_SIZE_M,
            gap_m: 0.03,
        }),
        ..AprilTagConfig::default()
    })
    .unwrap()
}

/// The board seen 1.3 m away, 45° off its normal, from a camera placed in the world.
fn board_view() -> (PlacedBoard, Pose) {
    let board = demo_board(Pose::new(
        Quat::from_rotation_x(-0.4),
        Vec3::new(0.1, 0.2, -0.3),
    ));
    let target = board.world_from_board.translation;
    let eye = target
        + board
            .world_from_board
            .transform_vector(Vec3::new(0.3, -0.95, 1.0).normalize() * 1.3);
    (
        board,
        Pose::look_at(eye, target + Vec3::new(0.02, 0.03, 0.0), Vec3::Y),
    )
}

fn board_error(observations: &Observations, truth: &DPose) -> (f64, f64, PoseFit) {
    let board = observations.board.as_ref().expect("board seen");
    let estimate = board.fit.fit.camera_from_object();
    (
        estimate.translation.distance(truth.translation),
        estimate.angle_to(truth).to_degrees(),
        board.fit.fit,
    )
}

#[test]
fn board_pose_comes_from_all_visible_tags_jointly() {
    let camera = camera();
    let (board, world_from_camera) = board_view();
    let (surfaces, truths) = board_scene(&board, &world_from_camera);
    let camera_from_board =
        DPose::from_pose(&(world_from_camera.inverse() * board.world_from_board));
    let image = render(
        &camera,
        &surfaces,
        &[],
        &RenderSettings {
            noise_sigma: 2.0,
            blur_sigma_px: 0.7,
            ..RenderSettings::default()
        },
    )
    .unwrap();
    let mut tracker = board_tracker();
    let observations = tracker.observe(&image, &camera).unwrap().clone();
    assert_eq!(observations.tags.len(), 4);
    let board_seen = observations.board.as_ref().unwrap();
    assert_eq!(board_seen.fit.tags_used, vec![0, 1, 2, 3]);
    assert_eq!(board_seen.fit.fit.points, 16);
    let budget = corner_budget_px(0.7);
    let (t_err, r_err, fit) = board_error(&observations, &camera_from_board);
    let (t_sigma, r_sigma) = predicted(&fit, budget);
    assert!(t_err < 3.0 * t_sigma, "{t_err} vs {t_sigma}");
    assert!(r_err < 3.0 * r_sigma, "{r_err} vs {r_sigma}");
    // Sixteen corners over a 27 cm board constrain the pose better than any one tag's four.
    for tag in &observations.tags {
        let (tag_t, tag_r) = predicted(&tag.fit, budget);
        assert!(
            r_sigma < 0.6 * tag_r && t_sigma < tag_t,
            "{r_sigma} vs {tag_r}"
        );
        let truth = truths
            .iter()
            .find(|(id, _)| *id == tag.marker_id)
            .unwrap()
            .1;
        let estimate = tag.fit.camera_from_object();
        assert!(estimate.translation.distance(truth.translation) < 3.0 * tag_t);
    }
    // The board's detection: named after the board, its pose, its outline around the tags.
    let mut set = MarkerSet::default();
    tracker.detect(&image, &camera, &mut set).unwrap();
    assert_eq!(set.detections.len(), 5);
    let detection = set.detections.last().unwrap();
    assert_eq!(
        (detection.family.as_str(), detection.marker_id),
        ("board", 0)
    );
    let outline = project_points(
        &camera,
        &camera_from_board,
        &[
            DVec3::new(-0.135, -0.135, 0.0),
            DVec3::new(0.135, 0.135, 0.0),
        ],
    )
    .unwrap();
    assert!(detection.corners_px[0].as_dvec2().distance(outline[0]) < 1.0);
    assert!(detection.corners_px[2].as_dvec2().distance(outline[1]) < 1.0);
    println!(
        "board at 1.3 m: {:.2} mm, {:.3}° (1-σ for {budget:.2} px corners: {:.2} mm, {:.3}°)",
        t_err * 1e3,
        r_err,
        t_sigma * 1e3,
        r_sigma
    );
}

#[test]
fn an_occluded_tag_is_lost_or_right_and_the_board_survives() {
    let camera = camera();
    let (board, world_from_camera) = board_view();
    let (surfaces, truths) = board_scene(&board, &world_from_camera);
    let camera_from_board =
        DPose::from_pose(&(world_from_camera.inverse() * board.world_from_board));
    let budget = corner_budget_px(0.0);
    // A card over one corner (and part of two edges) of tag 1, dark and bright.
    let (_, tag1) = truths[1];
    let corners = project_points(&camera, &tag1, &square_corners_in_marker(TAG_SIZE_M)).unwrap();
    let centre = corners.iter().sum::<DVec2>() / 4.0;
    let upper_right = corners[2];
    let inner = centre + 0.35 * (upper_right - centre);
    let outer = upper_right + 15.0 * (upper_right - centre).signum();
    for radiance in [0.02, 0.95] {
        let occluder = Occluder {
            min_px: inner.min(outer),
            max_px: inner.max(outer),
            radiance,
        };
        let image = render(
            &camera,
            &surfaces,
            &[occluder],
            &RenderSettings {
                noise_sigma: 2.0,
                ..RenderSettings::default()
            },
        )
        .unwrap();
        let mut tracker = board_tracker();
        let observations = tracker.observe(&image, &camera).unwrap().clone();
        for tag in &observations.tags {
            let truth = truths
                .iter()
                .find(|(id, _)| *id == tag.marker_id)
                .unwrap()
                .1;
            let estimate = tag.fit.camera_from_object();
            let (t_sigma, r_sigma) = predicted(&tag.fit, budget);
            assert!(
                estimate.translation.distance(truth.translation) < 3.0 * t_sigma
                    && estimate.angle_to(&truth).to_degrees() < 3.0 * r_sigma,
                "tag {} reported with a wrong pose (occluder radiance {radiance})",
                tag.marker_id
            );
        }
        let (t_err, r_err, fit) = board_error(&observations, &camera_from_board);
        let used = &observations.board.as_ref().unwrap().fit.tags_used;
        assert!(used.len() >= 3, "{used:?}");
        let (t_sigma, r_sigma) = predicted(&fit, budget);
        assert!(
            t_err < 3.0 * t_sigma && r_err < 3.0 * r_sigma,
            "{t_err} {r_err}"
        );
        println!(
            "occluder radiance {radiance}: tags {:?}, rejected {:?}, board from {used:?}: {:.2} mm, {:.3}°",
            observations
                .tags
                .iter()
                .map(|t| t.marker_id)
                .collect::<Vec<_>>(),
            observations
                .rejected
                .iter()
                .map(|r| (r.marker_id, &r.reason))
                .collect::<Vec<_>>(),
            t_err * 1e3,
            r_err
        );
    }
}

#[test]
fn a_fisheye_camera_gives_the_pose_through_its_own_model() {
    // A wide lens (~150° across) with strong Kannala–Brandt terms; the tag 50° off-axis.
    // (tag36h11: libapriltag decodes through a homography, and tagStandard41h12's data ring
    // outside its border is where a fish-eye bends the print away from it; it is lost here.)
    let camera = CameraModel::KannalaBrandt(KannalaBrandt {
        width: 640,
        height: 480,
        fx: 240.0,
        fy: 240.0,
        cx: 321.0,
        cy: 238.0,
        k1: -0.03,
        k2: 0.006,
        k3: -0.001,
        k4: 0.0002,
    });
    let mut tracker = tracker(&[Family::Tag36h11]);
    let axis_angle = 50f64.to_radians();
    let direction = DVec3::new(axis_angle.sin(), 0.1, -axis_angle.cos()).normalize();
    // The tag faces the camera, turned 20° further.
    let pose = DPose::new(
        DQuat::from_rotation_y(-(axis_angle + 20f64.to_radians())) * DQuat::from_rotation_z(0.3),
        direction * 0.45,
    );
    let image = render(
        &camera,
        &[tag_surface(Family::Tag36h11, 11, TAG_SIZE_M, pose)],
        &[],
        &RenderSettings {
            noise_sigma: 2.0,
            ..RenderSettings::default()
        },
    )
    .unwrap();
    let truth = project_points(&camera, &pose, &square_corners_in_marker(TAG_SIZE_M)).unwrap();
    let observations = tracker.observe(&image, &camera).unwrap();
    let [tag] = observations.tags.as_slice() else {
        panic!("{:?}", observations.rejected)
    };
    assert_eq!(tag.marker_id, 11);
    // The detector fits straight lines to edges the lens bends: a least-squares line through
    // an arc of sagitta δ lies 2δ/3 off its chord, so two such lines meet up to ~1.5 δ from the
    // true corner. δ: how far each edge's projected midpoint is from its chord.
    let midpoints = project_points(
        &camera,
        &pose,
        &[
            DVec3::new(0.0, -0.06, 0.0),
            DVec3::new(0.06, 0.0, 0.0),
            DVec3::new(0.0, 0.06, 0.0),
            DVec3::new(-0.06, 0.0, 0.0),
        ],
    )
    .unwrap();
    let sagitta = (0..4)
        .map(|i| {
            let (a, b) = (truth[i], truth[(i + 1) % 4]);
            (midpoints[i] - a).perp_dot((b - a).normalize()).abs()
        })
        .fold(0.0, f64::max);
    let budget = corner_budget_px(0.0) + 1.5 * sagitta;
    let rms = corner_rms_px(&tag.corners_px, &truth);
    println!("fish-eye: edge sagitta {sagitta:.2} px, corner rms {rms:.2} px");
    assert!(rms < budget, "{rms} vs {budget}");
    let estimate = tag.fit.camera_from_object();
    let (t_sigma, r_sigma) = predicted(&tag.fit, budget);
    assert!(estimate.translation.distance(pose.translation) < 3.0 * t_sigma);
    assert!(estimate.angle_to(&pose).to_degrees() < 3.0 * r_sigma);
    // A pinhole model of the same intrinsics misplaces it by more than twice the tolerance.
    let CameraModel::KannalaBrandt(kb) = camera else {
        unreachable!()
    };
    let pinhole = CameraModel::Pinhole(Pinhole {
        width: kb.width,
        height: kb.height,
        fx: kb.fx,
        fy: kb.fy,
        cx: kb.cx,
        cy: kb.cy,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    });
    let wrong = estimate_square_pose(
        &tag.corners_px,
        TAG_SIZE_M,
        &pinhole,
        &PoseSettings::default(),
    )
    .unwrap()
    .camera_from_object();
    println!(
        "fish-eye: {:.2} mm, {:.3}° with its model; {:.1} mm as a pinhole (3 σ = {:.2} mm)",
        estimate.translation.distance(pose.translation) * 1e3,
        estimate.angle_to(&pose).to_degrees(),
        wrong.translation.distance(pose.translation) * 1e3,
        3e3 * t_sigma
    );
    assert!(wrong.translation.distance(pose.translation) > 2.0 * 3.0 * t_sigma);
}

#[test]
fn bit_errors_and_weak_margins_are_rejected() {
    let camera = camera();
    let pose = tilted(0.7, 20.0, 0.0, 0.1, DVec2::ZERO);
    let mut bitmap = family_bitmap(Family::Tag36h11, 7).unwrap();
    // Flip one data cell (inside the black border).
    let flip = |bitmap: &mut TagBitmap, col: u32, row: u32| {
        let i = (row * bitmap.total_cells + col) as usize;
        bitmap.cells[i] = !bitmap.cells[i];
    };
    flip(&mut bitmap, 4, 4);
    let surface = |bitmap: &TagBitmap| Surface {
        camera_from_surface: pose,
        texture: PlanarTexture::tag(bitmap, TAG_SIZE_M, 1, WHITE, BLACK),
    };
    let image = render(
        &camera,
        &[surface(&bitmap)],
        &[],
        &RenderSettings::default(),
    )
    .unwrap();
    let mut one_bit = tracker(&[Family::Tag36h11]);
    let observations = one_bit.observe(&image, &camera).unwrap();
    assert_eq!(observations.tags.len(), 1);
    assert_eq!(
        (observations.tags[0].marker_id, observations.tags[0].hamming),
        (7, 1)
    );
    let mut exact = AprilTagTracker::new(&AprilTagConfig {
        max_hamming: 0,
        ..AprilTagConfig::default()
    })
    .unwrap();
    assert!(exact.observe(&image, &camera).unwrap().tags.is_empty());
    // Two flipped bits exceed what the one-bit table corrects.
    flip(&mut bitmap, 6, 3);
    let image = render(
        &camera,
        &[surface(&bitmap)],
        &[],
        &RenderSettings::default(),
    )
    .unwrap();
    assert!(one_bit.observe(&image, &camera).unwrap().tags.is_empty());
    // A margin threshold above what a clean print gives rejects it, with the reason.
    let clean = render(
        &camera,
        &[tag_surface(Family::Tag36h11, 7, TAG_SIZE_M, pose)],
        &[],
        &RenderSettings::default(),
    )
    .unwrap();
    let mut picky = AprilTagTracker::new(&AprilTagConfig {
        min_decision_margin: 250.0,
        ..AprilTagConfig::default()
    })
    .unwrap();
    let observations = picky.observe(&clean, &camera).unwrap();
    assert!(observations.tags.is_empty());
    assert!(matches!(
        observations.rejected.as_slice(),
        [r] if r.marker_id == 7 && matches!(r.reason, Rejection::DecisionMargin(m) if m > 100.0)
    ));
}

#[test]
fn bad_images_and_configs_are_typed_errors() {
    let camera = camera();
    let mut tracker = tracker(&[Family::Tag36h11]);
    let depth = Image::new(640, 480, PixelFormat::DepthU16Mm);
    assert!(matches!(
        tracker.observe(&depth, &camera),
        Err(DeviceError::BadData { .. })
    ));
    let small = Image::new(320, 240, PixelFormat::Rgb8);
    assert!(matches!(
        tracker.observe(&small, &camera),
        Err(DeviceError::Config { .. })
    ));
    // Images too small to hold a tag give no detections (libapriltag 3.3 itself crashes on
    // fewer than 3 rows after decimation), for every decimation.
    for decimate in [1.0, 1.5, 2.0, 3.0] {
        let mut tracker = AprilTagTracker::new(&AprilTagConfig {
            quad_decimate: decimate,
            ..AprilTagConfig::default()
        })
        .unwrap();
        for (w, h) in [
            (1, 1),
            (3, 2),
            (2, 7),
            (17, 5),
            (640, 3),
            (4, 4),
            (20, 7),
            (2, 20),
        ] {
            let tiny = camera.resized(w, h);
            let image = Image::new(w, h, PixelFormat::Mono8);
            assert!(tracker.observe(&image, &tiny).unwrap().tags.is_empty());
        }
    }
    let empty = Image::new(0, 0, PixelFormat::Mono8);
    assert!(tracker.observe(&empty, &camera.resized(0, 0)).is_err());

    let invalid = |config: AprilTagConfig| {
        matches!(
            AprilTagTracker::new(&config),
            Err(DeviceError::Config { .. })
        )
    };
    assert!(invalid(AprilTagConfig {
        families: vec![],
        ..AprilTagConfig::default()
    }));
    assert!(invalid(AprilTagConfig {
        max_hamming: 3,
        ..AprilTagConfig::default()
    }));
    assert!(invalid(AprilTagConfig {
        size_m: -0.1,
        ..AprilTagConfig::default()
    }));
    assert!(invalid(AprilTagConfig {
        quad_decimate: 0.5,
        ..AprilTagConfig::default()
    }));
    assert!(invalid(AprilTagConfig {
        board: Some(BoardConfig::Grid {
            name: "b".into(),
            family: "tagStandard41h12".into(),
            first_id: 0,
            cols: 1,
            rows: 1,
            tag_size_m: 0.1,
            gap_m: 0.0,
        }),
        ..AprilTagConfig::default()
    }));
    let parsed: AprilTagConfig = serde_json::from_str(
        r#"{"families": ["tag36h11", "tagStandard41h12"], "size_m": 0.1,
            "sizes": [{"marker_id": 4, "size_m": 0.05}], "quad_decimate": 1.0,
            "filter": {"beta": 5.0}, "board": {"layout": "grid", "first_id": 0, "cols": 2,
            "rows": 2, "tag_size_m": 0.1, "gap_m": 0.02}}"#,
    )
    .unwrap();
    assert_eq!(parsed.families.len(), 2);
    assert_eq!(parsed.filter.beta, 5.0);
    assert_eq!(parsed.max_hamming, 1);
    let tracker = AprilTagTracker::new(&parsed).unwrap();
    assert_eq!(tracker.family(), "tag36h11,tagStandard41h12");
    let repeated = AprilTagTracker::new(&AprilTagConfig {
        families: vec![Family::Tag36h11, Family::TagStandard41h12, Family::Tag36h11],
        ..AprilTagConfig::default()
    })
    .unwrap();
    assert_eq!(
        repeated.families(),
        [Family::Tag36h11, Family::TagStandard41h12]
    );
    assert!(serde_json::from_str::<AprilTagConfig>(r#"{"families": ["tag25h9"]}"#).is_err());
    assert!(serde_json::from_str::<AprilTagConfig>(r#"{"decimate": 2}"#).is_err());
}

#[test]
fn the_marker_device_tracks_a_moving_tag_on_the_colour_stream() {
    let camera = camera();
    let bus = Arc::new(Bus::new());
    let markers = bus.markers.subscribe(64);
    let config = AprilTagConfig {
        families: vec![Family::TagStandard41h12],
        filter: OneEuroConfig::default(),
        ..AprilTagConfig::default()
    };
    let device = apriltag_device(&config, camera).unwrap();
    let mut runner =
        DeviceRunner::spawn("markers", Box::new(device), bus.clone(), Backoff::default()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while bus.color.subscriber_count() == 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
    // A still tag, then a slide along x at 0.3 m/s; 30 fps, new noise every frame.
    let pose_at = |i: u32| {
        let moving = f64::from(i.saturating_sub(12)) / 30.0;
        tilted(0.9, 35.0, 60.0, 0.4, DVec2::new(-0.1 + 0.3 * moving, 0.02))
    };
    let (mut raw_still, mut filtered_still) = (Vec::new(), Vec::new());
    for i in 0..20u32 {
        let truth = pose_at(i);
        let image = render(
            &camera,
            &[tag_surface(Family::TagStandard41h12, 2, TAG_SIZE_M, truth)],
            &[],
            &RenderSettings {
                noise_sigma: 3.0,
                blur_sigma_px: 0.8,
                supersampling: 3,
                seed: u64::from(i),
                ..RenderSettings::default()
            },
        )
        .unwrap();
        let raw = tracker(&[Family::TagStandard41h12])
            .observe(&image, &camera)
            .unwrap()
            .tags[0]
            .fit
            .camera_from_object();
        let stamp = Timestamp::new(u64::from(i) * 33_333_333, 5_000 + u64::from(i) * 33_333_333);
        bus.publish(StreamMessage::Color(Arc::new(Frame::new(
            u64::from(100 + i),
            stamp,
            image,
        ))));
        let frame = markers
            .recv_timeout(Duration::from_secs(30))
            .expect("a marker set");
        assert_eq!((frame.seq, frame.stamp), (u64::from(100 + i), stamp));
        let [detection] = frame.payload.detections.as_slice() else {
            panic!("one tag");
        };
        assert_eq!(
            (detection.family.as_str(), detection.marker_id),
            ("tagStandard41h12", 2)
        );
        let filtered = DPose::from_pose(&detection.camera_from_marker);
        if (4..12).contains(&i) {
            raw_still.push(raw.translation);
            filtered_still.push(filtered.translation);
        }
        if i == 19 {
            // Every step blends at least α(f_c,min), so on a ramp from rest the lag never
            // exceeds the plain low-pass's steady lag v / (2π f_c,min); plus detection error.
            let lag_bound = 0.3 / (std::f64::consts::TAU * config.filter.min_cutoff_hz);
            let error = filtered.translation.x - truth.translation.x;
            println!(
                "lag after 7 frames at 0.3 m/s: {:.1} mm (bound {:.1} mm)",
                -error * 1e3,
                lag_bound * 1e3
            );
            assert!(
                error.abs() < lag_bound + 0.005,
                "lag {error} vs {lag_bound}"
            );
        }
    }
    runner.stop();
    assert_eq!(runner.status().drops(), 0);
    // At rest the filter removes part of the detection jitter (spread about the mean).
    let spread = |v: &[DVec3]| {
        let mean = v.iter().sum::<DVec3>() / v.len() as f64;
        (v.iter().map(|p| p.distance_squared(mean)).sum::<f64>() / v.len() as f64).sqrt()
    };
    let (raw_jitter, filtered_jitter) = (spread(&raw_still), spread(&filtered_still));
    println!(
        "still-tag jitter: raw {:.3} mm, filtered {:.3} mm",
        raw_jitter * 1e3,
        filtered_jitter * 1e3
    );
    assert!(
        filtered_jitter < 0.7 * raw_jitter,
        "{filtered_jitter} vs {raw_jitter}"
    );
}
