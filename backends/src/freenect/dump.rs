//! Writing fakenect dumps: depth and colour (from the simulator's `relight_sim::fakenect` or
//! anywhere else) in the directory format fakenect plays, so that the freenect backend — and the
//! daemon above it — can be run through the real libfreenect API without a Kinect.
//!
//! The format is what fakenect's `record` tool writes (`fakenect/record.c`):
//! - `INDEX.txt`: one file name per line, in playback order;
//! - `d-<time>-<timestamp>.pgm`: header line `P5 640 480 65535`, then 640 × 480 11-bit raw
//!   disparity codes as `u16` in the host's byte order (not PGM's big-endian: fakenect
//!   `memcpy`s the bytes into the depth buffer);
//! - `r-<time>-<timestamp>.ppm`: header line `P6 640 480 255`, then 640 × 480 RGB bytes;
//!
//! where `<time>` is the host time in seconds with six decimals (fakenect sleeps the
//! differences to keep the recorded pace) and `<timestamp>` the Kinect's 32-bit 60 MHz frame
//! counter (passed to the frame callbacks).
//!
//! Depth in mm becomes codes through [`disparity::mm_to_raw`], so it reads back within
//! [`disparity::round_trip_bound_mm`]. fakenect plays 640 × 480 frames only; smaller images
//! whose size divides 640 × 480 by one whole factor (320 × 240, 160 × 120, 80 × 60) are
//! enlarged by pixel replication, so a cheap simulation can feed it.

use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use relight_core::{Image, PixelFormat, StreamMessage, Timestamp};

use super::clock::KINECT_CLOCK_HZ;
use super::disparity;

/// Frame size of every fakenect stream.
pub const DUMP_WIDTH: u32 = 640;
pub const DUMP_HEIGHT: u32 = 480;

#[derive(Debug, thiserror::Error)]
pub enum DumpError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} already holds a fakenect dump (INDEX.txt); refusing to add to it")]
    Exists { path: PathBuf },
    #[error(
        "{stream} image is {width}×{height}; fakenect plays 640×480 only, and smaller images \
         must divide that by one whole factor"
    )]
    Size {
        stream: &'static str,
        width: u32,
        height: u32,
    },
    #[error("{stream} image is {actual:?}, expected {expected}")]
    Format {
        stream: &'static str,
        actual: PixelFormat,
        expected: &'static str,
    },
}

/// What a finished dump holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DumpSummary {
    pub dir: PathBuf,
    /// The lines of `INDEX.txt`, in order (file names relative to `dir`).
    pub entries: Vec<String>,
    pub depth_frames: u32,
    pub color_frames: u32,
}

/// Writes a dump frame by frame.
#[derive(Debug)]
pub struct DumpWriter {
    dir: PathBuf,
    index: BufWriter<File>,
    summary: DumpSummary,
    bytes: Vec<u8>,
}

