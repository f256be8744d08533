//! The ArUco backend against rendered markers with known poses: OpenCV's own marker bitmaps
//! printed on planes, seen through a calibrated camera (distortion included), blurred, noisy,
//! tilted and partly hidden. Run with `--nocapture` for the accuracy table.
#![cfg(feature = "opencv")]

use glam::{DQuat, DVec2, DVec3};
use relight_backends::DeviceError;
use relight_backends::markers::aruco::{
    ArucoConfig, ArucoDictionary, ArucoError, ArucoTracker, CornerRefinement, Dictionary,
};
use relight_backends::markers::board::{BoardConfig, corners_in_board};
use relight_backends::markers::pose::{
    DPose, PoseSettings, estimate_square_pose, square_corners_in_marker,
};
use relight_backends::markers::render::{
    Occluder, PlanarTexture, RenderSettings, Surface, TagBitmap, project_points, render,
};
use relight_backends::markers::tag36h11::tag36h11_cells;
use relight_backends::sources::MarkerTracker;
use relight_core::camera::{CameraModel, Pinhole};
use relight_core::{Image, MarkerDetection, MarkerSet, PixelFormat};

/// A 640 × 480 webcam-like camera with real (mild barrel) distortion, so every pixel goes
/// through the full camera model.
fn camera() -> CameraModel {
    CameraModel::Pinhole(Pinhole {
        width: 640,
        height: 480,
        fx: 600.0,
        fy: 600.0,
        cx: 318.2,
        cy: 241.7,
        k1: -0.08,
        k2: 0.05,
        p1: 0.0005,
        p2: -0.0003,
        k3: 0.0,
    })
}

const WHITE: f32 = 0.85;
const BLACK: f32 = 0.06;

fn marker_surface(bitmap: &TagBitmap, size_m: f64, camera_from_marker: DPose) -> Surface {
    Surface {
        camera_from_surface: camera_from_marker,
        texture: PlanarTexture::tag(bitmap, size_m, 1, WHITE, BLACK),
    }
}

fn settings(blur_sigma_px: f64, noise_sigma: f64, seed: u64) -> RenderSettings {
    RenderSettings {
        background: 0.35,
        blur_sigma_px,
        noise_sigma,
        seed,
        supersampling: 4,
        ..RenderSettings::default()
    }
}

/// A marker `distance_m` in front of the camera, off-axis by `offset`, tilted by `tilt_deg`
/// about an in-plane axis at `axis_deg`, and spun in its plane by `spin_deg`.
fn marker_pose(
    distance_m: f64,
    offset: DVec2,
    tilt_deg: f64,
    axis_deg: f64,
    spin_deg: f64,
) -> DPose {
    let axis_rad = axis_deg.to_radians();
    let tilt = DQuat::from_axis_angle(
        DVec3::new(axis_rad.cos(), axis_rad.sin(), 0.0),
        tilt_deg.to_radians(),
    );
    let spin = DQuat::from_rotation_z(spin_deg.to_radians());
    DPose::new(tilt * spin, DVec3::new(offset.x, offset.y, -distance_m))
}

fn truth_corners(camera_from_marker: &DPose, size_m: f64) -> [DVec2; 4] {
    let pixels = project_points(
        &camera(),
        camera_from_marker,
        &square_corners_in_marker(size_m),
    )
    .expect("marker in view");
    [pixels[0], pixels[1], pixels[2], pixels[3]]
}

fn corner_rms_px(detected: &[glam::Vec2; 4], truth: &[DVec2; 4]) -> f64 {
    let sum: f64 = detected
        .iter()
        .zip(truth)
        .map(|(d, t)| d.as_dvec2().distance_squared(*t))
        .sum();
    (sum / 4.0).sqrt()
}

fn translation_error_m(detection: &MarkerDetection, truth: &DPose) -> f64 {
    DPose::from_pose(&detection.camera_from_marker)
        .translation
        .distance(truth.translation)
}

fn rotation_error_deg(detection: &MarkerDetection, truth: &DPose) -> f64 {
    DPose::from_pose(&detection.camera_from_marker)
        .angle_to(truth)
        .to_degrees()
}

fn tracker(dictionary: ArucoDictionary, size_m: f64) -> ArucoTracker {
    ArucoTracker::new(&ArucoConfig::new(dictionary, size_m)).expect("valid configuration")
}

fn detect(tracker: &mut ArucoTracker, image: &Image) -> MarkerSet {
    let mut out = MarkerSet::default();
    tracker
        .detect(image, &camera(), &mut out)
        .expect("detection runs");
    out
}

