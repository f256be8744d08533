//! Where calibration images come from: a folder of image files, or one stream of an MCAP
//! recording made by `relightd` (or the simulator).
//!
//! - **Folder**: every `png`, `jpg`/`jpeg`, `bmp`, `tif`/`tiff` file directly inside (case
//!   insensitive; other files such as `exposures.toml` are ignored), in file-name order, decoded
//!   by OpenCV's `imread`. 8-bit grey, BGR and BGRA files are accepted (alpha is dropped); the
//!   folder must hold at least one image, every file must decode, and all must have one size —
//!   each failure is an error naming the files concerned.
//! - **Recording**: the frames of the `color` or `probe` stream, in log-time order, every `n`-th
//!   one ([`FrameSelection`]); probe frames carry their exposure time and gain, which a bracket
//!   needs. A corrupt chunk costs its frames (logged at WARN), not the run.
//! - **Exposures of a folder** (for a response bracket): from a sidecar `exposures.toml` in the
//!   folder (`[exposure_us]` mapping file names to microseconds, optional `[gain_db]`), or else
//!   from the file names: the last `_`/`-`/space-separated token of the stem that is a number
//!   with a unit `us`, `µs`, `ms` or `s` (`probe_1ms.png`, `probe_3.5ms.png`, `bracket-250us.jpg`).
//!
//! A live device is not read here: a rig being calibrated is recorded with `relightd record`
//! (every backend already writes MCAP), which also keeps the raw data of the calibration.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use opencv::core::{Mat, Vec3b};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use relight_core::recording::{RecordingError, RecordingReader};
use relight_core::{Image, PixelFormat, ProbeImage, StreamKind, StreamMessage};
use serde::Deserialize;

use crate::progress::ProgressSink;

/// Extensions read from a folder (lower case).
pub const IMAGE_EXTENSIONS: [&str; 6] = ["png", "jpg", "jpeg", "bmp", "tif", "tiff"];
/// Name of the exposure sidecar in an image folder.
pub const EXPOSURE_SIDECAR: &str = "exposures.toml";
/// Files listed per size in a mixed-size error.
const LISTED_FILES: usize = 4;

/// Why the calibration images could not be read.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not a directory")]
    NotADirectory { path: PathBuf },
    #[error("no images (.{}) in {dir}", IMAGE_EXTENSIONS.join(", ."))]
    NoImages { dir: PathBuf },
    #[error("{path}: not a readable image (corrupt, truncated, or not the format its name says)")]
    Corrupt { path: PathBuf },
    #[error("{path}: {reason}")]
    Unsupported { path: PathBuf, reason: String },
    #[error(
        "images in {dir} differ in size: {sizes}; calibrate one camera at one resolution per run"
    )]
    MixedSizes { dir: PathBuf, sizes: String },
    #[error("recording {path}: {source}")]
    Recording {
        path: PathBuf,
        #[source]
        source: RecordingError,
    },
    #[error("{stream} frames hold no image a target can be seen in; use the color or probe stream")]
    NotAnImageStream { stream: StreamKind },
    #[error("recording {path} has no {stream} frames{detail}")]
    NoFrames {
        path: PathBuf,
        stream: StreamKind,
        detail: String,
    },
    #[error(
        "no exposure time for {files}: name them like `probe_3ms.png` or list them in \
         {EXPOSURE_SIDECAR} under [exposure_us]"
    )]
    MissingExposure { files: String },
    #[error("{path}: {reason}")]
    Sidecar { path: PathBuf, reason: String },
    #[error("OpenCV {operation}: {source}")]
    OpenCv {
        operation: &'static str,
        #[source]
        source: opencv::Error,
    },
}

/// One calibration image and where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct InputFrame {
    /// File name, or `<stream> seq <n>` for a recorded frame: what messages and reports call it.
    pub label: String,
    /// The file it was read from.
    pub path: Option<PathBuf>,
    /// `Rgb8` or `Mono8`.
    pub image: Image,
    /// Exposure time, µs, when known (recorded probe frames; folders with exposures).
    pub exposure_us: Option<u32>,
    /// Amplitude gain, dB (0 when unknown).
    pub gain_db: f32,
}

