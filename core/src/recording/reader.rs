//! [`RecordingReader`]: reads recordings back, including damaged ones.
//!
//! Records are framed by hand (opcode, u64 length, body) so that a cut or a bad length stops the
//! walk instead of failing it; record bodies are parsed with [`mcap::parse_record`] and chunks
//! are decompressed and CRC-checked one at a time with [`mcap::sans_io::LinearReader`], so a bad
//! chunk is one error and the next chunk reads normally.

use std::borrow::Cow;
use std::cmp::Ordering;
use std::collections::{BTreeMap, BinaryHeap, HashMap};
use std::fmt;
use std::ops::Range;
use std::path::Path;
use std::sync::Arc;

use mcap::records::{ChunkHeader, MessageHeader, Record, op};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::camera_info::{camera_info_topic, decode_camera_info};
use super::channels::{Channel, ChannelSchema};
use super::ros_msgs::{self as msgs, FrameInfo};
use super::schema::{self, CDR_MESSAGE_ENCODING, JSON_MESSAGE_ENCODING};
use super::source::{MAX_READ_BYTES, Source};
use super::truth::{self, TruthKind, TruthMessage};
use super::{
    CALIBRATION_ATTACHMENT, CALIBRATION_KEY, CALIBRATION_METADATA, FORMAT_VERSION, OutputMessage,
    RECORDING_METADATA, RecordingError, RecordingMeta, TopicMap, channel_id, compressed, v1,
};
use crate::camera::CameraModel;
use crate::frame::{Frame, Image, Timestamp};
use crate::rig::RigCalibration;
use crate::stream::{ProbeImage, StreamKind, StreamMessage};

/// Opcode (1 byte) and body length (u64) in front of every record.
const RECORD_PREFIX_LEN: usize = 9;
/// Serialized size of a Message record's header: channel id, sequence, log and publish time.
const MESSAGE_HEADER_LEN: usize = 2 + 4 + 8 + 8;

/// Where a chunk lies in the file and what its header says.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChunkInfo {
    /// Position among the file's chunk records, from 0 (the chunk of schemas and channels).
    pub index: usize,
    /// Byte offset of the chunk record (its opcode).
    pub offset: u64,
    /// Byte offset just past the chunk record.
    pub end_offset: u64,
    /// Byte offset of the compressed payload.
    pub data_offset: u64,
    pub compressed_size: u64,
    pub uncompressed_size: u64,
    pub compression: String,
    /// Log-time (host) range of the chunk's messages, ns.
    pub message_start_ns: u64,
    pub message_end_ns: u64,
}

/// Who wrote a file, which decides how its messages read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Layout {
    /// relight before format 2 ([`v1`]).
    Format1,
    /// relight, format 2 (or a later one, read as far as it is the same).
    Format2,
    /// Another tool: `header.stamp` is the device clock, and MCAP's `sequence` means nothing
    /// (rosbag2 writes 0).
    Foreign,
}

#[doc(hidden)]
#[derive(Debug, Clone)]
pub struct ChannelInfo {
    topic: String,
    message_encoding: String,
    stream: Option<StreamKind>,
    /// The format-2 channel the topic is, in a relight recording.
    channel: Option<Channel>,
    layout: Layout,
}

/// A unit the message iterator loads at once: a chunk, a chunk whose header did not parse, or a
/// message outside any chunk.
#[derive(Debug)]
enum Block {
    Chunk {
        info: ChunkInfo,
        body: Range<usize>,
    },
    BadChunk {
        index: usize,
        offset: u64,
        reason: String,
        start_ns: u64,
    },
    Message {
        header: MessageHeader,
        data: Range<usize>,
    },
}

impl Block {
    /// Where the block's record starts (for a loose message, its data).
    fn file_offset(&self) -> usize {
        match self {
            Block::Chunk { info, .. } => usize::try_from(info.offset).unwrap_or(usize::MAX),
            Block::BadChunk { offset, .. } => usize::try_from(*offset).unwrap_or(usize::MAX),
            Block::Message { data, .. } => data.start,
        }
    }

    fn start_ns(&self) -> u64 {
        match self {
            Block::Chunk { info, .. } => info.message_start_ns,
            Block::BadChunk { start_ns, .. } => *start_ns,
            Block::Message { header, .. } => header.log_time,
        }
    }
}

/// How the linear walk over the records ended.
enum WalkEnd {
    /// A Footer record was read.
    Footer,
    /// The file ends exactly after a record, before any footer.
    AtRecordBoundary,
    /// The file ends inside the record starting at `offset`.
    InsideRecord {
        offset: usize,
        opcode: Option<u8>,
        length: Option<u64>,
    },
}

/// A recording, read from its file as needed (no memory map: a file cut shorter under it is a
/// read error, not a signal).
///
/// Opening walks the records once, reading each chunk's header but not its messages;
/// [`messages`](Self::messages) reads and decompresses chunk by chunk as it goes, so memory
/// holds the chunks in use, not the file.
pub struct RecordingReader {
    source: Source,
    meta: RecordingMeta,
    warnings: Vec<String>,
    blocks: Vec<Block>,
    channels: HashMap<u16, ChannelInfo>,
    summary_present: bool,
    topics: TopicMap,
    layout: Layout,
}

impl fmt::Debug for RecordingReader {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RecordingReader")
            .field("bytes", &self.source.len())
            .field("meta", &self.meta)
            .field("warnings", &self.warnings)
            .field("blocks", &self.blocks.len())
            .field("summary_present", &self.summary_present)
            .finish()
    }
}

impl RecordingReader {
    /// Open the file at `path` (a regular file only) and index it.
    pub fn open(path: &Path) -> Result<Self, RecordingError> {
        let io = |source| RecordingError::Io {
            path: path.to_owned(),
            source,
        };
        let file = crate::input_file::open_regular(path).map_err(io)?;
        let len = usize::try_from(file.metadata().map_err(io)?.len()).unwrap_or(usize::MAX);
        let reader = Self::from_source(Source::File { file, len })?;
        for warning in &reader.warnings {
            tracing::warn!(path = %path.display(), "{warning}");
        }
        Ok(reader)
    }

    /// Index a recording held in memory. Fails only when the bytes do not start with an MCAP
    /// magic and header record; any later damage becomes a warning or a per-chunk error.
    pub fn from_bytes(bytes: Vec<u8>) -> Result<Self, RecordingError> {
        Self::from_source(Source::Memory(bytes))
    }

    fn from_source(source: Source) -> Result<Self, RecordingError> {
        let mut reader = RecordingReader {
            source,
            meta: RecordingMeta::default(),
            warnings: Vec::new(),
            blocks: Vec::new(),
            channels: HashMap::new(),
            summary_present: false,
            topics: TopicMap::default(),
            layout: Layout::Foreign,
        };
        reader.index()?;
        Ok(reader)
    }

