//! A recording opens in the reference tooling (PyPI `mcap` + `mcap-ros2-support`) without relight:
//! topics, schemas, counts, metadata, and decoded images as documented.
//!
//! Needs `python3 -m pip install 'mcap>=1.2,<2' 'mcap-ros2-support>=0.5,<1'`. Set
//! `RELIGHT_SKIP_PYTHON_INTEROP=1` to skip on machines without them.

mod recording_support;

use std::path::PathBuf;
use std::process::Command;

use std::sync::Arc;

use glam::{Vec2, Vec3};
use recording_support::{calibration, record, small_chunks, traffic};
use relight_core::recording::{ColorEncoding, RecordingOptions};
use relight_core::rig::RigCalibration;
use relight_core::{MarkerDetection, Pose, StreamMessage};
use serde_json::Value;

const PIP_COMMAND: &str = "python3 -m pip install 'mcap>=1.2,<2' 'mcap-ros2-support>=0.5,<1'";

fn helper() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/helpers/mcap_check.py")
}

/// Runs the helper on `path` and returns its report, or `None` when the check is skipped.
fn python_report(path: &std::path::Path) -> Option<Value> {
    if std::env::var("RELIGHT_SKIP_PYTHON_INTEROP").is_ok_and(|v| v == "1") {
        eprintln!("RELIGHT_SKIP_PYTHON_INTEROP=1: skipping the Python interop check");
        return None;
    }
    let output = Command::new("python3")
        .arg(helper())
        .arg(path)
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
    Some(serde_json::from_slice(&output.stdout).unwrap())
}

/// A marker 1.86 m in front of the colour camera (z = −1.86 in relight's glTF frame).
fn marker_in_front() -> MarkerDetection {
    MarkerDetection {
        family: "tag36h11".into(),
        marker_id: 11,
        corners_px: [Vec2::new(10.0, 20.0); 4],
        camera_from_marker: Pose::from_translation(Vec3::new(0.1, 0.2, -1.86)),
        reprojection_rms_px: 0.25,
    }
}

