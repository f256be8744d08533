//! [`RecordingWriter`]: streams [`StreamMessage`]s into a chunked, compressed MCAP file.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fmt;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::Path;

use mcap::records::{MessageHeader, Metadata};
use mcap::{Attachment, Compression, WriteOptions};

use super::camera_info::encode_camera_info;
use super::channels::{CAMERAS, Channel, ChannelSchema, camera_index};
use super::compressed::{self, ColorEncoding};
use super::ros_msgs::{self as msgs, FrameInfo, Header, Transform};
use super::schema;
use super::truth::{self, TruthKind, TruthMessage};
use super::{
    CALIBRATION_ATTACHMENT, CALIBRATION_KEY, CALIBRATION_METADATA, FORMAT_VERSION, OutputMessage,
    RECORDING_METADATA, RecordingError, RecordingMeta, RecordingSummary,
};
use crate::camera::CameraModel;
use crate::frame::{Image, PixelFormat, host_now_ns};
use crate::pose::Pose;
use crate::rig::RigCalibration;
use crate::ros_frames;
use crate::stream::{StreamKind, StreamMessage};

/// The MCAP profile of a recording: ROS 2 (every channel `ros2msg` + `cdr`).
pub const PROFILE: &str = "ros2";

/// How chunks are compressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RecordingCompression {
    #[default]
    Zstd,
    Lz4,
    None,
}

/// Knobs of a [`RecordingWriter`].
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingOptions {
    /// Uncompressed bytes after which a chunk is closed. Smaller chunks lose less on corruption
    /// or a crash and seek finer; larger ones compress better.
    pub chunk_size_bytes: u64,
    pub compression: RecordingCompression,
    /// zstd level; 0 is zstd's default (3).
    pub compression_level: u32,
    /// zstd worker threads; 0 compresses on the writing thread.
    pub compression_threads: u32,
    /// How 8-bit colour images (and the composite) are stored; other formats are always raw.
    pub color_encoding: ColorEncoding,
}

impl Default for RecordingOptions {
    fn default() -> Self {
        Self {
            chunk_size_bytes: WriteOptions::DEFAULT_CHUNK_SIZE,
            compression: RecordingCompression::Zstd,
            compression_level: 0,
            compression_threads: 0,
            color_encoding: ColorEncoding::Raw,
        }
    }
}

/// Writes a recording in the layout described in [`crate::recording`].
///
/// Dropping the writer without [`finish`](Self::finish) still writes the summary (the `mcap`
/// writer finishes on drop), but errors are then lost; call `finish`.
pub struct RecordingWriter<W: Write + Seek> {
    mcap: mcap::Writer<W>,
    /// Encoded message payload, reused across messages.
    scratch: Vec<u8>,
    counts: BTreeMap<StreamKind, u64>,
    messages_written: u64,
    /// Schema IDs by name.
    schema_ids: HashMap<&'static str, u16>,
    declared: BTreeSet<Channel>,
    /// The depth, colour and probe cameras of the calibration, for their `camera_info`.
    cameras: [Option<CameraModel>; 3],
    /// `/tf_static`, written once, just before the first message (with its host time).
    static_transforms: Option<Vec<Transform>>,
    color_encoding: ColorEncoding,
}

impl<W: Write + Seek> fmt::Debug for RecordingWriter<W> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RecordingWriter")
            .field("counts", &self.counts)
            .field("messages_written", &self.messages_written)
            .finish_non_exhaustive()
    }
}

impl RecordingWriter<BufWriter<File>> {
    /// Create (or truncate) the file at `path` and start a recording with default options.
    pub fn create(path: &Path, meta: &RecordingMeta) -> Result<Self, RecordingError> {
        Self::create_with_options(path, meta, &RecordingOptions::default())
    }

    pub fn create_with_options(
        path: &Path,
        meta: &RecordingMeta,
        options: &RecordingOptions,
    ) -> Result<Self, RecordingError> {
        let file = File::create(path).map_err(|source| RecordingError::Io {
            path: path.to_owned(),
            source,
        })?;
        let writer = Self::with_options(BufWriter::with_capacity(1 << 20, file), meta, options)?;
        tracing::info!(path = %path.display(), "recording started");
        Ok(writer)
    }
}

/// The camera a stream's images come from, as `frame_id`: `depth`, `color`, `probe`.
fn camera_frame(kind: StreamKind) -> &'static str {
    kind.name()
}

