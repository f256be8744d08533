//! Where a recording's bytes come from: memory ([`RecordingReader::from_bytes`], the fuzz
//! target), or a file read on demand with positioned reads, so that reading a recording holds
//! the records in use (a chunk at a time), not the file.
//!
//! [`RecordingReader::from_bytes`]: super::RecordingReader::from_bytes

use std::borrow::Cow;
use std::fs::File;
use std::ops::Range;
use std::os::unix::fs::FileExt as _;

/// Largest single read: bounds what a corrupt length field can make the reader allocate (a
/// chunk is ~1 MiB; a 4096×4096 `Rgba16F` image is 128 MiB).
pub(super) const MAX_READ_BYTES: usize = 256 << 20;

pub(super) enum Source {
    Memory(Vec<u8>),
    /// The file and its length when opened: a file still being written is read as it was.
    File {
        file: File,
        len: usize,
    },
}

impl Source {
    pub(super) fn len(&self) -> usize {
        match self {
            Source::Memory(bytes) => bytes.len(),
            Source::File { len, .. } => *len,
        }
    }

    /// The bytes of `range`; `None` when it runs past the end, is larger than
    /// [`MAX_READ_BYTES`], or the read fails (a file cut shorter since it was opened).
    pub(super) fn get(&self, range: Range<usize>) -> Option<Cow<'_, [u8]>> {
        if range.start > range.end || range.end > self.len() {
            return None;
        }
        match self {
            Source::Memory(bytes) => bytes.get(range).map(Cow::Borrowed),
            Source::File { file, .. } => {
                let len = range.end - range.start;
                if len > MAX_READ_BYTES {
                    return None;
                }
                let mut buffer = vec![0; len];
                file.read_exact_at(&mut buffer, range.start as u64).ok()?;
                Some(Cow::Owned(buffer))
            }
        }
    }

    /// Up to `max` bytes from `start` (fewer at the end of the file).
    pub(super) fn get_up_to(&self, start: usize, max: usize) -> Option<Cow<'_, [u8]>> {
        self.get(start..start.saturating_add(max).min(self.len()))
    }
}
