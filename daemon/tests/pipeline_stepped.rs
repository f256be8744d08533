//! A stepped replay advances only when `replay.step` asks, so a frame can be examined at leisure.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use relight_daemon::config::{Config, ReplayConfig, ReplayMode, SourceConfig};
use relight_daemon::control::rpc::handle_line;
use relight_daemon::pipeline::{Pipeline, PipelineOptions};
use serde_json::Value;

fn stepped_config(dir: &Path) -> Config {
    let mut config = Config {
        source: SourceConfig::Replay(ReplayConfig {
            path: PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/demo.mcap"),
            mode: ReplayMode::Stepped,
            loop_playback: false,
            speed: 1.0,
            topics: Default::default(),
        }),
        ..Config::default()
    };
    config.snapshot.dir = dir.join("snapshots");
    config
}

fn call(pipeline: &Pipeline, request: &str) -> Value {
    let target = pipeline.control();
    serde_json::from_str(&handle_line(request.as_bytes(), target.as_ref()).unwrap()).unwrap()
}

fn frame_sets_after(pipeline: &Pipeline, expected: u64) -> u64 {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let sets = pipeline.status().frame_sets;
        if sets >= expected || Instant::now() > deadline {
            return sets;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn stepped_replay_renders_only_what_was_stepped() {
    let dir = tempfile::tempdir().unwrap();
    let mut pipeline =
        Pipeline::start(stepped_config(dir.path()), PipelineOptions::default()).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        pipeline.status().frame_sets,
        0,
        "nothing renders before a step"
    );

    // The fixture's first 10 frames hold 38 messages (depth, colour and markers every frame; probe
    // and lamp every third frame). Two more start frame 10, whose set stays undecided.
    let reply = call(
        &pipeline,
        r#"{"jsonrpc":"2.0","id":1,"method":"replay.step","params":{"frames":10}}"#,
    );
    assert_eq!(reply["result"]["frames"], 10, "{reply}");
    let sets = frame_sets_after(&pipeline, 10);
    assert_eq!(sets, 10, "sets after stepping 10 frame sets");
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        pipeline.status().frame_sets,
        sets,
        "no progress without a step"
    );

    let bad = call(
        &pipeline,
        r#"{"jsonrpc":"2.0","id":2,"method":"replay.step","params":{"frames":0}}"#,
    );
    assert_eq!(bad["error"]["code"], -32602, "{bad}");
    pipeline.shutdown();
}

#[test]
fn step_without_a_stepped_source_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = stepped_config(dir.path());
    if let SourceConfig::Replay(replay) = &mut config.source {
        replay.mode = ReplayMode::Fast;
    }
    let mut pipeline = Pipeline::start(config, PipelineOptions::default()).unwrap();
    let reply = call(
        &pipeline,
        r#"{"jsonrpc":"2.0","id":1,"method":"replay.step"}"#,
    );
    assert!(
        reply["error"]["message"]
            .as_str()
            .unwrap()
            .contains("not a stepped replay"),
        "{reply}"
    );
    pipeline.shutdown();
}

/// With a scene, status reports the live surface's albedo measurement: the bundled recording's
/// calibration has the colour camera's response, so eq. 1 runs on the `albedo` thread from the
/// first frame on, and a later frame takes its estimate (no frame waits for one).
#[test]
fn status_reports_the_albedo_measurement() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = stepped_config(dir.path());
    config.scene.dir =
        Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box"));
    let mut pipeline = Pipeline::start(config, PipelineOptions::default()).unwrap();
    // The estimate runs at the lowest CPU priority, so under a loaded suite (the other tests'
    // pipelines on the same two cores) it may wait long for the CPU: once it got 18 frames in
    // 60 s and none finished. The deadline only ends a test that would never pass.
    let deadline = Instant::now() + Duration::from_secs(240);
    let mut stepped = 0;
    let albedo = loop {
        assert!(
            Instant::now() < deadline,
            "no albedo estimate after {stepped} frames"
        );
        let reply = call(
            &pipeline,
            r#"{"jsonrpc":"2.0","id":1,"method":"replay.step","params":{"frames":1}}"#,
        );
        assert_eq!(reply["result"]["frames"], 1, "{reply}");
        stepped += 1;
        // A step's frame set is decided once the next frame's messages arrive.
        frame_sets_after(&pipeline, stepped - 1);
        // Time for the estimate the frame handed over to come back before the next one.
        std::thread::sleep(Duration::from_millis(200));
        if let Some(albedo) = pipeline.status().albedo
            && albedo.estimated
        {
            break albedo;
        }
    };
    assert!(stepped >= 2, "the first frame waited for its estimate");
    assert!(
        albedo.measured_vertices > 0 && albedo.measured_vertices <= albedo.vertices,
        "{albedo:?}"
    );
    pipeline.shutdown();
}