impl InputFrame {
    /// The frame as a probe exposure, if its exposure is known and it is RGB.
    pub fn probe_image(&self) -> Option<ProbeImage> {
        let exposure_us = self.exposure_us?;
        (self.image.format() == PixelFormat::Rgb8).then(|| ProbeImage {
            image: self.image.clone(),
            exposure_us,
            gain_db: self.gain_db,
        })
    }
}

/// Which recorded frames to use: every `every`-th (1: all), at most `max_frames`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameSelection {
    pub every: usize,
    pub max_frames: Option<usize>,
}

impl Default for FrameSelection {
    fn default() -> Self {
        Self {
            every: 1,
            max_frames: None,
        }
    }
}

/// The image files directly inside `dir`, sorted by file name.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>, InputError> {
    if !dir.is_dir() {
        return Err(InputError::NotADirectory {
            path: dir.to_owned(),
        });
    }
    let io = |source| InputError::Io {
        path: dir.to_owned(),
        source,
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        let is_image = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()));
        if is_image && path.is_file() {
            files.push(path);
        }
    }
    files.sort();
    if files.is_empty() {
        return Err(InputError::NoImages {
            dir: dir.to_owned(),
        });
    }
    Ok(files)
}

/// Every image in `dir` (module docs), all of one size.
pub fn read_image_folder(
    dir: &Path,
    progress: &ProgressSink,
) -> Result<Vec<InputFrame>, InputError> {
    let files = image_files(dir)?;
    let bar = progress.bar(files.len() as u64, "reading", "images");
    let mut frames = Vec::with_capacity(files.len());
    for path in files {
        let image = read_image(&path)?;
        frames.push(InputFrame {
            label: file_label(&path),
            path: Some(path),
            image,
            exposure_us: None,
            gain_db: 0.0,
        });
        bar.step();
    }
    check_one_size(dir, &frames)?;
    Ok(frames)
}