#[test]
fn every_opencv_dictionary_has_a_name_and_artoolkit_is_absent() {
    for dictionary in ArucoDictionary::ALL {
        assert_eq!(
            ArucoDictionary::from_name(dictionary.name()),
            Some(dictionary)
        );
        let loaded = Dictionary::load(dictionary).expect("OpenCV knows it");
        assert!(
            loaded.count() >= 30 && (4..=7).contains(&loaded.bits()),
            "{dictionary}"
        );
    }
    assert_eq!(
        ArucoDictionary::from_name("DICT_APRILTAG_36h11"),
        Some(ArucoDictionary::AprilTag36h11)
    );
    let original = Dictionary::load(ArucoDictionary::ArucoOriginal).unwrap();
    assert_eq!((original.bits(), original.count()), (5, 1024));
    let tag36h11 = Dictionary::load(ArucoDictionary::AprilTag36h11).unwrap();
    assert_eq!((tag36h11.bits(), tag36h11.count()), (6, 587));
    assert_eq!(ArucoDictionary::AprilTag36h11.family(), "tag36h11");
    assert_eq!(ArucoDictionary::Aruco5x5_100.family(), "aruco_5x5_100");
    // OpenCV 4.6 has no ARToolKit (matrix-code) dictionary.
    for name in ["artoolkit", "artoolkit_3x3", "aruco_mip_36h12"] {
        assert_eq!(ArucoDictionary::from_name(name), None);
        let json = serde_json::json!({ "dictionary": name, "size_m": 0.1 });
        let error = serde_json::from_value::<ArucoConfig>(json).unwrap_err();
        assert!(error.to_string().contains("no ARToolKit"), "{error}");
    }
}

#[test]
fn opencv_apriltag_36h11_is_the_simulators_tag36h11() {
    let dictionary = Dictionary::load(ArucoDictionary::AprilTag36h11).unwrap();
    for id in 0..32 {
        let opencv = dictionary.tag_bitmap(id).unwrap();
        let sim = tag36h11_cells(id).unwrap();
        assert_eq!((opencv.total_cells, opencv.size_cells), (8, 8));
        for row in 0..8 {
            for col in 0..8 {
                assert_eq!(
                    opencv.white_at(col, row),
                    sim[row as usize + 1][col as usize + 1],
                    "id {id} cell ({col}, {row})"
                );
            }
        }
    }
    assert!(matches!(
        dictionary.tag_bitmap(587),
        Err(ArucoError::UnknownMarker { count: 587, .. })
    ));
}

#[test]
fn config_keys_and_defaults() {
    let json = serde_json::json!({
        "dictionary": "5x5_100",
        "size_m": 0.12,
        "sizes": [{ "marker_id": 7, "size_m": 0.04 }],
        "corner_refinement": "contour",
        "max_correction_bits": 2,
        "pose": { "corner_sigma_px": 0.3 },
    });
    let config: ArucoConfig = serde_json::from_value(json).unwrap();
    assert_eq!(config.dictionary, ArucoDictionary::Aruco5x5_100);
    assert_eq!(config.tag_sizes().unwrap().size_m(7), 0.04);
    assert_eq!(config.tag_sizes().unwrap().size_m(8), 0.12);
    assert_eq!(
        config.pose.max_iterations,
        PoseSettings::default().max_iterations
    );
    let minimal: ArucoConfig =
        serde_json::from_value(serde_json::json!({ "size_m": 0.1 })).unwrap();
    assert_eq!(minimal, ArucoConfig::new(ArucoDictionary::Aruco4x4_50, 0.1));
    let tracker = ArucoTracker::new(&minimal).unwrap();
    assert_eq!(tracker.family(), "aruco_4x4_50");
    for bad in [
        serde_json::json!({}),
        serde_json::json!({ "size_m": 0.1, "dictionry": "4x4_50" }),
        serde_json::json!({ "size_m": 0.1, "corner_refinement": "magic" }),
    ] {
        assert!(serde_json::from_value::<ArucoConfig>(bad).is_err());
    }
}

#[test]
fn bad_configuration_is_a_config_error() {
    let base = ArucoConfig::new(ArucoDictionary::Aruco4x4_50, 0.1);
    let cases = [
        ArucoConfig {
            size_m: 0.0,
            ..base.clone()
        },
        ArucoConfig {
            size_m: f64::NAN,
            ..base.clone()
        },
        ArucoConfig {
            threshold_window_min_px: 30,
            ..base.clone()
        },
        ArucoConfig {
            max_reprojection_rms_px: -1.0,
            ..base.clone()
        },
        ArucoConfig {
            min_perimeter_rate: 5.0,
            ..base.clone()
        },
    ];
    for config in cases {
        let error = ArucoTracker::new(&config).unwrap_err();
        assert!(matches!(error, ArucoError::Config(_)), "{error}");
        assert!(matches!(
            DeviceError::from(error),
            DeviceError::Config { .. }
        ));
    }
    // 4x4_50 has minimum Hamming distance 4: at most one bit can be corrected.
    let error = ArucoTracker::new(&ArucoConfig {
        max_correction_bits: Some(2),
        ..base.clone()
    })
    .unwrap_err();
    assert_eq!(
        error,
        ArucoError::TooManyCorrectionBits {
            dictionary: ArucoDictionary::Aruco4x4_50,
            requested: 2,
            maximum: 1
        }
    );
    // A board needs markers of this dictionary.
    let board = |family: &str, first_id: u32| BoardConfig::Grid {
        name: "board".into(),
        family: family.into(),
        first_id,
        cols: 2,
        rows: 2,
        tag_size_m: 0.05,
        gap_m: 0.01,
    };
    for bad_board in [board("tag36h11", 0), board("aruco_4x4_50", 48)] {
        let config = ArucoConfig {
            board: Some(bad_board),
            ..base.clone()
        };
        assert!(ArucoTracker::new(&config).is_err());
    }
}

