//! Keeping fakenect from ending the process.
//!
//! fakenect (libfreenect's replay library, `fakenect/fakenect.c`) plays the dump directory named
//! by `FAKENECT_PATH`: `INDEX.txt` lists one file per line, and each call of
//! `freenect_process_events` reads the next line, sleeps to keep the recorded pace, and hands a
//! `d-…pgm` frame to the depth callback or an `r-…ppm` frame to the video callback. It calls
//! `exit(1)` when `FAKENECT_PATH` is unset, when `INDEX.txt` or a listed file cannot be opened,
//! or when a frame has no one-line header; and it copies a whole frame out of a file without
//! checking the file's length.
//!
//! So the backend mirrors fakenect's position in the index (process-wide, like fakenect's own
//! state) and, before every call, checks what fakenect is about to read:
//! - `FAKENECT_PATH` unset → `DeviceError::Config` (the environment cannot change);
//! - directory, `INDEX.txt` or the next listed file absent → `NotFound` on open and
//!   `Disconnected` while running (the recording "went away"; when the file is back the
//!   runner's reconnect resumes at the same line);
//! - a malformed `INDEX.txt` → `Config`;
//! - a frame file with a bad header or too few bytes → skipped without fakenect touching its
//!   pixels (streams are paused for that one line), reported as `BadData`.
//!
//! At the end of the index fakenect 0.5 (Debian's) returns −1 for good: the backend reports
//! `RunEnd::EndOfStream`. Later fakenect versions start over unless `FAKENECT_LOOP=0`; the
//! mirror follows them. A file that vanishes between the check and fakenect's `fopen` (a
//! microsecond window) still ends the process: only deleting files of a dump that is being
//! played can do that.

use std::ffi::{OsStr, OsString};
use std::io::Read;
use std::path::PathBuf;
use std::sync::{Mutex, PoisonError};

use crate::device::DeviceError;

/// Longest pause between two index lines accepted: fakenect sleeps through it inside
/// `freenect_process_events`, deaf to stop requests.
pub(super) const MAX_GAP_S: f64 = 10.0;

/// One line of `INDEX.txt`: `<kind>-<time s>-<timestamp>.<ext>`, as fakenect's `record` writes
/// it (`"%c-%f-%u.%s"`) and fakenect reads it (`"%c-%lf-%u-%*s"`).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct IndexEntry {
    /// `d` depth, `r` colour, `a` accelerometer (others are read and ignored by fakenect).
    pub(super) kind: u8,
    pub(super) time_s: f64,
    pub(super) ticks: u32,
    pub(super) file: String,
}

/// Parse `INDEX.txt` the way fakenect reads it: lines end at `\n` only, and an empty line ends
/// the playback (fakenect 0.5 reports "No more lines" there).
pub(super) fn parse_index(text: &[u8]) -> Result<Vec<IndexEntry>, String> {
    let lines: Vec<&[u8]> = text.split(|&b| b == b'\n').collect();
    let mut entries = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        if line.is_empty() {
            if lines[n..].iter().all(|l| l.is_empty()) {
                break;
            }
            return Err(format!(
                "line {}: empty line before the end (fakenect would stop there)",
                n + 1
            ));
        }
        let entry = std::str::from_utf8(line)
            .map_err(|_| "not UTF-8".to_string())
            .and_then(parse_entry)
            .map_err(|e| format!("line {}: {e}", n + 1))?;
        entries.push(entry);
    }
    for (n, pair) in entries.windows(2).enumerate() {
        let gap = pair[1].time_s - pair[0].time_s;
        if gap > MAX_GAP_S {
            return Err(format!(
                "line {}: {gap:.1} s after the previous line; fakenect would sleep that long \
                 (at most {MAX_GAP_S} s accepted)",
                n + 2
            ));
        }
    }
    Ok(entries)
}