/// The fixed transforms: the +z-up `map` over the board's `world`, and what the calibration
/// says of the rig, cameras as optical frames.
fn static_transforms(calibration: Option<&RigCalibration>) -> Vec<Transform> {
    let transform = |parent: &str, child: &str, parent_from_child: Pose| Transform {
        parent: parent.into(),
        child: child.into(),
        parent_from_child,
    };
    let mut transforms = vec![transform(
        ros_frames::MAP,
        ros_frames::WORLD,
        ros_frames::map_from_world(),
    )];
    if let Some(rig) = calibration {
        transforms.push(transform(
            ros_frames::WORLD,
            ros_frames::BOARD,
            rig.world_from_board,
        ));
        if rig.probe.is_some() {
            transforms.push(transform(
                ros_frames::WORLD,
                camera_frame(StreamKind::Probe),
                ros_frames::world_from_optical(rig.world_from_probe),
            ));
        }
        transforms.push(transform(
            camera_frame(StreamKind::Color),
            camera_frame(StreamKind::Depth),
            ros_frames::optical_between(rig.color_from_depth),
        ));
    }
    transforms
}

/// MCAP's 32-bit `sequence` of a message whose payload carries no full `seq`.
fn short_seq(channel: Channel, seq: u64) -> Result<u32, RecordingError> {
    u32::try_from(seq).map_err(|_| {
        encode_error(channel, seq)(
            "its sequence number does not fit the 32 bits MCAP and this channel hold".into(),
        )
    })
}

/// MCAP's `sequence` of a message that carries its full `seq` itself: the low 32 bits, which
/// pair an image with its `frame_info`.
fn low_sequence(seq: u64) -> u32 {
    (seq & u64::from(u32::MAX)) as u32
}

/// The error of message `seq` on `channel` that cannot be encoded for `reason`.
fn encode_error(channel: Channel, seq: u64) -> impl FnOnce(String) -> RecordingError {
    move |reason| RecordingError::Encode {
        channel: channel.topic().into(),
        seq,
        reason,
    }
}

impl<W: Write + Seek> RecordingWriter<W> {
    /// Start a recording in `writer` with default options.
    pub fn new(writer: W, meta: &RecordingMeta) -> Result<Self, RecordingError> {
        Self::with_options(writer, meta, &RecordingOptions::default())
    }

    /// Start a recording: writes header, metadata, calibration and the sensor channels.
    pub fn with_options(
        writer: W,
        meta: &RecordingMeta,
        options: &RecordingOptions,
    ) -> Result<Self, RecordingError> {
        let calibration_toml = meta
            .calibration
            .as_ref()
            .map(|calibration| calibration.to_toml())
            .transpose()?;
        let compression = match options.compression {
            RecordingCompression::Zstd => Some(Compression::Zstd),
            RecordingCompression::Lz4 => Some(Compression::Lz4),
            RecordingCompression::None => None,
        };
        let write_options = WriteOptions::new()
            .profile(PROFILE)
            .compression(compression)
            .compression_level(options.compression_level)
            .compression_threads(options.compression_threads)
            .chunk_size(Some(options.chunk_size_bytes.max(1)))
            .library(format!("relight-core {}", env!("CARGO_PKG_VERSION")));
        let mcap = mcap::Writer::with_options(writer, write_options)?;
        let cameras = CAMERAS.map(|kind| {
            let rig = meta.calibration.as_ref()?;
            match kind {
                StreamKind::Depth => rig.depth,
                StreamKind::Color => rig.color,
                _ => rig.probe,
            }
        });
        let mut writer = Self {
            mcap,
            scratch: Vec::new(),
            counts: BTreeMap::new(),
            messages_written: 0,
            schema_ids: HashMap::new(),
            declared: BTreeSet::new(),
            cameras,
            static_transforms: Some(static_transforms(meta.calibration.as_ref())),
            color_encoding: options.color_encoding,
        };

        writer.mcap.write_metadata(&Metadata {
            name: RECORDING_METADATA.into(),
            metadata: BTreeMap::from([
                ("source".to_string(), meta.source.clone()),
                ("format_version".to_string(), FORMAT_VERSION.to_string()),
            ]),
        })?;
        if let Some(toml) = calibration_toml {
            writer.mcap.write_metadata(&Metadata {
                name: CALIBRATION_METADATA.into(),
                metadata: BTreeMap::from([(CALIBRATION_KEY.to_string(), toml.clone())]),
            })?;
            let now_ns = host_now_ns();
            writer.mcap.attach(&Attachment {
                log_time: now_ns,
                create_time: now_ns,
                name: CALIBRATION_ATTACHMENT.into(),
                media_type: "application/toml".into(),
                data: toml.into_bytes().into(),
            })?;
        }

        // The sensors' channels up front, so that a file cut before their first message still
        // lists them; the rest are declared on first use.
        let colour = match options.color_encoding {
            ColorEncoding::Raw => Channel::Stream(StreamKind::Color),
            _ => Channel::ColorCompressed,
        };
        for channel in StreamKind::ALL
            .map(|kind| match kind {
                StreamKind::Color => colour,
                _ => Channel::Stream(kind),
            })
            .into_iter()
            .chain([Channel::Tf, Channel::TfStatic])
            .chain(CAMERAS.map(Channel::FrameInfo))
        {
            writer.declare(channel)?;
        }
        for (kind, camera) in CAMERAS.into_iter().zip(writer.cameras) {
            if camera.is_some() {
                writer.declare(Channel::CameraInfo(kind))?;
            }
        }
        // Close the chunk holding schemas and channels so that it is complete on disk before
        // the first message arrives.
        writer.mcap.flush()?;
        Ok(writer)
    }