#[test]
fn bad_images_are_typed_errors() {
    let mut tracker = tracker(ArucoDictionary::Aruco4x4_50, 0.1);
    let mut out = MarkerSet::default();
    let cases = [
        (
            Image::new(0, 0, PixelFormat::Rgb8),
            ArucoError::EmptyImage {
                width: 0,
                height: 0,
            },
        ),
        (
            Image::new(640, 480, PixelFormat::DepthU16Mm),
            ArucoError::UnsupportedFormat(PixelFormat::DepthU16Mm),
        ),
        (
            Image::new(640, 480, PixelFormat::Rgba16F),
            ArucoError::UnsupportedFormat(PixelFormat::Rgba16F),
        ),
        (
            Image::new(320, 240, PixelFormat::Mono8),
            ArucoError::CameraMismatch {
                width: 320,
                height: 240,
                camera_width: 640,
                camera_height: 480,
            },
        ),
    ];
    for (image, expected) in cases {
        assert_eq!(
            tracker.track(&image, &camera(), &mut out),
            Err(expected.clone())
        );
        let device_error = tracker.detect(&image, &camera(), &mut out).unwrap_err();
        match expected {
            ArucoError::CameraMismatch { .. } => {
                assert!(matches!(device_error, DeviceError::Config { .. }))
            }
            _ => assert!(matches!(device_error, DeviceError::BadData { .. })),
        }
        assert!(out.detections.is_empty());
    }
    // A blank frame is not an error, just no markers.
    let blank = Image::new(640, 480, PixelFormat::Mono8);
    tracker.track(&blank, &camera(), &mut out).unwrap();
    assert!(out.detections.is_empty());
}

/// Pose error allowed for a detection whose corners are `corner_rms_px` off the truth: three
/// standard deviations of the fit's covariance (first-order propagation of corner noise through
/// the pose, Hartley & Zisserman §5.2), rescaled from the noise the fit assumed to the corner
/// error actually made (at least 0.1 px). Returns (metres, degrees).
fn pose_tolerance(
    fit: &relight_backends::markers::pose::PoseFit,
    corner_rms_px: f64,
) -> (f64, f64) {
    let scale = corner_rms_px.max(0.1) / fit.sigma_px;
    (
        3.0 * fit.translation_sigma_m() * scale,
        3.0 * fit.rotation_sigma_deg() * scale,
    )
}

/// The shared solver's fit of a detection's corners: the tracker must report exactly its pose.
fn refit(detection: &MarkerDetection, size_m: f64) -> relight_backends::markers::pose::PoseFit {
    let fit = estimate_square_pose(
        &detection.corners_px.map(|c| c.as_dvec2()),
        size_m,
        &camera(),
        &PoseSettings::default(),
    )
    .expect("the detection's corners have a pose");
    assert_eq!(
        fit.detection(&detection.family, detection.marker_id, detection.corners_px),
        *detection,
        "the tracker's pose is the shared solver's"
    );
    fit
}

/// Renders one marker and returns the tracker's detection of `marker_id`, if any.
fn detect_marker(
    tracker: &mut ArucoTracker,
    bitmap: &TagBitmap,
    marker_id: u32,
    size_m: f64,
    truth: DPose,
    render_settings: &RenderSettings,
    occluders: &[Occluder],
) -> Option<MarkerDetection> {
    let image = render(
        &camera(),
        &[marker_surface(bitmap, size_m, truth)],
        occluders,
        render_settings,
    )
    .unwrap();
    let set = detect(tracker, &image);
    assert!(
        set.detections.iter().all(|d| d.marker_id == marker_id),
        "only the rendered marker is reported: {:?}",
        set.detections
    );
    set.detections.into_iter().next()
}

/// Per distance × blur: (corner RMS px, translation error mm, rotation error °) of each view.
type Table = Vec<(f64, f64, Vec<(f64, f64, f64)>)>;

fn print_table(title: &str, table: &Table) {
    println!("\n{title}");
    println!(
        "| distance | blur σ | corner RMS (px) | translation error (mm) | rotation error (°) |"
    );
    println!("|---|---|---|---|---|");
    for (distance_m, blur, stats) in table {
        let max = |f: fn(&(f64, f64, f64)) -> f64| stats.iter().map(f).fold(0.0, f64::max);
        let mean =
            |f: fn(&(f64, f64, f64)) -> f64| stats.iter().map(f).sum::<f64>() / stats.len() as f64;
        println!(
            "| {distance_m} m | {blur} px | {:.2} (max {:.2}) | {:.1} (max {:.1}) | {:.2} (max {:.2}) |",
            mean(|s| s.0),
            max(|s| s.0),
            mean(|s| s.1),
            max(|s| s.1),
            mean(|s| s.2),
            max(|s| s.2),
        );
    }
}

