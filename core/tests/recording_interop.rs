//! A recording opens in the reference tooling (PyPI `mcap` + `mcap-ros2-support`) without relight:
//! topics, schemas, counts, metadata, and decoded images as documented.
//!
//! Needs `python3 -m pip install 'mcap>=1.2,<2' 'mcap-ros2-support>=0.5,<1'`. Set
//! `RELIGHT_SKIP_PYTHON_INTEROP=1` to skip on machines without them.

mod recording_support;

use std::path::PathBuf;
use std::process::Command;

use recording_support::{calibration, record, small_chunks, traffic};
use relight_core::StreamMessage;
use relight_core::rig::RigCalibration;
use serde_json::Value;

const PIP_COMMAND: &str = "python3 -m pip install 'mcap>=1.2,<2' 'mcap-ros2-support>=0.5,<1'";

fn helper() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/helpers/mcap_check.py")
}

#[test]
fn reference_python_tooling_reads_the_recording() {
    if std::env::var("RELIGHT_SKIP_PYTHON_INTEROP").is_ok_and(|v| v == "1") {
        eprintln!("RELIGHT_SKIP_PYTHON_INTEROP=1: skipping the Python interop check");
        return;
    }
    let messages = traffic(5, 40, 30, 21);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("interop.mcap");
    std::fs::write(&path, record(&messages, &small_chunks())).unwrap();

    let output = Command::new("python3")
        .arg(helper())
        .arg(&path)
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run python3 ({e}); install Python 3 and then: {PIP_COMMAND}")
        });
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "mcap_check.py failed ({}); if a package is missing run: {PIP_COMMAND}\n{stderr}",
        output.status
    );
    let report: Value = serde_json::from_slice(&output.stdout).unwrap();

    let channels = report["channels"].as_array().unwrap();
    let channel = |topic: &str| {
        channels
            .iter()
            .find(|c| c["topic"] == topic)
            .unwrap_or_else(|| panic!("no {topic} in {channels:?}"))
    };
    for topic in ["/depth", "/color", "/probe"] {
        let c = channel(topic);
        assert_eq!(c["schema_name"], "sensor_msgs/msg/Image");
        assert_eq!(c["schema_encoding"], "ros2msg");
        assert_eq!(c["message_encoding"], "cdr");
        assert_eq!(c["message_count"], 5);
    }
    for (topic, schema) in [
        ("/markers", "relight.MarkerSet"),
        ("/lamp", "relight.LampState"),
    ] {
        let c = channel(topic);
        assert_eq!(c["schema_name"], schema);
        assert_eq!(c["schema_encoding"], "jsonschema");
        assert_eq!(c["message_encoding"], "json");
        assert_eq!(c["message_count"], 5);
    }
    assert_eq!(report["message_count"], 25);
    assert_eq!(report["statistics_message_count"], 25);

    let metadata = &report["metadata"];
    assert_eq!(
        metadata["relight.recording"]["source"],
        "relight-tests 0.1.0"
    );
    let toml = metadata["relight.calibration"]["toml"].as_str().unwrap();
    assert_eq!(RigCalibration::from_toml(toml).unwrap(), calibration());
    assert_eq!(report["attachments"][0]["name"], "calibration.toml");

    // The first frame of each image stream, as the ROS 2 decoder sees it.
    let first = |kind: &str| {
        messages
            .iter()
            .find(|m| m.kind().name() == kind)
            .unwrap()
            .clone()
    };
    for kind in ["depth", "color", "probe"] {
        let (image, device_ns) = match first(kind) {
            StreamMessage::Depth(f) | StreamMessage::Color(f) => {
                (f.payload.clone(), f.stamp.device_ns)
            }
            StreamMessage::Probe(f) => (f.payload.image.clone(), f.stamp.device_ns),
            _ => unreachable!("image streams only"),
        };
        let decoded = &report["images"][format!("/{kind}")];
        assert_eq!(decoded["width"], image.width(), "{kind}");
        assert_eq!(decoded["height"], image.height(), "{kind}");
        assert_eq!(decoded["encoding"], image.format().ros_encoding(), "{kind}");
        assert_eq!(decoded["step"], image.stride(), "{kind}");
        assert_eq!(
            decoded["data_len"],
            image.pixel_count() * image.format().bytes_per_pixel()
        );
        let stamp_ns = decoded["stamp_ns"].as_u64().unwrap();
        // header.stamp holds the device clock; seconds saturate at i32::MAX.
        let max_sec_ns = i32::MAX as u64 * 1_000_000_000;
        let expected_ns = if device_ns < max_sec_ns {
            device_ns
        } else {
            max_sec_ns + device_ns % 1_000_000_000
        };
        assert_eq!(stamp_ns, expected_ns, "{kind}");
    }
    let probe_frame_id = report["images"]["/probe"]["frame_id"].as_str().unwrap();
    assert!(
        probe_frame_id.starts_with("probe?exposure_us="),
        "{probe_frame_id}"
    );
    assert_eq!(report["images"]["/depth"]["frame_id"], "depth");

    assert!(report["json"]["/markers"]["detections"].is_array());
    assert!(report["json"]["/lamp"]["on"].is_boolean());
}