fn file_label(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// Reads one image file as `Rgb8` or `Mono8`.
pub fn read_image(path: &Path) -> Result<Image, InputError> {
    // imread says nothing about why it failed; a plain read tells permission and I/O errors
    // apart from undecodable content.
    std::fs::File::open(path).map_err(|source| InputError::Io {
        path: path.to_owned(),
        source,
    })?;
    let mat = imgcodecs::imread(path, imgcodecs::IMREAD_UNCHANGED).map_err(|source| {
        InputError::OpenCv {
            operation: "imread",
            source,
        }
    })?;
    if mat.empty() {
        return Err(InputError::Corrupt {
            path: path.to_owned(),
        });
    }
    image_from_mat(&mat).map_err(|reason| InputError::Unsupported {
        path: path.to_owned(),
        reason,
    })
}

/// An 8-bit OpenCV image (grey, BGR or BGRA) as a relight `Mono8` or `Rgb8` image.
pub fn image_from_mat(mat: &Mat) -> Result<Image, String> {
    if mat.depth() != opencv::core::CV_8U {
        return Err(format!(
            "{}-bit samples; only 8-bit images are supported (the response is an 8-bit table)",
            8 * mat.elem_size1()
        ));
    }
    let (width, height) = (
        u32::try_from(mat.cols()).map_err(|e| e.to_string())?,
        u32::try_from(mat.rows()).map_err(|e| e.to_string())?,
    );
    let (format, code) = match mat.channels() {
        1 => (PixelFormat::Mono8, None),
        3 => (PixelFormat::Rgb8, Some(imgproc::COLOR_BGR2RGB)),
        4 => (PixelFormat::Rgb8, Some(imgproc::COLOR_BGRA2RGB)),
        n => return Err(format!("{n} channels; grey, BGR or BGRA expected")),
    };
    let converted = match code {
        Some(code) => {
            let mut out = Mat::default();
            imgproc::cvt_color_def(mat, &mut out, code).map_err(|e| e.to_string())?;
            out
        }
        None => mat.try_clone().map_err(|e| e.to_string())?,
    };
    let bytes = converted.data_bytes().map_err(|e| e.to_string())?;
    let mut image = Image::new(width, height, format);
    let target = image
        .as_u8_mut()
        .ok_or_else(|| "not an 8-bit image".to_owned())?;
    if target.len() != bytes.len() {
        return Err(format!(
            "{} bytes of pixels, {} expected",
            bytes.len(),
            target.len()
        ));
    }
    target.copy_from_slice(bytes);
    Ok(image)
}

/// A relight `Rgb8` or `Mono8` image as an OpenCV BGR or grey `Mat` (a copy).
pub fn mat_from_image(image: &Image) -> Result<Mat, InputError> {
    let cv = |operation| move |source| InputError::OpenCv { operation, source };
    let (rows, cols) = (image.height() as i32, image.width() as i32);
    let unsupported = || InputError::Unsupported {
        path: PathBuf::new(),
        reason: format!(
            "{:?} images cannot be drawn on or detected in",
            image.format()
        ),
    };
    let bytes = image.as_u8().ok_or_else(unsupported)?;
    match image.format() {
        PixelFormat::Mono8 => Mat::new_rows_cols_with_bytes::<u8>(rows, cols, bytes)
            .and_then(|m| m.try_clone())
            .map_err(cv("wrapping a grey image")),
        PixelFormat::Rgb8 => {
            let rgb = Mat::new_rows_cols_with_bytes::<Vec3b>(rows, cols, bytes)
                .map_err(cv("wrapping an RGB image"))?;
            let mut bgr = Mat::default();
            imgproc::cvt_color_def(&rgb, &mut bgr, imgproc::COLOR_RGB2BGR)
                .map_err(cv("RGB to BGR"))?;
            Ok(bgr)
        }
        _ => Err(unsupported()),
    }
}

/// Fails with every size and the files of each when the frames are not all one size.
fn check_one_size(dir: &Path, frames: &[InputFrame]) -> Result<(), InputError> {
    let mut sizes: BTreeMap<(u32, u32), Vec<&str>> = BTreeMap::new();
    for frame in frames {
        sizes
            .entry((frame.image.width(), frame.image.height()))
            .or_default()
            .push(&frame.label);
    }
    if sizes.len() <= 1 {
        return Ok(());
    }
    let mut groups: Vec<_> = sizes.into_iter().collect();
    groups.sort_by_key(|(_, files)| std::cmp::Reverse(files.len()));
    let sizes = groups
        .iter()
        .map(|((w, h), files)| {
            let shown = files[..files.len().min(LISTED_FILES)].join(", ");
            let more = files.len().saturating_sub(LISTED_FILES);
            let more = if more > 0 {
                format!(" and {more} more")
            } else {
                String::new()
            };
            format!("{w}×{h} ({shown}{more})")
        })
        .collect::<Vec<_>>()
        .join("; ");
    Err(InputError::MixedSizes {
        dir: dir.to_owned(),
        sizes,
    })
}

/// The `color` or `probe` frames of a recording (module docs).
pub fn read_recording(
    path: &Path,
    stream: StreamKind,
    selection: &FrameSelection,
    progress: &ProgressSink,
) -> Result<Vec<InputFrame>, InputError> {
    if !matches!(stream, StreamKind::Color | StreamKind::Probe) {
        return Err(InputError::NotAnImageStream { stream });
    }
    let reader = RecordingReader::open(path).map_err(|source| InputError::Recording {
        path: path.to_owned(),
        source,
    })?;
    let bar = progress.spinner("reading the recording");
    let every = selection.every.max(1);
    let mut seen = 0usize;
    let mut damaged = 0usize;
    let mut frames = Vec::new();
    for message in reader.messages() {
        let message = match message {
            Ok(message) => message,
            Err(error) => {
                tracing::warn!(path = %path.display(), "skipping damaged data: {error}");
                damaged += 1;
                continue;
            }
        };
        if message.kind() != stream {
            continue;
        }
        seen += 1;
        if !(seen - 1).is_multiple_of(every) {
            continue;
        }
        let frame = match &message {
            StreamMessage::Color(frame) => InputFrame {
                label: format!("color seq {}", frame.seq),
                path: None,
                image: frame.payload.clone(),
                exposure_us: None,
                gain_db: 0.0,
            },
            StreamMessage::Probe(frame) => InputFrame {
                label: format!("probe seq {} ({} µs)", frame.seq, frame.payload.exposure_us),
                path: None,
                image: frame.payload.image.clone(),
                exposure_us: Some(frame.payload.exposure_us),
                gain_db: frame.payload.gain_db,
            },
            _ => continue,
        };
        if !matches!(frame.image.format(), PixelFormat::Rgb8 | PixelFormat::Mono8) {
            return Err(InputError::Unsupported {
                path: path.to_owned(),
                reason: format!(
                    "{} is {:?}; only 8-bit frames can be calibrated",
                    frame.label,
                    frame.image.format()
                ),
            });
        }
        frames.push(frame);
        bar.step();
        if selection.max_frames.is_some_and(|max| frames.len() >= max) {
            break;
        }
    }
    if frames.is_empty() {
        let detail = if damaged > 0 {
            format!(" ({damaged} damaged chunks or messages skipped)")
        } else {
            String::new()
        };
        return Err(InputError::NoFrames {
            path: path.to_owned(),
            stream,
            detail,
        });
    }
    check_one_size(path, &frames)?;
    Ok(frames)
}

/// The first complete bracket of a sequence of probe frames: frames in order up to the first
/// whose exposure (time and gain) repeats one already taken, i.e. one cycle of a bracketing
/// probe, all of the same static view.
pub fn first_bracket(frames: &[InputFrame]) -> Vec<ProbeImage> {
    let mut bracket: Vec<ProbeImage> = Vec::new();
    for probe in frames.iter().filter_map(InputFrame::probe_image) {
        let repeats = bracket
            .iter()
            .any(|b| b.exposure_us == probe.exposure_us && b.gain_db == probe.gain_db);
        if repeats {
            break;
        }
        bracket.push(probe);
    }
    bracket
}

/// The sidecar's layout.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Sidecar {
    exposure_us: BTreeMap<String, u32>,
    #[serde(default)]
    gain_db: BTreeMap<String, f32>,
}