    fn declare(&mut self, channel: Channel) -> Result<(), RecordingError> {
        if self.declared.contains(&channel) {
            return Ok(());
        }
        let schema = channel.schema();
        let schema_id = match self.schema_ids.get(schema.schema_name) {
            Some(&id) => id,
            None => {
                let id = u16::try_from(self.schema_ids.len() + 1).unwrap_or(u16::MAX);
                self.mcap.add_schema_with_id(
                    id,
                    schema.schema_name,
                    ChannelSchema::SCHEMA_ENCODING,
                    schema.schema_data.as_bytes(),
                )?;
                self.schema_ids.insert(schema.schema_name, id);
                id
            }
        };
        self.mcap.add_channel_with_id(
            channel.id(),
            schema_id,
            channel.topic(),
            ChannelSchema::MESSAGE_ENCODING,
            &BTreeMap::new(),
        )?;
        self.declared.insert(channel);
        Ok(())
    }

    /// Write what `scratch` holds on `channel`.
    fn emit(
        &mut self,
        channel: Channel,
        sequence: u32,
        host_ns: u64,
        device_ns: u64,
    ) -> Result<(), RecordingError> {
        self.declare(channel)?;
        let header = MessageHeader {
            channel_id: channel.id(),
            sequence,
            log_time: host_ns,
            publish_time: device_ns,
        };
        self.mcap.write_to_known_channel(&header, &self.scratch)?;
        Ok(())
    }

    fn write_static_transforms(&mut self, host_ns: u64) -> Result<(), RecordingError> {
        let Some(transforms) = self.static_transforms.take() else {
            return Ok(());
        };
        msgs::encode_tf(&mut self.scratch, host_ns, &transforms)
            .map_err(encode_error(Channel::TfStatic, 0))?;
        self.emit(Channel::TfStatic, 0, host_ns, host_ns)
    }

