//! The live loop end to end on simulated recordings with ground truth (`relightd score`'s path):
//! the marker-tracked camera keeps the virtual object on its true projection while the camera
//! orbits, and a board that goes out of sight leaves the camera untracked with no Δ drawn.

use std::path::{Path, PathBuf};

use relight_core::StreamKind;
use relight_core::recording::{RecordingMeta, RecordingWriter};
use relight_core::scene::Scene;
use relight_daemon::config::Config;
use relight_daemon::score::{self, ScoreReport, ScoreSettings};
use relight_engines::reference_cache::ReferenceCache;
use relight_sim::rig::{CameraPath, SimRig, SimSettings, write_recording};

fn desk() -> (PathBuf, Scene) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box");
    let scene = Scene::load(&dir).unwrap();
    (dir, scene)
}

/// 160 × 120 at 10 fps, 1 spp colour, truth on every frame, detected corners with 0.1 px noise.
fn rig(scene: &Scene, path: CameraPath, frames: u32) -> SimRig {
    let settings = SimSettings {
        width: 160,
        height: 120,
        fps: 10,
        frames,
        color_spp: 1,
        truth_every: 1,
        marker_corner_sigma_px: 0.1,
        trajectory: Some(path.trajectory(scene)),
        ..SimSettings::placed_in(scene)
    };
    SimRig::new(scene, settings).unwrap().metered()
}

/// `relightd score`'s run of `recording`, its truth rendered at `reference_spp`.
fn score(
    recording: &Path,
    scene: &Path,
    engine: &str,
    config: Config,
    reference_spp: u32,
) -> ScoreReport {
    score_cached(recording, scene, engine, config, reference_spp, None)
}

/// [`score`], keeping the truth's renders in `reference_cache`.
fn score_cached(
    recording: &Path,
    scene: &Path,
    engine: &str,
    config: Config,
    reference_spp: u32,
    reference_cache: Option<PathBuf>,
) -> ScoreReport {
    score::run(
        &ScoreSettings {
            recording: recording.to_owned(),
            scene: scene.to_owned(),
            engine: engine.into(),
            params: serde_json::Map::new(),
            reference_spp,
            reference_cache,
            out: None,
            config,
            threads: false,
        },
        |_, _| {},
    )
    .unwrap()
}

/// The object's projection error comes from the pose's error alone. A 3 × 3 board of 12 cm tags
/// about 1.9 m away at f ≈ 129 px, with 0.1 px corner noise, gives about 0.1 px at the object
/// (0.07 px median measured at 320 × 240); 1 px is ten times that, and far below what a pose
/// held from a previous frame of the orbit would give (several pixels).
#[test]
fn an_orbit_keeps_the_object_within_a_pixel_of_its_true_projection() {
    let (dir, scene) = desk();
    let tmp = tempfile::tempdir().unwrap();
    let recording = tmp.path().join("orbit.mcap");
    // 2 s at the orbit's 18°/s: from the middle of its swing to 36° around the object.
    write_recording(&rig(&scene, CameraPath::Orbit, 20), &recording, |_| {}).unwrap();
    let report = score(&recording, &dir, "passthrough", score::default_config(), 1);
    assert_eq!(report.frames, 20);
    assert_eq!(report.tracked_frames, 20, "the board is in view all along");
    for frame in &report.per_frame {
        let px = frame.object_reprojection_px.expect("tracked");
        assert!(px < 1.0, "frame {}: {px} px", frame.seq);
    }
    let moved = report
        .per_frame
        .iter()
        .filter_map(|f| f.pose_error_mm)
        .fold(0.0f64, f64::max);
    assert!(moved < 30.0, "worst pose error {moved} mm");
}