/// Gives every frame read from `dir` its exposure: from [`EXPOSURE_SIDECAR`] when present, else
/// from its file name (module docs). Fails naming every frame left without one.
pub fn attach_exposures(dir: &Path, frames: &mut [InputFrame]) -> Result<(), InputError> {
    let sidecar_path = dir.join(EXPOSURE_SIDECAR);
    let sidecar = match std::fs::read_to_string(&sidecar_path) {
        Ok(text) => Some(
            toml::from_str::<Sidecar>(&text).map_err(|e| InputError::Sidecar {
                path: sidecar_path.clone(),
                reason: e.to_string(),
            })?,
        ),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(source) => {
            return Err(InputError::Io {
                path: sidecar_path,
                source,
            });
        }
    };
    if let Some(sidecar) = &sidecar {
        let unknown: Vec<&String> = sidecar
            .exposure_us
            .keys()
            .chain(sidecar.gain_db.keys())
            .filter(|name| !frames.iter().any(|f| &f.label == *name))
            .collect();
        if let Some(name) = unknown.first() {
            return Err(InputError::Sidecar {
                path: sidecar_path,
                reason: format!("lists `{name}`, which is not an image in {}", dir.display()),
            });
        }
    }
    let mut missing = Vec::new();
    for frame in frames.iter_mut() {
        let from_sidecar = sidecar.as_ref().and_then(|s| {
            s.exposure_us
                .get(&frame.label)
                .map(|&t| (t, s.gain_db.get(&frame.label).copied().unwrap_or(0.0)))
        });
        let exposure = from_sidecar.or_else(|| {
            let stem = Path::new(&frame.label).file_stem()?.to_str()?;
            exposure_from_name(stem).map(|t| (t, 0.0))
        });
        match exposure {
            Some((exposure_us, gain_db)) if exposure_us > 0 => {
                frame.exposure_us = Some(exposure_us);
                frame.gain_db = gain_db;
            }
            _ => missing.push(frame.label.clone()),
        }
    }
    if missing.is_empty() {
        Ok(())
    } else {
        Err(InputError::MissingExposure {
            files: missing.join(", "),
        })
    }
}

