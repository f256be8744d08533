//! `relight-calibrate` as a user runs it: the built binary on folders of synthetic images. A
//! good session writes a calibration that relight loads; every bad input (no target, too few
//! views, mixed sizes, a corrupt image, an empty folder, a ladder bracket) exits non-zero with a
//! message that names the problem, and writes no file — an existing one stays as it was.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use glam::{DQuat, DVec3, Quat, Vec3};
use relight_calibrate::detect::Detector;
use relight_calibrate::input::{mat_from_image, read_image};
use relight_calibrate::report::write_png;
use relight_calibrate::rigid::{Rigid, frame_from_camera_gl, gl_from_optical_pair};
use relight_calibrate::synth::{
    PlacedTarget, RenderSettings, Scene, Sphere, SynthCamera, ViewPlan, plan_views,
};
use relight_calibrate::target::{AprilGrid, Chessboard, Target, TargetGeometry};
use relight_core::camera::{CameraModel, KannalaBrandt, Pinhole};
use relight_core::recording::{RecordingMeta, RecordingWriter};
use relight_core::rig::RigCalibration;
use relight_core::{Frame, Image, PixelFormat, Pose, ProbeImage, StreamMessage, Timestamp};
use relight_sim::probe::render_probe;
use relight_sim::response::CameraResponse;
use relight_sim::rig::equidistant_probe;

const BINARY: &str = env!("CARGO_BIN_EXE_relight-calibrate");