fn parse_entry(line: &str) -> Result<IndexEntry, String> {
    let bad = |why: &str| format!("`{line}`: {why}");
    if line.chars().any(char::is_control) {
        return Err(bad("control character in the file name"));
    }
    let kind = *line.as_bytes().first().ok_or_else(|| bad("empty"))?;
    let rest = line
        .get(1..)
        .and_then(|r| r.strip_prefix('-'))
        .ok_or_else(|| bad("expected `<kind>-<time>-<timestamp>.<ext>`"))?;
    let (time, rest) = rest
        .split_once('-')
        .ok_or_else(|| bad("expected `<kind>-<time>-<timestamp>.<ext>`"))?;
    let time_s: f64 = time
        .parse()
        .ok()
        .filter(|t: &f64| t.is_finite() && *t >= 0.0)
        .ok_or_else(|| bad("time is not a non-negative number of seconds"))?;
    let digits = rest.bytes().take_while(u8::is_ascii_digit).count();
    let ticks: u32 = rest[..digits]
        .parse()
        .map_err(|_| bad("timestamp is not a 32-bit unsigned integer"))?;
    Ok(IndexEntry {
        kind,
        time_s,
        ticks,
        file: line.to_string(),
    })
}

/// The layout fakenect copies out of a frame file for a running stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct FrameLayout {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) bytes: usize,
}

/// What the next call into fakenect will do.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Next {
    /// Read a line whose file is safe to play.
    Ready,
    /// Reach the end of the index (−1, or start over in a looping fakenect).
    End,
    /// Exit the process: a file it must open is not there.
    Missing(String),
    /// Read past a frame file's end or exit: play the line with streams paused.
    Malformed(String),
}

/// What the call did, by its return code.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Consumed {
    Line,
    End,
    /// A looping fakenect closed the index; it starts over at the next call.
    Looped,
    /// fakenect could not read the line's file (−1 mid-index); the line is gone.
    Unreadable(String),
}

/// fakenect's position in the index; one per process, like fakenect's own static state.
#[derive(Debug)]
struct Playback {
    dir: OsString,
    entries: Vec<IndexEntry>,
    /// The next line fakenect reads.
    cursor: usize,
    /// fakenect has `INDEX.txt` open (it opens it at the first call and after looping).
    index_open: bool,
    claimed: bool,
}

static PLAYBACK: Mutex<Option<Playback>> = Mutex::new(None);

fn join(dir: &OsStr, file: &str) -> PathBuf {
    // fakenect builds "%s/%s" from FAKENECT_PATH and the line.
    let mut path = dir.to_os_string();
    path.push("/");
    path.push(file);
    PathBuf::from(path)
}

/// This device's hold on the process's fakenect playback; released on drop.
#[derive(Debug)]
pub(super) struct Claim {
    device: String,
}