    /// Append one stream message, with what goes beside it: an image's `frame_info` and
    /// `camera_info`, the markers' and lamp's `/tf`. See the module docs for where each field
    /// goes.
    pub fn write(&mut self, msg: &StreamMessage) -> Result<(), RecordingError> {
        let kind = msg.kind();
        let seq = msg.seq();
        let stamp = msg.stamp();
        self.write_static_transforms(stamp.host_ns)?;
        let sequence = low_sequence(seq);
        let header = Header {
            stamp_ns: stamp.host_ns,
            frame_id: camera_frame(kind),
        };
        match msg {
            StreamMessage::Depth(frame) | StreamMessage::Color(frame) => {
                self.write_image(kind, header, seq, stamp.device_ns, &frame.payload, (0, 0.0))?;
            }
            StreamMessage::Probe(frame) => {
                let probe = &frame.payload;
                let exposure = (probe.exposure_us, probe.gain_db);
                self.write_image(kind, header, seq, stamp.device_ns, &probe.image, exposure)?;
            }
            StreamMessage::Markers(frame) => {
                let channel = Channel::Stream(kind);
                let header = Header {
                    frame_id: camera_frame(StreamKind::Color),
                    ..header
                };
                msgs::encode_markers(
                    &mut self.scratch,
                    header,
                    seq,
                    stamp.device_ns,
                    &frame.payload,
                )
                .map_err(encode_error(channel, seq))?;
                self.emit(channel, sequence, stamp.host_ns, stamp.device_ns)?;
                if !frame.payload.detections.is_empty() {
                    let transforms: Vec<Transform> = frame
                        .payload
                        .detections
                        .iter()
                        .map(|d| Transform {
                            parent: header.frame_id.into(),
                            child: ros_frames::marker(d.marker_id),
                            parent_from_child: ros_frames::optical_from(d.camera_from_marker),
                        })
                        .collect();
                    msgs::encode_tf(&mut self.scratch, stamp.host_ns, &transforms)
                        .map_err(encode_error(Channel::Tf, seq))?;
                    self.emit(Channel::Tf, sequence, stamp.host_ns, stamp.device_ns)?;
                }
            }
            StreamMessage::Lamp(frame) => {
                let channel = Channel::Stream(kind);
                let lamp = &frame.payload;
                let header = Header {
                    frame_id: ros_frames::WORLD,
                    ..header
                };
                msgs::encode_lamp(&mut self.scratch, header, seq, stamp.device_ns, lamp)
                    .map_err(encode_error(channel, seq))?;
                self.emit(channel, sequence, stamp.host_ns, stamp.device_ns)?;
                let transform = Transform {
                    parent: ros_frames::WORLD.into(),
                    child: ros_frames::LAMP.into(),
                    parent_from_child: Pose::from_translation(lamp.position_in_world),
                };
                msgs::encode_tf(&mut self.scratch, stamp.host_ns, &[transform])
                    .map_err(encode_error(Channel::Tf, seq))?;
                self.emit(Channel::Tf, sequence, stamp.host_ns, stamp.device_ns)?;
            }
        }
        *self.counts.entry(kind).or_insert(0) += 1;
        self.messages_written += 1;
        tracing::trace!(stream = %kind, seq, "recorded");
        Ok(())
    }

    /// An image with its `frame_info` (first, so a reader has it when the image arrives) and
    /// its camera's `camera_info`; 8-bit colour compressed as the options say.
    fn write_image(
        &mut self,
        kind: StreamKind,
        header: Header<'_>,
        seq: u64,
        device_ns: u64,
        image: &Image,
        (exposure_us, gain_db): (u32, f32),
    ) -> Result<(), RecordingError> {
        let sequence = low_sequence(seq);
        let host_ns = header.stamp_ns;
        let info = FrameInfo {
            seq,
            device_stamp_ns: device_ns,
            exposure_us,
            gain_db,
        };
        let channel = Channel::FrameInfo(kind);
        msgs::encode_frame_info(&mut self.scratch, header, &info)
            .map_err(encode_error(channel, seq))?;
        self.emit(channel, sequence, host_ns, device_ns)?;

        if let Some(camera) = self.cameras.get(camera_index(kind)).copied().flatten() {
            let channel = Channel::CameraInfo(kind);
            encode_camera_info(&mut self.scratch, host_ns, header.frame_id, &camera)
                .map_err(encode_error(channel, seq))?;
            self.emit(channel, sequence, host_ns, device_ns)?;
        }

        let encoding = if kind == StreamKind::Color {
            self.color_encoding
        } else {
            ColorEncoding::Raw
        };
        let channel = self
            .encode_picture(
                header,
                image,
                encoding,
                Channel::Stream(kind),
                Channel::ColorCompressed,
            )
            .map_err(encode_error(Channel::Stream(kind), seq))?;
        self.emit(channel, sequence, host_ns, device_ns)
    }

    /// Encode `image` into `scratch`: compressed on `compressed` when `encoding` asks and the
    /// image is 8-bit, else raw on `raw`. Returns the channel it is for.
    fn encode_picture(
        &mut self,
        header: Header<'_>,
        image: &Image,
        encoding: ColorEncoding,
        raw: Channel,
        compressed: Channel,
    ) -> Result<Channel, String> {
        let eight_bit = matches!(image.format(), PixelFormat::Rgb8 | PixelFormat::Mono8);
        match eight_bit
            .then(|| compressed::compress(image, encoding))
            .flatten()
        {
            Some(encoded) => {
                let (format, data) = encoded.map_err(|e| e.to_string())?;
                msgs::encode_compressed_image(&mut self.scratch, header, format, &data)?;
                Ok(compressed)
            }
            None => {
                schema::encode_image(&mut self.scratch, header.stamp_ns, header.frame_id, image)?;
                Ok(raw)
            }
        }
    }

