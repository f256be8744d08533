//! The simulated rig against what is known in closed form: the true depth, normals and albedo of
//! a plane; the Kinect model's error bounds; the colour of a plane under a point light through
//! the response curve; the marker board's print where its detections say it is; the lamp's
//! serial line; and the recording round trip through the replay backend.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{DVec2, Quat, Vec3};
use relight_backends::device::Backoff;
use relight_backends::lamp_protocol::parse_line;
use relight_backends::{DeviceRunner, Replay, ReplayConfig, ReplayMode};
use relight_core::bus::Bus;
use relight_core::camera::optical_from_gl;
use relight_core::light::Light;
use relight_core::recording::RecordingReader;
use relight_core::recording::truth::{TruthKind, TruthMessage};
use relight_core::scene::{Material, Scene, SceneCamera};
use relight_core::{Image, Pose, StreamMessage};
use relight_reference::shapes::{quad, uv_sphere};
use relight_sim::markers::MarkerBoard;
use relight_sim::rig::{
    SimLamp, SimProbe, SimRig, SimSettings, equidistant_probe, write_recording,
};

const ALBEDO: f32 = 0.6;
const LIGHT: Vec3 = Vec3::new(0.0, 2.0, 0.5);
const INTENSITY: f32 = 3.0;

/// A large diffuse floor (y = 0) under a point light, a virtual sphere on it, the camera 1.2 m
/// up looking at the origin.
fn floor_scene() -> Scene {
    let material = |albedo: f32| Material {
        name: "m".into(),
        albedo: Vec3::splat(albedo),
        specular: Vec3::ZERO,
        shininess: 0.0,
        emission: Vec3::ZERO,
    };
    Scene {
        name: "floor".into(),
        meshes: vec![
            quad("floor", Vec3::ZERO, Vec3::X * 4.0, -Vec3::Z * 4.0, 0, false),
            uv_sphere("ball", Vec3::new(0.0, 0.2, 0.0), 0.2, 12, 8, 1, true),
        ],
        materials: vec![material(ALBEDO), material(0.9)],
        camera: SceneCamera {
            world_from_camera: Pose::look_at(Vec3::new(0.0, 1.2, 1.8), Vec3::ZERO, Vec3::Y),
            yfov_rad: 0.8,
            width: 160,
            height: 120,
        },
        lights: vec![Light::Point {
            position_in_world: LIGHT,
            intensity: Vec3::splat(INTENSITY),
        }],
        environment: None,
        environment_lights: Vec::new(),
        shadow_proxy: None,
        surface_revision: None,
    }
}

fn settings(frames: u32) -> SimSettings {
    SimSettings {
        width: 80,
        height: 60,
        frames,
        color_spp: 4,
        ..SimSettings::default()
    }
}

/// Where a world ray through pixel (x, y) of `rig`'s camera meets the floor.
fn floor_hit(rig: &SimRig, pose: &Pose, x: u32, y: u32) -> (Vec3, f32) {
    let camera = rig.camera();
    let optical = Vec3::new(
        ((f64::from(x) - camera.cx) / camera.fx) as f32,
        ((f64::from(y) - camera.cy) / camera.fy) as f32,
        1.0,
    );
    let dir = pose.transform_vector(Vec3::new(optical.x, -optical.y, -1.0));
    let t = -pose.translation.y / dir.y;
    let point = pose.translation + dir * t;
    // z along the optical axis is t in units of the optical ray (whose z is 1).
    (point, t)
}

fn truth_images(reader: &RecordingReader, kind: TruthKind) -> Vec<Image> {
    reader
        .truth()
        .map(Result::unwrap)
        .filter_map(|m| match m {
            TruthMessage::Image(k, frame) if k == kind => Some(frame.payload),
            _ => None,
        })
        .collect()
}

fn rgba(image: &Image, i: usize) -> [f32; 4] {
    let bits = &image.as_u16().unwrap()[4 * i..4 * i + 4];
    bits.iter()
        .map(|b| half::f16::from_bits(*b).to_f32())
        .collect::<Vec<_>>()
        .try_into()
        .unwrap()
}

