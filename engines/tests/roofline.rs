//! The roofline's inputs: the adapter's measured rates, and the work every engine states for
//! the GPU passes it ran (`RelitFrame::work`), which `relightd bench --roofline` divides by the
//! passes' timings.

mod support;

use std::collections::BTreeSet;
use std::sync::Arc;

use relight_engines::gpu::GpuContext;
use relight_engines::roofline;
use support::{delta_of, engine_with, frame, load_scene};

#[test]
fn the_adapter_rates_are_finite_and_positive() {
    let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
    let rates = roofline::measure(&ctx).unwrap();
    assert!(
        rates.bytes_per_s.is_finite() && rates.bytes_per_s > 1e6,
        "{rates:?}"
    );
    assert!(
        rates.ops_per_s.is_finite() && rates.ops_per_s > 1e6,
        "{rates:?}"
    );
}

/// The passes whose work an engine states on a frame where everything is drawn, and on the
/// same frame again, where what it keeps is not run (and so has no work).
fn stated(name: &str, params: serde_json::Value, scene: &str) -> [BTreeSet<&'static str>; 2] {
    let scene = Arc::new(load_scene(scene));
    let mut engine = engine_with(name, params);
    let frame = frame(scene, 40, 30);
    let passes = |engine: &mut Box<dyn relight_engines::Engine>| {
        let (_, out) = delta_of(engine, &frame);
        for w in &out.work {
            assert!(
                w.work.bytes.is_finite()
                    && w.work.ops.is_finite()
                    && w.work.bytes + w.work.ops > 0.0,
                "{name}: {w:?}"
            );
        }
        // Every pass the adapter timed has its work stated (with timestamps; lavapipe has).
        let stated: BTreeSet<&'static str> = out.work.iter().map(|w| w.pass).collect();
        for timed in out
            .timings
            .iter()
            .filter_map(|t| t.pass.strip_prefix("gpu."))
        {
            assert!(
                stated.contains(timed),
                "{name}: pass {timed} is timed but states no work"
            );
        }
        stated
    };
    [passes(&mut engine), passes(&mut engine)]
}

fn set(passes: &[&'static str]) -> BTreeSet<&'static str> {
    passes.iter().copied().collect()
}

#[test]
fn every_engine_states_the_work_of_the_passes_it_ran() {
    let none = serde_json::json!({});
    assert_eq!(
        stated("differential", none.clone(), "desk_box"),
        [
            set(&["gbuffer", "shadow", "shade"]),
            set(&["gbuffer", "shade"])
        ]
    );
    assert_eq!(
        stated(
            "dlpv",
            serde_json::json!({ "volume_size": 8, "steps": 4 }),
            "desk_box"
        ),
        [
            set(&[
                "gbuffer",
                "shadow",
                "rsm",
                "inject",
                "propagate",
                "lookup",
                "shade"
            ]),
            set(&["gbuffer", "lookup", "shade"])
        ]
    );
    assert_eq!(
        stated("dvct", serde_json::json!({ "volume_size": 16 }), "desk_box"),
        [
            set(&[
                "gbuffer",
                "shadow",
                "rsm",
                "voxelize",
                "inject",
                "far_emitters",
                "mip",
                "probe",
                "trace",
                "shade"
            ]),
            set(&["gbuffer", "trace", "shade"])
        ]
    );
    assert_eq!(
        stated(
            "dir",
            serde_json::json!({ "vpl_count": 16, "accumulate": 1 }),
            "desk_box"
        ),
        [
            set(&["gbuffer", "shadow", "rsm", "vpls", "ism", "gather", "shade"]),
            set(&["gbuffer", "gather", "shade"])
        ]
    );
    let [first, again] = stated("ibl", none, "window_env");
    assert!(
        first.is_superset(&set(&[
            "gbuffer",
            "shadow",
            "convolve",
            "ibl_shade",
            "shade"
        ])),
        "{first:?}"
    );
    assert!(!again.contains("convolve"), "{again:?}");
}
