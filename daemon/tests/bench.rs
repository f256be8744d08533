//! `relightd bench` end to end on one small scene: every default case yields a finite error and
//! time, the differential baseline is exact where it should be, and the outputs are written.

use std::path::Path;

use relight_daemon::bench::{
    BenchCase, BenchSettings, default_cases, roofline_rows, roofline_table, run, table,
    write_outputs, write_roofline,
};
use relight_engines::roofline::Rates;

/// `cases` on spot_bleed at 48 × 36 against a reference of 16 to 64 spp, one timed frame and
/// four accumulated; each test changes what it is about.
fn on_spot_bleed(cases: Vec<BenchCase>) -> BenchSettings {
    BenchSettings {
        scenes: vec![Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/spot_bleed")],
        width: 48,
        height: 36,
        reference_spp: 16,
        max_reference_spp: 64,
        reference_cache: None,
        frames: 1,
        accumulate: Some(4),
        terms: false,
        wait_per_pass: false,
        cases,
    }
}

#[test]
fn bench_measures_every_case_and_writes_its_outputs() {
    let settings = on_spot_bleed(default_cases(false));
    let rows = run(&settings, |_| {}).unwrap();
    assert_eq!(rows.len(), default_cases(false).len());
    for row in &rows {
        assert!(row.median_ms.is_finite() && row.median_ms > 0.0, "{row:?}");
        assert!(row.static_ms.is_finite() && row.static_ms > 0.0, "{row:?}");
        assert!(
            row.relative_l2.is_finite() && row.relative_l2 < 2.0,
            "{row:?}"
        );
    }
    // The reference is refined towards a third of the best error, within its cap.
    for row in &rows {
        assert!((16..=64).contains(&row.reference_spp), "{row:?}");
        assert!(
            row.reference_noise.is_finite() && row.reference_noise > 0.0,
            "{row:?}"
        );
    }
    let best = rows
        .iter()
        .map(|r| r.relative_l2)
        .fold(f64::INFINITY, f64::min);
    assert!(
        rows[0].reference_spp == 64 || rows[0].reference_noise <= best / 3.0,
        "{:?}",
        rows[0]
    );
    // Every engine with sub-pixel accumulation accumulated 4 still frames, scored against the
    // pixel-area reference (pt samples the pixel's area from its first frame).
    let registry = relight_engines::EngineRegistry::new();
    for row in &rows {
        if !registry.spec(&row.engine).unwrap().schema.has("accumulate") {
            assert_eq!(row.accumulated_frames, 1, "{row:?}");
            continue;
        }
        assert_eq!(row.accumulated_frames, 4, "{row:?}");
        for error in [
            row.area_relative_l2,
            row.converged_relative_l2,
            row.converged_object_relative_l2,
            row.area_reference_noise,
        ] {
            assert!(error.is_some_and(f64::is_finite), "{row:?}");
        }
    }
    // spot_bleed's object both shadows and bleeds, and the reference says where.
    assert!(
        rows.iter()
            .all(|r| r.shadow_relative_l2.is_some_and(f64::is_finite))
    );
    assert!(
        rows.iter()
            .all(|r| r.bleeding_relative_l2.is_some_and(f64::is_finite))
    );
    // Direct light alone only ever takes light away: in the bleeding its Δ is ≤ 0 where the
    // reference's is > 0, an error of at least the whole bleeding.
    let differential = rows.iter().find(|r| r.engine == "differential").unwrap();
    assert!(
        differential.bleeding_relative_l2.unwrap() >= 0.99,
        "{differential:?}"
    );
    assert!(table(&rows).lines().count() == rows.len() + 1);
    let dir = tempfile::tempdir().unwrap();
    write_outputs(&rows, dir.path(), "test adapter").unwrap();
    for file in ["bench.csv", "bench.json", "bench.svg"] {
        let len = std::fs::metadata(dir.path().join(file)).unwrap().len();
        assert!(len > 100, "{file}: {len} bytes");
    }
    let csv = std::fs::read_to_string(dir.path().join("bench.csv")).unwrap();
    assert_eq!(csv.lines().count(), rows.len() + 1);

    // The roofline: a row per timed pass (lavapipe has timestamps), each with its work.
    let rates = Rates {
        bytes_per_s: 1e10,
        ops_per_s: 1e11,
    };
    let roofline = roofline_rows(&rows, &rates);
    let timed: usize = rows.iter().map(|r| r.gpu_passes.len()).sum();
    assert!(timed > 0);
    assert_eq!(roofline.len(), timed);
    for r in &roofline {
        let (bytes, ops) = (r.bytes.unwrap(), r.ops.unwrap());
        let expected = (bytes / 1e10).max(ops / 1e11) * 1e3;
        assert!(
            (r.roofline_ms.unwrap() - expected).abs() <= 1e-9 * expected.max(1.0),
            "{r:?}"
        );
        if r.ms > 0.0 {
            assert!(
                (r.roofline_fraction.unwrap() - expected / r.ms).abs() <= 1e-9 * (expected / r.ms),
                "{r:?}"
            );
        }
    }
    assert_eq!(
        roofline_table(&rates, &roofline).lines().count(),
        roofline.len() + 2
    );
    write_roofline(&rates, &roofline, dir.path(), "test adapter").unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("roofline.json")).unwrap())
            .unwrap();
    let first = &json["rows"][0];
    for key in ["pass", "ms", "roofline_fraction"] {
        assert!(!first[key].is_null(), "{key}: {first}");
    }
}