#[test]
fn recorded_truth_is_the_geometry_of_the_real_scene() {
    let scene = floor_scene();
    let rig = SimRig::new(&scene, settings(2)).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sim.mcap");
    write_recording(&rig, &path, |_| {}).unwrap();
    let reader = RecordingReader::open(&path).unwrap();
    assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
    let depth = truth_images(&reader, TruthKind::Depth);
    let normals = truth_images(&reader, TruthKind::Normals);
    let albedo = truth_images(&reader, TruthKind::Albedo);
    assert_eq!((depth.len(), normals.len(), albedo.len()), (2, 2, 2));

    let pose = scene.camera.world_from_camera;
    let (w, h) = (80, 60);
    let mut floor_pixels = 0;
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            let (point, z) = floor_hit(&rig, &pose, x, y);
            let recorded = depth[0].as_f32().unwrap()[i];
            let inside = point.x.abs().max(point.z.abs());
            if z > 0.0 && (3.99..4.01).contains(&inside) {
                continue; // the floor's edge may fall either way
            }
            if z > 0.0 && inside < 4.0 {
                floor_pixels += 1;
                // The virtual ball is not sensed: every pixel sees the floor.
                assert!(
                    (recorded - z).abs() <= 2e-5 * z,
                    "pixel ({x}, {y}): {recorded} vs {z}"
                );
                let n = rgba(&normals[0], i);
                assert!(
                    (Vec3::new(n[0], n[1], n[2]) - Vec3::Y).length() < 2e-3,
                    "{n:?}"
                );
                assert_eq!(n[3], 1.0);
                let a = rgba(&albedo[0], i);
                assert!((a[0] - ALBEDO).abs() < 1e-3 && a[3] == 0.0, "{a:?}");
            } else {
                assert_eq!(recorded, 0.0, "pixel ({x}, {y}) sees nothing");
            }
        }
    }
    assert!(floor_pixels > w * h / 2);
}

#[test]
fn kinect_depth_stays_within_its_noise_model_of_the_truth() {
    let scene = floor_scene();
    let rig = SimRig::new(&scene, settings(1)).unwrap();
    let frame = rig.frame(0);
    let StreamMessage::Depth(depth) = &frame.messages[0] else {
        panic!("depth comes first");
    };
    let TruthMessage::Image(TruthKind::Depth, truth) = &frame.truth[0] else {
        panic!("true depth comes first");
    };
    let model = relight_sim::kinect::KinectModel {
        focal_px: rig.camera().fx as f32,
        ..rig.settings().kinect
    };
    let measured = depth.payload.as_u16().unwrap();
    let truth = truth.payload.as_f32().unwrap();
    let (mut valid, mut seen) = (0, 0);
    for (&mm, &z) in measured.iter().zip(truth) {
        if z < model.min_range_m || z > model.max_range_m {
            assert_eq!(mm, 0, "out of range is invalid");
            continue;
        }
        seen += 1;
        if mm == 0 {
            continue;
        }
        valid += 1;
        let error = (f32::from(mm) / 1000.0 - z).abs();
        let bound = 5.0 * model.sigma_z_m(z) + model.quantum_m(z) + 0.0005;
        assert!(error <= bound, "z = {z}: error {error} > {bound}");
    }
    // A plain floor at moderate incidence: only grazing far pixels drop out.
    assert!(valid as f32 > 0.8 * seen as f32, "{valid} of {seen} valid");
}

#[test]
fn colour_is_the_lit_floor_through_the_response_curve() {
    let scene = floor_scene();
    let mut settings = settings(1);
    settings.color_spp = 16;
    settings.exposure = 2.0;
    let rig = SimRig::new(&scene, settings.clone()).unwrap();
    let frame = rig.frame(0);
    let StreamMessage::Color(color) = &frame.messages[1] else {
        panic!("colour comes second");
    };
    let pose = scene.camera.world_from_camera;
    let response = settings.response;
    let codes = color.payload.as_u8().unwrap();
    for (x, y) in [(20, 40), (40, 30), (60, 45), (40, 55)] {
        // Mean code over a 3 × 3 patch, back through the exact inverse response.
        let mut sum = 0.0;
        for dy in 0..3 {
            for dx in 0..3 {
                let i = 3 * ((y + dy - 1) * 80 + (x + dx - 1)) as usize;
                sum += f32::from(codes[i + 1]);
            }
        }
        let measured = response.inverse(sum / 9.0 / 255.0) / settings.exposure;
        let (point, _) = floor_hit(&rig, &pose, x, y);
        let to_light = LIGHT - point;
        let d2 = to_light.length_squared();
        // Lambertian floor, nothing else real to bounce from: L = ρ/π · I cos θ / d².
        let expected = ALBEDO / std::f32::consts::PI * INTENSITY * (to_light.y / d2.sqrt()) / d2;
        // 8-bit steps, sensor noise and pixel-footprint variation over the patch: a few percent.
        assert!(
            (measured - expected).abs() < 0.05 * expected,
            "pixel ({x}, {y}): {measured} vs {expected}"
        );
    }
}

fn board_settings() -> SimSettings {
    let mut settings = settings(3);
    settings.width = 320;
    settings.height = 240;
    settings.board = Some(MarkerBoard {
        first_id: 4,
        cols: 2,
        rows: 2,
        tag_size_m: 0.12,
        gap_m: 0.03,
        world_from_board: Pose::new(
            Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2),
            Vec3::new(0.35, 0.0, 0.5),
        ),
        white_albedo: 0.8,
        black_albedo: 0.04,
    });
    settings
}