    /// Read the streams from the topics `topics` names instead of relight's own.
    pub fn with_topics(mut self, topics: TopicMap) -> Self {
        self.topics = topics.in_format_1(self.layout == Layout::Format1);
        for info in self.channels.values_mut() {
            info.stream = self.topics.stream_of(&info.topic);
        }
        self.prefer_raw_images();
        self
    }

    /// The topics the streams are read from.
    pub fn topic_map(&self) -> &TopicMap {
        &self.topics
    }

    /// A bag that holds a stream both raw and as image_transport's `…/compressed` (as ROS
    /// drivers often record both) is read from the raw topic only, so no frame comes twice.
    /// relight's own recordings hold different frames on the two, and keep both.
    fn prefer_raw_images(&mut self) {
        if self.layout != Layout::Foreign {
            return;
        }
        let raw: Vec<StreamKind> = self
            .channels
            .values()
            .filter(|c| !c.topic.ends_with("/compressed"))
            .filter_map(|c| c.stream)
            .collect();
        for info in self.channels.values_mut() {
            if info.topic.ends_with("/compressed") && info.stream.is_some_and(|k| raw.contains(&k))
            {
                info.stream = None;
            }
        }
    }

    /// Every channel's topic, sorted, once each.
    pub fn topics(&self) -> Vec<String> {
        let mut topics: Vec<String> = self.channels.values().map(|c| c.topic.clone()).collect();
        topics.sort();
        topics.dedup();
        topics
    }

    /// Whether relight wrote the recording (else it is another tool's bag, read by topic).
    pub fn is_relight_recording(&self) -> bool {
        self.layout != Layout::Foreign
    }

