//! The latency policy end to end: a fast replay renders every frame set, a slow engine on a
//! realtime replay shows the newest one (and counts the rest), the watchdog follows the loop's
//! liveness, and outputs that would block (FIFOs) are refused while frames keep coming.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use relight_core::StreamKind;
use relight_daemon::config::{Config, ReplayConfig, ReplayMode, SourceConfig};
use relight_daemon::control::StatusReport;
use relight_daemon::control::rpc::handle_line;
use relight_daemon::pipeline::{Pipeline, PipelineOptions};
use serde_json::Value;

fn demo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/demo.mcap")
}

fn replay_config(mode: ReplayMode) -> Config {
    Config {
        source: SourceConfig::Replay(ReplayConfig {
            path: demo(),
            mode,
            loop_playback: false,
            speed: 1.0,
            topics: Default::default(),
        }),
        ..Config::default()
    }
}

fn run_to_end(
    config: Config,
    options: PipelineOptions,
    mut each: impl FnMut(&Pipeline),
) -> StatusReport {
    let options = PipelineOptions {
        exit_at_end: true,
        ..options
    };
    let mut pipeline = Pipeline::start(config, options).expect("pipeline");
    let deadline = Instant::now() + Duration::from_secs(120);
    while !pipeline.is_finished() {
        assert!(Instant::now() < deadline, "replay did not finish");
        each(&pipeline);
        std::thread::sleep(Duration::from_millis(10));
    }
    let status = pipeline.status();
    pipeline.shutdown();
    status
}

fn stage_p50(status: &StatusReport, name: &str) -> f64 {
    status
        .stages
        .iter()
        .find(|s| s.name == name)
        .map_or_else(|| panic!("no {name} stage"), |s| s.p50_ms)
}

/// The GPU comes up, the scene loads and the probe thread starts while the replay already
/// publishes: nothing may be lost to that, nor to a render slower than the replay.
#[test]
fn a_fast_replay_with_a_scene_renders_every_frame_set() {
    let mut config = replay_config(ReplayMode::Fast);
    config.scene.dir =
        Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box"));
    let status = run_to_end(config, PipelineOptions::default(), |_| {});
    assert_eq!(status.reference_frames, 60);
    assert_eq!(
        (status.frames_rendered, status.render_errors),
        (60, 0),
        "{status:?}"
    );
    assert_eq!(
        status.frames_skipped.total, 0,
        "{:?}",
        status.frames_skipped
    );
    assert_eq!(status.bus_drops, 0);
}

/// An engine four and a half frame periods slow on a 30 Hz realtime replay: each composite is
/// the newest set, so the latency stays within two periods of the render time instead of
/// growing with a queue, and every reference frame is either rendered or counted as skipped.
/// The watchdog's view stays healthy although every frame takes longer than its floor.
#[test]
fn a_slow_engine_shows_the_newest_frame_set_and_counts_the_rest() {
    let period_ms = 1000.0 / 30.0;
    let mut config = replay_config(ReplayMode::Realtime);
    // The fixture's probe and lamp report every third frame; waiting for them would add the
    // synchroniser's max_wait to every set. This test is about the render queue.
    config.sync.streams = vec![StreamKind::Color, StreamKind::Depth, StreamKind::Markers];
    let options = PipelineOptions {
        render_delay: Some(Duration::from_millis(150)),
        ..PipelineOptions::default()
    };
    let mut unhealthy = 0;
    let status = run_to_end(config, options, |pipeline| {
        if !pipeline.is_healthy(Duration::from_millis(50)) {
            unhealthy += 1;
        }
    });
    assert_eq!(unhealthy, 0, "the watchdog would have been withheld");
    let skipped = status.frames_skipped;
    assert!(skipped.superseded >= 30, "{skipped:?}");
    assert_eq!(
        status.frames_rendered + status.render_errors + skipped.superseded + skipped.sync_discarded,
        status.reference_frames,
        "every frame accounted: {status:?}"
    );
    let render_ms = stage_p50(&status, "render");
    assert!(render_ms >= 150.0);
    assert!(
        status.latency_ms.p50 <= render_ms + 2.0 * period_ms,
        "latency p50 {:.1} ms, render p50 {render_ms:.1} ms",
        status.latency_ms.p50
    );
}

fn call(pipeline: &Pipeline, request: &str) -> Value {
    let target = pipeline.control();
    serde_json::from_str(&handle_line(request.as_bytes(), target.as_ref()).expect("reply"))
        .expect("json")
}

fn mkfifo(path: &Path) {
    rustix::fs::mknodat(
        rustix::fs::CWD,
        path,
        rustix::fs::FileType::Fifo,
        rustix::fs::Mode::from_raw_mode(0o644),
        0,
    )
    .expect("mkfifo");
}

fn frame_sets_reach(pipeline: &Pipeline, n: u64) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while pipeline.status().frame_sets < n {
        assert!(Instant::now() < deadline, "render loop stalled");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn fifo_snapshot_and_recording_paths_are_refused_and_frames_keep_coming() {
    let dir = tempfile::tempdir().expect("temp dir");
    let snapshots = dir.path().join("snapshots");
    std::fs::create_dir(&snapshots).expect("snapshot dir");
    for seq in 0..64 {
        mkfifo(&snapshots.join(format!("snapshot_{seq:06}_composite.png")));
    }
    let fifo_recording = dir.path().join("rec.mcap");
    mkfifo(&fifo_recording);
    let mut config = replay_config(ReplayMode::Stepped);
    config.snapshot.dir = snapshots;
    let mut pipeline = Pipeline::start(config, PipelineOptions::default()).expect("pipeline");
    let step = |frames: u32| {
        let reply = call(
            &pipeline,
            &format!(
                r#"{{"jsonrpc":"2.0","id":1,"method":"replay.step","params":{{"frames":{frames}}}}}"#
            ),
        );
        assert!(reply.get("result").is_some(), "{reply}");
    };
    step(20);
    frame_sets_reach(&pipeline, 4);

    let snapshot = call(&pipeline, r#"{"jsonrpc":"2.0","id":2,"method":"snapshot"}"#);
    let message = snapshot["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains("FIFO"), "{snapshot}");

    let record = format!(
        r#"{{"jsonrpc":"2.0","id":3,"method":"record.start","params":{{"path":{}}}}}"#,
        Value::from(fifo_recording.display().to_string())
    );
    let refused = call(&pipeline, &record);
    let message = refused["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains("FIFO"), "{refused}");

    let sets = pipeline.status().frame_sets;
    step(20);
    frame_sets_reach(&pipeline, sets + 4);

    // The recorder is not wedged: a regular file records.
    let regular = dir.path().join("ok.mcap");
    let started = call(
        &pipeline,
        &format!(
            r#"{{"jsonrpc":"2.0","id":4,"method":"record.start","params":{{"path":{}}}}}"#,
            Value::from(regular.display().to_string())
        ),
    );
    assert!(started.get("result").is_some(), "{started}");
    let stopped = call(
        &pipeline,
        r#"{"jsonrpc":"2.0","id":5,"method":"record.stop"}"#,
    );
    assert!(stopped.get("result").is_some(), "{stopped}");
    pipeline.shutdown();
}