#[test]
fn reference_python_tooling_reads_the_recording() {
    let mut messages = traffic(5, 40, 30, 21);
    let first_markers = messages
        .iter_mut()
        .find(|m| matches!(m, StreamMessage::Markers(_)))
        .unwrap();
    if let StreamMessage::Markers(frame) = first_markers {
        let mut frame = (**frame).clone();
        frame.payload.detections = vec![marker_in_front()];
        *first_markers = StreamMessage::Markers(Arc::new(frame));
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("interop.mcap");
    std::fs::write(&path, record(&messages, &small_chunks())).unwrap();
    let Some(report) = python_report(&path) else {
        return;
    };

    assert_eq!(report["profile"], "ros2");
    let channels = report["channels"].as_array().unwrap();
    let channel = |topic: &str| {
        channels
            .iter()
            .find(|c| c["topic"] == topic)
            .unwrap_or_else(|| panic!("no {topic} in {channels:?}"))
    };
    for c in channels {
        assert_eq!(c["schema_encoding"], "ros2msg", "{c}");
        assert_eq!(c["message_encoding"], "cdr", "{c}");
    }
    for (topic, schema, count) in [
        ("/depth/image_raw", "sensor_msgs/msg/Image", 5),
        ("/color/image_raw", "sensor_msgs/msg/Image", 5),
        ("/probe/image_raw", "sensor_msgs/msg/Image", 5),
        ("/depth/frame_info", "relight_msgs/msg/FrameInfo", 5),
        ("/probe/frame_info", "relight_msgs/msg/FrameInfo", 5),
        ("/depth/camera_info", "sensor_msgs/msg/CameraInfo", 5),
        ("/markers", "relight_msgs/msg/MarkerSet", 5),
        ("/lamp", "relight_msgs/msg/LampState", 5),
        ("/tf_static", "tf2_msgs/msg/TFMessage", 1),
    ] {
        let c = channel(topic);
        assert_eq!(c["schema_name"], schema, "{topic}");
        assert_eq!(c["message_count"], count, "{topic}");
    }
    assert_eq!(report["message_count"], report["statistics_message_count"]);

    let metadata = &report["metadata"];
    assert_eq!(
        metadata["relight.recording"]["source"],
        "relight-tests 0.1.0"
    );
    assert_eq!(metadata["relight.recording"]["format_version"], "2");
    let toml = metadata["relight.calibration"]["toml"].as_str().unwrap();
    assert_eq!(RigCalibration::from_toml(toml).unwrap(), calibration());
    assert_eq!(report["attachments"][0]["name"], "calibration.toml");

    // The first frame of each image stream, as the ROS 2 decoder sees it: one frame_id per
    // camera, header.stamp the host clock, the device clock and exposure in frame_info.
    let first = |kind: &str| {
        messages
            .iter()
            .find(|m| m.kind().name() == kind)
            .unwrap()
            .clone()
    };
    for kind in ["depth", "color", "probe"] {
        let message = first(kind);
        let (image, exposure) = match &message {
            StreamMessage::Depth(f) | StreamMessage::Color(f) => (f.payload.clone(), (0, 0.0)),
            StreamMessage::Probe(f) => (
                f.payload.image.clone(),
                (f.payload.exposure_us, f.payload.gain_db),
            ),
            _ => unreachable!("image streams only"),
        };
        let decoded = &report["images"][format!("/{kind}/image_raw")];
        assert_eq!(decoded["width"], image.width(), "{kind}");
        assert_eq!(decoded["height"], image.height(), "{kind}");
        assert_eq!(decoded["frame_id"], kind);
        assert_eq!(decoded["stamp_ns"], message.stamp().host_ns, "{kind}");
        let info = &report["messages"][format!("/{kind}/frame_info")];
        assert_eq!(info["seq"], message.seq(), "{kind}");
        assert_eq!(info["device_stamp_ns"], message.stamp().device_ns, "{kind}");
        assert_eq!(info["exposure_us"], exposure.0, "{kind}");
        assert_eq!(
            info["gain_db"].as_f64().unwrap() as f32,
            exposure.1,
            "{kind}"
        );
        assert_eq!(info["header"]["stamp"], message.stamp().host_ns, "{kind}");
    }
    // A Rgba16F colour frame went out as ROS's float RGBA.
    let rgba = report["messages"]["/color/image_raw"]["encoding"]
        .as_str()
        .unwrap();
    assert!(["rgb8", "32FC4", "mono8"].contains(&rgba), "{rgba}");

    let camera_info = &report["messages"]["/depth/camera_info"];
    assert_eq!(camera_info["width"], 320);
    assert_eq!(camera_info["distortion_model"], "plumb_bob");
    assert_eq!(camera_info["k"][0], 285.5);

    // Marker poses in the optical convention: in front of the camera is +z.
    let markers = &report["messages"]["/markers"];
    assert_eq!(markers["header"]["frame_id"], "color");
    let detection = &markers["detections"][0];
    assert_eq!(detection["marker_id"], 11);
    let z = detection["camera_from_marker"]["position"]["z"]
        .as_f64()
        .unwrap();
    assert!((z - 1.86).abs() < 1e-6, "{z}");
    let tf = &report["messages"]["/tf"]["transforms"][0];
    assert_eq!(tf["header"]["frame_id"], "color");
    assert_eq!(tf["child_frame_id"], "marker_11");
    let y = tf["transform"]["translation"]["y"].as_f64().unwrap();
    assert!((y + 0.2).abs() < 1e-6, "optical +y is down: {y}");
    let tf_static = report["messages"]["/tf_static"]["transforms"]
        .as_array()
        .unwrap();
    assert_eq!(tf_static[0]["header"]["frame_id"], "map");
    assert_eq!(tf_static[0]["child_frame_id"], "world");
    assert!(
        tf_static
            .iter()
            .any(|t| t["header"]["frame_id"] == "color" && t["child_frame_id"] == "depth")
    );
    assert_eq!(report["messages"]["/lamp"]["header"]["frame_id"], "world");
}

/// Compressed colour is a `sensor_msgs/msg/CompressedImage` on image_transport's topic.
#[test]
fn compressed_colour_reads_as_compressed_image() {
    let messages = traffic(3, 40, 30, 4);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("compressed.mcap");
    let options = RecordingOptions {
        color_encoding: ColorEncoding::Png,
        ..small_chunks()
    };
    std::fs::write(&path, record(&messages, &options)).unwrap();
    let Some(report) = python_report(&path) else {
        return;
    };
    let compressed = &report["messages"]["/color/image_raw/compressed"];
    assert_eq!(compressed["format"], "png");
    assert_eq!(compressed["header"]["frame_id"], "color");
    assert!(compressed["data"]["bytes"].as_u64().unwrap() > 8);
}