    /// Append one ground-truth message (see [`super::truth`]); its channel is declared on first
    /// use. Its `seq` must fit MCAP's 32-bit `sequence`.
    pub fn write_truth(&mut self, msg: &TruthMessage) -> Result<(), RecordingError> {
        let kind = msg.kind();
        let channel = Channel::Truth(kind);
        let seq = msg.seq();
        let stamp = msg.stamp();
        self.write_static_transforms(stamp.host_ns)?;
        let sequence = short_seq(channel, seq)?;
        let encoded = match msg {
            TruthMessage::Image(_, frame) => {
                let frame_id = match kind {
                    TruthKind::Normals => ros_frames::WORLD,
                    _ => camera_frame(StreamKind::Depth),
                };
                match kind.pixel_format() {
                    Some(format) if format == frame.payload.format() => schema::encode_image(
                        &mut self.scratch,
                        stamp.host_ns,
                        frame_id,
                        &frame.payload,
                    ),
                    _ => Err(format!(
                        "{:?} image on a channel of {:?}",
                        frame.payload.format(),
                        kind.pixel_format()
                    )),
                }
            }
            TruthMessage::State(frame) => truth::encode_state(&frame.payload)
                .and_then(|json| msgs::encode_string(&mut self.scratch, &json)),
        };
        encoded.map_err(encode_error(channel, seq))?;
        self.emit(channel, sequence, stamp.host_ns, stamp.device_ns)?;
        self.messages_written += 1;
        Ok(())
    }

    /// Append what the daemon rendered for a frame set; its `seq` must fit MCAP's 32-bit
    /// `sequence`. The composite is compressed like the colour images.
    pub fn write_output(&mut self, msg: &OutputMessage) -> Result<(), RecordingError> {
        let channel = msg.channel();
        let (seq, stamp) = (msg.seq(), msg.stamp());
        self.write_static_transforms(stamp.host_ns)?;
        let sequence = short_seq(channel, seq)?;
        let header = Header {
            stamp_ns: stamp.host_ns,
            frame_id: camera_frame(StreamKind::Color),
        };
        let written = match msg {
            OutputMessage::Composite(frame) => self.encode_picture(
                header,
                &frame.payload,
                self.color_encoding,
                Channel::Composite,
                Channel::CompositeCompressed,
            ),
            OutputMessage::Delta(frame) => schema::encode_image(
                &mut self.scratch,
                header.stamp_ns,
                header.frame_id,
                &frame.payload,
            )
            .map(|()| Channel::Delta),
            OutputMessage::Lighting(frame) => {
                msgs::encode_string(&mut self.scratch, &frame.payload).map(|()| Channel::Lighting)
            }
        };
        let written = written.map_err(encode_error(channel, seq))?;
        self.emit(written, sequence, stamp.host_ns, stamp.device_ns)?;
        self.messages_written += 1;
        Ok(())
    }

    /// Stream, truth and output messages written (the `frame_info`, `camera_info` and `/tf`
    /// beside them are not counted).
    pub fn messages_written(&self) -> u64 {
        self.messages_written
    }

    /// Close the last chunk and write the summary section and footer, then flush.
    pub fn finish(self) -> Result<RecordingSummary, RecordingError> {
        self.finish_into_inner().map(|(summary, _)| summary)
    }

    /// Like [`finish`](Self::finish), and hand back the underlying writer (e.g. the
    /// `Cursor<Vec<u8>>` of an in-memory recording).
    pub fn finish_into_inner(mut self) -> Result<(RecordingSummary, W), RecordingError> {
        let summary = self.mcap.finish()?;
        let mut inner = self.mcap.into_inner();
        inner.flush().map_err(RecordingError::Flush)?;
        let stats = summary.stats.unwrap_or_default();
        let any = stats.message_count > 0;
        let result = RecordingSummary {
            messages: self.counts,
            start_ns: any.then_some(stats.message_start_time),
            end_ns: any.then_some(stats.message_end_time),
            chunks: stats.chunk_count,
        };
        tracing::info!(
            messages = result.total_messages(),
            chunks = result.chunks,
            "recording finished"
        );
        Ok((result, inner))
    }
}
