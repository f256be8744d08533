//! `relightd bench --governor` end to end, small: one scene and a tiny simulated recording at
//! two budgets. Every budget gets a row comparing `auto` with the fixed engines that fit it,
//! carrying the keys other tools read; `pt`'s curve and the CPU reference's are there; the
//! outputs are written.

use std::path::Path;

use relight_core::scene::Scene;
use relight_daemon::bench::BenchSettings;
use relight_daemon::governor_bench::{GovernorSettings, run, table, write_outputs};
use relight_sim::rig::{SimRig, SimSettings, write_recording};

#[test]
fn governor_bench_compares_auto_with_what_fits_and_writes_its_outputs() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes");
    let dir = tempfile::tempdir().unwrap();
    // Three frames of the desk at 80 × 60 with truth on each.
    let desk = Scene::load(&root.join("desk_box")).unwrap();
    let rig = SimRig::new(
        &desk,
        SimSettings {
            width: 80,
            height: 60,
            fps: 10,
            frames: 3,
            color_spp: 1,
            truth_every: 1,
            ..SimSettings::placed_in(&desk)
        },
    )
    .unwrap()
    .metered();
    let recording = dir.path().join("desk.mcap");
    write_recording(&rig, &recording, |_| {}).unwrap();

    let settings = GovernorSettings {
        bench: BenchSettings {
            scenes: vec![root.join("spot_bleed")],
            width: 40,
            height: 30,
            reference_spp: 16,
            max_reference_spp: 16,
            reference_cache: None,
            frames: 1,
            accumulate: None,
            terms: false,
            wait_per_pass: false,
            cases: Vec::new(),
        },
        budgets_ms: vec![33.0, 1000.0],
        seconds: 0.3,
        recording: Some((recording, root.join("desk_box"))),
        recording_reference_spp: 2,
        curve_seconds: 0.3,
    };
    let report = run(&settings, |_| {}).unwrap();
    let scenes: Vec<&str> = report.rows.iter().map(|r| r.scene.as_str()).collect();
    assert_eq!(
        scenes,
        [
            "spot_bleed",
            "spot_bleed",
            "recording:desk",
            "recording:desk"
        ]
    );
    for row in &report.rows {
        assert!(row.auto_relative_l2.is_finite(), "{row:?}");
        assert!(!row.auto_engine.is_empty(), "{row:?}");
        match (
            &row.best_fixed_engine,
            row.best_fixed_relative_l2,
            row.best_fixed_ms,
        ) {
            (Some(_), Some(error), Some(ms)) => {
                assert!(error.is_finite() && ms <= row.budget_ms, "{row:?}");
                assert_ne!(row.verdict, "none fits");
            }
            (None, None, None) => assert_eq!(row.verdict, "none fits"),
            _ => panic!("{row:?}"),
        }
    }
    // Every fixed setting ran once per scene, pt once per budget, auto once per budget.
    let spot: Vec<&str> = report
        .runs
        .iter()
        .filter(|r| r.scene == "spot_bleed")
        .map(|r| r.engine.as_str())
        .collect();
    assert!(spot.contains(&"pt budget_ms=33") && spot.contains(&"pt budget_ms=1000"));
    assert_eq!(spot.iter().filter(|e| e.starts_with("auto")).count(), 2);
    assert_eq!(spot.iter().filter(|e| **e == "differential").count(), 1);
    let auto = report
        .runs
        .iter()
        .find(|r| r.engine == "auto budget_ms=1000")
        .unwrap();
    assert!(auto.status.as_ref().unwrap()["candidates"].is_array());

    // Both curves, samples growing along each.
    for renderer in ["pt", "reference"] {
        let curve: Vec<_> = report
            .curve
            .iter()
            .filter(|p| p.renderer == renderer)
            .collect();
        assert!(!curve.is_empty(), "no {renderer} curve");
        assert!(
            curve
                .windows(2)
                .all(|w| w[1].spp > w[0].spp && w[1].seconds >= w[0].seconds)
        );
        assert!(curve.iter().all(|p| p.relative_l2.is_finite()));
    }

    assert!(table(&report).contains("auto matches or beats"));
    let out = dir.path().join("out");
    write_outputs(&report, &out, "test adapter").unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("governor.json")).unwrap()).unwrap();
    for key in [
        "scene",
        "budget_ms",
        "auto_engine",
        "auto_relative_l2",
        "best_fixed_engine",
        "best_fixed_relative_l2",
    ] {
        assert!(json["rows"][0].get(key).is_some(), "rows lack {key}");
    }
    for file in ["governor.csv", "governor.svg", "pt_curve.svg"] {
        assert!(out.join(file).exists(), "{file}");
    }
}
