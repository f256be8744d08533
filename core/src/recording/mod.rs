//! MCAP recordings of a rig's streams: [`RecordingWriter`] and [`RecordingReader`].
//!
//! A recording is an [MCAP](https://mcap.dev/spec) file that other labs can open without relight
//! (Foxglove, `mcap` CLI, the PyPI `mcap` + `mcap-ros2-support` packages;
//! `tests/helpers/mcap_check.py` is the reference check).
//!
//! # Layout
//!
//! ```text
//! magic, Header (library "relight-core <version>")
//! Metadata "relight.recording"   {source, format_version}
//! Metadata "relight.calibration" {toml}          (when the rig has a calibration)
//! Attachment "calibration.toml"  application/toml (same TOML, for tools that list attachments)
//! Chunk 0: the five Schema and Channel records only
//! Chunk 1..: messages, zstd, ~1 MiB uncompressed each (`RecordingOptions::chunk_size_bytes`),
//!            each followed by its MessageIndex records
//! DataEnd, summary (schemas, channels, statistics, chunk/metadata/attachment indexes), Footer
//! ```
//!
//! Metadata and calibration come before any message so that a file cut off mid-recording still
//! says which rig it came from. Channel IDs are fixed (depth 1, color 2, probe 3, markers 4,
//! lamp 5, see [`channel_id`]) so that the reader can still place messages when the chunk holding
//! the Channel records is lost.
//!
//! # Channels and encodings
//!
//! | topic      | schema (encoding)                        | message encoding |
//! |------------|------------------------------------------|------------------|
//! | `/depth`   | `sensor_msgs/msg/Image` (`ros2msg`)      | `cdr`            |
//! | `/color`   | `sensor_msgs/msg/Image` (`ros2msg`)      | `cdr`            |
//! | `/probe`   | `sensor_msgs/msg/Image` (`ros2msg`)      | `cdr`            |
//! | `/markers` | `relight.MarkerSet` (`jsonschema`)       | `json`           |
//! | `/lamp`    | `relight.LampState` (`jsonschema`)       | `json`           |
//!
//! Simulated recordings add ground-truth channels (`/truth/...`, IDs 16–19), described in
//! [`truth`]; [`RecordingReader::messages`] skips them and [`RecordingReader::truth`] reads them.
//!
//! Images use ROS 2 `sensor_msgs/msg/Image` (CDR, little endian) because every ROS-aware tool and
//! Foxglove's image panel decode it; the CDR is written by hand in [`schema`]. Image `encoding`
//! is [`PixelFormat::ros_encoding`](crate::PixelFormat::ros_encoding) (`16UC1`, `32FC1`, `rgb8`,
//! `mono8`, and the non-standard `rgba16f` for half-float RGBA), `is_bigendian` 0, `step` the
//! packed row size, `data` the little-endian pixels.
//!
//! The fields of a [`Frame`](crate::Frame) that `sensor_msgs/Image` lacks are stored so that the
//! round trip is exact:
//! - host timestamp → MCAP `log_time` (ns), so tools order and seek by arrival time;
//! - device timestamp → MCAP `publish_time` (ns, exact), and also the image `header.stamp`
//!   (seconds saturate at `i32::MAX`; the reader takes `publish_time`);
//! - `seq` → MCAP `sequence` when it fits in `u32`; otherwise `sequence` holds the low 32 bits
//!   and the full value is written in the payload (`seq=N` in the image `frame_id`, a `"seq"`
//!   member in JSON), which the reader prefers when present;
//! - probe exposure and gain → the image `frame_id`, which is `depth`, `color` or
//!   `probe?exposure_us=<u32>&gain_db=<f32>` (keys `&`-separated after `?`; floats written in
//!   Rust's shortest round-trip form). The part before `?` names the camera as in the calibration.
//!
//! Markers and lamp are JSON objects described by the JSON Schemas in [`schema`]: a
//! [`MarkerSet`](crate::MarkerSet) is `{"detections": [{"family", "marker_id", "corners_px":
//! [[x,y]×4], "camera_from_marker": {"rotation": [x,y,z,w], "translation": [x,y,z]},
//! "reprojection_rms_px"}]}`, a [`LampState`](crate::LampState) is `{"on", "position_in_world":
//! [x,y,z], "intensity": [r,g,b]}`. JSON has no NaN or infinity, so the writer refuses such
//! values with [`RecordingError::Encode`] rather than writing `null`.
//!
//! The calibration is the [`RigCalibration`] TOML, verbatim, in the `toml` key of the
//! `relight.calibration` metadata record (and in the `calibration.toml` attachment), so
//! `mcap get metadata --name relight.calibration` recovers it.
//!
//! # Reading other tools' bags
//!
//! A file without the `relight.recording` metadata is another tool's bag (rosbag2, a driver's
//! recorder). Its streams are found by topic through a [`TopicMap`]
//! ([`RecordingReader::with_topics`]); its images may also be `bgr8`, `rgba8` or `bgra8`
//! (read as `rgb8`); the device time comes from each image's `header.stamp`, and messages are
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
