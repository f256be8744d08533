//! The bundled demo recording is what `relightd synth` generates (so it can be rebuilt), and it
//! replays through the bus frame-exact.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use relight_backends::device::Backoff;
use relight_backends::synthetic::{SyntheticRig, SyntheticSettings};
use relight_backends::{DeviceRunner, Replay, ReplayConfig, ReplayMode};
use relight_core::bus::Bus;
use relight_core::recording::RecordingReader;

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/demo.mcap")
}

#[test]
fn bundled_recording_is_the_synthetic_rig_and_carries_its_calibration() {
    let reader = RecordingReader::open(&fixture()).expect("tests/fixtures/demo.mcap reads");
    assert!(reader.warnings().is_empty(), "{:?}", reader.warnings());
    let rig = SyntheticRig::new(SyntheticSettings::default());
    assert_eq!(reader.meta().calibration.as_ref(), Some(&rig.calibration()));
    let recorded: Vec<_> = reader.messages().collect::<Result<_, _>>().unwrap();
    let generated: Vec<_> = rig.messages().collect();
    assert_eq!(recorded.len(), generated.len());
    assert!(
        recorded == generated,
        "regenerate with: relightd synth --out tests/fixtures/demo.mcap"
    );
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
