//! The rig's streams and what each one carries.

use std::fmt;
use std::sync::Arc;

use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};

use crate::frame::{Frame, Image};
use crate::pose::Pose;

/// The five streams of a rig. Each has one bus topic and one recording channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StreamKind {
    Depth,
    Color,
    Probe,
    Markers,
    Lamp,
}

impl StreamKind {
    pub const ALL: [StreamKind; 5] = [
        StreamKind::Depth,
        StreamKind::Color,
        StreamKind::Probe,
        StreamKind::Markers,
        StreamKind::Lamp,
    ];

    pub fn name(self) -> &'static str {
        match self {
            StreamKind::Depth => "depth",
            StreamKind::Color => "color",
            StreamKind::Probe => "probe",
            StreamKind::Markers => "markers",
            StreamKind::Lamp => "lamp",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

impl fmt::Display for StreamKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A fish-eye probe image with the exposure it was taken at (for HDR merging of brackets).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ProbeImage {
    pub image: Image,
    pub exposure_us: u32,
    pub gain_db: f32,
}

/// One detected square marker (AprilTag / ArUco) in a camera image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkerDetection {
    /// Tag family, e.g. `tag36h11`, `aruco_4x4_50`.
    pub family: String,
    pub marker_id: u32,
    /// Corners in pixels, counter-clockwise from the tag's lower-left as seen in the image.
    pub corners_px: [Vec2; 4],
    /// The marker's pose in the observing camera's frame.
    pub camera_from_marker: Pose,
    /// Reprojection RMS of the pose fit in pixels (a pose quality estimate).
    pub reprojection_rms_px: f32,
}

/// All markers detected in one camera image.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MarkerSet {
    pub detections: Vec<MarkerDetection>,
}

/// The tracked pocket lamp: where it is (from its marker) and what its serial line says.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LampState {
    pub on: bool,
    /// The light's centre in the world frame, metres.
    pub position_in_world: Vec3,
    /// Radiant intensity, linear RGB, W/sr.
    pub intensity: Vec3,
}

impl Default for LampState {
    fn default() -> Self {
        Self {
            on: false,
            position_in_world: Vec3::ZERO,
            intensity: Vec3::ZERO,
        }
    }
}

/// A frame of any stream, as shared on the bus and stored in recordings.
#[derive(Debug, Clone, PartialEq)]
pub enum StreamMessage {
    Depth(Arc<Frame<Image>>),
    Color(Arc<Frame<Image>>),
    Probe(Arc<Frame<ProbeImage>>),
    Markers(Arc<Frame<MarkerSet>>),
    Lamp(Arc<Frame<LampState>>),
}

impl StreamMessage {
    pub fn kind(&self) -> StreamKind {
        match self {
            StreamMessage::Depth(_) => StreamKind::Depth,
            StreamMessage::Color(_) => StreamKind::Color,
            StreamMessage::Probe(_) => StreamKind::Probe,
            StreamMessage::Markers(_) => StreamKind::Markers,
            StreamMessage::Lamp(_) => StreamKind::Lamp,
        }
    }

    pub fn stamp(&self) -> crate::Timestamp {
        match self {
            StreamMessage::Depth(f) | StreamMessage::Color(f) => f.stamp,
            StreamMessage::Probe(f) => f.stamp,
            StreamMessage::Markers(f) => f.stamp,
            StreamMessage::Lamp(f) => f.stamp,
        }
    }

    pub fn seq(&self) -> u64 {
        match self {
            StreamMessage::Depth(f) | StreamMessage::Color(f) => f.seq,
            StreamMessage::Probe(f) => f.seq,
            StreamMessage::Markers(f) => f.seq,
            StreamMessage::Lamp(f) => f.seq,
        }
    }

    /// The frame's sequence number and timestamps, for a source that renumbers or restamps what
    /// it publishes (a replay's host time, a looped replay's numbering). The payload is copied
    /// only if the message is shared.
    pub fn header_mut(&mut self) -> (&mut u64, &mut crate::Timestamp) {
        match self {
            StreamMessage::Depth(a) | StreamMessage::Color(a) => {
                let frame = Arc::make_mut(a);
                (&mut frame.seq, &mut frame.stamp)
            }
            StreamMessage::Probe(a) => {
                let frame = Arc::make_mut(a);
                (&mut frame.seq, &mut frame.stamp)
            }
            StreamMessage::Markers(a) => {
                let frame = Arc::make_mut(a);
                (&mut frame.seq, &mut frame.stamp)
            }
            StreamMessage::Lamp(a) => {
                let frame = Arc::make_mut(a);
                (&mut frame.seq, &mut frame.stamp)
            }
        }
    }

    /// Same stream and same payload, whatever the sequence numbers and timestamps (a replay
    /// restamps host time; a looped one renumbers).
    pub fn payload_eq(&self, other: &StreamMessage) -> bool {
        match (self, other) {
            (StreamMessage::Depth(a), StreamMessage::Depth(b))
            | (StreamMessage::Color(a), StreamMessage::Color(b)) => a.payload == b.payload,
            (StreamMessage::Probe(a), StreamMessage::Probe(b)) => a.payload == b.payload,
            (StreamMessage::Markers(a), StreamMessage::Markers(b)) => a.payload == b.payload,
            (StreamMessage::Lamp(a), StreamMessage::Lamp(b)) => a.payload == b.payload,
            _ => false,
        }
    }
}