    /// The relight format the recording is read as (`"1"` or `"2"`); `None` for another
    /// tool's bag.
    pub fn format_version(&self) -> Option<&'static str> {
        match self.layout {
            Layout::Format1 => Some(v1::FORMAT_VERSION),
            Layout::Format2 => Some(FORMAT_VERSION),
            Layout::Foreign => None,
        }
    }

    /// For a bag without relight's calibration: the colour and depth cameras that the
    /// `sensor_msgs/msg/CameraInfo` beside their image topics describe ([`camera_info_topic`],
    /// as ROS drivers publish them; the first decodable message of each), read in one pass that
    /// stops once both are found; `None` when the bag has neither. Nothing else of a rig is in
    /// such a bag, so the depth is taken as registered to the colour camera (`color_from_depth`
    /// identity), and there is no probe, board or response.
    pub fn calibration_from_camera_info(&self) -> Result<Option<RigCalibration>, RecordingError> {
        let wanted = [StreamKind::Color, StreamKind::Depth]
            .map(|kind| camera_info_topic(self.topics.topic(kind)));
        let mut found: [Option<CameraModel>; 2] = [None, None];
        for message in self.iterate::<CameraInfoMessage>() {
            let message = match message {
                Ok(message) => message,
                Err(RecordingError::Decode { ref channel, .. })
                    if wanted
                        .iter()
                        .zip(&found)
                        .any(|(topic, camera)| topic == channel && camera.is_none()) =>
                {
                    return message.map(|_| None);
                }
                Err(_) => continue,
            };
            for (topic, camera) in wanted.iter().zip(&mut found) {
                if *topic == message.topic && camera.is_none() {
                    *camera = Some(message.camera);
                }
            }
            if found.iter().all(Option::is_some) {
                break;
            }
        }
        let [color, depth] = found;
        if color.is_none() && depth.is_none() {
            return Ok(None);
        }
        Ok(Some(RigCalibration {
            name: "camera_info".into(),
            color,
            depth,
            ..RigCalibration::default()
        }))
    }

    fn channel_info(&self, topic: &str, message_encoding: &str) -> ChannelInfo {
        ChannelInfo {
            topic: topic.to_owned(),
            message_encoding: message_encoding.to_owned(),
            stream: self.topics.stream_of(topic),
            channel: (self.layout == Layout::Format2)
                .then(|| Channel::of_topic(topic))
                .flatten(),
            layout: self.layout,
        }
    }

    pub fn meta(&self) -> &RecordingMeta {
        &self.meta
    }

    /// Problems found while indexing: truncation (with where it was cut and how many complete
    /// messages remain), corrupt non-chunk records, an unreadable calibration. Corrupt chunks
    /// are reported by [`messages`](Self::messages) instead. [`open`](Self::open) also logs each
    /// at WARN with the file's path, so callers of `open` need not log them again.
    pub fn warnings(&self) -> Vec<String> {
        self.warnings.clone()
    }

    /// Whether the file has a complete summary section and footer.
    pub fn has_summary(&self) -> bool {
        self.summary_present
    }

    /// The chunks whose record and header are intact, in file order.
    pub fn chunks(&self) -> Vec<ChunkInfo> {
        self.blocks
            .iter()
            .filter_map(|block| match block {
                Block::Chunk { info, .. } => Some(info.clone()),
                _ => None,
            })
            .collect()
    }

    /// Every complete message in log-time (host) order; messages with equal log time come in
    /// file order. A corrupt chunk yields one [`RecordingError::CorruptChunk`] where its
    /// messages would have been and reading goes on with the next chunk; a message that does
    /// not decode yields [`RecordingError::Decode`]. Messages on topics that are not relight
    /// streams are skipped.
    pub fn messages(&self) -> Messages<'_> {
        self.iterate()
    }

    /// The ground-truth messages (see [`super::truth`]) in log-time order, with the same
    /// handling of damage as [`messages`](Self::messages); empty for recordings of real rigs.
    pub fn truth(&self) -> Messages<'_, TruthMessage> {
        self.iterate()
    }

    /// What the daemon rendered, when the recorder recorded it (`[recorder] outputs`): the
    /// composites, Δ and lighting estimates, in log-time order.
    pub fn outputs(&self) -> Messages<'_, OutputMessage> {
        self.iterate()
    }

    fn iterate<T>(&self) -> Messages<'_, T> {
        let mut order: Vec<usize> = (0..self.blocks.len()).collect();
        order.sort_by_key(|&i| self.blocks.get(i).map(Block::start_ns));
        Messages {
            reader: self,
            order,
            next_block: 0,
            pending: BinaryHeap::new(),
            channels: self.channels.clone(),
            serial: 0,
            foreign_seq: HashMap::new(),
            frame_infos: HashMap::new(),
            decoded: std::marker::PhantomData,
        }
    }

    /// Walk every record once: collect chunks, loose messages, channels, metadata and the
    /// calibration attachment, and note how the file ends.
    fn index(&mut self) -> Result<(), RecordingError> {
        let source = std::mem::replace(&mut self.source, Source::Memory(Vec::new()));
        let result = self.index_bytes(&source);
        self.source = source;
        result
    }

    fn index_bytes(&mut self, bytes: &Source) -> Result<(), RecordingError> {
        let len = bytes.len();
        match bytes.get(0..mcap::MAGIC.len()) {
            Some(magic) if *magic == *mcap::MAGIC => {}
            Some(_) => {
                return Err(RecordingError::NotMcap {
                    reason: "the file does not start with the MCAP magic bytes".into(),
                });
            }
            None if bytes
                .get(0..len)
                .is_some_and(|start| mcap::MAGIC.starts_with(&start)) =>
            {
                return Err(RecordingError::NotMcap {
                    reason: format!("the file is cut off inside the magic bytes ({len} bytes)"),
                });
            }
            None => {
                return Err(RecordingError::NotMcap {
                    reason: format!("{len} bytes, not an MCAP file"),
                });
            }
        }
        let mut pos = mcap::MAGIC.len();

        let (header_opcode, header_body) = match frame_record(bytes, pos) {
            Framed::Record { opcode, body } => (opcode, body),
            Framed::End | Framed::Cut { .. } => {
                return Err(RecordingError::NotMcap {
                    reason: format!("the file is cut off inside the header record ({len} bytes)"),
                });
            }
        };
        let library = match body_of(bytes, &header_body).map(|b| parse_owned(header_opcode, &b)) {
            Some(Ok(Record::Header(header))) => header.library,
            Some(Ok(_)) | None => {
                return Err(RecordingError::NotMcap {
                    reason: format!(
                        "the first record has opcode {header_opcode:#04x}, not a header"
                    ),
                });
            }
            Some(Err(e)) => {
                return Err(RecordingError::NotMcap {
                    reason: format!("the header record does not parse: {e}"),
                });
            }
        };
        pos = header_body.end;

        let mut metadata: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
        let mut channels: BTreeMap<u16, (String, String)> = BTreeMap::new();
        let mut calibration_attachment: Option<Range<usize>> = None;
        let mut chunk_count = 0usize;
        let mut data_end_seen = false;
        let walk_end = loop {
            let (opcode, body_range) = match frame_record(bytes, pos) {
                Framed::Record { opcode, body } => (opcode, body),
                Framed::End => break WalkEnd::AtRecordBoundary,
                Framed::Cut { opcode, length } => {
                    break WalkEnd::InsideRecord {
                        offset: pos,
                        opcode,
                        length,
                    };
                }
            };
            let record_offset = pos;
            pos = body_range.end;
            let cut = WalkEnd::InsideRecord {
                offset: record_offset,
                opcode: Some(opcode),
                length: None,
            };
            match opcode {
                op::CHUNK => {
                    let index = chunk_count;
                    chunk_count += 1;
                    match chunk_header(bytes, &body_range) {
                        None => break cut,
                        Some(Ok(header)) => self.blocks.push(Block::Chunk {
                            info: chunk_info(index, record_offset, pos, &header),
                            body: body_range,
                        }),
                        Some(Err(e)) => {
                            let start_ns = self.blocks.last().map(Block::start_ns).unwrap_or(0);
                            self.blocks.push(Block::BadChunk {
                                index,
                                offset: record_offset as u64,
                                reason: format!("chunk header does not parse: {e}"),
                                start_ns,
                            });
                        }
                    }
                    continue;
                }
                op::DATA_END => {
                    data_end_seen = true;
                    continue;
                }
                op::FOOTER => break WalkEnd::Footer,
                op::MESSAGE | op::CHANNEL | op::METADATA | op::ATTACHMENT => {}
                _ => continue,
            }
            let mut corrupt = |reason: String| {
                self.warnings.push(
                    RecordingError::CorruptRecord {
                        offset: record_offset as u64,
                        opcode,
                        reason,
                    }
                    .to_string(),
                );
            };
            if body_range.len() > MAX_READ_BYTES {
                corrupt(format!(
                    "{} bytes, over the {MAX_READ_BYTES}-byte read limit: skipped",
                    body_range.len()
                ));
                continue;
            }
            let Some(body) = body_of(bytes, &body_range) else {
                break cut;
            };
            let body: &[u8] = &body;
            match opcode {
                op::MESSAGE => match parse_record(opcode, body) {
                    Ok(Record::Message { header, .. }) => self.blocks.push(Block::Message {
                        header,
                        data: body_range.start + MESSAGE_HEADER_LEN..body_range.end,
                    }),
                    Ok(_) => {}
                    Err(e) => corrupt(e.to_string()),
                },
                op::CHANNEL => match parse_record(opcode, body) {
                    Ok(Record::Channel(channel)) => {
                        channels
                            .entry(channel.id)
                            .or_insert((channel.topic, channel.message_encoding));
                    }
                    Ok(_) => {}
                    Err(e) => corrupt(e.to_string()),
                },
                op::METADATA => match parse_record(opcode, body) {
                    Ok(Record::Metadata(record)) => {
                        metadata.entry(record.name).or_insert(record.metadata);
                    }
                    Ok(_) => {}
                    Err(e) => corrupt(e.to_string()),
                },
                op::ATTACHMENT => match attachment_name_and_data(body) {
                    Ok((name, data)) => {
                        // It verifies the CRC.
                        match parse_record(opcode, body) {
                            Ok(_) if name == CALIBRATION_ATTACHMENT => {
                                calibration_attachment = Some(
                                    body_range.start + data.start..body_range.start + data.end,
                                );
                            }
                            Ok(_) => {}
                            Err(e) => corrupt(e.to_string()),
                        }
                    }
                    Err(reason) => corrupt(reason),
                },
                _ => {}
            }
        };

        self.meta.source = metadata
            .get(RECORDING_METADATA)
            .and_then(|m| m.get("source"))
            .cloned()
            .unwrap_or(library);
        let calibration_toml = metadata
            .get(CALIBRATION_METADATA)
            .and_then(|m| m.get(CALIBRATION_KEY))
            .map(|toml| (CALIBRATION_METADATA, toml.clone()))
            .or_else(|| {
                let data = calibration_attachment.and_then(|range| bytes.get(range))?;
                match std::str::from_utf8(&data) {
                    Ok(text) => Some((CALIBRATION_ATTACHMENT, text.to_owned())),
                    Err(e) => {
                        self.warnings
                            .push(format!("calibration attachment is not UTF-8: {e}"));
                        None
                    }
                }
            });
        if let Some((origin, toml)) = calibration_toml {
            match RigCalibration::from_toml(&toml) {
                Ok(calibration) => self.meta.calibration = Some(calibration),
                Err(e) => self
                    .warnings
                    .push(format!("calibration in {origin} does not parse: {e}")),
            }
        }

        self.layout = match metadata
            .get(RECORDING_METADATA)
            .map(|m| m.get("format_version").map(String::as_str))
        {
            None => Layout::Foreign,
            // Format 1 recordings all carry their version; a missing one is read as format 1.
            Some(Some(v1::FORMAT_VERSION) | None) => Layout::Format1,
            Some(Some(FORMAT_VERSION)) => Layout::Format2,
            Some(Some(other)) => {
                self.warnings.push(format!(
                    "recording format {other} is newer than this relight's ({FORMAT_VERSION}); read as format {FORMAT_VERSION}"
                ));
                Layout::Format2
            }
        };
        self.topics = std::mem::take(&mut self.topics).in_format_1(self.layout == Layout::Format1);
        for (id, (topic, encoding)) in channels {
            let info = self.channel_info(&topic, &encoding);
            self.channels.insert(id, info);
        }
        // A relight recording uses fixed channel IDs, so its messages stay readable when the
        // chunk holding the Channel records is lost.
        match self.layout {
            Layout::Format1 => {
                for kind in StreamKind::ALL {
                    let info = self.channel_info(v1::topic(kind), v1::message_encoding(kind));
                    self.channels.entry(channel_id(kind)).or_insert(info);
                }
                for kind in TruthKind::ALL {
                    let encoding = if kind == TruthKind::State {
                        JSON_MESSAGE_ENCODING
                    } else {
                        CDR_MESSAGE_ENCODING
                    };
                    let info = self.channel_info(kind.topic(), encoding);
                    self.channels.entry(kind.channel_id()).or_insert(info);
                }
            }
            Layout::Format2 => {
                for channel in Channel::ALL {
                    let info = self.channel_info(channel.topic(), ChannelSchema::MESSAGE_ENCODING);
                    self.channels.entry(channel.id()).or_insert(info);
                }
            }
            Layout::Foreign => self.prefer_raw_images(),
        }

        let stopped = match walk_end {
            WalkEnd::InsideRecord { offset, .. } => Some(offset),
            _ => None,
        };
        let bad_chunk = self
            .blocks
            .iter()
            .any(|b| matches!(b, Block::BadChunk { .. }));
        let resumed = (stopped.is_some() || bad_chunk)
            .then(|| self.resume_at_indexed_chunks(bytes, stopped.unwrap_or(usize::MAX)))
            .flatten();
        if let Some((damage, recovered)) = resumed {
            // The file ends in an intact footer and summary: the walk was stopped or thrown off
            // by a damaged record, not by the end of what was written.
            self.summary_present = true;
            let complete = self.count_complete_messages(bytes);
            self.warnings.push(format!(
                "record at byte {damage} is damaged; resumed from the summary's chunk index: {recovered} chunks from there recovered; read {complete} complete messages"
            ));
            return Ok(());
        }
        match walk_end {
            WalkEnd::Footer => {
                self.summary_present = true;
                let trailer = bytes.get(pos..len).unwrap_or_default();
                if trailer.len() < mcap::MAGIC.len() && mcap::MAGIC.starts_with(&trailer) {
                    let complete = self.count_complete_messages(bytes);
                    self.warnings.push(format!(
                        "recording truncated at byte {len} inside the closing magic bytes: \
                         summary section complete; read {complete} complete messages"
                    ));
                } else if *trailer != *mcap::MAGIC {
                    self.warnings.push(format!(
                        "footer at byte {pos} is followed by {} bytes that are not the closing magic",
                        trailer.len()
                    ));
                }
            }
            WalkEnd::AtRecordBoundary | WalkEnd::InsideRecord { .. } => {
                let place = match walk_end {
                    WalkEnd::InsideRecord {
                        offset,
                        opcode,
                        length,
                    } => {
                        let what = opcode.map_or("record", opcode_name);
                        match length {
                            Some(length) => format!(
                                "inside the {what} record at byte {offset} ({length}-byte body, {} bytes present)",
                                len.saturating_sub(offset + RECORD_PREFIX_LEN)
                            ),
                            None => format!("inside the {what} record at byte {offset}"),
                        }
                    }
                    _ => "after a complete record".to_string(),
                };
                let section = if data_end_seen {
                    "data section complete, summary section cut"
                } else {
                    "summary section missing"
                };
                let complete = self.count_complete_messages(bytes);
                self.warnings.push(format!(
                    "recording truncated at byte {len} {place}: {section}; read {complete} complete messages"
                ));
            }
        }
        Ok(())
    }

    /// Replaces what the linear walk read from the first damage on (the first chunk whose header
    /// did not parse, or where the walk stopped) with the chunks the summary's chunk index lists
    /// from there, each framed with the index's record length rather than its own length field:
    /// a corrupt length loses nothing when the chunk's bytes are intact (its CRC decides), and a
    /// walk thrown off its records by one reads no garbage after it. Returns where the damage
    /// was and how many chunks were recovered, or `None` when the file has no readable index.
    fn resume_at_indexed_chunks(
        &mut self,
        bytes: &Source,
        stopped: usize,
    ) -> Option<(usize, usize)> {
        let entries = summary_chunk_index(bytes)?;
        let damage = self
            .blocks
            .iter()
            .filter_map(|block| match block {
                Block::BadChunk { offset, .. } => usize::try_from(*offset).ok(),
                _ => None,
            })
            .fold(stopped, usize::min);
        self.blocks.retain(|block| block.file_offset() < damage);
        let mut recovered = 0;
        for (index, (offset, length)) in entries.into_iter().enumerate() {
            let (Ok(start), Ok(length)) = (usize::try_from(offset), usize::try_from(length)) else {
                continue;
            };
            let end = start.checked_add(length).filter(|&end| end <= bytes.len());
            let opcode = bytes.get(start..start + 1).map(|b| b[0]);
            let (Some(end), Some(op::CHUNK)) = (end, opcode) else {
                continue;
            };
            if start < damage || length < RECORD_PREFIX_LEN {
                continue;
            }
            let body = start + RECORD_PREFIX_LEN..end;
            match chunk_header(bytes, &body) {
                Some(Ok(header)) => {
                    self.blocks.push(Block::Chunk {
                        info: chunk_info(index, start, end, &header),
                        body,
                    });
                    recovered += 1;
                }
                Some(Err(e)) => self.blocks.push(Block::BadChunk {
                    index,
                    offset,
                    reason: format!("chunk header does not parse: {e}"),
                    start_ns: self.blocks.last().map(Block::start_ns).unwrap_or(0),
                }),
                _ => {}
            }
        }
        Some((damage, recovered))
    }

    /// Messages in loose records and in chunks that decompress cleanly. Used only for the
    /// truncation warning, when the summary's statistics are not there.
    fn count_complete_messages(&self, bytes: &Source) -> u64 {
        self.blocks
            .iter()
            .map(|block| match block {
                Block::Message { .. } => 1,
                Block::BadChunk { .. } => 0,
                Block::Chunk { info, body } => {
                    match load_chunk(bytes, info.offset as usize..body.end) {
                        Ok(records) => records
                            .iter()
                            .filter(|r| matches!(r, Record::Message { .. }))
                            .count() as u64,
                        Err(_) => 0,
                    }
                }
            })
            .sum()
    }
}