/// A 15 cm `4x4_50` marker at 0.5, 1 and 2 m, tilted 30°, 45° and 60° about different axes,
/// under blur σ 0, 1, 2 px and read noise σ 2 codes, for the default refinement (`edges`, with
/// the corner check on) and, for comparison, OpenCV's own `subpix` and `apriltag` (check off,
/// so that their raw corners are measured).
///
/// Each view must be found; its corners must be as accurate as the refinement allows (bounds
/// below, about twice the worst measured); its pose must be the shared solver's fit of those
/// corners and within [`pose_tolerance`] of the truth.
#[test]
fn pose_accuracy_over_distance_and_blur() {
    const SIZE_M: f64 = 0.15;
    const MARKER_ID: u32 = 23;
    let dictionary = ArucoDictionary::Aruco4x4_50;
    let bitmap = Dictionary::load(dictionary)
        .unwrap()
        .tag_bitmap(MARKER_ID)
        .unwrap();
    // Corner RMS bounds (px) by blur σ and distance. Lines fitted along whole edges are not
    // moved by blur; at 2 m and σ 2 px the blur reaches across the 7 px border cells. `subpix`
    // (cornerSubPix) pulls a blurred convex corner into the square by ~0.3 σ. The AprilTag quad
    // fit is unbiased but noisier.
    let edges_bound = |blur: f64, distance_m: f64| {
        if blur <= 1.0 || distance_m <= 1.0 {
            0.3
        } else {
            1.2
        }
    };
    let subpix_bound = |blur: f64, distance_m: f64| match (blur, distance_m) {
        (b, _) if b <= 1.0 => 0.6,
        (_, d) if d <= 1.0 => 1.2,
        _ => 3.0,
    };
    let apriltag_bound = |blur: f64, _distance_m: f64| if blur <= 1.0 { 0.6 } else { 1.0 };
    type CornerBound = fn(f64, f64) -> f64;
    let refinements: [(CornerRefinement, bool, &str, CornerBound); 3] = [
        (
            CornerRefinement::Edges,
            true,
            "edges (the default, corner check on)",
            edges_bound,
        ),
        (
            CornerRefinement::Subpix,
            false,
            "subpix (OpenCV cornerSubPix, cell-scaled window)",
            subpix_bound,
        ),
        (
            CornerRefinement::Apriltag,
            false,
            "apriltag (OpenCV's AprilTag 2 quad fit, ~50× slower)",
            apriltag_bound,
        ),
    ];
    let mut trackers: Vec<ArucoTracker> = refinements
        .iter()
        .map(|(refinement, verify_corners, ..)| {
            let config = ArucoConfig {
                corner_refinement: *refinement,
                verify_corners: *verify_corners,
                ..ArucoConfig::new(dictionary, SIZE_M)
            };
            ArucoTracker::new(&config).unwrap()
        })
        .collect();
    let mut tables: Vec<Table> = vec![Vec::new(); refinements.len()];
    for distance_m in [0.5, 1.0, 2.0] {
        for blur in [0.0, 1.0, 2.0] {
            let mut stats = vec![Vec::new(); refinements.len()];
            for (k, (tilt_deg, axis_deg, spin_deg)) in
                [(30.0, 10.0, 0.0), (45.0, 100.0, 35.0), (60.0, 200.0, -70.0)]
                    .into_iter()
                    .enumerate()
            {
                let offset = DVec2::new(0.04 * distance_m, -0.03 * distance_m) * (k as f64 - 1.0);
                let truth = marker_pose(distance_m, offset, tilt_deg, axis_deg, spin_deg);
                let image = render(
                    &camera(),
                    &[marker_surface(&bitmap, SIZE_M, truth)],
                    &[],
                    &settings(blur, 2.0, 7 + k as u64),
                )
                .unwrap();
                let corners_truth = truth_corners(&truth, SIZE_M);
                for (r, (refinement, _, _, corner_bound)) in refinements.iter().enumerate() {
                    let case = format!(
                        "{refinement:?} at {distance_m} m, blur σ {blur} px, tilt {tilt_deg}°"
                    );
                    let set = detect(&mut trackers[r], &image);
                    assert_eq!(set.detections.len(), 1, "{case}: {:?}", set.detections);
                    let found = &set.detections[0];
                    assert_eq!(
                        (found.family.as_str(), found.marker_id),
                        ("aruco_4x4_50", MARKER_ID)
                    );
                    let corner_rms = corner_rms_px(&found.corners_px, &corners_truth);
                    assert!(
                        corner_rms <= corner_bound(blur, distance_m),
                        "{case}: corners {corner_rms:.2} px off"
                    );
                    let fit = refit(found, SIZE_M);
                    let (t_tol_m, r_tol_deg) = pose_tolerance(&fit, corner_rms);
                    let t_err_m = translation_error_m(found, &truth);
                    let r_err_deg = rotation_error_deg(found, &truth);
                    assert!(
                        t_err_m <= t_tol_m && r_err_deg <= r_tol_deg,
                        "{case}: pose off by {:.1} mm / {r_err_deg:.2}° (allowed {:.1} mm / \
                         {r_tol_deg:.2}° for corners {corner_rms:.2} px off)",
                        t_err_m * 1e3,
                        t_tol_m * 1e3
                    );
                    stats[r].push((corner_rms, t_err_m * 1e3, r_err_deg));
                }
            }
            for (table, stats) in tables.iter_mut().zip(stats) {
                table.push((distance_m, blur, stats));
            }
        }
    }
    for ((_, _, title, _), table) in refinements.iter().zip(&tables) {
        print_table(&format!("corner_refinement = {title}"), table);
    }
}

