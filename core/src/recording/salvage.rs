//! What a damaged recording still holds, counted ([`Inspection`], `relightd recording check`) and
//! copied into a new, complete file ([`salvage`], `relightd recording repair`): the copy has a
//! summary section and footer, so tools that need them (the reference Python `mcap` reader
//! rejects a file cut by SIGKILL) read it.

use std::collections::BTreeMap;
use std::io::{Seek, Write};
use std::iter::Peekable;

use super::truth::TruthMessage;
use super::{RecordingError, RecordingReader, RecordingWriter};
use crate::stream::{StreamKind, StreamMessage};

/// What [`inspect`] or [`salvage`] found in a recording.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct Inspection {
    /// Stream messages read, per stream.
    pub messages: BTreeMap<StreamKind, u64>,
    /// Ground-truth messages read (simulated recordings).
    pub truth_messages: u64,
    /// Chunks whose data is lost (bad CRC, does not decompress).
    pub corrupt_chunks: u64,
    /// Messages in intact chunks that do not decode.
    pub undecodable: u64,
    /// Whether the file had its summary section and footer.
    pub has_summary: bool,
    /// The reader's warnings: truncation, corrupt records, where it resumed.
    pub warnings: Vec<String>,
}

impl Inspection {
    /// Whether the file is whole: nothing lost, nothing missing, nothing to warn about.
    pub fn is_clean(&self) -> bool {
        self.corrupt_chunks == 0
            && self.undecodable == 0
            && self.has_summary
            && self.warnings.is_empty()
    }

    pub fn total_messages(&self) -> u64 {
        self.messages.values().sum::<u64>() + self.truth_messages
    }

    fn count_error(&mut self, error: &RecordingError, count_chunks: bool) {
        match error {
            RecordingError::CorruptChunk { .. } if count_chunks => self.corrupt_chunks += 1,
            RecordingError::CorruptChunk { .. } => {}
            _ => self.undecodable += 1,
        }
    }
}

/// Read every message of `reader` and count what is there and what is lost.
pub fn inspect(reader: &RecordingReader) -> Inspection {
    let Ok(found) = copy::<std::convert::Infallible>(reader, |_| Ok(()));
    found
}

/// Every readable stream and ground-truth message of `reader`, merged in log-time order, into
/// `writer`, which is left open: finishing it writes the summary and footer. Unreadable parts
/// are skipped and counted.
pub fn salvage<W: Write + Seek>(
    reader: &RecordingReader,
    writer: &mut RecordingWriter<W>,
) -> Result<Inspection, RecordingError> {
    copy(reader, |message| match message {
        Item::Stream(message) => writer.write(message),
        Item::Truth(message) => writer.write_truth(message),
    })
}

enum Item<'a> {
    Stream(&'a StreamMessage),
    Truth(&'a TruthMessage),
}

fn copy<E>(
    reader: &RecordingReader,
    mut sink: impl FnMut(Item<'_>) -> Result<(), E>,
) -> Result<Inspection, E> {
    let mut found = Inspection {
        has_summary: reader.has_summary(),
        warnings: reader.warnings(),
        ..Inspection::default()
    };
    let mut streams = reader.messages().peekable();
    let mut truth = reader.truth().peekable();
    loop {
        // A corrupt chunk is reported by both iterators; it is counted once, from the streams.
        skip_errors(&mut streams, &mut found, true);
        skip_errors(&mut truth, &mut found, false);
        let stream_ns = streams
            .peek()
            .and_then(|m| m.as_ref().ok())
            .map(|m| m.stamp().host_ns);
        let truth_ns = truth
            .peek()
            .and_then(|m| m.as_ref().ok())
            .map(|m| m.stamp().host_ns);
        let take_stream = match (stream_ns, truth_ns) {
            (None, None) => break,
            (Some(s), Some(t)) => s <= t,
            (Some(_), None) => true,
            (None, Some(_)) => false,
        };
        if take_stream {
            if let Some(Ok(message)) = streams.next() {
                sink(Item::Stream(&message))?;
                *found.messages.entry(message.kind()).or_insert(0) += 1;
            }
        } else if let Some(Ok(message)) = truth.next() {
            sink(Item::Truth(&message))?;
            found.truth_messages += 1;
        }
    }
    Ok(found)
}

/// Consume the errors at the head of `messages`, counting them.
fn skip_errors<T, I: Iterator<Item = Result<T, RecordingError>>>(
    messages: &mut Peekable<I>,
    found: &mut Inspection,
    count_chunks: bool,
) {
    while let Some(Err(error)) = messages.next_if(Result::is_err) {
        found.count_error(&error, count_chunks);
    }
}