/// Result of framing one record at a position.
enum Framed {
    Record {
        opcode: u8,
        body: Range<usize>,
    },
    /// The file ends exactly here.
    End,
    /// The file ends inside this record (its opcode and length if they were read).
    Cut {
        opcode: Option<u8>,
        length: Option<u64>,
    },
}

fn frame_record(bytes: &Source, pos: usize) -> Framed {
    if pos >= bytes.len() {
        return Framed::End;
    }
    let opcode = bytes.get(pos..pos + 1).map(|b| b[0]);
    let Some(prefix) = bytes.get(pos..pos + RECORD_PREFIX_LEN) else {
        return Framed::Cut {
            opcode,
            length: None,
        };
    };
    let mut length_bytes = [0u8; 8];
    length_bytes.copy_from_slice(prefix.get(1..).unwrap_or(&[0; 8]));
    let length = u64::from_le_bytes(length_bytes);
    let start = pos + RECORD_PREFIX_LEN;
    let end = usize::try_from(length)
        .ok()
        .and_then(|length| start.checked_add(length))
        .filter(|&end| end <= bytes.len());
    match (opcode, end) {
        (Some(opcode), Some(end)) => Framed::Record {
            opcode,
            body: start..end,
        },
        _ => Framed::Cut {
            opcode,
            length: Some(length),
        },
    }
}

