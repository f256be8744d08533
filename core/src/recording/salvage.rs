//! What a damaged recording still holds, counted ([`Inspection`], `relightd recording check`) and
//! copied into a new, complete file ([`salvage`], `relightd recording repair`): the copy has a
//! summary section and footer, so tools that need them (the reference Python `mcap` reader
//! rejects a file cut by SIGKILL) read it.

use std::collections::BTreeMap;
use std::io::{Seek, Write};
use std::iter::Peekable;

use super::truth::TruthMessage;
use super::{OutputMessage, RecordingError, RecordingReader, RecordingWriter};
use crate::stream::{StreamKind, StreamMessage};

/// What [`inspect`] or [`salvage`] found in a recording.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct Inspection {
    /// Stream messages read, per stream.
    pub messages: BTreeMap<StreamKind, u64>,
    /// Ground-truth messages read (simulated recordings).
    pub truth_messages: u64,
    /// Composites, Δ and lighting estimates the daemon recorded.
    pub output_messages: u64,
    /// The relight format (`"1"`, `"2"`); `None` for another tool's bag.
    pub format_version: Option<&'static str>,
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
        self.messages.values().sum::<u64>() + self.truth_messages + self.output_messages
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

/// Every readable stream, ground-truth and output message of `reader`, merged in log-time
/// order, into `writer`, which is left open: finishing it writes the summary and footer (in the
/// current format, so this also converts a format-1 recording). Unreadable parts are skipped
/// and counted.
pub fn salvage<W: Write + Seek>(
    reader: &RecordingReader,
    writer: &mut RecordingWriter<W>,
) -> Result<Inspection, RecordingError> {
    copy(reader, |message| match message {
        Item::Stream(message) => writer.write(message),
        Item::Truth(message) => writer.write_truth(message),
        Item::Output(message) => writer.write_output(message),
    })
}

enum Item {
    Stream(StreamMessage),
    Truth(TruthMessage),
    Output(OutputMessage),
}

impl Item {
    fn host_ns(&self) -> u64 {
        match self {
            Item::Stream(m) => m.stamp().host_ns,
            Item::Truth(m) => m.stamp().host_ns,
            Item::Output(m) => m.stamp().host_ns,
        }
    }
}

type Items<'a> = Peekable<Box<dyn Iterator<Item = Result<Item, RecordingError>> + 'a>>;

fn items<'a, T: 'a>(
    messages: impl Iterator<Item = Result<T, RecordingError>> + 'a,
    wrap: fn(T) -> Item,
) -> Items<'a> {
    let boxed: Box<dyn Iterator<Item = _>> = Box::new(messages.map(move |m| m.map(wrap)));
    boxed.peekable()
}

fn copy<E>(
    reader: &RecordingReader,
    mut sink: impl FnMut(&Item) -> Result<(), E>,
) -> Result<Inspection, E> {
    let mut found = Inspection {
        format_version: reader.format_version(),
        has_summary: reader.has_summary(),
        warnings: reader.warnings(),
        ..Inspection::default()
    };
    // Streams first: on equal log times they come before truth and outputs.
    let mut sources = [
        items(reader.messages(), Item::Stream),
        items(reader.truth(), Item::Truth),
        items(reader.outputs(), Item::Output),
    ];
    loop {
        // A corrupt chunk is reported by every iterator; it is counted once, from the streams.
        for (i, source) in sources.iter_mut().enumerate() {
            skip_errors(source, &mut found, i == 0);
        }
        let earliest = sources
            .iter_mut()
            .enumerate()
            .filter_map(|(i, source)| Some((source.peek()?.as_ref().ok()?.host_ns(), i)))
            .min();
        let Some((_, i)) = earliest else {
            break;
        };
        let Some(Ok(item)) = sources.get_mut(i).and_then(Iterator::next) else {
            continue;
        };
        sink(&item)?;
        match &item {
            Item::Stream(message) => *found.messages.entry(message.kind()).or_insert(0) += 1,
            Item::Truth(_) => found.truth_messages += 1,
            Item::Output(_) => found.output_messages += 1,
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