#[test]
fn rgb8_and_mono8_frames_give_the_same_detection() {
    let dictionary = ArucoDictionary::Aruco6x6_250;
    let bitmap = Dictionary::load(dictionary)
        .unwrap()
        .tag_bitmap(201)
        .unwrap();
    let truth = marker_pose(0.8, DVec2::new(0.05, 0.02), 35.0, 60.0, 15.0);
    let surfaces = [marker_surface(&bitmap, 0.12, truth)];
    let mut tracker = tracker(dictionary, 0.12);
    let mut sets = Vec::new();
    for format in [PixelFormat::Rgb8, PixelFormat::Mono8] {
        let image = render(
            &camera(),
            &surfaces,
            &[],
            &RenderSettings {
                format,
                ..settings(1.0, 0.0, 5)
            },
        )
        .unwrap();
        sets.push(detect(&mut tracker, &image));
    }
    assert_eq!(sets[0].detections.len(), 1);
    assert_eq!(sets[0].detections[0].marker_id, 201);
    assert_eq!(sets[0].detections[0].family, "aruco_6x6_250");
    // Without read noise (drawn per channel) a grey RGB frame converts to exactly the grey
    // values the Mono8 frame carries.
    assert_eq!(sets[0], sets[1]);
}

/// OpenCV 4's AprilTag codes are upside down against the AprilTag library's prints; the
/// simulator's (official) `tag36h11` print must still come out with its corners and pose the
/// right way up.
#[test]
fn official_apriltag_prints_are_tracked_the_right_way_up() {
    const SIZE_M: f64 = 0.1;
    let mut tracker = tracker(ArucoDictionary::AprilTag36h11, SIZE_M);
    for (marker_id, spin_deg) in [(0, 0.0), (5, 20.0), (17, 110.0), (31, -150.0)] {
        let truth = marker_pose(0.7, DVec2::new(-0.04, 0.03), 35.0, 80.0, spin_deg);
        let bitmap = TagBitmap::tag36h11(marker_id).unwrap();
        let image = render(
            &camera(),
            &[Surface {
                camera_from_surface: truth,
                texture: PlanarTexture::tag(&bitmap, SIZE_M, 1, WHITE, BLACK),
            }],
            &[],
            &settings(1.0, 2.0, 11),
        )
        .unwrap();
        let set = detect(&mut tracker, &image);
        assert_eq!(set.detections.len(), 1, "tag {marker_id}");
        let found = &set.detections[0];
        assert_eq!(
            (found.family.as_str(), found.marker_id),
            ("tag36h11", marker_id)
        );
        let corner_rms = corner_rms_px(&found.corners_px, &truth_corners(&truth, SIZE_M));
        assert!(
            corner_rms < 0.6,
            "tag {marker_id}: corners {corner_rms:.2} px off"
        );
        let (t_tol_m, r_tol_deg) = pose_tolerance(&refit(found, SIZE_M), corner_rms);
        assert!(translation_error_m(found, &truth) <= t_tol_m);
        assert!(rotation_error_deg(found, &truth) <= r_tol_deg);
    }
}

/// `max_correction_bits` bounds how many payload bits may be wrong: a print with one data cell
/// flipped is rejected with 0 and decoded to its own ID with 1. (OpenCV's default rate, 0.6 of
/// `4x4_50`'s maximum of 1, truncates to 0.)
#[test]
fn correction_bits_bound_the_accepted_bit_errors() {
    let dictionary = ArucoDictionary::Aruco4x4_50;
    let mut bitmap = Dictionary::load(dictionary)
        .unwrap()
        .tag_bitmap(12)
        .unwrap();
    let side = bitmap.total_cells as usize;
    let data_cell = 2 * side + 3;
    bitmap.cells[data_cell] = !bitmap.cells[data_cell];
    let truth = marker_pose(0.6, DVec2::ZERO, 20.0, 45.0, 0.0);
    let image = render(
        &camera(),
        &[marker_surface(&bitmap, 0.1, truth)],
        &[],
        &settings(0.5, 1.0, 2),
    )
    .unwrap();
    let found_with = |bits: Option<u32>| {
        let config = ArucoConfig {
            max_correction_bits: bits,
            ..ArucoConfig::new(dictionary, 0.1)
        };
        detect(&mut ArucoTracker::new(&config).unwrap(), &image).detections
    };
    assert!(found_with(Some(0)).is_empty());
    assert!(found_with(None).is_empty());
    let corrected = found_with(Some(1));
    assert_eq!(corrected.len(), 1);
    assert_eq!(corrected[0].marker_id, 12);
}