/// Footer record: prefix, summary start, summary offset start, summary CRC.
const FOOTER_RECORD_LEN: usize = RECORD_PREFIX_LEN + 8 + 8 + 4;

/// The chunk offsets and record lengths the summary section's Chunk Index records give, found
/// through the footer at the very end of the file; `None` when the file does not end in a
/// footer and the magic, or its summary has no chunk index.
fn summary_chunk_index(bytes: &Source) -> Option<Vec<(u64, u64)>> {
    let magic_start = bytes.len().checked_sub(mcap::MAGIC.len())?;
    if *bytes.get(magic_start..bytes.len())? != *mcap::MAGIC {
        return None;
    }
    let footer_start = magic_start.checked_sub(FOOTER_RECORD_LEN)?;
    let Framed::Record {
        opcode: op::FOOTER,
        body,
    } = frame_record(bytes, footer_start)
    else {
        return None;
    };
    let Ok(Record::Footer(footer)) = parse_owned(op::FOOTER, &body_of(bytes, &body)?) else {
        return None;
    };
    let mut pos = usize::try_from(footer.summary_start)
        .ok()
        .filter(|&start| start > mcap::MAGIC.len() && start < footer_start)?;
    let mut offsets = Vec::new();
    while pos < footer_start {
        let Framed::Record { opcode, body } = frame_record(bytes, pos) else {
            break;
        };
        pos = body.end;
        if opcode == op::CHUNK_INDEX
            && let Some(Ok(Record::ChunkIndex(index))) =
                body_of(bytes, &body).map(|b| parse_owned(opcode, &b))
        {
            offsets.push((index.chunk_start_offset, index.chunk_length));
        }
    }
    (!offsets.is_empty()).then_some(offsets)
}

fn body_of<'a>(bytes: &'a Source, range: &Range<usize>) -> Option<Cow<'a, [u8]>> {
    bytes.get(range.clone())
}

/// [`parse_record`] of a record read into a buffer of its own.
fn parse_owned(opcode: u8, body: &[u8]) -> Result<Record<'static>, String> {
    parse_record(opcode, body).map(Record::into_owned)
}

/// The header of the chunk record whose body is `body`, read without the compressed records
/// after it: `None` when it cannot be read, else the header or why it is corrupt (as
/// [`mcap::parse_record`] checks it: the compressed size must fit the record).
fn chunk_header(bytes: &Source, body: &Range<usize>) -> Option<Result<ChunkHeader, String>> {
    // Times, uncompressed size (3 × u64), CRC (u32), compression (u32 length + name),
    // compressed size (u64); a name this long is corrupt anyway.
    let head = bytes.get_up_to(body.start, 4096.min(body.len()))?;
    Some(parse_chunk_header(&head, body.len()))
}

fn parse_chunk_header(head: &[u8], body_len: usize) -> Result<ChunkHeader, String> {
    let u64_at = |at: usize| read_u64(head, at);
    let name_len = read_u32(head, 28)? as usize;
    let name = head
        .get(32..32usize.saturating_add(name_len))
        .ok_or("compression name runs past the chunk header")?;
    let compression = String::from_utf8(name.to_vec()).map_err(|e| e.to_string())?;
    let compressed_size = u64_at(32 + name_len)?;
    let available = body_len.saturating_sub(32 + name_len + 8) as u64;
    if compressed_size > available {
        return Err(format!(
            "chunk claims {compressed_size} compressed bytes, its record holds {available}"
        ));
    }
    Ok(ChunkHeader {
        message_start_time: u64_at(0)?,
        message_end_time: u64_at(8)?,
        uncompressed_size: u64_at(16)?,
        uncompressed_crc: read_u32(head, 24)?,
        compression,
        compressed_size,
    })
}

fn opcode_name(opcode: u8) -> &'static str {
    match opcode {
        op::HEADER => "header",
        op::FOOTER => "footer",
        op::SCHEMA => "schema",
        op::CHANNEL => "channel",
        op::MESSAGE => "message",
        op::CHUNK => "chunk",
        op::MESSAGE_INDEX => "message index",
        op::CHUNK_INDEX => "chunk index",
        op::ATTACHMENT => "attachment",
        op::ATTACHMENT_INDEX => "attachment index",
        op::STATISTICS => "statistics",
        op::METADATA => "metadata",
        op::METADATA_INDEX => "metadata index",
        op::SUMMARY_OFFSET => "summary offset",
        op::DATA_END => "data end",
        _ => "unknown",
    }
}

fn chunk_info(index: usize, offset: usize, end_offset: usize, header: &ChunkHeader) -> ChunkInfo {
    // Chunk body: start, end, uncompressed size (3 × u64), crc (u32), compression (u32 length
    // + bytes), compressed size (u64), then the compressed bytes.
    let data_offset = offset + RECORD_PREFIX_LEN + 8 * 3 + 4 + 4 + header.compression.len() + 8;
    ChunkInfo {
        index,
        offset: offset as u64,
        end_offset: end_offset as u64,
        data_offset: data_offset as u64,
        compressed_size: header.compressed_size,
        uncompressed_size: header.uncompressed_size,
        compression: header.compression.clone(),
        message_start_ns: header.message_start_time,
        message_end_ns: header.message_end_time,
    }
}

