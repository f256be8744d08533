//! `relight-calibrate`: calibrates a relight rig and writes its calibration TOML.
//!
//! ```text
//! relight-calibrate intrinsics --target board.toml --images DIR --camera color --out rig.toml --report DIR
//! relight-calibrate intrinsics --target board.toml --mcap session.mcap --stream probe --fisheye --camera probe --out rig.toml
//! relight-calibrate response   --images BRACKET_DIR --out rig.toml --report DIR
//! relight-calibrate vignetting --images FLAT_DIR --rig rig.toml --out vignetting.toml
//! relight-calibrate render-target board.toml --out board.png --dpi 300
//! ```
//!
//! Each run computes everything first (detection, view selection, optimisation, the report) and
//! writes the calibration file last, atomically and merged into the file already there (only
//! what this run calibrated is replaced). Any failure — no target found, too few views, mixed
//! image sizes, an unreadable image — exits with status 1 and a message, and leaves no file
//! behind and an existing one untouched.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, anyhow, bail, ensure};
use clap::{Args, Parser, Subcommand, ValueEnum};
use glam::DVec2;
use relight_calibrate::Rigid;
use relight_calibrate::detect::{Detection, Detector};
use relight_calibrate::extrinsics::{
    LampMarker, calibrate_color_from_depth, locate_lamp_light, locate_probe, observe_lamp,
};
use relight_calibrate::fisheye::{FisheyeSettings, calibrate_fisheye};
use relight_calibrate::input::{
    FrameSelection, InputFrame, attach_exposures, first_bracket, read_image_folder, read_recording,
};
use relight_calibrate::intrinsics::{DroppedView, PinholeSettings, ViewFit, calibrate_pinhole};
use relight_calibrate::output::{
    CalibratedParts, read_existing, write_atomically, write_calibration,
};
use relight_calibrate::photometric::{
    PixelRect, ResponseSettings, calibrate_response, radiance_scale,
};
use relight_calibrate::progress::ProgressSink;
use relight_calibrate::report::{
    self, ImageCircle, ReprojectionPlot, ViewResiduals, camera_summary, error_stats,
};
use relight_calibrate::target::{Dictionary, Target, TargetGeometry};
use relight_calibrate::views::{Candidate, SelectionSettings, select_views};
use relight_calibrate::vignetting::{FlatField, Vignetting, VignettingSettings, fit_vignetting};
use relight_core::camera::{CameraModel, Pinhole};
use relight_core::rig::RigCalibration;
use relight_core::{Image, PixelFormat, ProbeImage, StreamKind};
use relight_recon::hdr::{Response, merge};

#[derive(Debug, Parser)]
#[command(
    version,
    about = "Calibrates a relight rig: camera intrinsics, the probe's response and vignetting."
)]
struct Cli {
    /// No progress bars.
    #[arg(long, short, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Intrinsics of one camera from views of a target (pinhole, or Kannala–Brandt with --fisheye).
    Intrinsics(IntrinsicsArgs),
    /// The rig's extrinsics: depth ↔ colour registration, the probe's pose in the world, the
    /// lamp's light centre. Intrinsics come from --out, the rig file the result is merged into.
    #[command(subcommand)]
    Extrinsics(ExtrinsicsCommand),
    /// The probe's inverse response curve from a bracket of one static view (uneven exposures,
    /// e.g. 1/3/11/64 ms), and optionally its absolute radiance scale.
    Response(ResponseArgs),
    /// A camera's vignetting from images of a uniform field.
    Vignetting(VignettingArgs),
    /// Renders a target to print.
    RenderTarget(RenderTargetArgs),
}

/// Where the images come from: a folder, or a stream of a recording.
#[derive(Debug, Args)]
#[group(required = true, multiple = false)]
struct Source {
    /// A folder of images (png, jpg, bmp, tiff), read in file-name order.
    #[arg(long, value_name = "DIR")]
    images: Option<PathBuf>,
    /// An MCAP recording made by relightd.
    #[arg(long, value_name = "FILE")]
    mcap: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct RecordingOptions {
    /// The recorded stream to read (with --mcap).
    #[arg(long, value_enum)]
    stream: Option<StreamArg>,
    /// Use every n-th recorded frame (with --mcap).
    #[arg(long, default_value_t = 1, value_name = "N")]
    every: usize,
    /// Stop after this many frames (with --mcap).
    #[arg(long, value_name = "N")]
    max_frames: Option<usize>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum StreamArg {
    Color,
    Probe,
}

impl From<StreamArg> for StreamKind {
    fn from(stream: StreamArg) -> Self {
        match stream {
            StreamArg::Color => StreamKind::Color,
            StreamArg::Probe => StreamKind::Probe,
        }
    }
}

/// A camera of the rig, as named in the calibration file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum CameraArg {
    Depth,
    Color,
    Probe,
}

impl CameraArg {
    fn name(self) -> &'static str {
        match self {
            CameraArg::Depth => "depth",
            CameraArg::Color => "color",
            CameraArg::Probe => "probe",
        }
    }

