//! The channels of a format-2 recording: fixed IDs, topics in ROS 2 naming (an image topic's
//! `camera_info`, `frame_info` and `compressed` siblings beside it), and their schemas.

use super::camera_info::{CAMERA_INFO_SCHEMA, CAMERA_INFO_SCHEMA_NAME};
use super::ros_msgs as msgs;
use super::schema::{
    CDR_MESSAGE_ENCODING, IMAGE_SCHEMA, IMAGE_SCHEMA_NAME, ROS2MSG_SCHEMA_ENCODING,
};
use super::truth::TruthKind;
use crate::stream::StreamKind;

/// The image streams, which have cameras.
pub const CAMERAS: [StreamKind; 3] = [StreamKind::Depth, StreamKind::Color, StreamKind::Probe];

/// Where `kind` is in [`CAMERAS`] (the probe for any other stream).
pub fn camera_index(kind: StreamKind) -> usize {
    match kind {
        StreamKind::Depth => 0,
        StreamKind::Color => 1,
        _ => 2,
    }
}

/// A channel relight writes. IDs are fixed so that messages stay readable when the chunk
/// holding the Channel records is lost.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Channel {
    /// A stream's own messages: the depth, colour or probe image, the markers, the lamp.
    Stream(StreamKind),
    /// The colour images as `CompressedImage`, when the recorder compresses them.
    ColorCompressed,
    /// A camera's intrinsics beside each of its images (one of [`CAMERAS`]).
    CameraInfo(StreamKind),
    /// A camera's per-image facts: sequence number, device time, exposure.
    FrameInfo(StreamKind),
    /// Marker poses (camera → marker) and the lamp (world → lamp) as they arrive.
    Tf,
    /// The fixed frames: `map` → `world`, and the rig calibration's camera poses.
    TfStatic,
    Truth(TruthKind),
    /// The relit composite the daemon rendered, raw or compressed like the colour.
    Composite,
    CompositeCompressed,
    /// Δ = L^ρ − L^μ, linear RGBA.
    Delta,
    /// The lighting estimate, as `lights.get` returns it, JSON in a `std_msgs/String`.
    Lighting,
}

/// A channel's schema.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChannelSchema {
    pub schema_name: &'static str,
    pub schema_data: &'static str,
}

impl ChannelSchema {
    pub const SCHEMA_ENCODING: &'static str = ROS2MSG_SCHEMA_ENCODING;
    pub const MESSAGE_ENCODING: &'static str = CDR_MESSAGE_ENCODING;
}

const IMAGE: ChannelSchema = ChannelSchema {
    schema_name: IMAGE_SCHEMA_NAME,
    schema_data: IMAGE_SCHEMA,
};
const COMPRESSED: ChannelSchema = ChannelSchema {
    schema_name: msgs::COMPRESSED_IMAGE_SCHEMA_NAME,
    schema_data: msgs::COMPRESSED_IMAGE_SCHEMA,
};
const STRING: ChannelSchema = ChannelSchema {
    schema_name: msgs::STRING_SCHEMA_NAME,
    schema_data: msgs::STRING_SCHEMA,
};
const TF: ChannelSchema = ChannelSchema {
    schema_name: msgs::TF_MESSAGE_SCHEMA_NAME,
    schema_data: msgs::TF_MESSAGE_SCHEMA,
};

impl Channel {
    pub const ALL: [Channel; 22] = [
        Channel::Stream(StreamKind::Depth),
        Channel::Stream(StreamKind::Color),
        Channel::Stream(StreamKind::Probe),
        Channel::Stream(StreamKind::Markers),
        Channel::Stream(StreamKind::Lamp),
        Channel::ColorCompressed,
        Channel::CameraInfo(StreamKind::Depth),
        Channel::CameraInfo(StreamKind::Color),
        Channel::CameraInfo(StreamKind::Probe),
        Channel::FrameInfo(StreamKind::Depth),
        Channel::FrameInfo(StreamKind::Color),
        Channel::FrameInfo(StreamKind::Probe),
        Channel::Tf,
        Channel::TfStatic,
        Channel::Truth(TruthKind::Depth),
        Channel::Truth(TruthKind::Normals),
        Channel::Truth(TruthKind::Albedo),
        Channel::Truth(TruthKind::State),
        Channel::Composite,
        Channel::CompositeCompressed,
        Channel::Delta,
        Channel::Lighting,
    ];

