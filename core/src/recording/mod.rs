//! MCAP recordings of a rig's streams: [`RecordingWriter`] and [`RecordingReader`].
//!
//! A recording is an [MCAP](https://mcap.dev/spec) file that other labs can open without relight
//! (Foxglove, `mcap` CLI, the PyPI `mcap` + `mcap-ros2-support` packages;
//! `tests/helpers/mcap_check.py` is the reference check).
//!
//! # Layout (format 2)
//!
//! ```text
//! magic, Header (profile "ros2", library "relight-core <version>")
//! Metadata "relight.recording"   {source, format_version = "2"}
//! Metadata "relight.calibration" {toml}          (when the rig has a calibration)
//! Attachment "calibration.toml"  application/toml (same TOML, for tools that list attachments)
//! Chunk 0: the sensors' Schema and Channel records only
//! Chunk 1..: messages, zstd, ~1 MiB uncompressed each (`RecordingOptions::chunk_size_bytes`),
//!            each followed by its MessageIndex records
//! DataEnd, summary (schemas, channels, statistics, chunk/metadata/attachment indexes), Footer
//! ```
//!
//! Metadata and calibration come before any message so that a file cut off mid-recording still
//! says which rig it came from. Channel IDs are fixed ([`Channel::id`]) so that the reader can
//! still place messages when the chunk holding the Channel records is lost.
//!
//! # Channels (ROS 2 conventions)
//!
//! Every channel is a ROS 2 message in CDR (MCAP's `ros2` profile: schema encoding `ros2msg`,
//! the concatenated `.msg` text, message encoding `cdr`), written by hand ([`schema`],
//! [`ros_msgs`], [`camera_info`]), so Foxglove and every ROS 2 tool decode them:
//!
//! | id | topic | type | per |
//! |----|-------|------|-----|
//! | 1, 2, 3 | `/depth/image_raw`, `/color/image_raw`, `/probe/image_raw` | `sensor_msgs/msg/Image` | image |
//! | 6 | `/color/image_raw/compressed` | `sensor_msgs/msg/CompressedImage` (`png`, `jpeg`) | colour image, when [`RecordingOptions::color_encoding`] asks |
//! | 7, 8, 9 | `/depth/camera_info`, `/color/camera_info`, `/probe/camera_info` | `sensor_msgs/msg/CameraInfo` | image, when the calibration has the camera |
//! | 10, 11, 12 | `/depth/frame_info`, … | `relight_msgs/msg/FrameInfo` | image, written just before it |
//! | 4 | `/markers` | `relight_msgs/msg/MarkerSet` | marker set |
//! | 5 | `/lamp` | `relight_msgs/msg/LampState` | lamp report |
//! | 13 | `/tf` | `tf2_msgs/msg/TFMessage` | marker set with detections (`color` → `marker_<id>`), lamp report (`world` → `lamp`) |
//! | 14 | `/tf_static` | `tf2_msgs/msg/TFMessage` | once, before the first message |
//! | 16–19 | `/truth/...` | see [`truth`] | simulated frame |
//! | 20, 21 | `/relight/composite`, `/relight/composite/compressed` | `Image` rgb8 / `CompressedImage` | rendered frame ([`OutputMessage`]) |
//! | 22 | `/relight/delta` | `Image` `32FC4` | rendered frame |
//! | 23 | `/relight/lighting` | `std_msgs/msg/String`, JSON as `lights.get` returns it | changed estimate |
//!
//! Where each field of a [`Frame`](crate::Frame) goes, so that the round trip is exact:
//! - host timestamp → every `header.stamp` (seconds saturate at `i32::MAX`) and MCAP
//!   `log_time`, so tools order, seek and sync by arrival time;
//! - device timestamp → `device_stamp_ns` (FrameInfo, MarkerSet, LampState) and MCAP
//!   `publish_time`, which the reader uses when an image's FrameInfo is lost;
//! - `seq` → `seq` in the same messages, and its low 32 bits in MCAP `sequence` (which pairs an
//!   image with its FrameInfo);
//! - probe exposure and gain → FrameInfo's `exposure_us` and `gain_db` (0 for the other
//!   cameras); a probe image whose FrameInfo is lost does not decode (its exposure is unknown);
//! - the camera → `header.frame_id`, one per sensor: `depth`, `color`, `probe`, as the
//!   calibration names them; markers carry `color`, the lamp `world`.
//!
//! Image `encoding` is [`PixelFormat::ros_encoding`](crate::PixelFormat::ros_encoding)
//! (`16UC1`, `32FC1`, `rgb8`, `mono8`) except half-float RGBA, which goes out widened to
//! `32FC4` ([`schema::RGBA16F_WIRE_ENCODING`]); `is_bigendian` 0, `step` the packed row.
//! A compressed image ([`compressed`]) decodes to `rgb8` or `mono8`; only 8-bit colour is
//! compressed, other formats stay raw on `/color/image_raw`.
//!
//! Poses are relight's glTF convention inside and the ROS optical convention (+z forward, +y
//! down) in the file, converted by [`crate::ros_frames`] bit-exactly both ways: MarkerSet's
//! `camera_from_marker` and `/tf`'s camera-to-marker transforms are in the colour camera's
//! optical frame; `/tf_static` holds `map` → `world` (+z up over the board's +y-up world),
//! `world` → `board`, `world` → `probe` (optical) and `color` → `depth` (optical). A MarkerSet,
//! LampState or `/tf` with a non-finite number is refused with [`RecordingError::Encode`].
//!
//! The calibration is the [`RigCalibration`] TOML, verbatim, in the `toml` key of the
//! `relight.calibration` metadata record (and in the `calibration.toml` attachment), so
//! `mcap get metadata --name relight.calibration` recovers it.
//!
//! Format 1 (relight before these conventions, [`v1`]) still reads; `relightd recording repair`
//! rewrites such a file in format 2.
//!
//! # Reading other tools' bags
//!
//! A file without the `relight.recording` metadata is another tool's bag (rosbag2, a driver's
//! recorder). Its streams are found by topic through a [`TopicMap`]
//! ([`RecordingReader::with_topics`]); its images may also be `bgr8`, `rgba8` or `bgra8`
//! (read as `rgb8`), or PNG/JPEG `CompressedImage` on the image topic's `…/compressed` sibling,
//! read only when the raw topic is not in the bag (drivers often record both); the device time
//! comes from each image's `header.stamp`, and messages are
//! numbered per channel in log-time order, since such bags leave MCAP's `sequence` at 0. Its
//! cameras come from the `sensor_msgs/msg/CameraInfo` topics beside the images
//! ([`camera_info`], [`RecordingReader::calibration_from_camera_info`]).
//!
//! # Reading damaged files
//!
//! [`RecordingReader`] reads the file with positioned reads as it needs it (no memory map, and
//! never the whole file at once: a chunk at a time) and walks its records linearly from the
//! start; it never needs the summary section. Each chunk is
//! decompressed and CRC-checked on its own, so a corrupt chunk costs its own messages and one
//! [`RecordingError::CorruptChunk`], and a file cut off mid-write yields every message of every
//! complete chunk plus a warning saying where it was cut.