/// Read an Attachment body's name and the range of its data, checking that every length field
/// fits: log time, create time (u64 each), name, media type (u32-prefixed strings), data length
/// (u64), data, CRC (u32).
/// [`mcap::parse_record`], which slices an attachment's body by its length fields unchecked
/// (a short or inconsistent one panicked: found by the `recording_reader` fuzz target), with
/// those lengths checked first. Every record the reader parses goes through here.
fn parse_record(opcode: u8, body: &[u8]) -> Result<Record<'_>, String> {
    if opcode == op::ATTACHMENT {
        attachment_name_and_data(body)?;
    }
    mcap::parse_record(opcode, body).map_err(|e| e.to_string())
}

fn attachment_name_and_data(body: &[u8]) -> Result<(String, Range<usize>), String> {
    let mut pos = 16usize;
    let string = |pos: &mut usize| -> Result<String, String> {
        let len = read_u32(body, *pos)? as usize;
        let start = *pos + 4;
        let text = body
            .get(start..start.saturating_add(len))
            .ok_or("attachment string runs past the record")?;
        *pos = start + len;
        String::from_utf8(text.to_vec()).map_err(|e| e.to_string())
    };
    let name = string(&mut pos)?;
    let _media_type = string(&mut pos)?;
    let data_len = read_u64(body, pos)?;
    let start = pos + 8;
    let end = usize::try_from(data_len)
        .ok()
        .and_then(|n| start.checked_add(n))
        .filter(|&end| end.checked_add(4) == Some(body.len()))
        .ok_or_else(|| {
            format!(
                "attachment data length {data_len} does not match its {}-byte record",
                body.len()
            )
        })?;
    Ok((name, start..end))
}

fn read_u32(body: &[u8], pos: usize) -> Result<u32, String> {
    body.get(pos..pos.saturating_add(4))
        .and_then(|b| b.try_into().ok())
        .map(u32::from_le_bytes)
        .ok_or_else(|| format!("u32 at {pos} runs past the record"))
}

fn read_u64(body: &[u8], pos: usize) -> Result<u64, String> {
    body.get(pos..pos.saturating_add(8))
        .and_then(|b| b.try_into().ok())
        .map(u64::from_le_bytes)
        .ok_or_else(|| format!("u64 at {pos} runs past the record"))
}

/// Decompress one chunk record (`opcode..end` in `bytes`) and parse all its records; any failure
/// (decompression, CRC, framing, a record over [`MAX_READ_BYTES`]) fails the whole chunk, so
/// that no message of a chunk with a bad CRC escapes.
/// The records of the chunk record at `record`. Its prefix is rebuilt from the range rather
/// than read from the file, so a chunk framed by the summary's index despite a corrupt length
/// field reads as what it is.
fn load_chunk(bytes: &Source, record: Range<usize>) -> Result<Vec<Record<'static>>, String> {
    let body = bytes
        .get(record.start + RECORD_PREFIX_LEN..record.end)
        .ok_or("chunk record cannot be read (outside the file, or over the read limit)")?;
    let body: &[u8] = &body;
    check_uncompressed_records(body)?;
    let mut prefix = [0u8; RECORD_PREFIX_LEN];
    prefix[0] = op::CHUNK;
    prefix[1..].copy_from_slice(&(body.len() as u64).to_le_bytes());
    let mut parts = [&prefix[..], body];
    let limit = (body.len() + RECORD_PREFIX_LEN).max(MAX_READ_BYTES);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_emit_chunks(false)
            .with_validate_chunk_crcs(true)
            .with_record_length_limit(limit),
    );
    let mut records = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            LinearReadEvent::ReadRequest(wanted) => {
                let mut empty: &[u8] = &[];
                let input = parts
                    .iter_mut()
                    .find(|part| !part.is_empty())
                    .unwrap_or(&mut empty);
                let len = wanted.min(input.len());
                let (now, rest) = input.split_at(len);
                reader.insert(len).copy_from_slice(now);
                reader.notify_read(len);
                *input = rest;
            }
            LinearReadEvent::Record { data, opcode } => {
                let record = parse_record(opcode, data)?;
                records.push(record.into_owned());
            }
        }
    }
    Ok(records)
}

/// An uncompressed chunk's records must each fit inside the chunk. The mcap crate (0.26)
/// subtracts a record's length from what is left of the chunk before checking it, which panics
/// with overflow checks on and wraps without them (found by the `recording_reader` fuzz
/// target); so the records are walked here first and an overrun is the chunk's corruption.
/// Compressed chunks are framed by their decompressed size and need no such walk.
fn check_uncompressed_records(body: &[u8]) -> Result<(), String> {
    let truncated = || "chunk header is truncated".to_owned();
    let u64_at = |at: usize| -> Option<u64> {
        Some(u64::from_le_bytes(body.get(at..at + 8)?.try_into().ok()?))
    };
    // message_start_time, message_end_time, uncompressed_size: u64; uncompressed_crc: u32.
    let compression_at = 8 + 8 + 8 + 4;
    let compression_len = body
        .get(compression_at..compression_at + 4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
        .ok_or_else(truncated)?;
    if compression_len != 0 {
        return Ok(());
    }
    let records_len_at = compression_at + 4;
    let records_len = u64_at(records_len_at).ok_or_else(truncated)?;
    let records = body
        .get(records_len_at + 8..)
        .filter(|rest| records_len <= rest.len() as u64)
        .map(|rest| &rest[..records_len as usize])
        .ok_or("chunk records overrun the chunk")?;
    let mut at = 0usize;
    while at < records.len() {
        let length = records
            .get(at + 1..at + RECORD_PREFIX_LEN)
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
            .ok_or_else(|| format!("record at {at} of the chunk is cut off"))?;
        let left = (records.len() - at - RECORD_PREFIX_LEN) as u64;
        if length > left {
            return Err(format!(
                "record at {at} of the chunk claims {length} bytes, {left} are left"
            ));
        }
        at += RECORD_PREFIX_LEN + length as usize;
    }
    Ok(())
}

/// A message waiting in the merge heap, ordered by log time, then by arrival (file order).
struct Pending {
    log_time: u64,
    serial: u64,
    header: MessageHeader,
    data: PendingData,
}

enum PendingData {
    Owned(Vec<u8>),
    InFile(Range<usize>),
}

impl PartialEq for Pending {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Pending {}
impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Pending {
    /// Reversed, so that `BinaryHeap` (a max-heap) pops the earliest message first.
    fn cmp(&self, other: &Self) -> Ordering {
        (other.log_time, other.serial).cmp(&(self.log_time, self.serial))
    }
}

/// Iterator of [`RecordingReader::messages`].
///
/// Blocks (chunks, loose messages) are loaded in order of their first log time; a message is
/// handed out once no unloaded block can hold an earlier one, so overlapping chunks merge
/// correctly while at most the overlapping chunks are held decompressed.
pub struct Messages<'a, T = StreamMessage> {
    reader: &'a RecordingReader,
    order: Vec<usize>,
    next_block: usize,
    pending: BinaryHeap<Pending>,
    channels: HashMap<u16, ChannelInfo>,
    serial: u64,
    /// Per channel of a foreign bag: the messages handed out so far, their sequence numbers.
    foreign_seq: HashMap<u16, u32>,
    /// The latest `frame_info` of each camera, for the image that follows it.
    frame_infos: HashMap<StreamKind, FrameInfo>,
    decoded: std::marker::PhantomData<T>,
}

impl<T> fmt::Debug for Messages<'_, T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Messages")
            .field("blocks_loaded", &self.next_block)
            .field("blocks", &self.order.len())
            .field("pending", &self.pending.len())
            .finish()
    }
}