    fn model(self, rig: &RigCalibration) -> Option<CameraModel> {
        match self {
            CameraArg::Depth => rig.depth,
            CameraArg::Color => rig.color,
            CameraArg::Probe => rig.probe,
        }
    }

    fn parts(self, model: CameraModel) -> CalibratedParts {
        let mut parts = CalibratedParts::default();
        match self {
            CameraArg::Depth => parts.depth = Some(model),
            CameraArg::Color => parts.color = Some(model),
            CameraArg::Probe => parts.probe = Some(model),
        }
        parts
    }
}

#[derive(Debug, Args)]
struct IntrinsicsArgs {
    /// The target's description (TOML: kind = "chessboard" | "charuco" | "april_grid", …).
    #[arg(long, value_name = "FILE")]
    target: PathBuf,
    #[command(flatten)]
    source: Source,
    #[command(flatten)]
    recording: RecordingOptions,
    /// Which camera of the rig the images come from.
    #[arg(long, value_enum)]
    camera: CameraArg,
    /// Fit the Kannala–Brandt fish-eye model instead of the pinhole.
    #[arg(long)]
    fisheye: bool,
    /// Keep k3 at zero (pinhole): for lenses with little distortion or few corner views.
    #[arg(long, conflicts_with = "fisheye")]
    fix_k3: bool,
    /// The fish-eye lens's full field of view, degrees (e.g. 185); the distortion must be
    /// monotonic over all of it. Default: the field the image shows.
    #[arg(long, requires = "fisheye", value_name = "DEGREES")]
    field_deg: Option<f64>,
    /// The rig's calibration file; created, or merged into (only this camera is replaced).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write summary.txt, reprojection.png and coverage.png into this folder.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
}

#[derive(Debug, Subcommand)]
enum ExtrinsicsCommand {
    /// `color_from_depth` from views of a target taken by the depth sensor's IR camera and the
    /// colour camera at once (the n-th depth image with the n-th colour image, file-name order).
    DepthColor(DepthColorArgs),
    /// `world_from_probe`: the fixed probe's pose in the world defined by the target (origin at
    /// the pattern's centre, +Z out of the print).
    Probe(ProbeArgs),
    /// `lamp_marker_from_light`: the lamp's light centre in its marker's frame, from images of
    /// the lit lamp held in eight or more poses turned 30° or more apart.
    Lamp(LampArgs),
}

#[derive(Debug, Args)]
struct DepthColorArgs {
    /// The target's description (TOML).
    #[arg(long, value_name = "FILE")]
    target: PathBuf,
    /// The depth sensor's IR images.
    #[arg(long, value_name = "DIR")]
    depth_images: PathBuf,
    /// The colour camera's images, taken with them.
    #[arg(long, value_name = "DIR")]
    color_images: PathBuf,
    /// The rig's calibration: depth and colour intrinsics are read from it, color_from_depth
    /// is replaced.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write summary.txt into this folder.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct ProbeArgs {
    /// The target that defines the world (TOML).
    #[arg(long, value_name = "FILE")]
    target: PathBuf,
    #[command(flatten)]
    source: Source,
    #[command(flatten)]
    recording: RecordingOptions,
    /// The rig's calibration: the probe's intrinsics are read from it, world_from_probe is
    /// replaced.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write summary.txt into this folder.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct LampArgs {
    /// The lamp marker's family, e.g. `tag36h11` or `aruco_4x4_50`.
    #[arg(long, default_value = "tag36h11")]
    dictionary: String,
    /// The lamp marker's id.
    #[arg(long)]
    marker_id: u32,
    /// Edge of the lamp marker's black square, metres.
    #[arg(long, value_name = "METRES")]
    marker_size_m: f64,
    /// 8-bit level at or above which a pixel belongs to the bulb.
    #[arg(long, default_value_t = 250)]
    threshold: u8,
    #[command(flatten)]
    source: Source,
    #[command(flatten)]
    recording: RecordingOptions,
    /// The camera that took the images.
    #[arg(long, value_enum, default_value = "color")]
    camera: CameraArg,
    /// The rig's calibration: the camera's intrinsics are read from it,
    /// lamp_marker_from_light is replaced.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write summary.txt into this folder.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct ResponseArgs {
    #[command(flatten)]
    source: Source,
    #[command(flatten)]
    recording: RecordingOptions,
    /// A patch of known radiance in the bracket, pixels: x,y,width,height (with
    /// --reference-radiance) for the absolute scale; without it the scale stays relative (1).
    #[arg(long, value_name = "X,Y,W,H", requires = "reference_radiance", value_parser = parse_rect)]
    reference_patch: Option<PixelRect>,
    /// The patch's radiance (luminance-weighted), W/(m²·sr).
    #[arg(long, value_name = "W/(m²·sr)", requires = "reference_patch")]
    reference_radiance: Option<f32>,
    /// The probe's vignetting (the file `vignetting` writes), to read the patch as if on the
    /// optical axis; needs the probe's intrinsics in --out.
    #[arg(long, value_name = "FILE", requires = "reference_patch")]
    vignetting: Option<PathBuf>,
    /// The rig's calibration file; probe_response (and the scale) are replaced.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write summary.txt and response.png into this folder.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct VignettingArgs {
    #[command(flatten)]
    source: Source,
    #[command(flatten)]
    recording: RecordingOptions,
    /// The rig's calibration: the camera's model (the fall-off is fitted about its principal
    /// point) and, for the probe, its response.
    #[arg(long, value_name = "FILE")]
    rig: PathBuf,
    /// Which camera of the rig the images come from.
    #[arg(long, value_enum, default_value = "probe")]
    camera: CameraArg,
    /// The camera is linear (no response curve needed).
    #[arg(long)]
    linear: bool,
    /// Where to write the coefficients (TOML). The probe's also go into the rig file's
    /// `probe_vignetting`.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write summary.txt into this folder.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct RenderTargetArgs {
    /// The target's description (TOML).
    target: PathBuf,
    /// The PNG to write.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Printer resolution, dots per inch.
    #[arg(long, default_value_t = 300.0)]
    dpi: f64,
    /// White margin around the sheet, millimetres.
    #[arg(long, default_value_t = 10.0)]
    margin_mm: f64,
}