/// The board disappears after frame 3: frames 4 and 5 hold the last pose (100 and 200 ms old,
/// under the default 250 ms), from frame 6 on the camera is untracked and the engine draws no Δ
/// (the composite is the camera image: Δ's error is exactly 1).
#[test]
fn a_hidden_board_leaves_the_camera_untracked_and_draws_no_delta() {
    let (dir, scene) = desk();
    let tmp = tempfile::tempdir().unwrap();
    let recording = tmp.path().join("hidden.mcap");
    let rig = rig(&scene, CameraPath::Static, 9);
    let meta = RecordingMeta {
        calibration: Some(rig.calibration()),
        source: "live_loop test".into(),
    };
    let mut writer = RecordingWriter::create(&recording, &meta).unwrap();
    for (i, frame) in rig.frames().enumerate() {
        for message in &frame.messages {
            if i < 4 || message.kind() != StreamKind::Markers {
                writer.write(message).unwrap();
            }
        }
        for truth in &frame.truth {
            writer.write_truth(truth).unwrap();
        }
    }
    writer.finish().unwrap();

    let report = score(&recording, &dir, "differential", score::default_config(), 1);
    let states: Vec<&str> = report
        .per_frame
        .iter()
        .map(|f| f.tracking.as_str())
        .collect();
    assert_eq!(
        states,
        [
            "tracked",
            "tracked",
            "tracked",
            "tracked",
            "held",
            "held",
            "untracked",
            "untracked",
            "untracked"
        ]
    );
    assert_eq!(report.tracked_frames, 6);
    for frame in &report.per_frame {
        if frame.tracking == "untracked" {
            assert_eq!(frame.delta_rel_l2, 1.0, "no Δ untracked");
            assert!(frame.pose_error_mm.is_none());
        } else {
            // Drawn, and closer to the truth than drawing nothing.
            assert!(frame.delta_rel_l2 < 1.0, "{frame:?}");
        }
    }
}

/// The truth's renders are kept: a second run, of another engine, reads every frame's back (its
/// noise as stored: here the stored noise is zeroed), and a run at other samples renders its own.
#[test]
fn a_second_score_reads_the_truth_from_the_cache() {
    let (dir, scene) = desk();
    let tmp = tempfile::tempdir().unwrap();
    let recording = tmp.path().join("orbit.mcap");
    write_recording(&rig(&scene, CameraPath::Orbit, 3), &recording, |_| {}).unwrap();
    let cache_dir = tmp.path().join("refs");
    let run = |engine, spp| {
        let config = score::default_config();
        score_cached(
            &recording,
            &dir,
            engine,
            config,
            spp,
            Some(cache_dir.clone()),
        )
    };
    let first = run("passthrough", 2);
    assert!(first.per_frame.iter().all(|f| f.delta_truth_noise > 0.0));
    let cache = ReferenceCache::new(&cache_dir);
    let mut keys = Vec::new();
    for entry in std::fs::read_dir(&cache_dir).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        let key = u64::from_str_radix(name.strip_suffix(".ref").unwrap(), 16).unwrap();
        let mut images = cache.load(key).unwrap();
        images.delta_std_error.fill(glam::Vec3::ZERO);
        cache.store(key, &images).unwrap();
        keys.push(key);
    }
    assert_eq!(keys.len(), 3, "one truth per frame of the orbit");
    let second = run("differential", 2);
    for (a, b) in first.per_frame.iter().zip(&second.per_frame) {
        assert_eq!(b.delta_truth_noise, 0.0, "read back");
        assert_eq!(a.pose_error_mm, b.pose_error_mm);
    }
    let other_samples = run("passthrough", 3);
    assert!(
        other_samples
            .per_frame
            .iter()
            .all(|f| f.delta_truth_noise > 0.0)
    );
    assert_eq!(std::fs::read_dir(&cache_dir).unwrap().count(), 6);
}

fn probe_lit() -> Config {
    let mut config = score::default_config();
    config.scene.lighting = relight_engines::live_scene::LightSource::Probe;
    config
}