impl<T: Recorded> Iterator for Messages<'_, T> {
    type Item = Result<T, RecordingError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let next_block = self
                .order
                .get(self.next_block)
                .and_then(|&i| self.reader.blocks.get(i));
            let earliest_pending = self.pending.peek().map(|p| p.log_time);
            match (next_block, earliest_pending) {
                (Some(block), Some(log_time)) if block.start_ns() <= log_time => {
                    self.next_block += 1;
                    if let Err(e) = self.load(block) {
                        return Some(Err(e));
                    }
                }
                (Some(block), None) => {
                    self.next_block += 1;
                    if let Err(e) = self.load(block) {
                        return Some(Err(e));
                    }
                }
                (_, Some(_)) => {
                    let pending = self.pending.pop()?;
                    if let Some(result) = self.decode(pending) {
                        return Some(result);
                    }
                }
                (None, None) => return None,
            }
        }
    }
}

impl<'a, T: Recorded> Messages<'a, T> {
    fn push(&mut self, header: MessageHeader, data: PendingData) {
        self.serial += 1;
        self.pending.push(Pending {
            log_time: header.log_time,
            serial: self.serial,
            header,
            data,
        });
    }

    fn load(&mut self, block: &'a Block) -> Result<(), RecordingError> {
        match block {
            Block::Message { header, data } => {
                self.push(*header, PendingData::InFile(data.clone()));
                Ok(())
            }
            Block::BadChunk {
                index,
                offset,
                reason,
                ..
            } => Err(RecordingError::CorruptChunk {
                index: *index,
                offset: *offset,
                reason: reason.clone(),
            }),
            Block::Chunk { info, body } => {
                let records = load_chunk(&self.reader.source, info.offset as usize..body.end)
                    .map_err(|reason| RecordingError::CorruptChunk {
                        index: info.index,
                        offset: info.offset,
                        reason,
                    })?;
                for record in records {
                    match record {
                        Record::Channel(channel) => {
                            let reader = self.reader;
                            self.channels.entry(channel.id).or_insert_with(|| {
                                reader.channel_info(&channel.topic, &channel.message_encoding)
                            });
                        }
                        Record::Message { header, data } => {
                            self.push(header, PendingData::Owned(data.into_owned()));
                        }
                        _ => {}
                    }
                }
                Ok(())
            }
        }
    }

    /// Decode one message; `None` for messages on topics this iterator does not read.
    fn decode(&mut self, pending: Pending) -> Option<Result<T, RecordingError>> {
        let mut header = pending.header;
        let in_file: Cow<'_, [u8]>;
        let data: &[u8] = match &pending.data {
            PendingData::Owned(data) => data,
            PendingData::InFile(range) => {
                in_file = self.reader.source.get(range.clone()).unwrap_or_default();
                &in_file
            }
        };
        let Some(channel) = self.channels.get(&header.channel_id) else {
            return Some(Err(RecordingError::Decode {
                channel: format!("channel {}", header.channel_id),
                seq: u64::from(header.sequence),
                reason: "no Channel record describes this channel".into(),
            }));
        };
        if channel.layout == Layout::Foreign {
            let count = self.foreign_seq.entry(header.channel_id).or_insert(0);
            header.sequence = *count;
            *count = count.wrapping_add(1);
        }
        if let Some(Channel::FrameInfo(kind)) = channel.channel {
            return match msgs::decode_frame_info(data) {
                Ok(info) => {
                    self.frame_infos.insert(kind, info);
                    None
                }
                Err(reason) => Some(Err(RecordingError::Decode {
                    channel: channel.topic.clone(),
                    seq: u64::from(header.sequence),
                    reason,
                })),
            };
        }
        // The frame_info written just before this image, if it survived.
        let info = channel
            .stream
            .and_then(|kind| self.frame_infos.get(&kind))
            .filter(|info| info.seq as u32 == header.sequence);
        let decoded = T::decode(channel, &header, data, info)?;
        Some(decoded.map_err(|reason| RecordingError::Decode {
            channel: channel.topic.clone(),
            seq: u64::from(header.sequence),
            reason,
        }))
    }
}

/// A kind of message the reader hands out: the sensor streams, or the ground truth.
pub trait Recorded: Sized {
    /// `None` when the channel is not one of this kind's. `info` is the image's `frame_info`
    /// (format 2) when it was read.
    #[doc(hidden)]
    fn decode(
        channel: &ChannelInfo,
        header: &MessageHeader,
        data: &[u8],
        info: Option<&FrameInfo>,
    ) -> Option<Result<Self, String>>;
}

impl Recorded for StreamMessage {
    fn decode(
        channel: &ChannelInfo,
        header: &MessageHeader,
        data: &[u8],
        info: Option<&FrameInfo>,
    ) -> Option<Result<Self, String>> {
        let Some(stream) = channel.stream else {
            tracing::trace!(topic = %channel.topic, "skipping message of another topic");
            return None;
        };
        Some(decode_message(stream, channel, header, data, info))
    }
}

/// A `sensor_msgs/msg/CameraInfo` message, on a topic ending in `camera_info`
/// ([`RecordingReader::calibration_from_camera_info`]).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfoMessage {
    pub topic: String,
    pub camera: CameraModel,
}

impl Recorded for CameraInfoMessage {
    fn decode(
        channel: &ChannelInfo,
        _header: &MessageHeader,
        data: &[u8],
        _info: Option<&FrameInfo>,
    ) -> Option<Result<Self, String>> {
        if !channel.topic.ends_with("camera_info")
            || channel.message_encoding != CDR_MESSAGE_ENCODING
        {
            return None;
        }
        Some(decode_camera_info(data).map(|camera| CameraInfoMessage {
            topic: channel.topic.clone(),
            camera,
        }))
    }
}

