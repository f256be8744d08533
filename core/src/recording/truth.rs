//! Ground-truth channels: what the simulator knows and a real rig never does (true depth,
//! normals, albedo, the camera's pose, the lights, the markers' poses), recorded next to the
//! sensor streams so every estimator can be scored against the recording it ran on.
//!
//! | topic            | id | schema                  | payload                        | `frame_id` |
//! |------------------|----|-------------------------|--------------------------------|------------|
//! | `/truth/depth`   | 16 | `sensor_msgs/msg/Image` | `32FC1`: z along the optical axis, m; 0 = no surface | `depth` |
//! | `/truth/normals` | 17 | `sensor_msgs/msg/Image` | `32FC4`: unit normal in the world frame, a = 1 where a surface is | `world` |
//! | `/truth/albedo`  | 18 | `sensor_msgs/msg/Image` | `32FC4`: diffuse albedo k_d, a = specular k_s (luminance) | `depth` |
//! | `/truth/state`   | 19 | `std_msgs/msg/String`   | [`TruthState`] as JSON (poses glTF-convention) | — |
//!
//! The images are per pixel of the depth camera (registered to colour), of the **real** scene
//! only, as the sensors see it; `frame_id` names the frame their values are expressed in. They
//! hold `Rgba16F` in memory and go out widened to `32FC4` (ROS's float RGBA; format 1 wrote
//! relight's own `rgba16f`). Channels are declared when their first message is written, with
//! the fixed IDs above so that a file whose channel records are lost still reads.

use serde::{Deserialize, Serialize};

use crate::frame::{Frame, Image, PixelFormat};
use crate::light::Light;
use crate::pose::Pose;

/// Which ground-truth channel a message belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TruthKind {
    Depth,
    Normals,
    Albedo,
    State,
}

impl TruthKind {
    pub const ALL: [TruthKind; 4] = [
        TruthKind::Depth,
        TruthKind::Normals,
        TruthKind::Albedo,
        TruthKind::State,
    ];

    pub fn topic(self) -> &'static str {
        match self {
            TruthKind::Depth => "/truth/depth",
            TruthKind::Normals => "/truth/normals",
            TruthKind::Albedo => "/truth/albedo",
            TruthKind::State => "/truth/state",
        }
    }

    pub fn channel_id(self) -> u16 {
        match self {
            TruthKind::Depth => 16,
            TruthKind::Normals => 17,
            TruthKind::Albedo => 18,
            TruthKind::State => 19,
        }
    }

    pub fn of_topic(topic: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|kind| kind.topic() == topic)
    }

    /// The pixel format an image channel carries; `None` for the state channel.
    pub fn pixel_format(self) -> Option<PixelFormat> {
        match self {
            TruthKind::Depth => Some(PixelFormat::DepthF32M),
            TruthKind::Normals | TruthKind::Albedo => Some(PixelFormat::Rgba16F),
            TruthKind::State => None,
        }
    }
}

/// A marker's true placement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkerTruth {
    pub family: String,
    pub marker_id: u32,
    /// Marker frame: origin at the centre, +x right, +y up on the printed tag, +z out of it.
    pub world_from_marker: Pose,
    /// Edge length of the black square, metres.
    pub size_m: f32,
}

/// The scene's true state at one instant.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TruthState {
    /// Colour/depth camera, glTF convention (looks down −Z, +Y up).
    pub world_from_camera: Pose,
    /// The fish-eye probe, same convention; absent on rigs without one (and then left out of
    /// the JSON, so a `null` always means a non-finite number).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub world_from_probe: Option<Pose>,
    /// Every light of the real scene at this instant, the pocket lamp included (as a point).
    pub lights: Vec<Light>,
    pub markers: Vec<MarkerTruth>,
}

/// One ground-truth message.
#[derive(Debug, Clone, PartialEq)]
pub enum TruthMessage {
    /// An image channel (`kind` is never [`TruthKind::State`]).
    Image(TruthKind, Frame<Image>),
    State(Frame<TruthState>),
}

impl TruthMessage {
    pub fn kind(&self) -> TruthKind {
        match self {
            TruthMessage::Image(kind, _) => *kind,
            TruthMessage::State(_) => TruthKind::State,
        }
    }

    pub fn stamp(&self) -> crate::Timestamp {
        match self {
            TruthMessage::Image(_, frame) => frame.stamp,
            TruthMessage::State(frame) => frame.stamp,
        }
    }

    pub fn seq(&self) -> u64 {
        match self {
            TruthMessage::Image(_, frame) => frame.seq,
            TruthMessage::State(frame) => frame.seq,
        }
    }
}

/// A truth state as JSON. Non-finite numbers are refused.
pub fn encode_state(state: &TruthState) -> Result<String, String> {
    let json = serde_json::to_string(state).map_err(|e| e.to_string())?;
    // serde_json writes NaN/∞ as `null`, which would not read back: refuse instead.
    let reread: serde_json::Value = serde_json::from_str(&json).map_err(|e| e.to_string())?;
    if contains_null_number(&reread) {
        return Err("truth state holds a non-finite number".into());
    }
    Ok(json)
}

fn contains_null_number(value: &serde_json::Value) -> bool {
    match value {
        serde_json::Value::Array(items) => {
            items.iter().any(|v| v.is_null() || contains_null_number(v))
        }
        serde_json::Value::Object(map) => {
            map.values().any(|v| v.is_null() || contains_null_number(v))
        }
        _ => false,
    }
}

pub fn decode_state(data: &[u8]) -> Result<TruthState, String> {
    serde_json::from_slice(data).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use glam::{Quat, Vec3};

    use super::*;

    #[test]
    fn state_round_trips_and_refuses_nan() {
        let state = TruthState {
            world_from_camera: Pose::new(Quat::from_rotation_y(0.3), Vec3::new(1.0, 2.0, 3.0)),
            world_from_probe: None,
            lights: vec![Light::Point {
                position_in_world: Vec3::Y,
                intensity: Vec3::ONE,
            }],
            markers: vec![MarkerTruth {
                family: "tag36h11".into(),
                marker_id: 3,
                world_from_marker: Pose::IDENTITY,
                size_m: 0.08,
            }],
        };
        let json = encode_state(&state).unwrap();
        assert_eq!(decode_state(json.as_bytes()).unwrap(), state);

        let mut bad = state;
        bad.lights[0] = Light::Point {
            position_in_world: Vec3::new(f32::NAN, 0.0, 0.0),
            intensity: Vec3::ONE,
        };
        assert!(encode_state(&bad).is_err());
    }
}
