//! [`RecordingWriter`]: streams [`StreamMessage`]s into a chunked, compressed MCAP file.

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::Path;

use mcap::records::{MessageHeader, Metadata};
use mcap::{Attachment, Compression, WriteOptions};

use super::schema::{self, FrameIdExtras};
use super::truth::{self, TruthKind, TruthMessage};
use super::{
    CALIBRATION_ATTACHMENT, CALIBRATION_KEY, CALIBRATION_METADATA, FORMAT_VERSION,
    RECORDING_METADATA, RecordingError, RecordingMeta, RecordingSummary, channel_id, topic,
};
use crate::frame::host_now_ns;
use crate::stream::{StreamKind, StreamMessage};

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
}

impl Default for RecordingOptions {
    fn default() -> Self {
        Self {
            chunk_size_bytes: WriteOptions::DEFAULT_CHUNK_SIZE,
            compression: RecordingCompression::Zstd,
            compression_level: 0,
            compression_threads: 0,
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
    /// Image `frame_id`, reused across messages.
    frame_id: String,
    counts: BTreeMap<StreamKind, u64>,
    messages_written: u64,
    /// Schema IDs by name, for channels declared after the start (ground truth).
    schema_ids: HashMap<&'static str, u16>,
    /// Ground-truth channels declared so far, and how many messages each got.
    truth_counts: BTreeMap<TruthKind, u64>,
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

impl<W: Write + Seek> RecordingWriter<W> {
    /// Start a recording in `writer` with default options.
    pub fn new(writer: W, meta: &RecordingMeta) -> Result<Self, RecordingError> {
        Self::with_options(writer, meta, &RecordingOptions::default())
    }

    /// Start a recording: writes header, metadata, calibration and the five channels.
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
            .compression(compression)
            .compression_level(options.compression_level)
            .compression_threads(options.compression_threads)
            .chunk_size(Some(options.chunk_size_bytes.max(1)))
            .library(format!("relight-core {}", env!("CARGO_PKG_VERSION")));
        let mut mcap = mcap::Writer::with_options(writer, write_options)?;

        mcap.write_metadata(&Metadata {
            name: RECORDING_METADATA.into(),
            metadata: BTreeMap::from([
                ("source".to_string(), meta.source.clone()),
                ("format_version".to_string(), FORMAT_VERSION.to_string()),
            ]),
        })?;
        if let Some(toml) = calibration_toml {
            mcap.write_metadata(&Metadata {
                name: CALIBRATION_METADATA.into(),
                metadata: BTreeMap::from([(CALIBRATION_KEY.to_string(), toml.clone())]),
            })?;
            let now_ns = host_now_ns();
            mcap.attach(&Attachment {
                log_time: now_ns,
                create_time: now_ns,
                name: CALIBRATION_ATTACHMENT.into(),
                media_type: "application/toml".into(),
                data: toml.into_bytes().into(),
            })?;
        }

        let mut schema_ids: HashMap<&'static str, u16> = HashMap::new();
        for kind in StreamKind::ALL {
            let schema = schema::channel_schema(kind);
            let schema_id = match schema_ids.get(schema.schema_name) {
                Some(&id) => id,
                None => {
                    let id = u16::try_from(schema_ids.len() + 1).unwrap_or(u16::MAX);
                    mcap.add_schema_with_id(
                        id,
                        schema.schema_name,
                        schema.schema_encoding,
                        schema.schema_data.as_bytes(),
                    )?;
                    schema_ids.insert(schema.schema_name, id);
                    id
                }
            };
            mcap.add_channel_with_id(
                channel_id(kind),
                schema_id,
                topic(kind),
                schema.message_encoding,
                &BTreeMap::new(),
            )?;
        }
        // Close the chunk holding schemas and channels so that it is complete on disk before
        // the first message arrives.
        mcap.flush()?;

        Ok(Self {
            mcap,
            scratch: Vec::new(),
            frame_id: String::new(),
            counts: BTreeMap::new(),
            messages_written: 0,
            schema_ids,
            truth_counts: BTreeMap::new(),
        })
    }

    /// Append one message. Host time becomes the MCAP log time; see the module docs for where
    /// every other field goes.
    pub fn write(&mut self, msg: &StreamMessage) -> Result<(), RecordingError> {
        let kind = msg.kind();
        let seq = msg.seq();
        let stamp = msg.stamp();
        let (sequence, long_seq) = schema::split_seq(seq);
        let encoded = match msg {
            StreamMessage::Depth(frame) | StreamMessage::Color(frame) => {
                let extras = FrameIdExtras {
                    seq: long_seq,
                    ..Default::default()
                };
                schema::write_frame_id(&mut self.frame_id, kind.name(), &extras);
                schema::encode_image(
                    &mut self.scratch,
                    stamp.device_ns,
                    &self.frame_id,
                    &frame.payload,
                )
            }
            StreamMessage::Probe(frame) => {
                let extras = FrameIdExtras {
                    seq: long_seq,
                    exposure_us: Some(frame.payload.exposure_us),
                    gain_db: Some(frame.payload.gain_db),
                };
                schema::write_frame_id(&mut self.frame_id, kind.name(), &extras);
                schema::encode_image(
                    &mut self.scratch,
                    stamp.device_ns,
                    &self.frame_id,
                    &frame.payload.image,
                )
            }
            StreamMessage::Markers(frame) => {
                schema::encode_markers(&mut self.scratch, long_seq, &frame.payload)
            }
            StreamMessage::Lamp(frame) => {
                schema::encode_lamp(&mut self.scratch, long_seq, &frame.payload)
            }
        };
        encoded.map_err(|reason| RecordingError::Encode {
            channel: topic(kind).into(),
            seq,
            reason,
        })?;

        let header = MessageHeader {
            channel_id: channel_id(kind),
            sequence,
            log_time: stamp.host_ns,
            publish_time: stamp.device_ns,
        };
        self.mcap.write_to_known_channel(&header, &self.scratch)?;
        *self.counts.entry(kind).or_insert(0) += 1;
        self.messages_written += 1;
        tracing::trace!(stream = %kind, seq, bytes = self.scratch.len(), "recorded");
        Ok(())
    }

    /// Append one ground-truth message (see [`super::truth`]); its channel is declared on first
    /// use.
    pub fn write_truth(&mut self, msg: &TruthMessage) -> Result<(), RecordingError> {
        let kind = msg.kind();
        let seq = msg.seq();
        let stamp = msg.stamp();
        let (sequence, long_seq) = schema::split_seq(seq);
        let encoded = match msg {
            TruthMessage::Image(_, frame) => {
                let extras = FrameIdExtras {
                    seq: long_seq,
                    ..Default::default()
                };
                schema::write_frame_id(&mut self.frame_id, "depth", &extras);
                match kind.pixel_format() {
                    Some(format) if format == frame.payload.format() => schema::encode_image(
                        &mut self.scratch,
                        stamp.device_ns,
                        &self.frame_id,
                        &frame.payload,
                    ),
                    _ => Err(format!(
                        "{:?} image on a channel of {:?}",
                        frame.payload.format(),
                        kind.pixel_format()
                    )),
                }
            }
            TruthMessage::State(frame) => truth::encode_state(&mut self.scratch, &frame.payload),
        };
        encoded.map_err(|reason| RecordingError::Encode {
            channel: kind.topic().into(),
            seq,
            reason,
        })?;
        if !self.truth_counts.contains_key(&kind) {
            self.declare_truth_channel(kind)?;
        }
        let header = MessageHeader {
            channel_id: kind.channel_id(),
            sequence,
            log_time: stamp.host_ns,
            publish_time: stamp.device_ns,
        };
        self.mcap.write_to_known_channel(&header, &self.scratch)?;
        *self.truth_counts.entry(kind).or_insert(0) += 1;
        self.messages_written += 1;
        Ok(())
    }

    fn declare_truth_channel(&mut self, kind: TruthKind) -> Result<(), RecordingError> {
        let (name, encoding, data, message_encoding) = match kind {
            TruthKind::State => (
                truth::TRUTH_STATE_SCHEMA_NAME,
                schema::JSON_SCHEMA_ENCODING,
                truth::TRUTH_STATE_JSON_SCHEMA,
                schema::JSON_MESSAGE_ENCODING,
            ),
            _ => {
                let image = schema::channel_schema(StreamKind::Depth);
                (
                    image.schema_name,
                    image.schema_encoding,
                    image.schema_data,
                    image.message_encoding,
                )
            }
        };
        let schema_id = match self.schema_ids.get(name) {
            Some(&id) => id,
            None => {
                let id = u16::try_from(self.schema_ids.len() + 1).unwrap_or(u16::MAX);
                self.mcap
                    .add_schema_with_id(id, name, encoding, data.as_bytes())?;
                self.schema_ids.insert(name, id);
                id
            }
        };
        self.mcap.add_channel_with_id(
            kind.channel_id(),
            schema_id,
            kind.topic(),
            message_encoding,
            &BTreeMap::new(),
        )?;
        Ok(())
    }

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
