mod support;
use std::sync::Arc;
use std::time::Instant;
use support::*;

#[test]
#[ignore]
fn scratch_features() {
    for name in [
        "desk_box",
        "glossy_floor",
        "spot_bleed",
        "touching_wall",
        "window_env",
    ] {
        let scene = load_scene(name);
        let started = Instant::now();
        let f = relight_engines::auto::features::scene_features(&scene);
        let ms = started.elapsed().as_secs_f64() * 1e3;
        eprintln!(
            "{name}: {ms:.1} ms S {:.2} B {:.2} O {:.2} G {:.2} share {:.2} n {}",
            f.shadow,
            f.bleeding,
            f.occlusion,
            f.glossy,
            f.indirect_share(),
            f.samples
        );
        let _ = Arc::new(scene);
    }
}