/// Markers half hidden behind a dark or bright card at every corner, edge and across the
/// middle: each is either reported with a pose as good as an unhidden marker's, or not at all.
#[test]
fn an_occluded_marker_is_found_right_or_not_at_all() {
    const SIZE_M: f64 = 0.12;
    let dictionary = ArucoDictionary::Aruco5x5_100;
    let bitmap = Dictionary::load(dictionary)
        .unwrap()
        .tag_bitmap(42)
        .unwrap();
    let mut tracker = tracker(dictionary, SIZE_M);
    let truth = marker_pose(0.8, DVec2::new(0.03, -0.02), 35.0, 30.0, 20.0);
    let render_settings = settings(1.0, 2.0, 21);
    let clean = detect_marker(
        &mut tracker,
        &bitmap,
        42,
        SIZE_M,
        truth,
        &render_settings,
        &[],
    )
    .expect("the unhidden marker is found");
    let clean_rms = corner_rms_px(&clean.corners_px, &truth_corners(&truth, SIZE_M));
    let (t_tol_m, r_tol_deg) = pose_tolerance(&refit(&clean, SIZE_M), clean_rms.max(0.5));

    let corners = truth_corners(&truth, SIZE_M);
    let lo = corners
        .iter()
        .fold(DVec2::splat(f64::INFINITY), |a, c| a.min(*c));
    let hi = corners
        .iter()
        .fold(DVec2::splat(f64::NEG_INFINITY), |a, c| a.max(*c));
    let extent = hi - lo;
    let rect = |fx0: f64, fy0: f64, fx1: f64, fy1: f64| {
        (
            lo + extent * DVec2::new(fx0, fy0),
            lo + extent * DVec2::new(fx1, fy1),
        )
    };
    let mut placements = vec![
        rect(-0.1, -0.1, 0.3, 0.3),
        rect(0.7, -0.1, 1.1, 0.3),
        rect(0.7, 0.7, 1.1, 1.1),
        rect(-0.1, 0.7, 0.3, 1.1),
        rect(0.35, -0.1, 0.65, 0.2),
        rect(0.8, 0.35, 1.1, 0.65),
        rect(0.35, 0.8, 0.65, 1.1),
        rect(-0.1, 0.35, 0.2, 0.65),
        rect(0.4, 0.4, 0.6, 0.6),
        rect(0.45, -0.2, 0.55, 1.2),
        rect(-0.2, 0.45, 1.2, 0.55),
    ];
    // The marker's own corners, each covered by a small patch.
    placements.extend(corners.iter().map(|c| (*c - 4.0, *c + 4.0)));
    let (mut found, mut absent) = (0, 0);
    for (min_px, max_px) in placements {
        for radiance in [0.03, 0.95] {
            let occluder = Occluder {
                min_px,
                max_px,
                radiance,
            };
            match detect_marker(
                &mut tracker,
                &bitmap,
                42,
                SIZE_M,
                truth,
                &render_settings,
                &[occluder],
            ) {
                Some(detection) => {
                    let t_err_m = translation_error_m(&detection, &truth);
                    let r_err_deg = rotation_error_deg(&detection, &truth);
                    assert!(
                        t_err_m <= t_tol_m && r_err_deg <= r_tol_deg,
                        "occluder {min_px}–{max_px} ({radiance}): wrong pose, {:.1} mm / \
                         {r_err_deg:.2}° off (allowed {:.1} mm / {r_tol_deg:.2}°)",
                        t_err_m * 1e3,
                        t_tol_m * 1e3
                    );
                    found += 1;
                }
                None => absent += 1,
            }
        }
    }
    println!("occluded views: {found} found with a good pose, {absent} not reported, 0 wrong");
}

