//! Reading format-1 recordings (relight before the ROS 2 conventions of format 2): what differs.
//!
//! | topic      | id | schema (encoding)                  | message encoding |
//! |------------|----|------------------------------------|------------------|
//! | `/depth`   | 1  | `sensor_msgs/msg/Image` (`ros2msg`) | `cdr`           |
//! | `/color`   | 2  | `sensor_msgs/msg/Image` (`ros2msg`) | `cdr`           |
//! | `/probe`   | 3  | `sensor_msgs/msg/Image` (`ros2msg`) | `cdr`           |
//! | `/markers` | 4  | `relight.MarkerSet` (`jsonschema`)  | `json`          |
//! | `/lamp`    | 5  | `relight.LampState` (`jsonschema`)  | `json`          |
//! | `/truth/*` | 16–19 | images as in format 2 but `rgba16f`; `/truth/state` plain JSON |
//!
//! - `header.stamp` and MCAP `publish_time` are the device clock, `log_time` the host's.
//! - The image `frame_id` is the camera name followed by per-frame values:
//!   `probe?exposure_us=<u32>&gain_db=<f32>`, and `seq=<u64>` on any image whose sequence
//!   number does not fit MCAP's 32-bit `sequence` (keys `&`-separated after `?`).
//! - Markers and lamp are JSON: `{"seq"?, "detections": [{"family", "marker_id",
//!   "corners_px": [[x,y]×4], "camera_from_marker": {"rotation": [x,y,z,w], "translation":
//!   [x,y,z]}, "reprojection_rms_px"}]}` with the pose in the glTF camera frame (a marker in
//!   front has z < 0), and `{"seq"?, "on", "position_in_world", "intensity"}`.
//!
//! relight no longer writes this format; `tests/fixtures/demo.mcap` is one, and replays.

use serde::Deserialize;

use crate::stream::{LampState, MarkerDetection, MarkerSet, StreamKind};

/// The value of `format_version` in a format-1 recording's `relight.recording` metadata.
pub const FORMAT_VERSION: &str = "1";

/// A stream's topic in format 1.
pub fn topic(kind: StreamKind) -> &'static str {
    match kind {
        StreamKind::Depth => "/depth",
        StreamKind::Color => "/color",
        StreamKind::Probe => "/probe",
        StreamKind::Markers => "/markers",
        StreamKind::Lamp => "/lamp",
    }
}

/// A stream's message encoding in format 1.
pub fn message_encoding(kind: StreamKind) -> &'static str {
    match kind {
        StreamKind::Markers | StreamKind::Lamp => super::schema::JSON_MESSAGE_ENCODING,
        _ => super::schema::CDR_MESSAGE_ENCODING,
    }
}

/// Per-frame values carried in a format-1 image's `frame_id` after `?`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FrameIdExtras {
    pub seq: Option<u64>,
    pub exposure_us: Option<u32>,
    pub gain_db: Option<f32>,
}

/// Split a `frame_id` into the camera name and its extras. Unknown keys are ignored; a known
/// key with a bad value is an error.
pub fn parse_frame_id(frame_id: &str) -> Result<(&str, FrameIdExtras), String> {
    let (camera, query) = frame_id.split_once('?').unwrap_or((frame_id, ""));
    let mut extras = FrameIdExtras::default();
    for pair in query.split('&').filter(|p| !p.is_empty()) {
        let (key, value) = pair
            .split_once('=')
            .ok_or_else(|| format!("frame_id `{frame_id}`: `{pair}` is not key=value"))?;
        let bad = |e: &dyn std::fmt::Display| format!("frame_id `{frame_id}`: {key}: {e}");
        match key {
            "seq" => extras.seq = Some(value.parse().map_err(|e| bad(&e))?),
            "exposure_us" => extras.exposure_us = Some(value.parse().map_err(|e| bad(&e))?),
            "gain_db" => extras.gain_db = Some(value.parse().map_err(|e| bad(&e))?),
            _ => {}
        }
    }
    Ok((camera, extras))
}

#[derive(Deserialize)]
struct MarkersIn {
    #[serde(default)]
    seq: Option<u64>,
    detections: Vec<MarkerDetection>,
}

#[derive(Deserialize)]
struct LampIn {
    #[serde(default)]
    seq: Option<u64>,
    on: bool,
    position_in_world: [f32; 3],
    intensity: [f32; 3],
}

/// Decode a `/markers` JSON message; returns the set and the `seq` member if present.
pub fn decode_markers(data: &[u8]) -> Result<(MarkerSet, Option<u64>), String> {
    let message: MarkersIn = serde_json::from_slice(data).map_err(|e| e.to_string())?;
    Ok((
        MarkerSet {
            detections: message.detections,
        },
        message.seq,
    ))
}

/// Decode a `/lamp` JSON message; returns the state and the `seq` member if present.
pub fn decode_lamp(data: &[u8]) -> Result<(LampState, Option<u64>), String> {
    let message: LampIn = serde_json::from_slice(data).map_err(|e| e.to_string())?;
    Ok((
        LampState {
            on: message.on,
            position_in_world: message.position_in_world.into(),
            intensity: message.intensity.into(),
        },
        message.seq,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_id_extras_parse() {
        let (camera, extras) =
            parse_frame_id("probe?exposure_us=33333&gain_db=0.10000001&seq=18446744073709551615")
                .unwrap();
        assert_eq!(camera, "probe");
        assert_eq!(
            extras,
            FrameIdExtras {
                seq: Some(u64::MAX),
                exposure_us: Some(33_333),
                gain_db: Some(0.100_000_01),
            }
        );
        assert_eq!(
            parse_frame_id("depth").unwrap(),
            ("depth", FrameIdExtras::default())
        );
        assert!(parse_frame_id("probe?gain_db=loud").is_err());
        assert!(parse_frame_id("probe?gain_db").is_err());
    }

    #[test]
    fn json_markers_and_lamp_decode() {
        let markers = br#"{"seq":5000000000,"detections":[{"family":"tag36h11","marker_id":3,
            "corners_px":[[1,2],[3,2],[3,4],[1,4]],
            "camera_from_marker":{"rotation":[0,0,0,1],"translation":[0,0,-1.86]},
            "reprojection_rms_px":0.2}]}"#;
        let (set, seq) = decode_markers(markers).unwrap();
        assert_eq!(seq, Some(5_000_000_000));
        assert_eq!(set.detections[0].camera_from_marker.translation.z, -1.86);
        let (lamp, seq) =
            decode_lamp(br#"{"on":true,"position_in_world":[0,1,0],"intensity":[2,2,2]}"#).unwrap();
        assert!(lamp.on && seq.is_none());
        assert!(decode_lamp(b"{}").is_err());
    }
}
