//! Resident memory stays flat over a looped replay with a scene (its own test binary, so that no
//! other test's allocations share the process). The tolerance comes from the run's own
//! warm-up: RSS may move after it by no more than three times the largest step between two
//! samples of the warm-up's second half (or 3 %), and the measured stretch is twelve samples
//! long, so a steady leak, whose every step is as large as the warm-up's, cannot hide in it.

use std::path::PathBuf;
use std::time::Duration;

use relight_daemon::config::Config;
use relight_daemon::soak::{SoakSettings, run};

#[test]
fn rss_is_flat_over_a_looped_replay_with_a_scene() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let sample = Duration::from_millis(750);
    let warmup_samples = 6;
    let measured_samples = 12;
    let settings = SoakSettings {
        recording: root.join("tests/fixtures/demo.mcap"),
        scene: Some(root.join("tests/scenes/desk_box")),
        engines: vec!["passthrough".into()],
        duration: sample * (warmup_samples + measured_samples),
        switch_every: None,
        sample_every: sample,
        warmup: sample * warmup_samples,
        config: Config::default(),
    };
    let report = run(&settings, |_| {}).expect("soak");
    let rss: Vec<f64> = report.samples.iter().map(|s| s.resources.rss_mb).collect();
    let warmup = warmup_samples as usize;
    assert!(rss.len() > warmup + 4, "{rss:?}");
    // The first samples hold the GPU's and the scene's start-up; the warm-up's second half is
    // the steady state's own noise.
    let noise_mb = rss[warmup / 2..=warmup]
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(0.0, f64::max);
    let base = rss[warmup];
    let tolerance_mb = (3.0 * noise_mb).max(0.03 * base);
    let last = *rss.last().expect("samples");
    let frames = report.samples.last().map_or(0, |s| s.frames_rendered);
    assert!(frames > 20, "too few frames to judge: {frames}");
    assert!(
        last - base <= tolerance_mb,
        "RSS grew {:.1} MB after warm-up (tolerance {tolerance_mb:.1} MB) over {frames} frames: {rss:?}",
        last - base
    );
    assert!(
        report.fds_growth <= 0 && report.threads_growth <= 0,
        "{report:?}"
    );
}