#[test]
fn marker_detections_sit_on_the_printed_tags() {
    let scene = floor_scene();
    let rig = SimRig::new(&scene, board_settings()).unwrap();
    let frame = rig.frame(0);
    let markers = frame
        .messages
        .iter()
        .find_map(|m| match m {
            StreamMessage::Markers(f) => Some(f.payload.clone()),
            _ => None,
        })
        .unwrap();
    let ids: Vec<u32> = markers.detections.iter().map(|d| d.marker_id).collect();
    assert_eq!(ids, [4, 5, 6, 7]);
    let StreamMessage::Color(color) = &frame.messages[1] else {
        panic!()
    };
    let codes = color.payload.as_u8().unwrap();
    let code_at = |p: DVec2| {
        let i = 3 * (p.y.round() as usize * 320 + p.x.round() as usize);
        codes[i + 1]
    };
    for d in &markers.detections {
        let project = |p: Vec3| {
            rig.camera()
                .project(optical_from_gl(
                    d.camera_from_marker.transform_point(p).as_dvec3(),
                ))
                .unwrap()
        };
        // The detection's corners are the projected corners of its pose.
        let s = 0.06;
        for (corner, expected) in d.corners_px.iter().zip([
            Vec3::new(-s, -s, 0.0),
            Vec3::new(s, -s, 0.0),
            Vec3::new(s, s, 0.0),
            Vec3::new(-s, s, 0.0),
        ]) {
            assert!((*corner - project(expected).as_vec2()).length() < 1e-3);
        }
        // Inside the black border the print is dark; in the quiet zone it is white.
        let cell = 0.12 / 8.0;
        let mean_code = |offset: f32| {
            let sides = [(0.0, -1.0), (0.0, 1.0), (-1.0, 0.0), (1.0, 0.0)];
            sides
                .iter()
                .map(|&(x, y)| f32::from(code_at(project(Vec3::new(x * offset, y * offset, 0.0)))))
                .sum::<f32>()
                / 4.0
        };
        let border = mean_code(s - cell / 2.0);
        let quiet = mean_code(s + cell / 2.0);
        assert!(
            border < 0.6 * quiet,
            "tag {}: {border} vs {quiet}",
            d.marker_id
        );
    }
    // The board is in the truth with the same poses.
    let state = frame
        .truth
        .iter()
        .find_map(|m| match m {
            TruthMessage::State(f) => Some(f.payload.clone()),
            _ => None,
        })
        .unwrap();
    assert_eq!(state.markers.len(), 4);
    let world_from_camera = state.world_from_camera;
    for (d, t) in markers.detections.iter().zip(&state.markers) {
        let via_camera = world_from_camera * d.camera_from_marker;
        assert!((via_camera.translation - t.world_from_marker.translation).length() < 1e-5);
    }
}

#[test]
fn lamp_reports_parse_and_light_the_scene() {
    let scene = floor_scene();
    let mut settings = settings(7);
    settings.lamp = Some(SimLamp {
        center: Vec3::new(0.0, 1.0, 0.0),
        radius_m: 0.3,
        period_s: 2.0,
        max_intensity: 2.0,
        cct_k: 4000,
        level: 0.8,
        off_frames: 3..4,
        bulb_radius_m: 0.02,
        every: 3,
    });
    let rig = SimRig::new(&scene, settings).unwrap();
    for i in 0..7 {
        let frame = rig.frame(i);
        let lamp_message = frame.messages.iter().find_map(|m| match m {
            StreamMessage::Lamp(f) => Some(f.clone()),
            _ => None,
        });
        assert_eq!(frame.lamp_line.is_some(), i % 3 == 0);
        let Some(line) = frame.lamp_line else {
            continue;
        };
        let report = parse_line(line.trim_end()).unwrap();
        let message = lamp_message.unwrap();
        let (_, position) = rig.lamp(i).unwrap();
        assert_eq!(message.payload, report.state(position, 2.0));
        assert_eq!(message.seq, u64::from(report.seq));
        assert_eq!(report.on, i != 3);
        let lamp_lights = rig
            .lights(i)
            .iter()
            .filter(|l| matches!(l, Light::Point { position_in_world, .. } if *position_in_world == position))
            .count();
        assert_eq!(lamp_lights, usize::from(report.on));
    }
}

