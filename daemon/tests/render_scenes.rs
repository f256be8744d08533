//! `relightd render` works on every shipped scene and writes Δ, L^ρ, L^μ (EXR) and the
//! composite (PNG).

use std::path::Path;
use std::process::Command;

const SCENES: [&str; 5] = [
    "desk_box",
    "spot_bleed",
    "touching_wall",
    "glossy_floor",
    "window_env",
];

#[test]
fn render_writes_every_output_for_every_shipped_scene() {
    let out_root = tempfile::tempdir().unwrap();
    for name in SCENES {
        let scene = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/scenes")
            .join(name);
        let out = out_root.path().join(name);
        render_40x30(&scene, &out, &["--engine", "reference", "--bounces", "2"]);
        for file in ["l_rho.exr", "l_mu.exr", "delta.exr", "delta_std_error.exr"] {
            let pixels = read_rgb_40x30(&out.join(file));
            assert_eq!(pixels.len(), 40 * 30);
            assert!(
                pixels.iter().flatten().all(|v| v.is_finite()),
                "{name}/{file}"
            );
        }
        let png = std::fs::read(out.join("composite.png")).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        // The object is in view in every shipped scene, and covers part of it.
        let decoder = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(out.join("virtual_mask.png")).unwrap(),
        ));
        let mut reader = decoder.read_info().unwrap();
        let mut mask = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut mask).unwrap();
        assert_eq!(
            (info.width, info.height, info.color_type),
            (40, 30, png::ColorType::Grayscale)
        );
        let object = mask.iter().filter(|&&m| m == 255).count();
        assert!(mask.iter().all(|&m| m == 0 || m == 255), "{name}");
        assert!(
            object > 0 && object < 40 * 30,
            "{name}: {object} object pixels"
        );
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
        assert_eq!(summary["spp"], 4);
    }
}

#[test]
fn relighting_engines_render_offline_scenes_and_bad_requests_are_refused() {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box");
    let out = tempfile::tempdir().unwrap();
    let render = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_relightd"))
            .args([
                "render", "--width", "48", "--height", "36", "--spp", "4", "--scene",
            ])
            .arg(&scene)
            .arg("--out")
            .arg(out.path())
            .args(args)
            .output()
            .unwrap()
    };
    let ok = render(&["--engine", "differential", "--param", "rsm_size=128"]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["engine"], "differential");
    assert_eq!(summary["params"]["rsm_size"], 128);
    assert!(summary["delta_relative_l2"].as_f64().unwrap().is_finite());
    for file in [
        "delta.exr",
        "delta_reference.exr",
        "l_rho_reference.exr",
        "composite.png",
        "virtual_mask.png",
    ] {
        assert!(out.path().join(file).exists(), "{file}");
    }
    // `differential` is direct light alone, so against the reference at `--bounces 0` (pixel
    // centres, a point light: no noise) it is exact up to its shadow map's edges.
    let direct = render(&["--engine", "differential", "--bounces", "0"]);
    assert!(direct.status.success());
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["reference_bounces"], 0);
    let (delta, object) = (
        summary["delta_relative_l2"].as_f64().unwrap(),
        summary["object_relative_l2"].as_f64().unwrap(),
    );
    assert!(delta < 0.01 && object < 0.02, "Δ {delta}, object {object}");
    let unknown = render(&["--engine", "dlvp"]);
    assert!(!unknown.status.success());
    let stderr = String::from_utf8_lossy(&unknown.stderr);
    assert!(
        stderr.contains("possible values") && stderr.contains("dlpv"),
        "the error lists the engines: {stderr}"
    );
    let bad = render(&["--engine", "dlpv", "--param", "steps=-3"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("steps"));
    let missing = Command::new(env!("CARGO_BIN_EXE_relightd"))
        .args(["render", "--scene", "/nonexistent-scene", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("/nonexistent-scene/scene.toml"));
}

/// `--pixel-centres` renders the reference an engine is judged against: the same bits as the
/// `delta_reference.exr` that `--engine` writes, at the same samples, bounces and seed, where
/// the default (the pixel's area) differs from it.
#[test]
fn pixel_centres_give_the_reference_an_engine_is_judged_against() {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box");
    let out = tempfile::tempdir().unwrap();
    let delta = |name: &str, args: &[&str], file: &str| -> Vec<u32> {
        let dir = out.path().join(name);
        render_40x30(&scene, &dir, &[&["--bounces", "1"], args].concat());
        read_rgb_40x30(&dir.join(file))
            .iter()
            .flatten()
            .map(|v| v.to_bits())
            .collect()
    };
    let judged = delta(
        "engine",
        &["--engine", "differential"],
        "delta_reference.exr",
    );
    let centres = delta("centres", &["--pixel-centres"], "delta.exr");
    let area = delta("area", &[], "delta.exr");
    assert!(
        judged == centres,
        "the centres' reference differs from the engine's"
    );
    assert!(area != centres, "the area's reference equals the centres'");
}

/// `relightd render` of `scene` into `out` at 40 × 30 and 4 spp, with `args`; the test fails
/// with its stderr where it does.
fn render_40x30(scene: &Path, out: &Path, args: &[&str]) {
    let output = Command::new(env!("CARGO_BIN_EXE_relightd"))
        .args(["render", "--spp", "4", "--width", "40", "--height", "30"])
        .arg("--scene")
        .arg(scene)
        .arg("--out")
        .arg(out)
        .args(args)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}: {}",
        out.display(),
        String::from_utf8_lossy(&output.stderr)
    );
}

/// A 40 × 30 EXR's RGB pixels, row by row.
fn read_rgb_40x30(path: &Path) -> Vec<[f32; 3]> {
    exr::prelude::read_first_rgba_layer_from_file(
        path,
        |r, _| vec![[0f32; 3]; r.width() * r.height()],
        |b: &mut Vec<[f32; 3]>, p, (r, g, bl, _a): (f32, f32, f32, f32)| {
            b[p.y() * 40 + p.x()] = [r, g, bl]
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
    .layer_data
    .channel_data
    .pixels
}