impl DumpWriter {
    /// Start a dump in `dir` (created if needed). Like `record`, refuses a directory that
    /// already has an `INDEX.txt`.
    pub fn create(dir: &Path) -> Result<Self, DumpError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| DumpError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let index_path = dir.join("INDEX.txt");
        let index = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&index_path)
            .map_err(|source| {
                if source.kind() == std::io::ErrorKind::AlreadyExists {
                    DumpError::Exists {
                        path: dir.to_path_buf(),
                    }
                } else {
                    DumpError::Io {
                        path: index_path.clone(),
                        source,
                    }
                }
            })?;
        Ok(Self {
            dir: dir.to_path_buf(),
            index: BufWriter::new(index),
            summary: DumpSummary {
                dir: dir.to_path_buf(),
                entries: Vec::new(),
                depth_frames: 0,
                color_frames: 0,
            },
            bytes: Vec::new(),
        })
    }

    /// Append a depth frame (`DepthU16Mm`, or `DepthF32M`) captured at `stamp`; returns its
    /// file name.
    pub fn write_depth(&mut self, depth: &Image, stamp: Timestamp) -> Result<String, DumpError> {
        let factor = replication_factor("depth", depth)?;
        let depth_mm: Vec<u16> = match (depth.format(), depth.as_u16(), depth.as_f32()) {
            (PixelFormat::DepthU16Mm, Some(mm), _) => mm.to_vec(),
            (PixelFormat::DepthF32M, _, Some(m)) => m
                .iter()
                .map(|&z| {
                    let mm = (z * 1000.0).round();
                    if mm.is_finite() && mm > 0.0 && mm < 65536.0 {
                        mm as u16
                    } else {
                        0
                    }
                })
                .collect(),
            (actual, _, _) => {
                return Err(DumpError::Format {
                    stream: "depth",
                    actual,
                    expected: "DepthU16Mm or DepthF32M",
                });
            }
        };
        self.bytes.clear();
        self.bytes
            .extend_from_slice(format!("P5 {DUMP_WIDTH} {DUMP_HEIGHT} 65535\n").as_bytes());
        let width = depth.width() as usize;
        for y in 0..DUMP_HEIGHT as usize {
            let row = &depth_mm[(y / factor) * width..(y / factor + 1) * width];
            for x in 0..DUMP_WIDTH as usize {
                let raw = disparity::mm_to_raw(row[x / factor]);
                self.bytes.extend_from_slice(&raw.to_ne_bytes());
            }
        }
        let name = entry_name('d', stamp, "pgm");
        self.write_file(&name)?;
        self.summary.depth_frames += 1;
        Ok(name)
    }

    /// Append a colour frame (`Rgb8`) captured at `stamp`; returns its file name.
    pub fn write_color(&mut self, color: &Image, stamp: Timestamp) -> Result<String, DumpError> {
        let factor = replication_factor("colour", color)?;
        let rgb = match (color.format(), color.as_u8()) {
            (PixelFormat::Rgb8, Some(rgb)) => rgb,
            (actual, _) => {
                return Err(DumpError::Format {
                    stream: "colour",
                    actual,
                    expected: "Rgb8",
                });
            }
        };
        self.bytes.clear();
        self.bytes
            .extend_from_slice(format!("P6 {DUMP_WIDTH} {DUMP_HEIGHT} 255\n").as_bytes());
        let width = color.width() as usize;
        for y in 0..DUMP_HEIGHT as usize {
            let row = &rgb[(y / factor) * width * 3..(y / factor + 1) * width * 3];
            for x in 0..DUMP_WIDTH as usize {
                let i = (x / factor) * 3;
                self.bytes.extend_from_slice(&row[i..i + 3]);
            }
        }
        let name = entry_name('r', stamp, "ppm");
        self.write_file(&name)?;
        self.summary.color_frames += 1;
        Ok(name)
    }

    /// Append a depth or colour message; other streams have no place in a Kinect dump and are
    /// skipped (`Ok(None)`).
    pub fn write_message(&mut self, msg: &StreamMessage) -> Result<Option<String>, DumpError> {
        match msg {
            StreamMessage::Depth(frame) => self.write_depth(&frame.payload, frame.stamp).map(Some),
            StreamMessage::Color(frame) => self.write_color(&frame.payload, frame.stamp).map(Some),
            _ => Ok(None),
        }
    }

    /// Flush the index.
    pub fn finish(mut self) -> Result<DumpSummary, DumpError> {
        let index_path = self.dir.join("INDEX.txt");
        self.index.flush().map_err(|source| DumpError::Io {
            path: index_path,
            source,
        })?;
        Ok(self.summary)
    }

    fn write_file(&mut self, name: &str) -> Result<(), DumpError> {
        let path = self.dir.join(name);
        let io = |source| DumpError::Io {
            path: path.clone(),
            source,
        };
        let mut file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(io)?;
        file.write_all(&self.bytes).map_err(io)?;
        writeln!(self.index, "{name}").map_err(|source| DumpError::Io {
            path: self.dir.join("INDEX.txt"),
            source,
        })?;
        self.summary.entries.push(name.to_string());
        Ok(())
    }
}

/// The Kinect's 32-bit frame counter at `device_ns`.
pub fn ticks_at(device_ns: u64) -> u32 {
    let ticks = u128::from(device_ns) * u128::from(KINECT_CLOCK_HZ) / 1_000_000_000;
    (ticks % (1u128 << 32)) as u32
}

/// `<kind>-<seconds>.<micros>-<ticks>.<ext>`, `record`'s `"%c-%f-%u.%s"`.
fn entry_name(kind: char, stamp: Timestamp, ext: &str) -> String {
    let secs = stamp.host_ns / 1_000_000_000;
    let micros = (stamp.host_ns % 1_000_000_000) / 1000;
    format!(
        "{kind}-{secs}.{micros:06}-{}.{ext}",
        ticks_at(stamp.device_ns)
    )
}

fn replication_factor(stream: &'static str, image: &Image) -> Result<usize, DumpError> {
    let (width, height) = (image.width(), image.height());
    let size_error = DumpError::Size {
        stream,
        width,
        height,
    };
    if width == 0
        || height == 0
        || !DUMP_WIDTH.is_multiple_of(width)
        || !DUMP_HEIGHT.is_multiple_of(height)
    {
        return Err(size_error);
    }
    let factor = DUMP_WIDTH / width;
    if DUMP_HEIGHT / height != factor {
        return Err(size_error);
    }
    Ok(factor as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entry_names_follow_record() {
        let stamp = Timestamp::new(1_000_000_000, 1_294_184_523_348_316_123);
        assert_eq!(
            entry_name('d', stamp, "pgm"),
            "d-1294184523.348316-60000000.pgm"
        );
        // The counter wraps at 2^32 ticks (71.6 s).
        assert_eq!(ticks_at(71_582_788_250), u32::MAX);
        assert_eq!(ticks_at(71_582_788_267), 0);
    }
}