#[test]
fn probe_sees_the_lamp_where_the_lens_puts_it() {
    let scene = floor_scene();
    let mut settings = settings(1);
    let world_from_probe = Pose::new(
        Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        Vec3::new(0.0, 0.05, 0.0),
    );
    settings.probe = Some(SimProbe {
        lens: equidistant_probe(64, 185.0),
        world_from_probe,
        exposures_us: vec![1_000],
        every: 1,
        exposure_scale: 1.0,
    });
    let rig = SimRig::new(&scene, settings).unwrap();
    let frame = rig.frame(0);
    let probe = frame
        .messages
        .iter()
        .find_map(|m| match m {
            StreamMessage::Probe(f) => Some(f.payload.clone()),
            _ => None,
        })
        .unwrap();
    let lens = equidistant_probe(64, 185.0).model;
    let dir_in_probe = world_from_probe
        .inverse()
        .transform_vector((LIGHT - world_from_probe.translation).normalize());
    let pixel = lens
        .project(optical_from_gl(dir_in_probe.as_dvec3()))
        .unwrap();
    let codes = probe.image.as_u8().unwrap();
    let brightest = (0..64 * 64)
        .max_by_key(|&i| codes[3 * i] as u32 + codes[3 * i + 1] as u32)
        .unwrap();
    let found = DVec2::new((brightest % 64) as f64, (brightest / 64) as f64);
    assert!((found - pixel).length() < 1.5, "{found} vs {pixel}");
    assert!(codes[3 * brightest] > 0);
}

#[test]
fn recording_replays_frame_exact() {
    let scene = floor_scene();
    let rig = SimRig::new(&scene, board_settings()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sim.mcap");
    write_recording(&rig, &path, |_| {}).unwrap();
    let expected: Vec<StreamMessage> = rig.frames().flat_map(|f| f.messages).collect();
    let reader = RecordingReader::open(&path).unwrap();
    assert_eq!(reader.meta().calibration.as_ref(), Some(&rig.calibration()));
    let read: Vec<StreamMessage> = reader.messages().collect::<Result<_, _>>().unwrap();
    assert_eq!(read, expected);
    let played = played(&path, expected.len());
    assert_eq!(played.len(), expected.len());
    for (p, e) in played.iter().zip(&expected) {
        // The replay restamps host time to now; everything else is as recorded.
        assert_eq!(
            (p.kind(), p.seq(), p.stamp().device_ns),
            (e.kind(), e.seq(), e.stamp().device_ns)
        );
        assert!(
            p.payload_eq(e),
            "{} seq {} differs after replay",
            p.kind(),
            p.seq()
        );
    }
}

fn played(path: &Path, count: usize) -> Vec<StreamMessage> {
    let bus = Arc::new(Bus::new());
    let sub = bus.all.subscribe(count + 1);
    let config = ReplayConfig {
        path: path.to_owned(),
        mode: ReplayMode::Fast,
        looping: false,
    };
    let replay = Replay::new(config).unwrap();
    let mut runner =
        DeviceRunner::spawn("replay", Box::new(replay), bus, Backoff::default()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut got = Vec::new();
    while got.len() < count && Instant::now() < deadline {
        got.extend(sub.recv_timeout(Duration::from_millis(20)));
    }
    runner.stop();
    got
}

#[test]
fn props_are_placed_in_view_in_the_shipped_desk_scene() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box");
    let scene = Scene::load(&dir).unwrap();
    let mut settings = SimSettings::placed_in(&scene);
    settings.frames = 1;
    settings.color_spp = 1;
    let rig = SimRig::new(&scene, settings).unwrap();
    let board = rig
        .settings()
        .board
        .clone()
        .expect("the desk's floor is in view");
    assert!(
        board.world_from_board.translation.y.abs() < 1e-3,
        "on the floor"
    );
    let frame = rig.frame(0);
    let detected = frame
        .messages
        .iter()
        .find_map(|m| match m {
            StreamMessage::Markers(f) => Some(f.payload.detections.len()),
            _ => None,
        })
        .unwrap();
    assert_eq!(detected, 9, "the whole 3 × 3 board is visible");
    let kinds: Vec<_> = frame.messages.iter().map(StreamMessage::kind).collect();
    assert_eq!(
        kinds.len(),
        5,
        "depth, colour, markers, probe and lamp at frame 0: {kinds:?}"
    );
}

#[test]
fn metering_puts_the_bright_end_of_the_image_near_the_top_of_the_response() {
    let scene = floor_scene();
    let mut settings = settings(1);
    settings.exposure = 1e-3; // far too dark before metering
    settings.color_spp = 8;
    let rig = SimRig::new(&scene, settings).unwrap().metered();
    let frame = rig.frame(0);
    let StreamMessage::Color(color) = &frame.messages[1] else {
        panic!()
    };
    let mut maxima: Vec<u8> = color
        .payload
        .as_u8()
        .unwrap()
        .chunks_exact(3)
        .map(|rgb| rgb.iter().copied().max().unwrap())
        .filter(|&c| c > 0)
        .collect();
    maxima.sort_unstable();
    let p95 = maxima[maxima.len() * 95 / 100];
    let target = rig.settings().response.to_code(0.8);
    assert!(
        p95.abs_diff(target) <= 12,
        "95th percentile code {p95}, target {target}"
    );
}