    /// The fixed MCAP channel ID.
    pub fn id(self) -> u16 {
        let camera = |kind| camera_index(kind) as u16;
        match self {
            Channel::Stream(kind) => super::channel_id(kind),
            Channel::ColorCompressed => 6,
            Channel::CameraInfo(kind) => 7 + camera(kind),
            Channel::FrameInfo(kind) => 10 + camera(kind),
            Channel::Tf => 13,
            Channel::TfStatic => 14,
            Channel::Truth(kind) => kind.channel_id(),
            Channel::Composite => 20,
            Channel::CompositeCompressed => 21,
            Channel::Delta => 22,
            Channel::Lighting => 23,
        }
    }

    pub fn topic(self) -> &'static str {
        match self {
            Channel::Stream(kind) => super::topic(kind),
            Channel::ColorCompressed => "/color/image_raw/compressed",
            Channel::CameraInfo(StreamKind::Depth) => "/depth/camera_info",
            Channel::CameraInfo(StreamKind::Color) => "/color/camera_info",
            Channel::CameraInfo(_) => "/probe/camera_info",
            Channel::FrameInfo(StreamKind::Depth) => "/depth/frame_info",
            Channel::FrameInfo(StreamKind::Color) => "/color/frame_info",
            Channel::FrameInfo(_) => "/probe/frame_info",
            Channel::Tf => "/tf",
            Channel::TfStatic => "/tf_static",
            Channel::Truth(kind) => kind.topic(),
            Channel::Composite => "/relight/composite",
            Channel::CompositeCompressed => "/relight/composite/compressed",
            Channel::Delta => "/relight/delta",
            Channel::Lighting => "/relight/lighting",
        }
    }

    pub fn of_topic(topic: &str) -> Option<Channel> {
        Self::ALL.into_iter().find(|c| c.topic() == topic)
    }

    pub fn schema(self) -> ChannelSchema {
        match self {
            Channel::Stream(StreamKind::Markers) => ChannelSchema {
                schema_name: msgs::MARKER_SET_SCHEMA_NAME,
                schema_data: msgs::MARKER_SET_SCHEMA,
            },
            Channel::Stream(StreamKind::Lamp) => ChannelSchema {
                schema_name: msgs::LAMP_STATE_SCHEMA_NAME,
                schema_data: msgs::LAMP_STATE_SCHEMA,
            },
            Channel::Stream(_) | Channel::Composite | Channel::Delta => IMAGE,
            Channel::Truth(TruthKind::State) | Channel::Lighting => STRING,
            Channel::Truth(_) => IMAGE,
            Channel::ColorCompressed | Channel::CompositeCompressed => COMPRESSED,
            Channel::CameraInfo(_) => ChannelSchema {
                schema_name: CAMERA_INFO_SCHEMA_NAME,
                schema_data: CAMERA_INFO_SCHEMA,
            },
            Channel::FrameInfo(_) => ChannelSchema {
                schema_name: msgs::FRAME_INFO_SCHEMA_NAME,
                schema_data: msgs::FRAME_INFO_SCHEMA,
            },
            Channel::Tf | Channel::TfStatic => TF,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use super::*;

    #[test]
    fn ids_and_topics_are_unique_and_round_trip() {
        let ids: HashSet<u16> = Channel::ALL.iter().map(|c| c.id()).collect();
        assert_eq!(ids.len(), Channel::ALL.len());
        for channel in Channel::ALL {
            assert_eq!(Channel::of_topic(channel.topic()), Some(channel));
        }
    }
}