/// `relightd bench` with `args` on spot_bleed, from the repository root.
fn bench_on_spot_bleed(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_relightd"))
        .arg("bench")
        .args(args)
        .args(["--scene", "tests/scenes/spot_bleed"])
        .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join(".."))
        .output()
        .unwrap()
}

/// `bench --engine nosuch` used to print an empty table and exit 0.
#[test]
fn an_unknown_engine_is_an_error_that_lists_the_benched_ones() {
    let out = bench_on_spot_bleed(&["--engine", "nosuch"]);
    assert_eq!(out.status.code(), Some(2), "a usage error");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("nosuch") && stderr.contains("differential"),
        "{stderr}"
    );
    assert!(
        out.stdout.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}

/// A `--case` the engine cannot take is refused before anything renders, naming the parameter.
#[test]
fn a_bad_case_is_refused_with_its_reason() {
    let out = bench_on_spot_bleed(&["--case", "dir vpl_count=0"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("dir vpl_count=0") && stderr.contains("outside [1, 1024]"),
        "{stderr}"
    );
    assert!(
        out.stdout.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}

/// A reference rendered once is read from the cache on the next run, and scores the same.
#[test]
fn a_cached_reference_is_read_back_on_the_next_run() {
    use relight_daemon::bench::BenchProgress;
    let cache = tempfile::tempdir().unwrap();
    let settings = BenchSettings {
        width: 32,
        height: 24,
        reference_spp: 8,
        max_reference_spp: 8,
        reference_cache: Some(cache.path().to_owned()),
        accumulate: Some(2),
        ..on_spot_bleed(vec![BenchCase::new("differential", serde_json::json!({}))])
    };
    let run_once = || {
        let mut cached = Vec::new();
        let rows = run(&settings, |event| {
            if let BenchProgress::Reference { cached: c, .. } = event {
                cached.push(c);
            }
        })
        .unwrap();
        (rows, cached)
    };
    let (first, cached) = run_once();
    // The pixel-centre reference, then the pixel-area one, each under its own key.
    assert_eq!(cached, [false, false]);
    let (second, cached) = run_once();
    assert_eq!(cached, [true, true], "the second run reads the cache");
    assert_eq!(first[0].relative_l2, second[0].relative_l2);
    assert_eq!(
        first[0].converged_relative_l2,
        second[0].converged_relative_l2
    );
    assert_eq!(second[0].reference_spp, 8);
}

/// `--terms`: an engine rendered with its direct light alone, both terms swapped for the
/// reference's. The shadow-mapped direct light is the same in every engine, and only an engine
/// with indirect light can bring the indirect term's error below the reference's own indirect
/// share.
#[test]
fn terms_say_which_term_an_error_comes_from() {
    use relight_daemon::bench::terms_table;
    let settings = BenchSettings {
        width: 64,
        height: 48,
        terms: true,
        ..on_spot_bleed(
            ["differential", "dvct", "ibl"]
                .map(|e| BenchCase::new(e, serde_json::json!({})))
                .to_vec(),
        )
    };
    let rows = run(&settings, |_| {}).unwrap();
    let [differential, dvct, ibl] = [&rows[0], &rows[1], &rows[2]];
    // ibl carries the environment's light in its indirect buffer, so it has no such split.
    assert_eq!(ibl.direct_term_relative_l2, None);
    assert_eq!(ibl.object_indirect_term_relative_l2, None);
    for row in [differential, dvct] {
        for error in [
            row.direct_term_relative_l2,
            row.indirect_term_relative_l2,
            row.object_direct_term_relative_l2,
            row.object_indirect_term_relative_l2,
            row.direct_reference_noise,
        ] {
            assert!(error.is_some_and(f64::is_finite), "{row:?}");
        }
        assert!(row.direct_reference_spp.is_some_and(|spp| spp >= 16));
    }
    let term = |row: &relight_daemon::bench::BenchRow| {
        (
            row.direct_term_relative_l2.unwrap(),
            row.indirect_term_relative_l2.unwrap(),
        )
    };
    let (differential_direct, differential_indirect) = term(differential);
    let (dvct_direct, dvct_indirect) = term(dvct);
    // One direct light: `indirect=off` shades exactly what `differential` shades.
    assert!(
        (differential_direct - dvct_direct).abs() < 1e-9,
        "{differential_direct} {dvct_direct}"
    );
    assert_eq!(
        differential.object_direct_term_relative_l2,
        dvct.object_direct_term_relative_l2
    );
    // The same of the converged pictures against the pixel-area references.
    let converged = |row: &relight_daemon::bench::BenchRow| {
        (
            row.converged_direct_term_relative_l2.unwrap(),
            row.converged_indirect_term_relative_l2.unwrap(),
        )
    };
    let (differential_converged, _) = converged(differential);
    let (dvct_converged, dvct_converged_indirect) = converged(dvct);
    assert!(
        (differential_converged - dvct_converged).abs() < 1e-9,
        "{differential_converged} {dvct_converged}"
    );
    assert!(dvct_converged_indirect.is_finite());
    assert_eq!(ibl.converged_direct_term_relative_l2, None);
    // spot_bleed's object bleeds onto the floor: without indirect light that is most of the
    // error, and dvct's bleeding brings it down.
    assert!(
        differential_indirect > differential_direct,
        "{differential_indirect} {differential_direct}"
    );
    assert!(
        dvct_indirect < 0.9 * differential_indirect,
        "{dvct_indirect} {differential_indirect}"
    );
    assert!(terms_table(&rows).lines().count() == 4);
}

/// Timed by waiting, every pass of a `dvct` frame has its own time, and together they fit in
/// the frame: lavapipe's timestamps give the later compute passes of a submission almost
/// nothing, and waiting is what makes each pass's time its own.
///
/// Nothing here compares one clock reading with another taken at a different moment, so a
/// loaded machine cannot fail it: how much of the frame the passes cover is a speed, and the
/// bench reports it (`--pass-times wait`).
#[test]
fn passes_timed_by_waiting_each_take_time_within_the_frame() {
    let case = BenchCase::parse(
        "dvct volume_size=16",
        &relight_engines::EngineRegistry::new(),
    );
    let settings = BenchSettings {
        max_reference_spp: 16,
        frames: 3,
        accumulate: Some(1),
        wait_per_pass: true,
        ..on_spot_bleed(vec![case.unwrap()])
    };
    let rows = run(&settings, |_| {}).unwrap();
    let row = &rows[0];
    let names: Vec<&str> = row.gpu_passes.iter().map(|(n, _)| n.as_str()).collect();
    for pass in [
        "gbuffer", "shadow", "rsm", "voxelize", "inject", "mip", "trace", "shade",
    ] {
        assert!(names.contains(&pass), "{pass} missing from {names:?}");
    }
    // Each pass waits for what came before it, so none is free: an empty dispatch costs
    // llvmpipe tens of microseconds.
    for (pass, ms) in &row.gpu_passes {
        assert!(*ms > 0.0 && ms.is_finite(), "{pass}: {ms} ms");
    }
    // A frame's passes run one after another inside its `render` call, so each frame's sum is
    // at most its wall time, and so the median of the sums is at most the median frame.
    let gpu_ms = row.gpu_ms.expect("lavapipe has timestamp queries");
    assert!(
        gpu_ms <= row.median_ms,
        "passes {gpu_ms} ms; the median frame {} ms",
        row.median_ms
    );
}