/// A 2 × 2 board of `4x4_50` markers: one pose from all sixteen corners, which survives a
/// hidden tag.
#[test]
fn a_board_of_markers_gives_one_pose() {
    const TAG_M: f64 = 0.08;
    let dictionary = ArucoDictionary::Aruco4x4_50;
    let board_config = BoardConfig::Grid {
        name: "desk".into(),
        family: "aruco_4x4_50".into(),
        first_id: 10,
        cols: 2,
        rows: 2,
        tag_size_m: TAG_M,
        gap_m: 0.03,
    };
    let config = ArucoConfig {
        board: Some(board_config),
        ..ArucoConfig::new(dictionary, TAG_M)
    };
    let mut tracker = ArucoTracker::new(&config).unwrap();
    let board = tracker.board().unwrap().clone();
    let loaded = Dictionary::load(dictionary).unwrap();
    let camera_from_board = marker_pose(1.3, DVec2::new(-0.05, 0.04), 40.0, 120.0, 10.0);
    let mut surfaces: Vec<Surface> = board
        .tags()
        .iter()
        .map(|tag| {
            marker_surface(
                &loaded.tag_bitmap(tag.marker_id).unwrap(),
                TAG_M,
                camera_from_board * DPose::from_pose(&tag.board_from_marker),
            )
        })
        .collect();
    // The white card the tags are printed on, just behind the prints.
    surfaces.push(Surface {
        camera_from_surface: camera_from_board
            * DPose::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, -1e-3)),
        texture: PlanarTexture::uniform(0.3, 0.3, WHITE).unwrap(),
    });
    let hidden_tag = board.tag(13).unwrap();
    let hidden_corners =
        project_points(&camera(), &camera_from_board, &corners_in_board(hidden_tag)).unwrap();
    let lo = hidden_corners
        .iter()
        .fold(DVec2::splat(f64::INFINITY), |a, c| a.min(*c));
    let hi = hidden_corners
        .iter()
        .fold(DVec2::splat(f64::NEG_INFINITY), |a, c| a.max(*c));
    // A card over the middle of tag 13 (its bounding box, shrunk so as to stay off tag 12).
    let card = Occluder {
        min_px: lo + (hi - lo) * 0.15,
        max_px: hi - (hi - lo) * 0.15,
        radiance: 0.2,
    };
    for (occluders, tags) in [
        (vec![], vec![10, 11, 12, 13]),
        (vec![card], vec![10, 11, 12]),
    ] {
        let image = render(&camera(), &surfaces, &occluders, &settings(1.0, 2.0, 4)).unwrap();
        let set = detect(&mut tracker, &image);
        let mut ids: Vec<u32> = set
            .detections
            .iter()
            .filter(|d| d.family == "aruco_4x4_50")
            .map(|d| d.marker_id)
            .collect();
        ids.sort_unstable();
        assert_eq!(ids, tags);
        let boards: Vec<&MarkerDetection> = set
            .detections
            .iter()
            .filter(|d| d.family == "desk")
            .collect();
        assert_eq!(boards.len(), 1, "one board detection");
        let found = boards[0];
        assert_eq!(found.marker_id, 10);
        // Tolerance from the tags' corner accuracy, propagated through the board's own fit.
        let tag_corners: Vec<(u32, [DVec2; 4])> = set
            .detections
            .iter()
            .filter(|d| d.family == "aruco_4x4_50")
            .map(|d| (d.marker_id, d.corners_px.map(|c| c.as_dvec2())))
            .collect();
        let corner_rms = (tag_corners
            .iter()
            .map(|(id, corners)| {
                let truth = project_points(
                    &camera(),
                    &camera_from_board,
                    &corners_in_board(board.tag(*id).unwrap()),
                )
                .unwrap();
                corners
                    .iter()
                    .zip(&truth)
                    .map(|(c, t)| c.distance_squared(*t))
                    .sum::<f64>()
            })
            .sum::<f64>()
            / (4 * tag_corners.len()) as f64)
            .sqrt();
        let fit = board
            .estimate(&tag_corners, &camera(), &PoseSettings::default())
            .unwrap();
        assert_eq!(fit.tags_used.len(), tags.len());
        let (t_tol_m, r_tol_deg) = pose_tolerance(&fit.fit, corner_rms);
        let t_err_m = translation_error_m(found, &camera_from_board);
        let r_err_deg = rotation_error_deg(found, &camera_from_board);
        println!(
            "board with {} tags: corners {corner_rms:.2} px, pose {:.1} mm / {r_err_deg:.2}° off \
             (allowed {:.1} mm / {r_tol_deg:.2}°)",
            tags.len(),
            t_err_m * 1e3,
            t_tol_m * 1e3
        );
        assert!(t_err_m <= t_tol_m && r_err_deg <= r_tol_deg);
    }
}

/// The tracker under the device contract: colour frames in on the bus, marker sets out with
/// the colour frame's sequence number.
#[test]
fn marker_device_publishes_aruco_detections_of_colour_frames() {
    use std::sync::Arc;
    use std::time::{Duration, Instant};

    use relight_backends::device::{Backoff, DeviceRunner};
    use relight_backends::markers::aruco::aruco_device;
    use relight_backends::markers::one_euro::OneEuroConfig;
    use relight_core::bus::Bus;
    use relight_core::{Frame, StreamMessage, Timestamp};

    let dictionary = ArucoDictionary::Aruco4x4_50;
    let bitmap = Dictionary::load(dictionary).unwrap().tag_bitmap(7).unwrap();
    let truth = marker_pose(0.6, DVec2::ZERO, 30.0, 0.0, 0.0);
    let image = render(
        &camera(),
        &[marker_surface(&bitmap, 0.1, truth)],
        &[],
        &settings(1.0, 2.0, 9),
    )
    .unwrap();
    let bus = Arc::new(Bus::new());
    let markers = bus.markers.subscribe(8);
    let config = ArucoConfig {
        filter: OneEuroConfig {
            enabled: false,
            ..OneEuroConfig::default()
        },
        ..ArucoConfig::new(dictionary, 0.1)
    };
    let device = aruco_device(&config, camera()).unwrap();
    let mut runner =
        DeviceRunner::spawn("markers", Box::new(device), bus.clone(), Backoff::default()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while bus.color.subscriber_count() == 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(2));
    }
    bus.publish(StreamMessage::Color(Arc::new(Frame::new(
        41,
        Timestamp::new(5, 6),
        image,
    ))));
    let frame = markers
        .recv_timeout(Duration::from_secs(20))
        .expect("a marker set");
    runner.stop();
    assert_eq!(frame.seq, 41);
    assert_eq!(frame.stamp, Timestamp::new(5, 6));
    assert_eq!(frame.payload.detections.len(), 1);
    let found = &frame.payload.detections[0];
    assert_eq!(
        (found.family.as_str(), found.marker_id),
        ("aruco_4x4_50", 7)
    );
    assert!(translation_error_m(found, &truth) < 0.01);
}

