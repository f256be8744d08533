//! The bundled demo recording is what the simulator makes of the desk scene (so it can be
//! rebuilt, see `scripts/make-demo`), it carries ground truth, and it replays through the bus
//! frame-exact.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use relight_backends::device::Backoff;
use relight_backends::{DeviceRunner, Replay, ReplayConfig, ReplayMode};
use relight_core::StreamKind;
use relight_core::bus::Bus;
use relight_core::recording::truth::TruthKind;
use relight_core::recording::{RecordingReader, RecordingWriter, salvage};
use relight_core::scene::Scene;
use relight_sim::rig::{CameraPath, SimRig, SimSettings};

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/demo.mcap")
}

/// The settings `scripts/make-demo` passes to `relightd simulate`.
fn demo_rig() -> SimRig {
    let scene =
        Scene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/desk_box")).unwrap();
    let settings = SimSettings {
        frames: 60,
        truth_every: 3,
        trajectory: Some(CameraPath::Walk.trajectory(&scene)),
        marker_corner_sigma_px: 0.1,
        ..SimSettings::placed_in(&scene)
    };
    SimRig::new(&scene, settings).unwrap().metered()
}

#[test]
fn bundled_recording_is_the_simulated_desk_with_its_truth() {
    let reader = RecordingReader::open(&fixture()).expect("tests/fixtures/demo.mcap reads");
    assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
    // Kept in format 1, so that recordings made before format 2 are known to replay.
    assert_eq!(reader.format_version(), Some("1"));
    let rig = demo_rig();
    assert_eq!(reader.meta().calibration.as_ref(), Some(&rig.calibration()));
    let recorded: Vec<_> = reader.messages().collect::<Result<_, _>>().unwrap();
    let count = |kind| recorded.iter().filter(|m| m.kind() == kind).count();
    assert_eq!(
        [
            StreamKind::Depth,
            StreamKind::Color,
            StreamKind::Markers,
            StreamKind::Probe,
            StreamKind::Lamp
        ]
        .map(count),
        [60, 60, 60, 20, 20]
    );
    // Regenerating is minutes of path tracing; the first frame's messages must match exactly.
    let first = rig.frame(0);
    for generated in &first.messages {
        let recorded = recorded
            .iter()
            .find(|m| m.kind() == generated.kind() && m.seq() == generated.seq())
            .unwrap();
        assert!(
            recorded == generated,
            "{} of frame 0 differs; regenerate with scripts/make-demo",
            generated.kind()
        );
    }
    let truth: Vec<_> = reader.truth().collect::<Result<_, _>>().unwrap();
    assert_eq!(
        truth.len(),
        4 * 20,
        "depth, normals, albedo and state every third frame"
    );
    assert_eq!(truth[..4], first.truth[..], "frame 0's truth");
    assert!(truth.iter().any(|t| t.kind() == TruthKind::State));
}

#[test]
fn bundled_recording_replays_through_the_bus_frame_exact() {
    let reader = RecordingReader::open(&fixture()).unwrap();
    let source: Vec<_> = reader.messages().collect::<Result<_, _>>().unwrap();
    let bus = Arc::new(Bus::new());
    let sub = bus.all.subscribe(source.len() + 1);
    let config = ReplayConfig {
        path: fixture(),
        mode: ReplayMode::Fast,
        looping: false,
    };
    let mut runner = DeviceRunner::spawn(
        "replay",
        Box::new(Replay::new(config).unwrap()),
        bus,
        Backoff::default(),
    )
    .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut got = Vec::new();
    while got.len() < source.len() && Instant::now() < deadline {
        got.extend(sub.recv_timeout(Duration::from_millis(50)));
    }
    runner.stop();
    assert_eq!(sub.dropped(), 0);
    assert_eq!(got.len(), source.len());
    for (g, s) in got.iter().zip(&source) {
        assert_eq!(
            (g.kind(), g.seq(), g.stamp().device_ns),
            (s.kind(), s.seq(), s.stamp().device_ns)
        );
    }
}

/// `relightd recording repair` rewrites a format-1 recording in format 2 without losing a bit:
/// every stream and truth message of the bundled (format-1) recording reads back equal.
#[test]
fn the_bundled_recording_converts_to_format_2_exactly() {
    let old = RecordingReader::open(&fixture()).unwrap();
    let mut writer = RecordingWriter::new(std::io::Cursor::new(Vec::new()), old.meta()).unwrap();
    let found = salvage::salvage(&old, &mut writer).unwrap();
    assert!(found.is_clean(), "{found:?}");
    let (_, cursor) = writer.finish_into_inner().unwrap();
    let new = RecordingReader::from_bytes(cursor.into_inner()).unwrap();
    assert_eq!(new.format_version(), Some("2"));
    assert_eq!(new.meta(), old.meta());
    let streams = |r: &RecordingReader| r.messages().collect::<Result<Vec<_>, _>>().unwrap();
    assert!(streams(&new) == streams(&old), "stream messages differ");
    let truth = |r: &RecordingReader| r.truth().collect::<Result<Vec<_>, _>>().unwrap();
    assert!(truth(&new) == truth(&old), "truth messages differ");
}