fn run(args: &[&str]) -> Output {
    let output = Command::new(BINARY)
        .args(args)
        .output()
        .expect("the binary runs");
    println!(
        "$ relight-calibrate {}\nstatus {:?}\nstdout:\n{}stderr:\n{}",
        args.join(" "),
        output.status.code(),
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

fn arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

const TARGET_TOML: &str =
    "kind = \"chessboard\"\ninner_cols = 7\ninner_rows = 4\nsquare_m = 0.03\n";

fn target() -> TargetGeometry {
    Target::Chessboard(Chessboard {
        inner_cols: 7,
        inner_rows: 4,
        square_m: 0.03,
    })
    .geometry()
    .unwrap()
}

fn camera() -> Pinhole {
    Pinhole {
        width: 320,
        height: 240,
        fx: 262.0,
        fy: 261.0,
        cx: 161.3,
        cy: 118.4,
        k1: -0.2,
        k2: 0.05,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    }
}

/// A session folder: `views` synthetic views of the chessboard, and the target's TOML beside it.
struct Session {
    dir: tempfile::TempDir,
}

impl Session {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("images")).unwrap();
        std::fs::write(dir.path().join("target.toml"), TARGET_TOML).unwrap();
        Self { dir }
    }

    fn with_views(views: usize) -> Self {
        Self::with_camera_views(CameraModel::Pinhole(camera()), views)
    }

    fn with_camera_views(model: CameraModel, views: usize) -> Self {
        let session = Self::new();
        let geometry = target();
        let synth = SynthCamera::new(model, RenderSettings::default()).unwrap();
        let poses = plan_views(
            &model,
            &geometry,
            &ViewPlan {
                count: views,
                ..ViewPlan::default()
            },
        );
        for (i, pose) in poses.iter().enumerate() {
            session.save(
                &format!("view-{i:02}.png"),
                &synth.render_target(&geometry, pose),
            );
        }
        session
    }

    fn images(&self) -> PathBuf {
        self.dir.path().join("images")
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn save(&self, name: &str, image: &Image) {
        write_png(&self.images().join(name), &mat_from_image(image).unwrap()).unwrap();
    }

    fn intrinsics(&self, out: &Path) -> Output {
        self.intrinsics_with(out, &["--camera", "color"])
    }

    fn intrinsics_with(&self, out: &Path, extra: &[&str]) -> Output {
        let target = self.path("target.toml");
        let images = self.images();
        let report = self.path("report");
        let mut args = vec![
            "intrinsics",
            "--target",
            arg(&target),
            "--images",
            arg(&images),
            "--out",
            arg(out),
            "--report",
            arg(&report),
        ];
        args.extend_from_slice(extra);
        run(&args)
    }
}

#[test]
fn a_good_session_writes_a_calibration_relight_loads_and_keeps_the_rest_of_the_file() {
    let session = Session::with_views(10);
    let out = session.path("rig.toml");
    let existing = RigCalibration {
        name: "desk".into(),
        depth: Some(CameraModel::Pinhole(Pinhole {
            fx: 100.0,
            fy: 100.0,
            ..camera()
        })),
        probe_response: (0..256).map(|m| m as f32 / 128.0).collect(),
        ..RigCalibration::default()
    };
    std::fs::write(&out, existing.to_toml().unwrap()).unwrap();

    let output = session.intrinsics(&out);
    assert!(output.status.success(), "{}", stderr(&output));
    let rig = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let Some(CameraModel::Pinhole(color)) = rig.color else {
        panic!("no pinhole colour camera in {rig:?}");
    };
    let truth = camera();
    println!(
        "fx {:.3} (truth {}), fy {:.3} ({}), cx {:.3} ({}), cy {:.3} ({}), k1 {:.4} ({})",
        color.fx,
        truth.fx,
        color.fy,
        truth.fy,
        color.cx,
        truth.cx,
        color.cy,
        truth.cy,
        color.k1,
        truth.k1
    );
    // A working calibration, not a bench mark (tests/intrinsics.rs holds those): within 1% on
    // ten small views.
    assert!((color.fx / truth.fx - 1.0).abs() < 0.01);
    assert!((color.fy / truth.fy - 1.0).abs() < 0.01);
    assert!((color.cx - truth.cx).abs() < 0.01 * truth.fx);
    assert!((color.cy - truth.cy).abs() < 0.01 * truth.fx);
    assert_eq!((color.width, color.height), (320, 240));
    // Merged: what this run did not calibrate is as it was.
    assert_eq!(rig.name, "desk");
    assert_eq!(rig.depth, existing.depth);
    assert_eq!(rig.probe_response, existing.probe_response);
    for file in ["summary.txt", "reprojection.png", "coverage.png"] {
        assert!(session.path("report").join(file).is_file(), "report/{file}");
    }
    let summary = String::from_utf8_lossy(&output.stdout);
    assert!(summary.contains("reprojection RMS"), "{summary}");
}

#[test]
fn a_fisheye_session_writes_the_probe_model() {
    let truth = KannalaBrandt {
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
    };
    let session = Session::with_camera_views(CameraModel::KannalaBrandt(truth), 20);
    let out = session.path("rig.toml");
    let output = session.intrinsics_with(
        &out,
        &["--camera", "probe", "--fisheye", "--field-deg", "185"],
    );
    assert!(output.status.success(), "{}", stderr(&output));
    let rig = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let Some(CameraModel::KannalaBrandt(probe)) = rig.probe else {
        panic!("no fish-eye probe in {rig:?}");
    };
    println!(
        "fx {:.3} (truth {}), cx {:.3} ({}), cy {:.3} ({})",
        probe.fx, truth.fx, probe.cx, truth.cx, probe.cy, truth.cy
    );
    assert!((probe.fx / truth.fx - 1.0).abs() < 0.01);
    assert!((probe.cx - truth.cx).abs() < 0.01 * truth.fx);
    assert!((probe.cy - truth.cy).abs() < 0.01 * truth.fx);
    assert!(rig.color.is_none());
    assert!(session.path("report").join("coverage.png").is_file());
}

/// The run failed with a message containing `needle`, and `out` is as `before` left it.
fn assert_failed_cleanly(output: &Output, needle: &str, out: &Path, before: Option<&str>) {
    assert!(!output.status.success(), "the run should fail");
    assert_eq!(output.status.code(), Some(1));
    let message = stderr(output);
    assert!(message.contains(needle), "`{needle}` not in: {message}");
    match before {
        Some(text) => assert_eq!(std::fs::read_to_string(out).unwrap(), text),
        None => assert!(!out.exists(), "{} was written", out.display()),
    }
    let leftovers: Vec<_> = std::fs::read_dir(out.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| name.ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");
}

/// Uniform grey with a gentle gradient: no chessboard anywhere.
fn blank(width: u32, height: u32) -> Image {
    let mut image = Image::new(width, height, PixelFormat::Mono8);
    for (i, px) in image.as_u8_mut().unwrap().iter_mut().enumerate() {
        *px = 100 + ((i % width as usize) * 50 / width as usize) as u8;
    }
    image
}

#[test]
fn a_folder_without_the_target_fails_and_writes_nothing() {
    let session = Session::new();
    for i in 0..3 {
        session.save(&format!("wall-{i}.png"), &blank(320, 240));
    }
    let out = session.path("rig.toml");
    let output = session.intrinsics(&out);
    assert_failed_cleanly(
        &output,
        "no chessboard 7x4 detected in any of the 3 images",
        &out,
        None,
    );
    assert!(
        !session.path("report").exists(),
        "no report for a failed run"
    );

    // An existing calibration stays as it was.
    let existing = "name = \"desk\"\n";
    std::fs::write(&out, existing).unwrap();
    let output = session.intrinsics(&out);
    assert_failed_cleanly(&output, "no chessboard", &out, Some(existing));
}

#[test]
fn too_few_views_fail_and_write_nothing() {
    let session = Session::with_views(3);
    let out = session.path("rig.toml");
    let output = session.intrinsics(&out);
    assert_failed_cleanly(&output, "usable views", &out, None);
}

#[test]
fn mixed_image_sizes_fail_naming_the_files() {
    let session = Session::with_views(2);
    session.save("small.png", &blank(160, 120));
    let out = session.path("rig.toml");
    let output = session.intrinsics(&out);
    assert_failed_cleanly(&output, "differ in size", &out, None);
    let message = stderr(&output);
    assert!(message.contains("160×120 (small.png)"), "{message}");
    assert!(
        message.contains("320×240 (view-00.png, view-01.png)"),
        "{message}"
    );
}

#[test]
fn a_corrupt_image_fails_naming_it() {
    let session = Session::with_views(2);
    // A PNG signature followed by garbage: the extension promises an image.
    let mut bytes = vec![0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];
    bytes.extend((0..200u32).map(|i| (i * 37 % 251) as u8));
    std::fs::write(session.images().join("view-01b.png"), bytes).unwrap();
    let out = session.path("rig.toml");
    let output = session.intrinsics(&out);
    assert_failed_cleanly(&output, "view-01b.png: not a readable image", &out, None);
}

#[test]
fn an_empty_folder_fails() {
    let session = Session::new();
    std::fs::write(session.images().join("notes.txt"), "not an image").unwrap();
    let out = session.path("rig.toml");
    let output = session.intrinsics(&out);
    assert_failed_cleanly(&output, "no images", &out, None);
}

/// The simulator's probe bracket of a world spanning four decades.
fn render_bracket(exposures_us: &[u32], exposure_scale: f32) -> Vec<ProbeImage> {
    let lens = equidistant_probe(96, 185.0);
    let pose = Pose::new(
        Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        Vec3::ZERO,
    );
    let world = |d: Vec3| {
        let u = 0.5 + 0.25 * ((4.0 * d.x).sin() + (3.0 * d.z + 1.0).cos());
        Vec3::new(1.0, 0.8, 0.6) * 10f32.powf(4.0 * u - 3.0)
    };
    exposures_us
        .iter()
        .map(|&t| {
            render_probe(
                &world,
                &lens,
                &pose,
                t,
                exposure_scale,
                &CameraResponse::default(),
            )
        })
        .collect()
}

/// [`render_bracket`] saved as `probe_<t>us.png`.
fn save_bracket(session: &Session, exposures_us: &[u32], exposure_scale: f32) {
    for probe in render_bracket(exposures_us, exposure_scale) {
        session.save(&format!("probe_{}us.png", probe.exposure_us), &probe.image);
    }
}

#[test]
fn a_bracket_folder_calibrates_the_response() {
    let session = Session::new();
    save_bracket(&session, &[1_000, 3_000, 11_000, 64_000], 90.0);
    let out = session.path("rig.toml");
    let output = run(&[
        "response",
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
        "--report",
        arg(&session.path("report")),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let rig = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(rig.probe_response.len(), 256);
    assert_eq!(rig.probe_response[128], 1.0);
    assert_eq!(rig.probe_radiance_scale, 1.0);
    let truth = CameraResponse::default().inverse_table();
    let error = (rig.probe_response[64] / (truth[64] / truth[128]) - 1.0).abs();
    assert!(error < 0.02, "code 64 off by {error}");
    assert!(session.path("report").join("response.png").is_file());

    // With a reference patch of known radiance the absolute scale is measured too.
    let output = run(&[
        "response",
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
        "--reference-patch",
        "40,40,16,16",
        "--reference-radiance",
        "0.5",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let rig = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let scale = rig.probe_radiance_scale;
    assert!(scale.is_finite() && scale > 0.0 && scale != 1.0, "{scale}");
}

/// A recording as relightd writes it: two cycles of the probe's bracket, colour frames between.
fn record(path: &Path, probe_frames: bool) {
    let mut writer = RecordingWriter::create(path, &RecordingMeta::default()).unwrap();
    let bracket = render_bracket(&[1_000, 3_000, 11_000, 64_000], 90.0);
    let color = blank(32, 24);
    let mut seq = 0u64;
    for _cycle in 0..2 {
        for probe in &bracket {
            let stamp = Timestamp::new(seq * 33_000_000, 1_000 + seq * 33_000_000);
            writer
                .write(&StreamMessage::Color(std::sync::Arc::new(Frame::new(
                    seq,
                    stamp,
                    {
                        let mut rgb = Image::new(32, 24, PixelFormat::Rgb8);
                        for (g, px) in color
                            .as_u8()
                            .unwrap()
                            .iter()
                            .zip(rgb.as_u8_mut().unwrap().chunks_exact_mut(3))
                        {
                            px.fill(*g);
                        }
                        rgb
                    },
                ))))
                .unwrap();
            if probe_frames {
                writer
                    .write(&StreamMessage::Probe(std::sync::Arc::new(Frame::new(
                        seq,
                        stamp,
                        probe.clone(),
                    ))))
                    .unwrap();
            }
            seq += 1;
        }
    }
    writer.finish().unwrap();
}

#[test]
fn the_response_is_calibrated_from_a_recorded_probe_stream() {
    let session = Session::new();
    let recording = session.path("bracket.mcap");
    record(&recording, true);
    let out = session.path("rig.toml");
    let output = run(&["response", "--mcap", arg(&recording), "--out", arg(&out)]);
    assert!(output.status.success(), "{}", stderr(&output));
    let summary = String::from_utf8_lossy(&output.stdout);
    // One cycle of the bracket, not both.
    assert!(
        summary.contains("exposures: 1.000 ms, 3.000 ms, 11.000 ms, 64.000 ms\n"),
        "{summary}"
    );
    let rig = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let truth = CameraResponse::default().inverse_table();
    let error = (rig.probe_response[64] / (truth[64] / truth[128]) - 1.0).abs();
    assert!(error < 0.02, "code 64 off by {error}");

    let colour_only = session.path("colour.mcap");
    record(&colour_only, false);
    let output = run(&["response", "--mcap", arg(&colour_only), "--out", arg(&out)]);
    let before = std::fs::read_to_string(&out).unwrap();
    assert_failed_cleanly(&output, "has no probe frames", &out, Some(&before));
}

#[test]
fn a_ladder_bracket_is_refused_and_writes_nothing() {
    let session = Session::new();
    save_bracket(&session, &[250, 2_000, 16_000], 360.0);
    let out = session.path("rig.toml");
    let output = run(&[
        "response",
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
    ]);
    assert_failed_cleanly(&output, "power of 8.000", &out, None);
}

#[test]
fn a_bracket_without_exposure_times_is_refused() {
    let session = Session::new();
    session.save("a.png", &blank(32, 32));
    session.save("b.png", &blank(32, 32));
    let out = session.path("rig.toml");
    let output = run(&[
        "response",
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
    ]);
    assert_failed_cleanly(&output, "no exposure time for a.png, b.png", &out, None);
}

#[test]
fn a_rendered_target_prints_at_scale_and_is_detected_whole() {
    let session = Session::new();
    let png = session.path("board.png");
    let output = run(&[
        "render-target",
        arg(&session.path("target.toml")),
        "--out",
        arg(&png),
        "--dpi",
        "100",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let image = read_image(&png).unwrap();
    let geometry = target();
    let print = geometry.print();
    let dots_per_m = 100.0 / 0.0254;
    let expected_width = ((print.max.x - print.min.x + 0.02) * dots_per_m).round() as u32;
    assert_eq!(image.width(), expected_width);
    let detection = Detector::new(&geometry)
        .unwrap()
        .detect("board.png", &image)
        .unwrap();
    assert_eq!(detection.len(), geometry.ids().len(), "every corner found");
}

#[test]
fn vignetting_is_written_to_its_own_file_and_the_rig() {
    let session = Session::new();
    let lens = equidistant_probe(96, 185.0);
    let rig = session.path("rig.toml");
    let calibration = RigCalibration {
        probe: Some(CameraModel::KannalaBrandt(lens.model)),
        ..RigCalibration::default()
    };
    std::fs::write(&rig, calibration.to_toml().unwrap()).unwrap();
    // A linear camera seeing a uniform field with V(θ) = 1 − 0.2 θ².
    let model = CameraModel::KannalaBrandt(lens.model);
    let mut image = Image::new(96, 96, PixelFormat::Mono8);
    for (i, px) in image.as_u8_mut().unwrap().iter_mut().enumerate() {
        let pixel = glam::DVec2::new((i % 96) as f64, (i / 96) as f64);
        *px = match model.unproject(pixel) {
            Some(ray) if ray.z >= (92.5f64).to_radians().cos() => {
                let theta_d =
                    ((pixel.x - 47.5).powi(2) + (pixel.y - 47.5).powi(2)).sqrt() / lens.model.fx;
                (200.0 * (1.0 - 0.2 * theta_d * theta_d)).round() as u8
            }
            _ => 0,
        };
    }
    session.save("flat.png", &image);
    let out = session.path("vignetting.toml");
    let output = run(&[
        "vignetting",
        "--images",
        arg(&session.images()),
        "--rig",
        arg(&rig),
        "--linear",
        "--out",
        arg(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let table: toml::Table = std::fs::read_to_string(&out).unwrap().parse().unwrap();
    let coefficients: Vec<f64> = table["coefficients"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_float().unwrap())
        .collect();
    println!("coefficients {coefficients:?}");
    // 8-bit rounding of a level-200 field: half a level is 0.25%, so a1 is within 0.01 of −0.2.
    assert!((coefficients[0] + 0.2).abs() < 0.01, "{coefficients:?}");
    // The rig file gains the probe's vignetting and keeps everything else.
    let written = RigCalibration::from_toml(&std::fs::read_to_string(&rig).unwrap()).unwrap();
    let in_rig: Vec<f64> = written
        .probe_vignetting
        .iter()
        .map(|&a| f64::from(a))
        .collect();
    assert_eq!(in_rig.len(), 3);
    for (a, b) in in_rig.iter().zip(&coefficients) {
        assert!(
            (a - b).abs() <= 1e-6 * b.abs().max(1e-6),
            "{in_rig:?} vs {coefficients:?}"
        );
    }
    assert_eq!(
        RigCalibration {
            probe_vignetting: Vec::new(),
            ..written
        },
        calibration
    );

    // Without a response curve or --linear, it refuses.
    let output = run(&[
        "vignetting",
        "--images",
        arg(&session.images()),
        "--rig",
        arg(&rig),
        "--out",
        arg(&session.path("other.toml")),
    ]);
    assert_failed_cleanly(
        &output,
        "no response curve",
        &session.path("other.toml"),
        None,
    );
}

/// The chessboard facing the camera from `distance_m`, centred on the optical axis, turned by
/// `rotation` about its centre.
fn facing(geometry: &TargetGeometry, rotation: DQuat, distance_m: f64) -> Rigid {
    let print = geometry.print();
    let centre = ((print.min + print.max) / 2.0).extend(0.0);
    Rigid::new(
        rotation,
        DVec3::new(0.0, 0.0, distance_m) - rotation * centre,
    )
}

/// Rotation angle between two poses, degrees, and translation distance, metres.
fn pose_error(a: &Pose, b: &Pose) -> (f32, f32) {
    (
        a.rotation.angle_between(b.rotation).to_degrees(),
        a.translation.distance(b.translation),
    )
}

#[test]
fn the_probe_is_located_in_the_targets_world() {
    let lens = equidistant_probe(320, 185.0);
    let probe = CameraModel::KannalaBrandt(lens.model);
    let geometry = target();
    let camera_from_target = facing(
        &geometry,
        DQuat::from_rotation_x(0.3) * DQuat::from_rotation_z(0.2),
        0.3,
    );
    let session = Session::new();
    for seed in 0..2 {
        let synth = SynthCamera::new(
            probe,
            RenderSettings {
                seed,
                ..RenderSettings::default()
            },
        )
        .unwrap();
        session.save(
            &format!("still-{seed}.png"),
            &synth.render_target(&geometry, &camera_from_target),
        );
    }
    let out = session.path("rig.toml");
    let rig = RigCalibration {
        probe: Some(probe),
        ..RigCalibration::default()
    };
    std::fs::write(&out, rig.to_toml().unwrap()).unwrap();
    let output = run(&[
        "extrinsics",
        "probe",
        "--target",
        arg(&session.path("target.toml")),
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let written = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let truth = frame_from_camera_gl(&geometry.world_from_target(), &camera_from_target).to_pose();
    let (angle_deg, distance_m) = pose_error(&written.world_from_probe, &truth);
    println!(
        "world_from_probe off by {angle_deg:.4}° and {:.3} mm",
        distance_m * 1e3
    );
    // A 3-pixel-per-centimetre view of a 7 × 4 board: a working pose, not a bench mark.
    assert!(angle_deg < 0.5 && distance_m < 0.005);
    assert_eq!(written.probe, Some(probe));

    // Images of another size than the intrinsics are refused.
    let other = Session::new();
    other.save("small.png", &blank(160, 120));
    let output = run(&[
        "extrinsics",
        "probe",
        "--target",
        arg(&session.path("target.toml")),
        "--images",
        arg(&other.images()),
        "--out",
        arg(&out),
    ]);
    let before = std::fs::read_to_string(&out).unwrap();
    assert_failed_cleanly(&output, "small.png is 160x120", &out, Some(&before));
}

#[test]
fn depth_and_colour_are_registered() {
    let depth = Pinhole {
        width: 320,
        height: 240,
        fx: 285.0,
        fy: 285.0,
        cx: 159.5,
        cy: 119.5,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };
    let color = camera();
    let color_from_depth = Rigid::new(
        DQuat::from_rotation_y(0.03) * DQuat::from_rotation_x(-0.01),
        DVec3::new(-0.025, 0.001, 0.002),
    );
    let geometry = target();
    let session = Session::new();
    std::fs::create_dir(session.path("depth")).unwrap();
    std::fs::create_dir(session.path("color")).unwrap();
    let depth_model = CameraModel::Pinhole(depth);
    let depth_synth = SynthCamera::new(depth_model, RenderSettings::default()).unwrap();
    let color_synth =
        SynthCamera::new(CameraModel::Pinhole(color), RenderSettings::default()).unwrap();
    let poses = plan_views(
        &depth_model,
        &geometry,
        &ViewPlan {
            count: 6,
            ..ViewPlan::default()
        },
    );
    let save = |dir: &str, name: &str, image: &Image| {
        write_png(
            &session.path(dir).join(name),
            &mat_from_image(image).unwrap(),
        )
        .unwrap();
    };
    for (i, depth_from_target) in poses.iter().enumerate() {
        let name = format!("pose-{i}.png");
        save(
            "depth",
            &name,
            &depth_synth.render_target(&geometry, depth_from_target),
        );
        let color_from_target = color_from_depth * *depth_from_target;
        save(
            "color",
            &name,
            &color_synth.render_target(&geometry, &color_from_target),
        );
    }
    let out = session.path("rig.toml");
    let rig = RigCalibration {
        depth: Some(depth_model),
        color: Some(CameraModel::Pinhole(color)),
        ..RigCalibration::default()
    };
    std::fs::write(&out, rig.to_toml().unwrap()).unwrap();
    let output = run(&[
        "extrinsics",
        "depth-color",
        "--target",
        arg(&session.path("target.toml")),
        "--depth-images",
        arg(&session.path("depth")),
        "--color-images",
        arg(&session.path("color")),
        "--out",
        arg(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let written = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let truth = gl_from_optical_pair(&color_from_depth).to_pose();
    let (angle_deg, distance_m) = pose_error(&written.color_from_depth, &truth);
    println!(
        "color_from_depth off by {angle_deg:.4}° and {:.3} mm",
        distance_m * 1e3
    );
    assert!(angle_deg < 0.2 && distance_m < 0.002);

    // Without the depth intrinsics it refuses, naming what to do.
    let bare = session.path("bare.toml");
    std::fs::write(&bare, "name = \"desk\"\n").unwrap();
    let output = run(&[
        "extrinsics",
        "depth-color",
        "--target",
        arg(&session.path("target.toml")),
        "--depth-images",
        arg(&session.path("depth")),
        "--color-images",
        arg(&session.path("color")),
        "--out",
        arg(&bare),
    ]);
    assert_failed_cleanly(
        &output,
        "has no depth intrinsics",
        &bare,
        Some("name = \"desk\"\n"),
    );
}

#[test]
fn the_lamps_light_centre_is_found_in_its_markers_frame() {
    let camera = CameraModel::Pinhole(Pinhole {
        width: 640,
        height: 480,
        fx: 500.0,
        fy: 500.0,
        cx: 319.5,
        cy: 239.5,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    });
    // The lamp's marker: one tag36h11, id 7, 6 cm; a 1 × 1 AprilGrid prints exactly it, and its
    // board frame (centre, +Y up, +Z out of the print) is relight's marker frame.
    let marker = Target::AprilGrid(AprilGrid {
        cols: 1,
        rows: 1,
        tag_m: 0.06,
        spacing_m: 0.01,
        first_id: 7,
    })
    .geometry()
    .unwrap();
    let marker_from_target = marker.world_from_target();
    let light_in_marker = DVec3::new(0.005, 0.075, 0.02);
    let synth = SynthCamera::new(camera, RenderSettings::default()).unwrap();
    let session = Session::new();
    let turns = [
        (0.0, 0.0),
        (0.6, 0.0),
        (-0.6, 0.0),
        (0.0, 0.6),
        (0.0, -0.6),
        (0.45, 0.45),
        (-0.45, 0.45),
        (0.45, -0.45),
        (-0.45, -0.45),
    ];
    for (i, (about_x, about_y)) in turns.iter().enumerate() {
        let camera_from_marker = Rigid::new(
            DQuat::from_rotation_x(std::f64::consts::PI + about_x)
                * DQuat::from_rotation_y(*about_y),
            DVec3::new(0.0, 0.02, 0.45),
        );
        let camera_from_target = camera_from_marker * marker_from_target;
        let scene = Scene {
            targets: vec![PlacedTarget {
                geometry: &marker,
                camera_from_target,
            }],
            spheres: vec![Sphere {
                centre_in_camera: camera_from_marker.transform_point(light_in_marker),
                radius_m: 0.006,
                radiance: 5.0,
            }],
        };
        session.save(&format!("lamp-{i}.png"), &synth.render(&scene));
    }
    let out = session.path("rig.toml");
    let rig = RigCalibration {
        color: Some(camera),
        ..RigCalibration::default()
    };
    std::fs::write(&out, rig.to_toml().unwrap()).unwrap();
    let output = run(&[
        "extrinsics",
        "lamp",
        "--marker-id",
        "7",
        "--marker-size-m",
        "0.06",
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let written = RigCalibration::from_toml(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let found = written.lamp_marker_from_light.translation.as_dvec3();
    println!(
        "light centre {found:?} (truth {light_in_marker:?}), off by {:.2} mm",
        found.distance(light_in_marker) * 1e3
    );
    assert!(found.distance(light_in_marker) < 0.003);

    // The wrong marker id: nothing found, nothing written.
    let before = std::fs::read_to_string(&out).unwrap();
    let output = run(&[
        "extrinsics",
        "lamp",
        "--marker-id",
        "8",
        "--marker-size-m",
        "0.06",
        "--images",
        arg(&session.images()),
        "--out",
        arg(&out),
    ]);
    assert_failed_cleanly(&output, "tag36h11 8", &out, Some(&before));
}