impl Claim {
    /// Take the playback for `device`: `FAKENECT_PATH` set, its `INDEX.txt` valid, and the next
    /// file fakenect will read present.
    pub(super) fn take(device: &str) -> Result<Claim, DeviceError> {
        let config = |reason: String| DeviceError::Config {
            device: device.to_string(),
            reason,
        };
        let not_found = |reason: String| DeviceError::NotFound {
            device: device.to_string(),
            reason,
        };
        let Some(dir) = std::env::var_os("FAKENECT_PATH") else {
            return Err(config(
                "libfreenect here is fakenect (the replay library), but FAKENECT_PATH is not \
                 set; fakenect would exit the process"
                    .into(),
            ));
        };
        let mut guard = PLAYBACK.lock().unwrap_or_else(PoisonError::into_inner);
        if guard.as_ref().is_some_and(|p| p.claimed) {
            return Err(not_found(
                "fakenect plays one device per process and another one holds it".into(),
            ));
        }
        // Until fakenect has opened the index, read it afresh: a dump may still be written.
        let reparse = guard
            .as_ref()
            .is_none_or(|p| p.dir != dir || (p.cursor == 0 && !p.index_open));
        if reparse {
            let shown = PathBuf::from(&dir);
            if !shown.is_dir() {
                return Err(not_found(format!(
                    "fakenect dump directory {} (FAKENECT_PATH) does not exist",
                    shown.display()
                )));
            }
            let index_path = join(&dir, "INDEX.txt");
            let text = std::fs::read(&index_path)
                .map_err(|e| not_found(format!("fakenect index {}: {e}", index_path.display())))?;
            let entries = parse_index(&text)
                .map_err(|e| config(format!("fakenect index {}: {e}", index_path.display())))?;
            *guard = Some(Playback {
                dir,
                entries,
                cursor: 0,
                index_open: false,
                claimed: false,
            });
        }
        let Some(playback) = guard.as_mut() else {
            return Err(config("fakenect playback state lost".into()));
        };
        if let Some(entry) = playback.entries.get(playback.cursor) {
            let path = join(&playback.dir, &entry.file);
            if !path.is_file() {
                return Err(not_found(format!(
                    "fakenect dump file {} is missing",
                    path.display()
                )));
            }
        }
        playback.claimed = true;
        Ok(Claim {
            device: device.to_string(),
        })
    }

    /// Check what the next call will read, given the layouts of the running streams.
    pub(super) fn next(&self, depth: Option<FrameLayout>, video: Option<FrameLayout>) -> Next {
        let guard = PLAYBACK.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(playback) = guard.as_ref() else {
            return Next::Missing("fakenect playback state lost".into());
        };
        if !playback.index_open {
            let index_path = join(&playback.dir, "INDEX.txt");
            if !index_path.is_file() {
                return Next::Missing(format!("fakenect index {} vanished", index_path.display()));
            }
        }
        let Some(entry) = playback.entries.get(playback.cursor) else {
            return Next::End;
        };
        let path = join(&playback.dir, &entry.file);
        let mut file = match std::fs::File::open(&path) {
            Ok(file) => file,
            Err(e) => return Next::Missing(format!("fakenect dump file {}: {e}", path.display())),
        };
        let layout = match entry.kind {
            b'd' => depth.map(|l| (l, "P5")),
            b'r' => video.map(|l| (l, "P6")),
            _ => None,
        };
        let Some((layout, magic)) = layout else {
            return Next::Ready;
        };
        match check_frame(&mut file, layout, magic) {
            Ok(()) => Next::Ready,
            Err(why) => Next::Malformed(format!("fakenect frame {}: {why}", path.display())),
        }
    }

    /// Account for one call that returned `code`.
    pub(super) fn consumed(&self, code: i32) -> Consumed {
        let mut guard = PLAYBACK.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(playback) = guard.as_mut() else {
            return Consumed::End;
        };
        let Some(entry) = playback.entries.get(playback.cursor) else {
            if code < 0 {
                return Consumed::End;
            }
            playback.cursor = 0;
            playback.index_open = false;
            return Consumed::Looped;
        };
        let file = entry.file.clone();
        playback.cursor += 1;
        playback.index_open = true;
        if code < 0 {
            Consumed::Unreadable(format!("fakenect could not read {file}"))
        } else {
            Consumed::Line
        }
    }

    /// The device holding the claim, for messages.
    pub(super) fn device(&self) -> &str {
        &self.device
    }
}

impl Drop for Claim {
    fn drop(&mut self) {
        let mut guard = PLAYBACK.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(playback) = guard.as_mut() {
            playback.claimed = false;
        }
    }
}