/// A probe frame every third frame cycles through three exposures; the cycle is known once its
/// first exposure comes round again, so the first estimate comes at frame 9. Before it, the estimate is
/// the tracked lamp alone (short of the truth by the scene's own light); after it, the probe's
/// median-cut lights (with the lamp's disc masked out of its map) plus the tracked lamp carry
/// the true total irradiance at the probe within 5 %. Unmasked, the lamp counted twice gave 3.7×.
#[test]
fn the_lamp_is_counted_once_in_the_probe_estimate() {
    let (dir, scene) = desk();
    let tmp = tempfile::tempdir().unwrap();
    let recording = tmp.path().join("probe.mcap");
    write_recording(&rig(&scene, CameraPath::Static, 13), &recording, |_| {}).unwrap();
    let report = score(&recording, &dir, "passthrough", probe_lit(), 4);
    for (i, frame) in report.per_frame.iter().enumerate() {
        let ratio = frame.light_irradiance_ratio.expect("lit");
        if i < 9 {
            assert!(ratio < 0.9, "frame {i}: the lamp alone gives {ratio}");
        } else {
            assert!(
                (ratio - 1.0).abs() < 0.05,
                "frame {i}: total irradiance × {ratio}"
            );
            // 5 % of the energy misplaced turns the irradiance vector by at most asin(0.05) =
            // 2.9°; the map's 2.8° texels place the sun-sized disc within one more texel.
            let deg = frame.light_direction_error_deg.unwrap();
            assert!(deg < 5.7, "frame {i}: {deg}°");
        }
    }
}

/// `differential` lit by the probe's estimate against `differential` lit by the true lights, on
/// the desk under a sun (a distant light, which the probe's directional lights model exactly),
/// 35° above the horizon: away from the lamp's circle at 58°, since the lamp's mask hides
/// whatever lies behind the lamp.
/// Δ is linear in the light, so an estimate whose irradiance is off by a ratio `r` and whose
/// direction is off by `θ` moves Δ by at most `|1 − r| + 2 sin(θ / 2)` of itself (the shadow's
/// shift, `h θ` for the 30 cm box, is far below a pixel), and the composite by that times Δ's
/// share of it. 0.01 more covers the 4-spp truth's noise in the difference.
#[test]
fn differential_lit_by_the_probe_matches_differential_lit_by_the_truth() {
    let (desk_dir, _) = desk();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("desk_sun");
    std::fs::create_dir(&dir).unwrap();
    for file in ["scene.gltf", "scene.bin"] {
        std::fs::copy(desk_dir.join(file), dir.join(file)).unwrap();
    }
    std::fs::write(
        dir.join("scene.toml"),
        "gltf = \"scene.gltf\"\nvirtual = [\"box\"]\n\n[camera]\nwidth = 160\nheight = 120\n\n\
         [[lights]]\ntype = \"directional\"\ndirection_in_world = [0.8192, -0.5736, 0.0]\nirradiance = [3, 3, 3]\n",
    )
    .unwrap();
    let scene = Scene::load(&dir).unwrap();
    let recording = tmp.path().join("sun.mcap");
    write_recording(&rig(&scene, CameraPath::Static, 12), &recording, |_| {}).unwrap();
    let truth_lit = score(&recording, &dir, "differential", score::default_config(), 4);
    let probe_lit = score(&recording, &dir, "differential", probe_lit(), 4);
    for (i, (t, p)) in truth_lit
        .per_frame
        .iter()
        .zip(&probe_lit.per_frame)
        .enumerate()
        .skip(9)
    {
        let r = p.light_irradiance_ratio.unwrap();
        let theta = p.light_direction_error_deg.unwrap().to_radians();
        let bound = t.delta_share_real * ((1.0 - r).abs() + 2.0 * (theta / 2.0).sin()) + 0.01;
        let difference = (p.composite_rel_l2_real - t.composite_rel_l2_real).abs();
        println!(
            "frame {i}: r {r:.3}, θ {:.2}°, composite {:.4} vs {:.4}, bound {bound:.4}",
            theta.to_degrees(),
            p.composite_rel_l2_real,
            t.composite_rel_l2_real
        );
        assert!(difference <= bound, "frame {i}: {difference} > {bound}");
    }
}