impl Recorded for TruthMessage {
    fn decode(
        channel: &ChannelInfo,
        header: &MessageHeader,
        data: &[u8],
        _info: Option<&FrameInfo>,
    ) -> Option<Result<Self, String>> {
        let kind = TruthKind::of_topic(&channel.topic)?;
        let stamp = Timestamp::new(header.publish_time, header.log_time);
        let short_seq = u64::from(header.sequence);
        let format_1 = channel.layout == Layout::Format1;
        Some(match kind {
            TruthKind::State if format_1 => truth::decode_state(data)
                .map(|state| TruthMessage::State(Frame::new(short_seq, stamp, state))),
            TruthKind::State => msgs::decode_string(data)
                .and_then(|json| truth::decode_state(json.as_bytes()))
                .map(|state| TruthMessage::State(Frame::new(short_seq, stamp, state))),
            _ => schema::decode_image(data).and_then(|decoded| {
                let seq = if format_1 {
                    v1::parse_frame_id(&decoded.frame_id)?.1.seq
                } else {
                    None
                };
                if Some(decoded.image.format()) != kind.pixel_format() {
                    return Err(format!(
                        "{:?} image on {}",
                        decoded.image.format(),
                        kind.topic()
                    ));
                }
                Ok(TruthMessage::Image(
                    kind,
                    Frame::new(seq.unwrap_or(short_seq), stamp, decoded.image),
                ))
            }),
        })
    }
}

impl Recorded for OutputMessage {
    fn decode(
        channel: &ChannelInfo,
        header: &MessageHeader,
        data: &[u8],
        _info: Option<&FrameInfo>,
    ) -> Option<Result<Self, String>> {
        let stamp = Timestamp::new(header.publish_time, header.log_time);
        let seq = u64::from(header.sequence);
        let frame = |image: Image| Frame::new(seq, stamp, image);
        Some(match channel.channel? {
            Channel::Composite => {
                schema::decode_image(data).map(|d| OutputMessage::Composite(frame(d.image)))
            }
            Channel::CompositeCompressed => msgs::decode_compressed_image(data)
                .and_then(|c| compressed::decompress(c.data))
                .map(|image| OutputMessage::Composite(frame(image))),
            Channel::Delta => {
                schema::decode_image(data).map(|d| OutputMessage::Delta(frame(d.image)))
            }
            Channel::Lighting => msgs::decode_string(data)
                .map(|json| OutputMessage::Lighting(Frame::new(seq, stamp, json.to_owned()))),
            _ => return None,
        })
    }
}

/// The image of an image stream's message: `sensor_msgs/msg/Image`, or on a `…/compressed`
/// topic `sensor_msgs/msg/CompressedImage` (JPEG or PNG; not depth, whose compressed form is
/// image_transport's own `compressedDepth`).
fn decode_picture(
    stream: StreamKind,
    topic: &str,
    data: &[u8],
) -> Result<schema::DecodedImage, String> {
    if !topic.ends_with("/compressed") {
        return schema::decode_image(data);
    }
    if stream == StreamKind::Depth {
        return Err("compressed depth images are not read; record or remap raw depth".into());
    }
    let message = msgs::decode_compressed_image(data)?;
    Ok(schema::DecodedImage {
        stamp_ns: message.stamp_ns,
        frame_id: message.frame_id.to_owned(),
        image: compressed::decompress(message.data)?,
    })
}

/// Turn one message back into a [`StreamMessage`] (inverse of the writer; see the module docs).
/// A format-2 image takes its device time, full `seq` and exposure from its `frame_info`
/// (without one, device time and `seq` from MCAP's `publish_time` and `sequence`); a foreign
/// bag's image takes its device time from `header.stamp`, the driver's clock.
fn decode_message(
    stream: StreamKind,
    channel: &ChannelInfo,
    header: &MessageHeader,
    data: &[u8],
    info: Option<&FrameInfo>,
) -> Result<StreamMessage, String> {
    let message_encoding = channel.message_encoding.as_str();
    let mut stamp = Timestamp::new(header.publish_time, header.log_time);
    let short_seq = u64::from(header.sequence);
    let expected = match channel.layout {
        Layout::Format1 => v1::message_encoding(stream),
        _ => CDR_MESSAGE_ENCODING,
    };
    if message_encoding != expected {
        return Err(format!(
            "message encoding `{message_encoding}`, expected `{expected}`"
        ));
    }
    Ok(match stream {
        StreamKind::Depth | StreamKind::Color | StreamKind::Probe => {
            let decoded = decode_picture(stream, &channel.topic, data)?;
            let mut seq = short_seq;
            let mut exposure = None;
            match channel.layout {
                Layout::Foreign => stamp.device_ns = decoded.stamp_ns,
                Layout::Format1 => {
                    let (_, extras) = v1::parse_frame_id(&decoded.frame_id)?;
                    seq = extras.seq.unwrap_or(seq);
                    exposure = extras.exposure_us.zip(extras.gain_db);
                }
                Layout::Format2 => {
                    if let Some(info) = info {
                        seq = info.seq;
                        stamp.device_ns = info.device_stamp_ns;
                        exposure = Some((info.exposure_us, info.gain_db));
                    }
                }
            }
            let frame = |image| Arc::new(Frame::new(seq, stamp, image));
            match stream {
                StreamKind::Depth => StreamMessage::Depth(frame(decoded.image)),
                StreamKind::Color => StreamMessage::Color(frame(decoded.image)),
                _ => {
                    let (exposure_us, gain_db) = exposure.ok_or(match channel.layout {
                        Layout::Format1 => "probe frame_id lacks exposure_us or gain_db",
                        _ => {
                            "the probe image's exposure is unknown: its frame_info message is missing"
                        }
                    })?;
                    let probe = ProbeImage {
                        image: decoded.image,
                        exposure_us,
                        gain_db,
                    };
                    StreamMessage::Probe(Arc::new(Frame::new(seq, stamp, probe)))
                }
            }
        }
        StreamKind::Markers if channel.layout == Layout::Format1 => {
            let (markers, long_seq) = v1::decode_markers(data)?;
            StreamMessage::Markers(Arc::new(Frame::new(
                long_seq.unwrap_or(short_seq),
                stamp,
                markers,
            )))
        }
        StreamKind::Markers => {
            let (markers, seq, device_ns) = msgs::decode_markers(data)?;
            stamp.device_ns = device_ns;
            StreamMessage::Markers(Arc::new(Frame::new(seq, stamp, markers)))
        }
        StreamKind::Lamp if channel.layout == Layout::Format1 => {
            let (lamp, long_seq) = v1::decode_lamp(data)?;
            StreamMessage::Lamp(Arc::new(Frame::new(
                long_seq.unwrap_or(short_seq),
                stamp,
                lamp,
            )))
        }
        StreamKind::Lamp => {
            let (lamp, seq, device_ns) = msgs::decode_lamp(data)?;
            stamp.device_ns = device_ns;
            StreamMessage::Lamp(Arc::new(Frame::new(seq, stamp, lamp)))
        }
    })
}