fn parse_rect(text: &str) -> Result<PixelRect, String> {
    let values: Vec<u32> = text
        .split(',')
        .map(|v| v.trim().parse::<u32>().map_err(|e| format!("`{v}`: {e}")))
        .collect::<Result<_, _>>()?;
    match values[..] {
        [x, y, width, height] if width > 0 && height > 0 => Ok(PixelRect {
            x,
            y,
            width,
            height,
        }),
        _ => Err("expected x,y,width,height with a positive width and height".to_owned()),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    relight_log::init("warn");
    let progress = ProgressSink::terminal(cli.quiet);
    let result = match &cli.command {
        Command::Intrinsics(args) => intrinsics(args, &progress),
        Command::Extrinsics(ExtrinsicsCommand::DepthColor(args)) => depth_color(args, &progress),
        Command::Extrinsics(ExtrinsicsCommand::Probe(args)) => probe_pose(args, &progress),
        Command::Extrinsics(ExtrinsicsCommand::Lamp(args)) => lamp_light(args, &progress),
        Command::Response(args) => response(args, &progress),
        Command::Vignetting(args) => vignetting(args, &progress),
        Command::RenderTarget(args) => render_target(args),
    };
    match result {
        Ok(summary) => {
            let _ = std::io::stdout().write_all(summary.as_bytes());
            ExitCode::SUCCESS
        }
        Err(error) => {
            eprintln!("relight-calibrate: error: {}", message(&error));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes joined by `: `, leaving out a cause whose text the message already
/// holds (many library errors repeat their source in their own message).
fn message(error: &anyhow::Error) -> String {
    let mut text = error.to_string();
    for cause in error.chain().skip(1) {
        let cause = cause.to_string();
        if !text.contains(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
    }
    text
}

/// The frames of `source`; `default_stream` when --stream is not given.
fn read_frames(
    source: &Source,
    recording: &RecordingOptions,
    default_stream: StreamArg,
    progress: &ProgressSink,
) -> Result<Vec<InputFrame>> {
    match (&source.images, &source.mcap) {
        (Some(dir), _) => Ok(read_image_folder(dir, progress)?),
        (None, Some(path)) => {
            let selection = FrameSelection {
                every: recording.every,
                max_frames: recording.max_frames,
            };
            let stream = recording.stream.unwrap_or(default_stream);
            Ok(read_recording(path, stream.into(), &selection, progress)?)
        }
        (None, None) => bail!("give --images DIR or --mcap FILE"),
    }
}

fn source_name(source: &Source) -> String {
    source
        .images
        .as_ref()
        .or(source.mcap.as_ref())
        .map_or_else(String::new, |p| p.display().to_string())
}

fn load_target(path: &Path) -> Result<TargetGeometry> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the target description {}", path.display()))?;
    let target = Target::from_toml(&text).with_context(|| format!("target {}", path.display()))?;
    Ok(target.geometry()?)
}

fn intrinsics(args: &IntrinsicsArgs, progress: &ProgressSink) -> Result<String> {
    let geometry = load_target(&args.target)?;
    let default_stream = if args.camera == CameraArg::Probe {
        StreamArg::Probe
    } else {
        StreamArg::Color
    };
    let frames = read_frames(&args.source, &args.recording, default_stream, progress)?;
    let detections = detect_all(&geometry, &frames, &source_name(&args.source), progress)?;

    let candidates: Vec<Candidate<'_>> = detections
        .iter()
        .map(|(index, detection)| Candidate {
            detection,
            image: &frames[*index].image,
        })
        .collect();
    let selection = select_views(&geometry, &candidates, &SelectionSettings::default())?;
    let accepted: Vec<Detection> = selection
        .accepted
        .iter()
        .map(|&i| detections[i].1.clone())
        .collect();

    let spinner = progress.spinner("optimising");
    let mut notes = String::new();
    let (model, rms_px, fits, circle) = if args.fisheye {
        let settings = FisheyeSettings {
            field_of_view_deg: args.field_deg,
            ..FisheyeSettings::default()
        };
        let calibration = calibrate_fisheye(&accepted, &settings)?;
        notes.push_str(&dropped_views(&calibration.dropped));
        let bands: Vec<String> = calibration
            .theta_histogram
            .iter()
            .map(|bin| format!("{:.0}–{:.0}°: {}", bin.from_deg, bin.to_deg, bin.points))
            .collect();
        notes.push_str(&format!(
            "corners reach {:.1}° off the axis (half field {:.1}°); corners per band: {}\n",
            calibration.max_theta_deg,
            calibration.field_deg,
            bands.join(", ")
        ));
        let circle =
            ImageCircle::of_fisheye(&calibration.camera, calibration.field_deg.to_radians());
        (
            CameraModel::KannalaBrandt(calibration.camera),
            calibration.rms_px,
            poses(&calibration.views),
            Some(circle),
        )
    } else {
        let settings = PinholeSettings {
            fix_k3: args.fix_k3,
            ..PinholeSettings::default()
        };
        let calibration = calibrate_pinhole(&accepted, &settings)?;
        notes.push_str(&dropped_views(&calibration.dropped));
        (
            CameraModel::Pinhole(calibration.camera),
            calibration.rms_px,
            poses(&calibration.views),
            None,
        )
    };
    drop(spinner);

    let residuals: Vec<ViewResiduals> = fits
        .iter()
        .filter_map(|(view, camera_from_target)| {
            let detection = accepted.iter().find(|d| &d.view == view)?;
            let (detected, reprojected): (Vec<DVec2>, Vec<DVec2>) = detection
                .object_points
                .iter()
                .zip(&detection.image_points)
                .filter_map(|(object, image)| {
                    let pixel = model.project(camera_from_target.transform_point(*object))?;
                    Some((*image, pixel))
                })
                .unzip();
            Some(ViewResiduals {
                view: view.clone(),
                detected_px: detected,
                reprojected_px: reprojected,
            })
        })
        .collect();
    let (_, max_px) = error_stats(&residuals);

    let mut summary = format!(
        "{} intrinsics from {} images of {} ({}): {} views used, reprojection RMS {rms_px:.3} px, \
         max {max_px:.3} px\n",
        args.camera.name(),
        frames.len(),
        source_name(&args.source),
        geometry.target().describe(),
        fits.len(),
    );
    summary.push_str(&camera_summary(args.camera.name(), &model));
    for rejected in &selection.rejected {
        summary.push_str(&format!(
            "  left out {}: {}\n",
            rejected.view, rejected.reason
        ));
    }
    summary.push_str(&notes);
    let coverage = &selection.coverage;
    let corners: Vec<DVec2> = accepted
        .iter()
        .flat_map(|d| d.image_points.iter().copied())
        .collect();
    summary.push_str(&format!("coverage:\n{}", coverage.render()));
    if let Some(advice) = coverage.advice() {
        summary.push_str(&format!("advice: {advice}\n"));
    }

    if let Some(dir) = &args.report {
        let background = selection
            .accepted
            .first()
            .map(|&i| &frames[detections[i].0].image);
        report::write_reprojection_png(
            &dir.join("reprojection.png"),
            model.width(),
            model.height(),
            background,
            &residuals,
            &ReprojectionPlot::default(),
        )?;
        report::write_coverage_png(
            &dir.join("coverage.png"),
            coverage,
            &corners,
            circle.as_ref(),
        )?;
        report::write_summary(dir, &summary)?;
    }
    write_calibration(&args.out, &args.camera.parts(model))?;
    summary.push_str(&format!("written: {}\n", args.out.display()));
    Ok(summary)
}

/// Each view's name and the target's pose in it.
fn poses(views: &[ViewFit]) -> Vec<(String, Rigid)> {
    views
        .iter()
        .map(|v| (v.view.clone(), v.camera_from_target))
        .collect()
}

/// One line per view left out of the fit.
fn dropped_views(dropped: &[DroppedView]) -> String {
    dropped
        .iter()
        .map(|d| format!("  dropped {}: {}\n", d.view, d.reason))
        .collect()
}

/// Detects the target in every frame; fails when it is found in none. Returns the index of
/// each frame with a detection and the detection.
fn detect_all(
    geometry: &TargetGeometry,
    frames: &[InputFrame],
    source: &str,
    progress: &ProgressSink,
) -> Result<Vec<(usize, Detection)>> {
    let detector = Detector::new(geometry)?;
    let bar = progress.bar(frames.len() as u64, "detecting", "views");
    let mut found = Vec::new();
    let mut first_failure = None;
    for (index, frame) in frames.iter().enumerate() {
        match detector.detect(&frame.label, &frame.image) {
            Ok(detection) => found.push((index, detection)),
            Err(error) => {
                tracing::debug!(view = %frame.label, "no detection: {error}");
                first_failure.get_or_insert(error);
            }
        }
        bar.step();
    }
    if found.is_empty() {
        let reason = first_failure.map_or_else(String::new, |e| format!(" (first: {e})"));
        bail!(
            "no {} detected in any of the {} images of {source}{reason}",
            geometry.target().describe(),
            frames.len()
        );
    }
    Ok(found)
}

/// The rig file the extrinsics are computed against; it must exist.
fn existing_rig(path: &Path) -> Result<RigCalibration> {
    read_existing(path)?.ok_or_else(|| {
        anyhow!(
            "{} does not exist: calibrate the cameras' intrinsics into it first \
             (relight-calibrate intrinsics --out {})",
            path.display(),
            path.display()
        )
    })
}

/// The camera's model in `rig`, or an error saying which intrinsics are missing.
fn camera_in(rig: &RigCalibration, camera: CameraArg, path: &Path) -> Result<CameraModel> {
    camera.model(rig).ok_or_else(|| {
        anyhow!(
            "{} has no {} intrinsics: calibrate them first (relight-calibrate intrinsics \
             --camera {})",
            path.display(),
            camera.name(),
            camera.name()
        )
    })
}

/// Fails, naming the first frame, unless every frame has the size `model` was calibrated at.
fn check_frame_size(
    frames: &[InputFrame],
    model: &CameraModel,
    camera: CameraArg,
    rig: &Path,
) -> Result<()> {
    let expected = (model.width(), model.height());
    match frames
        .iter()
        .find(|f| (f.image.width(), f.image.height()) != expected)
    {
        Some(frame) => bail!(
            "{} is {}x{} but the {} intrinsics in {} are for {}x{}",
            frame.label,
            frame.image.width(),
            frame.image.height(),
            camera.name(),
            rig.display(),
            expected.0,
            expected.1
        ),
        None => Ok(()),
    }
}

/// The pinhole model of `camera` in `rig` (registration needs pinholes).
fn pinhole_in(rig: &RigCalibration, camera: CameraArg, path: &Path) -> Result<Pinhole> {
    match camera_in(rig, camera, path)? {
        CameraModel::Pinhole(pinhole) => Ok(pinhole),
        CameraModel::KannalaBrandt(_) => bail!(
            "the {} camera in {} is a fish-eye; depth ↔ colour registration needs pinhole models",
            camera.name(),
            path.display()
        ),
    }
}

fn depth_color(args: &DepthColorArgs, progress: &ProgressSink) -> Result<String> {
    let rig = existing_rig(&args.out)?;
    let depth_camera = pinhole_in(&rig, CameraArg::Depth, &args.out)?;
    let color_camera = pinhole_in(&rig, CameraArg::Color, &args.out)?;
    let geometry = load_target(&args.target)?;
    let depth_frames = read_image_folder(&args.depth_images, progress)?;
    let color_frames = read_image_folder(&args.color_images, progress)?;
    ensure!(
        depth_frames.len() == color_frames.len(),
        "{} depth images in {} but {} colour images in {}: they are paired in file-name order, \
         one of each per pose of the target",
        depth_frames.len(),
        args.depth_images.display(),
        color_frames.len(),
        args.color_images.display()
    );
    let detector = Detector::new(&geometry)?;
    let bar = progress.bar(depth_frames.len() as u64, "detecting", "pairs");
    let mut pairs = Vec::new();
    let mut unseen = Vec::new();
    for (depth, color) in depth_frames.iter().zip(&color_frames) {
        match (
            detector.detect(&depth.label, &depth.image),
            detector.detect(&color.label, &color.image),
        ) {
            (Ok(d), Ok(c)) => pairs.push((d, c)),
            _ => unseen.push(format!("{} + {}", depth.label, color.label)),
        }
        bar.step();
    }
    drop(bar);
    ensure!(
        !pairs.is_empty(),
        "no {} seen in both images of any pair of {} and {}",
        geometry.target().describe(),
        args.depth_images.display(),
        args.color_images.display()
    );
    let stereo = calibrate_color_from_depth(&depth_camera, &color_camera, &pairs)?;
    let t = stereo.color_from_depth.translation;
    let mut summary = format!(
        "color_from_depth from {} of {} pairs: stereo RMS {:.3} px, translation ({:.4}, {:.4}, \
         {:.4}) m, rotation {:.3}°\n",
        stereo.pairs.len(),
        depth_frames.len(),
        stereo.rms_px,
        t.x,
        t.y,
        t.z,
        stereo
            .color_from_depth
            .rotation
            .angle_between(glam::Quat::IDENTITY)
            .to_degrees()
    );
    for pair in &stereo.pairs {
        summary.push_str(&format!(
            "  {} + {}: {} points, RMS {:.3} px (depth), {:.3} px (colour)\n",
            pair.depth_view, pair.color_view, pair.points, pair.depth_rms_px, pair.color_rms_px
        ));
    }
    for line in stereo.skipped.iter().chain(&unseen) {
        summary.push_str(&format!("  left out {line}\n"));
    }
    finish_extrinsics(
        &args.out,
        args.report.as_deref(),
        summary,
        CalibratedParts {
            color_from_depth: Some(stereo.color_from_depth),
            ..CalibratedParts::default()
        },
    )
}

fn probe_pose(args: &ProbeArgs, progress: &ProgressSink) -> Result<String> {
    let rig = existing_rig(&args.out)?;
    let probe = camera_in(&rig, CameraArg::Probe, &args.out)?;
    let geometry = load_target(&args.target)?;
    let frames = read_frames(&args.source, &args.recording, StreamArg::Probe, progress)?;
    check_frame_size(&frames, &probe, CameraArg::Probe, &args.out)?;
    let detections: Vec<Detection> =
        detect_all(&geometry, &frames, &source_name(&args.source), progress)?
            .into_iter()
            .map(|(_, d)| d)
            .collect();
    let pose = locate_probe(&probe, &geometry, &detections)?;
    let t = pose.world_from_probe.translation;
    let summary = format!(
        "world_from_probe from {} views ({} points) of {}: RMS {:.3} px, probe at ({:.4}, {:.4}, \
         {:.4}) m in the target's frame\n",
        detections.len(),
        pose.points,
        geometry.target().describe(),
        pose.rms_px,
        t.x,
        t.y,
        t.z
    );
    finish_extrinsics(
        &args.out,
        args.report.as_deref(),
        summary,
        CalibratedParts {
            world_from_probe: Some(pose.world_from_probe),
            ..CalibratedParts::default()
        },
    )
}

fn lamp_light(args: &LampArgs, progress: &ProgressSink) -> Result<String> {
    let rig = existing_rig(&args.out)?;
    let camera = camera_in(&rig, args.camera, &args.out)?;
    let dictionary: Dictionary = args
        .dictionary
        .parse()
        .map_err(|e| anyhow!("--dictionary: {e}"))?;
    ensure!(
        args.marker_size_m.is_finite() && args.marker_size_m > 0.0,
        "--marker-size-m must be a positive length"
    );
    let marker = LampMarker {
        dictionary,
        marker_id: args.marker_id,
        size_m: args.marker_size_m,
    };
    let default_stream = if args.camera == CameraArg::Probe {
        StreamArg::Probe
    } else {
        StreamArg::Color
    };
    let frames = read_frames(&args.source, &args.recording, default_stream, progress)?;
    check_frame_size(&frames, &camera, args.camera, &args.out)?;
    let bar = progress.bar(frames.len() as u64, "finding", "views");
    let mut observations = Vec::new();
    let mut unseen = Vec::new();
    for frame in &frames {
        match observe_lamp(&camera, &marker, &frame.label, &frame.image, args.threshold) {
            Ok(observation) => observations.push(observation),
            Err(error) => unseen.push(format!("{}: {error}", frame.label)),
        }
        bar.step();
    }
    drop(bar);
    ensure!(
        !observations.is_empty(),
        "the lamp (marker {} {} and a bulb at or above level {}) is in none of the {} images of \
         {}{}",
        marker.dictionary,
        marker.marker_id,
        args.threshold,
        frames.len(),
        source_name(&args.source),
        unseen
            .first()
            .map_or_else(String::new, |first| format!(" (first: {first})"))
    );
    let lamp = locate_lamp_light(&camera, &observations)?;
    let p = lamp.light_in_marker;
    let mut summary = format!(
        "lamp_marker_from_light from {} of {} views: light centre ({:.4}, {:.4}, {:.4}) m in the \
         marker's frame, ray residual RMS {:.2} mm, views {:.0}° apart at most\n",
        observations.len(),
        frames.len(),
        p.x,
        p.y,
        p.z,
        lamp.rms_m * 1e3,
        lamp.spread_deg
    );
    for line in &unseen {
        summary.push_str(&format!("  left out {line}\n"));
    }
    finish_extrinsics(
        &args.out,
        args.report.as_deref(),
        summary,
        CalibratedParts {
            lamp_marker_from_light: Some(lamp.lamp_marker_from_light),
            ..CalibratedParts::default()
        },
    )
}

/// Writes the report (when asked) and then the calibration; returns the summary.
fn finish_extrinsics(
    out: &Path,
    report_dir: Option<&Path>,
    mut summary: String,
    parts: CalibratedParts,
) -> Result<String> {
    if let Some(dir) = report_dir {
        report::write_summary(dir, &summary)?;
    }
    write_calibration(out, &parts)?;
    summary.push_str(&format!("written: {}\n", out.display()));
    Ok(summary)
}

fn response(args: &ResponseArgs, progress: &ProgressSink) -> Result<String> {
    let mut frames = read_frames(&args.source, &args.recording, StreamArg::Probe, progress)?;
    let bracket: Vec<ProbeImage> = match &args.source.images {
        Some(dir) => {
            attach_exposures(dir, &mut frames)?;
            frames.iter().filter_map(probe_image).collect()
        }
        None => {
            let rgb: Vec<InputFrame> = frames.iter().map(as_rgb).collect();
            first_bracket(&rgb)
        }
    };
    ensure!(
        !bracket.is_empty(),
        "no frame of {} carries an exposure time",
        source_name(&args.source)
    );
    let spinner = progress.spinner("recovering the response");
    let calibration =
        calibrate_response(&bracket, &ResponseSettings::default()).with_context(|| {
            format!(
                "calibrating the response from {}",
                source_name(&args.source)
            )
        })?;
    drop(spinner);
    let mut summary = report::response_summary(&calibration);
    let mut parts = CalibratedParts {
        probe_response: Some(calibration.inverse_response.clone()),
        ..CalibratedParts::default()
    };
    if let (Some(patch), Some(known)) = (args.reference_patch, args.reference_radiance) {
        let response = calibration.response()?;
        let hdr = merge(&bracket, &response)?;
        let vignetting = match &args.vignetting {
            Some(path) => Some(read_vignetting(path, &args.out)?),
            None => None,
        };
        let scale = radiance_scale(&hdr, patch, known, vignetting.as_ref())?;
        summary.push_str(&format!(
            "  radiance scale: {scale:.6e} W/(m²·sr) per response unit per second (patch \
             {},{} {}x{} at {known} W/(m²·sr))\n",
            patch.x, patch.y, patch.width, patch.height
        ));
        parts.probe_radiance_scale = Some(scale);
    } else {
        summary.push_str("  radiance scale: not measured (relative units, 1)\n");
    }
    if let Some(dir) = &args.report {
        report::write_response_png(&dir.join("response.png"), &calibration)?;
        report::write_summary(dir, &summary)?;
    }
    write_calibration(&args.out, &parts)?;
    summary.push_str(&format!("written: {}\n", args.out.display()));
    Ok(summary)
}

/// A grey frame as RGB (the three channels equal), so that it can be a probe exposure.
fn as_rgb(frame: &InputFrame) -> InputFrame {
    if frame.image.format() != PixelFormat::Mono8 {
        return frame.clone();
    }
    let mut image = Image::new(frame.image.width(), frame.image.height(), PixelFormat::Rgb8);
    if let (Some(grey), Some(rgb)) = (frame.image.as_u8(), image.as_u8_mut()) {
        for (g, px) in grey.iter().zip(rgb.chunks_exact_mut(3)) {
            px.fill(*g);
        }
    }
    InputFrame {
        image,
        ..frame.clone()
    }
}

fn probe_image(frame: &InputFrame) -> Option<ProbeImage> {
    as_rgb(frame).probe_image()
}

fn vignetting(args: &VignettingArgs, progress: &ProgressSink) -> Result<String> {
    let rig = read_existing(&args.rig)?
        .ok_or_else(|| anyhow!("{} does not exist", args.rig.display()))?;
    let model = args.camera.model(&rig).ok_or_else(|| {
        anyhow!(
            "{} has no {} camera: calibrate its intrinsics first (relight-calibrate intrinsics)",
            args.rig.display(),
            args.camera.name()
        )
    })?;
    let response = if args.linear {
        Response::linear()
    } else if args.camera == CameraArg::Probe && !rig.probe_response.is_empty() {
        Response::from_calibration(&rig)?
    } else {
        bail!(
            "no response curve for the {} camera in {}: calibrate it (relight-calibrate \
             response) or pass --linear for a linear camera",
            args.camera.name(),
            args.rig.display()
        );
    };
    let mut frames = read_frames(&args.source, &args.recording, StreamArg::Probe, progress)?;
    if let Some(dir) = &args.source.images {
        // Exposures are optional here: several exposures are merged, one is used as is.
        if attach_exposures(dir, &mut frames).is_err() {
            for frame in &mut frames {
                frame.exposure_us = None;
            }
        }
    }
    let exposures: Vec<u32> = frames.iter().filter_map(|f| f.exposure_us).collect();
    let bracketed = exposures.len() == frames.len() && exposures.iter().any(|&t| t != exposures[0]);
    let field = if bracketed {
        let bracket: Vec<ProbeImage> = frames.iter().filter_map(probe_image).collect();
        FlatField::from_hdr(&merge(&bracket, &response)?)
    } else {
        let images: Vec<Image> = frames.iter().map(|f| f.image.clone()).collect();
        FlatField::from_codes(&images, &response)?
    };
    let fit = fit_vignetting(&field, &model, &VignettingSettings::default())?;
    let mut summary = format!(
        "{} vignetting from {} images of {}{}\n",
        args.camera.name(),
        frames.len(),
        source_name(&args.source),
        if bracketed { " (merged bracket)" } else { "" }
    );
    summary.push_str(&report::vignetting_summary(&fit));
    if let Some(dir) = &args.report {
        report::write_summary(dir, &summary)?;
    }
    write_atomically(
        &args.out,
        vignetting_toml(args.camera, &args.rig, &fit.vignetting, fit.max_radius).as_bytes(),
    )?;
    summary.push_str(&format!("written: {}\n", args.out.display()));
    if args.camera == CameraArg::Probe {
        // The daemon divides the probe's fall-off out of every bracket it merges.
        let parts = CalibratedParts {
            probe_vignetting: Some(fit.vignetting.coefficients_f32()),
            ..CalibratedParts::default()
        };
        write_calibration(&args.rig, &parts)?;
        summary.push_str(&format!(
            "written: {} (probe_vignetting)\n",
            args.rig.display()
        ));
    }
    Ok(summary)
}

/// What `vignetting` writes (see [`vignetting_toml`]).
#[derive(Debug, serde::Deserialize)]
struct VignettingFile {
    camera: String,
    coefficients: Vec<f32>,
}

/// The probe's vignetting from a file `vignetting` wrote, about the probe model in `rig`.
fn read_vignetting(path: &Path, rig: &Path) -> Result<Vignetting> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the vignetting {}", path.display()))?;
    let file: VignettingFile =
        toml::from_str(&text).with_context(|| format!("vignetting {}", path.display()))?;
    ensure!(
        file.camera == CameraArg::Probe.name(),
        "{} is the vignetting of the {} camera, not the probe's",
        path.display(),
        file.camera
    );
    let probe = read_existing(rig)?.and_then(|r| r.probe).ok_or_else(|| {
        anyhow!(
            "{} holds no probe intrinsics, which the vignetting is relative to",
            rig.display()
        )
    })?;
    Ok(Vignetting::new(&probe, &file.coefficients))
}

/// The vignetting file: the coefficients and what they mean, until the rig file has a field
/// for them.
fn vignetting_toml(camera: CameraArg, rig: &Path, v: &Vignetting, max_radius: f64) -> String {
    let [a1, a2, a3] = v.coefficients;
    format!(
        "# Vignetting V(r) = 1 + a1 r² + a2 r⁴ + a3 r⁶ of the {camera} camera of {rig}:\n\
         # r² = ((u − cx) / fx)² + ((v − cy) / fy)² with that camera's intrinsics; a pixel records\n\
         # radiance × V(r). Fitted up to r = {max_radius:.4}; extrapolated beyond.\n\
         camera = \"{camera}\"\n\
         coefficients = [{a1:e}, {a2:e}, {a3:e}]\n\
         max_radius = {max_radius}\n",
        camera = camera.name(),
        rig = rig.display(),
    )
}

/// Renders a target's print at `dpi` with a white margin, black on white, 8-bit grey.
fn render_target(args: &RenderTargetArgs) -> Result<String> {
    ensure!(
        args.dpi.is_finite() && args.dpi >= 50.0 && args.dpi <= 2400.0,
        "--dpi {} is outside 50–2400",
        args.dpi
    );
    ensure!(
        args.margin_mm.is_finite() && args.margin_mm >= 0.0,
        "--margin-mm must be a non-negative length"
    );
    let geometry = load_target(&args.target)?;
    let print = geometry.print();
    let metres_per_dot = 0.0254 / args.dpi;
    let margin_m = args.margin_mm * 1e-3;
    let origin = print.min - DVec2::splat(margin_m);
    let size_m = print.max - print.min + DVec2::splat(2.0 * margin_m);
    let (width, height) = (
        (size_m.x / metres_per_dot).round() as u32,
        (size_m.y / metres_per_dot).round() as u32,
    );
    ensure!(
        u64::from(width) * u64::from(height) <= 400_000_000,
        "a {width}×{height} image is too large; lower --dpi"
    );
    let mut image = Image::new(width, height, PixelFormat::Mono8);
    let pixels = image
        .as_u8_mut()
        .ok_or_else(|| anyhow!("an 8-bit image has 8-bit pixels"))?;
    for (i, pixel) in pixels.iter_mut().enumerate() {
        let dot = DVec2::new(
            (i % width as usize) as f64 + 0.5,
            (i / width as usize) as f64 + 0.5,
        );
        let point = origin + dot * metres_per_dot;
        *pixel = if print.is_white(point).unwrap_or(true) {
            255
        } else {
            0
        };
    }
    let mat = relight_calibrate::input::mat_from_image(&image)?;
    report::write_png(&args.out, &mat)?;
    Ok(format!(
        "{}: {} at {} dpi, {width}x{height} px = {:.1} x {:.1} mm with the margin. Print at 100% \
         (no fit-to-page) and check one square or tag with a ruler: it must measure {:.2} mm.\n",
        args.out.display(),
        geometry.target().describe(),
        args.dpi,
        size_m.x * 1e3,
        size_m.y * 1e3,
        geometry.feature_m() * 1e3
    ))
}