/// A frame file fakenect can copy `layout.bytes` out of: a one-line ASCII header
/// `<magic> <width> <height> <maxval>` and at least that many bytes after it.
fn check_frame(file: &mut std::fs::File, layout: FrameLayout, magic: &str) -> Result<(), String> {
    let len = file.metadata().map_err(|e| e.to_string())?.len();
    let mut head = [0u8; 64];
    let mut filled = 0;
    while filled < head.len() {
        match file.read(&mut head[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(e) => return Err(e.to_string()),
        }
    }
    let head = &head[..filled];
    let newline = head
        .iter()
        .position(|&b| b == b'\n')
        .ok_or("no one-line header")?;
    let header = std::str::from_utf8(&head[..newline])
        .ok()
        .filter(|h| h.bytes().all(|b| b.is_ascii_graphic() || b == b' '))
        .ok_or("header is not printable ASCII")?;
    let fields: Vec<&str> = header.split_ascii_whitespace().collect();
    let expected_size = [layout.width.to_string(), layout.height.to_string()];
    if fields.len() != 4
        || fields[0] != magic
        || fields[1] != expected_size[0]
        || fields[2] != expected_size[1]
    {
        return Err(format!(
            "header `{header}`, expected `{magic} {} {} <maxval>`",
            layout.width, layout.height
        ));
    }
    let pixels = len.saturating_sub(newline as u64 + 1);
    if pixels < layout.bytes as u64 {
        return Err(format!("{pixels} bytes of pixels, {} needed", layout.bytes));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_lines_parse_as_fakenect_reads_them() {
        let text = b"d-1294184523.348316-3047104436.pgm\nr-1294184523.364593-3047404436.ppm\na-1294184523.364600-3047404436.dump\n";
        let entries = parse_index(text).unwrap();
        assert_eq!(entries.len(), 3);
        assert_eq!(entries[0].kind, b'd');
        assert_eq!(entries[0].ticks, 3_047_104_436);
        assert!((entries[1].time_s - 1_294_184_523.364_593).abs() < 1e-6);
        assert_eq!(entries[2].file, "a-1294184523.364600-3047404436.dump");
        // Trailing empty lines end the playback like the end of the file.
        assert_eq!(parse_index(b"d-1.0-2.pgm\n\n\n").unwrap().len(), 1);
        assert!(parse_index(b"").unwrap().is_empty());
    }

    #[test]
    fn index_lines_fakenect_would_misread_are_rejected() {
        for (text, why) in [
            (&b"d-1.0-2.pgm\n\nd-1.1-3.pgm\n"[..], "empty line"),
            (b"hello\n", "expected"),
            (b"d-x-2.pgm\n", "time"),
            (b"d-1.0-99999999999.pgm\n", "32-bit"),
            (b"d-1.0-2.pgm\r\n", "control"),
            (b"d-1.0-2.pgm\nd-20.0-3.pgm\n", "sleep"),
        ] {
            let error = parse_index(text).unwrap_err();
            assert!(error.contains(why), "{error}");
        }
    }

    #[test]
    fn frame_headers_and_lengths_are_checked() {
        let dir = tempfile::tempdir().unwrap();
        let layout = FrameLayout {
            width: 4,
            height: 2,
            bytes: 16,
        };
        let check = |contents: &[u8]| {
            let path = dir.path().join("f.pgm");
            std::fs::write(&path, contents).unwrap();
            check_frame(&mut std::fs::File::open(&path).unwrap(), layout, "P5")
        };
        let mut good = b"P5 4 2 65535\n".to_vec();
        good.extend([7u8; 16]);
        assert_eq!(check(&good), Ok(()));
        assert!(
            check(&good[..good.len() - 1])
                .unwrap_err()
                .contains("15 bytes")
        );
        assert!(check(b"P5 4 2 65535").unwrap_err().contains("header"));
        let mut wrong = b"P6 4 2 255\n".to_vec();
        wrong.extend([7u8; 16]);
        assert!(check(&wrong).unwrap_err().contains("expected `P5 4 2"));
        let mut nul = b"P5 4\0 2 65535\n".to_vec();
        nul.extend([7u8; 16]);
        assert!(check(&nul).unwrap_err().contains("ASCII"));
    }
}