pub mod camera_info;
mod channels;
pub mod compressed;
mod reader;
pub mod ros_msgs;
pub mod salvage;
pub mod schema;
mod source;
pub mod truth;
pub mod v1;
mod writer;

use std::collections::BTreeMap;
use std::path::PathBuf;

pub use channels::{CAMERAS, Channel, ChannelSchema};
pub use compressed::ColorEncoding;
pub use reader::{CameraInfoMessage, ChunkInfo, Messages, Recorded, RecordingReader};
pub use writer::{RecordingCompression, RecordingOptions, RecordingWriter};

use crate::rig::{RigCalibration, RigCalibrationError};
use crate::stream::StreamKind;

/// Version of the layout described in the module docs, stored in `relight.recording`
/// ([`v1`] describes the previous one, which still reads).
pub const FORMAT_VERSION: &str = "2";

/// The most bytes of pixels a compressed image may decode to (a lying header cannot make the
/// reader allocate more).
pub const MAX_IMAGE_BYTES: usize = source::MAX_READ_BYTES;

/// Name of the metadata record holding [`RecordingMeta::source`] and [`FORMAT_VERSION`].
pub const RECORDING_METADATA: &str = "relight.recording";
/// Name of the metadata record holding the calibration TOML under the key [`CALIBRATION_KEY`].
pub const CALIBRATION_METADATA: &str = "relight.calibration";
/// Key of the calibration TOML inside [`CALIBRATION_METADATA`].
pub const CALIBRATION_KEY: &str = "toml";
/// Name of the attachment holding the calibration TOML.
pub const CALIBRATION_ATTACHMENT: &str = "calibration.toml";

/// The MCAP topic of a stream: `/depth/image_raw`, `/color/image_raw`, `/probe/image_raw`,
/// `/markers`, `/lamp` ([`v1::topic`] for format 1).
pub fn topic(kind: StreamKind) -> &'static str {
    match kind {
        StreamKind::Depth => "/depth/image_raw",
        StreamKind::Color => "/color/image_raw",
        StreamKind::Probe => "/probe/image_raw",
        StreamKind::Markers => "/markers",
        StreamKind::Lamp => "/lamp",
    }
}

/// Which topic each stream is read from: relight's own ([`topic`], or [`v1::topic`] in a
/// format-1 recording) unless remapped, as for a bag another rig recorded
/// (`[replay] topics = { color = "/camera/color/image_raw" }`). A remapped stream is read only
/// from its new topic. An image stream is also read from its `…/compressed` sibling
/// (image_transport's name for `sensor_msgs/msg/CompressedImage`).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct TopicMap {
    remapped: BTreeMap<StreamKind, String>,
    format_1: bool,
}