/// The exposure time, µs, a file stem states: its last token (split at `_`, `-`, space) that is
/// a number followed by `us`, `µs`, `ms` or `s`.
pub fn exposure_from_name(stem: &str) -> Option<u32> {
    stem.split(['_', '-', ' ']).rev().find_map(|token| {
        let (number, factor) = [("µs", 1.0), ("us", 1.0), ("ms", 1e3), ("s", 1e6)]
            .into_iter()
            .find_map(|(unit, factor)| token.strip_suffix(unit).map(|n| (n, factor)))?;
        let value: f64 = number.parse().ok()?;
        let micros = (value * factor).round();
        (value.is_finite() && micros >= 1.0 && micros <= f64::from(u32::MAX))
            .then_some(micros as u32)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposures_are_read_from_names() {
        assert_eq!(exposure_from_name("probe_1ms"), Some(1_000));
        assert_eq!(exposure_from_name("probe_3.5ms"), Some(3_500));
        assert_eq!(exposure_from_name("bracket-250us"), Some(250));
        assert_eq!(exposure_from_name("b 64000µs"), Some(64_000));
        assert_eq!(exposure_from_name("long_0.5s"), Some(500_000));
        assert_eq!(exposure_from_name("a_2ms_b_7ms"), Some(7_000));
        assert_eq!(exposure_from_name("probe_3"), None);
        assert_eq!(exposure_from_name("ms"), None);
        assert_eq!(exposure_from_name("x_0.0001us"), None);
        assert_eq!(exposure_from_name("x_nanms"), None);
    }

    fn frame(label: &str, width: u32, exposure_us: Option<u32>) -> InputFrame {
        InputFrame {
            label: label.into(),
            path: None,
            image: Image::new(width, 2, PixelFormat::Rgb8),
            exposure_us,
            gain_db: 0.0,
        }
    }

    #[test]
    fn mixed_sizes_name_every_size_and_its_files() {
        let frames: Vec<InputFrame> = (0..7)
            .map(|i| frame(&format!("f{i}.png"), if i == 3 { 8 } else { 4 }, None))
            .collect();
        let message = check_one_size(Path::new("dir"), &frames)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("4×2 (f0.png, f1.png, f2.png, f4.png and 2 more); 8×2 (f3.png)"),
            "{message}"
        );
    }

    #[test]
    fn the_first_bracket_ends_where_an_exposure_repeats() {
        let frames = [
            frame("a", 4, Some(1_000)),
            frame("b", 4, None),
            frame("c", 4, Some(3_000)),
            frame("d", 4, Some(11_000)),
            frame("e", 4, Some(1_000)),
            frame("f", 4, Some(64_000)),
        ];
        let bracket: Vec<u32> = first_bracket(&frames)
            .iter()
            .map(|b| b.exposure_us)
            .collect();
        assert_eq!(bracket, vec![1_000, 3_000, 11_000]);
    }

    #[test]
    fn image_mat_round_trip_keeps_channel_order() {
        let mut image = Image::new(3, 2, PixelFormat::Rgb8);
        let pixels: Vec<u8> = (0..18).collect();
        image.as_u8_mut().unwrap().copy_from_slice(&pixels);
        let mat = mat_from_image(&image).unwrap();
        assert_eq!(mat.channels(), 3);
        let bgr = mat.data_bytes().unwrap();
        assert_eq!(&bgr[..3], &[2, 1, 0]);
        assert_eq!(image_from_mat(&mat).unwrap(), image);
    }
}