/// What the corner check is for: `subpix` corners next to a fingertip are pulled pixels away
/// and give a confidently wrong pose; with the check on, that marker is not reported.
#[test]
fn the_corner_check_drops_a_marker_whose_corner_is_hidden() {
    const SIZE_M: f64 = 0.12;
    let dictionary = ArucoDictionary::Aruco5x5_100;
    let bitmap = Dictionary::load(dictionary)
        .unwrap()
        .tag_bitmap(42)
        .unwrap();
    let truth = marker_pose(0.8, DVec2::new(0.03, -0.02), 35.0, 30.0, 20.0);
    let corner = truth_corners(&truth, SIZE_M)[1];
    let fingertip = Occluder {
        min_px: corner - 4.0,
        max_px: corner + 4.0,
        radiance: 0.03,
    };
    let render_settings = settings(1.0, 2.0, 21);
    let with_check = |verify_corners: bool| {
        // The reprojection gate alone catches some hidden corners (a square fit has two
        // residual degrees of freedom); open it to see what the corner check does.
        let config = ArucoConfig {
            corner_refinement: CornerRefinement::Subpix,
            verify_corners,
            max_reprojection_rms_px: 10.0,
            ..ArucoConfig::new(dictionary, SIZE_M)
        };
        let mut tracker = ArucoTracker::new(&config).unwrap();
        let clean = detect_marker(
            &mut tracker,
            &bitmap,
            42,
            SIZE_M,
            truth,
            &render_settings,
            &[],
        )
        .expect("the unhidden marker is found");
        let hidden = detect_marker(
            &mut tracker,
            &bitmap,
            42,
            SIZE_M,
            truth,
            &render_settings,
            &[fingertip],
        );
        (clean, hidden)
    };
    let (clean, hidden) = with_check(false);
    let clean_rms = corner_rms_px(&clean.corners_px, &truth_corners(&truth, SIZE_M));
    let (t_tol_m, r_tol_deg) = pose_tolerance(&refit(&clean, SIZE_M), clean_rms.max(0.5));
    let hidden = hidden.expect("OpenCV still finds the marker");
    assert!(
        translation_error_m(&hidden, &truth) > t_tol_m
            || rotation_error_deg(&hidden, &truth) > r_tol_deg,
        "without the check the hidden corner gives a wrong pose"
    );
    let (_, hidden) = with_check(true);
    assert_eq!(hidden, None);
}

/// The pose goes through the camera model: a fish-eye (Kannala–Brandt) camera sees a marker
/// 35° off its axis, where a pinhole reading of the corners would be far off.
#[test]
fn markers_seen_through_a_fisheye_are_posed_through_its_model() {
    use relight_core::camera::KannalaBrandt;
    const SIZE_M: f64 = 0.1;
    let fisheye = CameraModel::KannalaBrandt(KannalaBrandt {
        width: 640,
        height: 480,
        fx: 260.0,
        fy: 260.0,
        cx: 319.5,
        cy: 239.5,
        k1: -0.02,
        k2: 0.004,
        k3: 0.0,
        k4: 0.0,
    });
    let dictionary = ArucoDictionary::Aruco4x4_50;
    let bitmap = Dictionary::load(dictionary).unwrap().tag_bitmap(4).unwrap();
    let angle = 35f64.to_radians();
    let distance_m = 0.45;
    let centre = DVec3::new(angle.sin(), 0.1, -angle.cos()) * distance_m;
    // Facing the camera, then tilted 20° about its own x axis.
    let facing = DQuat::from_rotation_y(-angle) * DQuat::from_rotation_x(20f64.to_radians());
    let truth = DPose::new(facing, centre);
    let image = render(
        &fisheye,
        &[marker_surface(&bitmap, SIZE_M, truth)],
        &[],
        &settings(1.0, 2.0, 13),
    )
    .unwrap();
    let mut tracker = tracker(dictionary, SIZE_M);
    let mut set = MarkerSet::default();
    tracker.detect(&image, &fisheye, &mut set).unwrap();
    assert_eq!(set.detections.len(), 1);
    let found = &set.detections[0];
    let truth_px = project_points(&fisheye, &truth, &square_corners_in_marker(SIZE_M)).unwrap();
    let corner_rms = corner_rms_px(
        &found.corners_px,
        &[truth_px[0], truth_px[1], truth_px[2], truth_px[3]],
    );
    assert!(corner_rms < 0.4, "corners {corner_rms:.2} px off");
    let fit = estimate_square_pose(
        &found.corners_px.map(|c| c.as_dvec2()),
        SIZE_M,
        &fisheye,
        &PoseSettings::default(),
    )
    .unwrap();
    let (t_tol_m, r_tol_deg) = pose_tolerance(&fit, corner_rms);
    let t_err_m = translation_error_m(found, &truth);
    let r_err_deg = rotation_error_deg(found, &truth);
    println!(
        "fish-eye, 35° off axis: corners {corner_rms:.2} px, pose {:.1} mm / {r_err_deg:.2}° off",
        t_err_m * 1e3
    );
    assert!(t_err_m <= t_tol_m && r_err_deg <= r_tol_deg);
}