impl TopicMap {
    pub fn new(remapped: BTreeMap<StreamKind, String>) -> Self {
        Self {
            remapped,
            format_1: false,
        }
    }

    /// The same remapping, over format 1's topics.
    pub(crate) fn in_format_1(self, format_1: bool) -> Self {
        Self { format_1, ..self }
    }

    /// The topic `kind` is read from.
    pub fn topic(&self, kind: StreamKind) -> &str {
        let own = if self.format_1 {
            v1::topic(kind)
        } else {
            topic(kind)
        };
        self.remapped.get(&kind).map_or(own, String::as_str)
    }

    /// The stream read from `topic` (its own or its compressed sibling), if any.
    pub fn stream_of(&self, topic: &str) -> Option<StreamKind> {
        StreamKind::ALL.into_iter().find(|&kind| {
            let own = self.topic(kind);
            own == topic
                || (CAMERAS.contains(&kind) && topic.strip_suffix("/compressed") == Some(own))
        })
    }

    /// The streams whose topic is not relight's own.
    pub fn remapped(&self) -> &BTreeMap<StreamKind, String> {
        &self.remapped
    }
}

/// The fixed MCAP channel ID of a stream (1 to 5, in [`StreamKind::ALL`] order).
pub fn channel_id(kind: StreamKind) -> u16 {
    match kind {
        StreamKind::Depth => 1,
        StreamKind::Color => 2,
        StreamKind::Probe => 3,
        StreamKind::Markers => 4,
        StreamKind::Lamp => 5,
    }
}

/// What the daemon made of a frame set, recorded beside the streams when the recorder is asked
/// to (`[recorder] outputs = true`); `seq` and stamp are the frame set's.
#[derive(Debug, Clone, PartialEq)]
pub enum OutputMessage {
    /// The relit composite, 8-bit RGB.
    Composite(crate::Frame<crate::Image>),
    /// Δ = L^ρ − L^μ, `Rgba16F`.
    Delta(crate::Frame<crate::Image>),
    /// The lighting estimate as `lights.get` returns it, JSON text.
    Lighting(crate::Frame<String>),
}

impl OutputMessage {
    pub fn channel(&self) -> Channel {
        match self {
            OutputMessage::Composite(_) => Channel::Composite,
            OutputMessage::Delta(_) => Channel::Delta,
            OutputMessage::Lighting(_) => Channel::Lighting,
        }
    }

    /// The frame set's number.
    pub fn seq(&self) -> u64 {
        match self {
            OutputMessage::Composite(f) | OutputMessage::Delta(f) => f.seq,
            OutputMessage::Lighting(f) => f.seq,
        }
    }

    /// The frame set's stamp.
    pub fn stamp(&self) -> crate::Timestamp {
        match self {
            OutputMessage::Composite(f) | OutputMessage::Delta(f) => f.stamp,
            OutputMessage::Lighting(f) => f.stamp,
        }
    }
}

/// What a recording says about itself besides its messages.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RecordingMeta {
    /// The rig's calibration, if it had one when recording.
    pub calibration: Option<RigCalibration>,
    /// What wrote the recording, e.g. `relightd 0.1.0`.
    pub source: String,
}

/// Counts and time span of a finished recording.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RecordingSummary {
    /// Messages written per stream (streams without messages are absent).
    pub messages: BTreeMap<StreamKind, u64>,
    /// Earliest host timestamp (MCAP log time) of any message, ns; `None` when empty.
    pub start_ns: Option<u64>,
    /// Latest host timestamp (MCAP log time) of any message, ns; `None` when empty.
    pub end_ns: Option<u64>,
    /// Chunk records in the file, including the one holding schemas and channels.
    pub chunks: u32,
}

impl RecordingSummary {
    /// Messages over all streams.
    pub fn total_messages(&self) -> u64 {
        self.messages.values().sum()
    }
}

/// Everything that can go wrong writing or reading a recording.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("recording {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("flushing recording: {0}")]
    Flush(#[source] std::io::Error),
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error("not a readable MCAP recording: {reason}")]
    NotMcap { reason: String },
    #[error("chunk {index} at byte {offset} is corrupt: {reason}")]
    CorruptChunk {
        index: usize,
        offset: u64,
        reason: String,
    },
    #[error("record at byte {offset} (opcode {opcode:#04x}) is corrupt: {reason}")]
    CorruptRecord {
        offset: u64,
        opcode: u8,
        reason: String,
    },
    #[error("message seq {seq} on {channel} cannot be decoded: {reason}")]
    Decode {
        channel: String,
        seq: u64,
        reason: String,
    },
    #[error("message seq {seq} on {channel} cannot be encoded: {reason}")]
    Encode {
        channel: String,
        seq: u64,
        reason: String,
    },
    #[error("calibration: {0}")]
    Calibration(#[from] RigCalibrationError),
}
