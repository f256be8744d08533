//! What a calibration run tells its user: a text summary, and PNG pictures drawn with OpenCV's
//! `imgproc` and written with `imwrite`:
//!
//! - **reprojection errors** over the image: per detected corner a dot where it was detected, a
//!   cross where the calibrated model reprojects it, and the error vector from one to the other
//!   magnified ([`ReprojectionPlot::arrow_scale`], printed in the legend), coloured from green
//!   (no error) through yellow to red (the largest error, but at least 0.05 px so that noise
//!   stays green; in the legend); errors that line up across the image betray a wrong model,
//!   random ones are noise;
//! - **coverage**: the views' corners accumulated over the image frame on the
//!   [`CoverageMap`]'s grid, each cell shaded by how many corners fell in it (empty cells in
//!   dark red: the model is extrapolated there), and for a fish-eye the image circle;
//! - **response**: the recovered inverse response curve on a log scale, the usable codes marked.
//!
//! Pictures are drawn at an integer multiple of the image size (at least 960 px wide) so that
//! sub-pixel errors stay visible; points are placed with OpenCV's fixed-point `shift` (1/16 px).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::DVec2;
use opencv::core::{Mat, Point, Rect, Scalar, Size, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use relight_core::Image;
use relight_core::camera::{CameraModel, KannalaBrandt};

use crate::input::mat_from_image;
use crate::photometric::ResponseCalibration;
use crate::views::CoverageMap;
use crate::vignetting::VignettingFit;

/// Why a report could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("OpenCV {operation}: {source}")]
    OpenCv {
        operation: &'static str,
        #[source]
        source: opencv::Error,
    },
    #[error("{path}: OpenCV could not encode a PNG there")]
    Encode { path: PathBuf },
    #[error("nothing to draw: {0}")]
    Empty(&'static str),
}

fn cv(operation: &'static str) -> impl FnOnce(opencv::Error) -> ReportError {
    move |source| ReportError::OpenCv { operation, source }
}

/// Fixed-point bits of drawn coordinates (OpenCV's `shift`).
const SHIFT: i32 = 4;
/// Smallest width of a drawn picture, pixels.
const MIN_CANVAS_WIDTH: u32 = 960;

/// One view's corners: where they were detected and where the calibration puts them.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewResiduals {
    pub view: String,
    pub detected_px: Vec<DVec2>,
    pub reprojected_px: Vec<DVec2>,
}

impl ViewResiduals {
    /// `|reprojected − detected|` of every corner, pixels.
    pub fn errors_px(&self) -> impl Iterator<Item = f64> + '_ {
        self.detected_px
            .iter()
            .zip(&self.reprojected_px)
            .map(|(d, r)| d.distance(*r))
    }
}

/// Root-mean-square and largest reprojection error over all views, pixels (0 for none).
pub fn error_stats(views: &[ViewResiduals]) -> (f64, f64) {
    let (mut sum_sq, mut n, mut max) = (0.0, 0usize, 0.0f64);
    for e in views.iter().flat_map(ViewResiduals::errors_px) {
        sum_sq += e * e;
        n += 1;
        max = max.max(e);
    }
    if n == 0 {
        (0.0, 0.0)
    } else {
        ((sum_sq / n as f64).sqrt(), max)
    }
}

/// A fish-eye's image circle: the ellipse where rays `half_field_rad` off the axis land.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageCircle {
    pub centre_px: DVec2,
    pub radii_px: DVec2,
}

impl ImageCircle {
    /// The circle of a Kannala–Brandt lens at `half_field_rad` off its axis (clamped to the
    /// lens's valid field).
    pub fn of_fisheye(model: &KannalaBrandt, half_field_rad: f64) -> Self {
        let theta_d = model.distort_theta(half_field_rad.min(model.max_theta()));
        Self {
            centre_px: DVec2::new(model.cx, model.cy),
            radii_px: DVec2::new(model.fx, model.fy) * theta_d,
        }
    }
}

/// How [`write_reprojection_png`] draws.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ReprojectionPlot {
    /// Error vectors are drawn this many times longer than they are; `None` picks the scale at
    /// which the 95th-percentile error spans 3% of the image diagonal.
    pub arrow_scale: Option<f64>,
}

/// Draws every view's reprojection errors over `background` (dimmed; a grey canvas of
/// `width × height` without one) and writes the PNG; returns the arrow scale used.
pub fn write_reprojection_png(
    path: &Path,
    width: u32,
    height: u32,
    background: Option<&Image>,
    views: &[ViewResiduals],
    plot: &ReprojectionPlot,
) -> Result<f64, ReportError> {
    let mut errors: Vec<f64> = views.iter().flat_map(ViewResiduals::errors_px).collect();
    if errors.is_empty() {
        return Err(ReportError::Empty("no reprojected corners"));
    }
    errors.sort_by(f64::total_cmp);
    let max_error = errors.last().copied().unwrap_or(0.0);
    let p95 = errors[(errors.len() - 1) * 95 / 100];
    let diagonal = f64::from(width).hypot(f64::from(height));
    let arrow_scale = plot
        .arrow_scale
        .unwrap_or_else(|| 0.03 * diagonal / p95.max(0.01));
    let (mut canvas, zoom) = canvas(width, height, background)?;
    let colour_max = max_error.max(0.05);
    for view in views {
        for (detected, reprojected) in view.detected_px.iter().zip(&view.reprojected_px) {
            let error = detected.distance(*reprojected);
            let colour = ramp(error / colour_max);
            let tip = *detected + (*reprojected - *detected) * arrow_scale;
            imgproc::line(
                &mut canvas,
                fixed(*detected, zoom),
                fixed(tip, zoom),
                colour,
                1,
                imgproc::LINE_AA,
                SHIFT,
            )
            .map_err(cv("line"))?;
            imgproc::circle(
                &mut canvas,
                fixed(*detected, zoom),
                2 << SHIFT,
                Scalar::new(255.0, 255.0, 255.0, 0.0),
                imgproc::FILLED,
                imgproc::LINE_AA,
                SHIFT,
            )
            .map_err(cv("circle"))?;
            cross(&mut canvas, *reprojected, zoom, colour)?;
        }
    }
    let (rms, _) = error_stats(views);
    let canvas = with_legend(
        &canvas,
        &[
            format!(
                "{} views, {} corners: RMS {rms:.3} px, max {max_error:.3} px",
                views.len(),
                errors.len()
            ),
            format!(
                "dot: detected, cross: reprojected, line: error x{arrow_scale:.0}; green 0 .. red {colour_max:.2} px"
            ),
        ],
    )?;
    write_png(path, &canvas)?;
    Ok(arrow_scale)
}

/// Draws the coverage of the views' corners (module docs) and writes the PNG.
pub fn write_coverage_png(
    path: &Path,
    coverage: &CoverageMap,
    corners_px: &[DVec2],
    circle: Option<&ImageCircle>,
) -> Result<(), ReportError> {
    let (mut canvas, zoom) = canvas(coverage.width, coverage.height, None)?;
    let most = coverage.counts.iter().copied().max().unwrap_or(0).max(1);
    let cell_w = f64::from(coverage.width) / f64::from(coverage.cols);
    let cell_h = f64::from(coverage.height) / f64::from(coverage.rows);
    for row in 0..coverage.rows {
        for col in 0..coverage.cols {
            let count = coverage.counts[(row * coverage.cols + col) as usize];
            let colour = if count == 0 {
                Scalar::new(30.0, 30.0, 110.0, 0.0)
            } else {
                // Dark to bright green with the share of the fullest cell.
                let t = f64::from(count) / f64::from(most);
                Scalar::new(40.0, 80.0 + 175.0 * t, 40.0, 0.0)
            };
            let x0 = (f64::from(col) * cell_w * f64::from(zoom)).round() as i32;
            let y0 = (f64::from(row) * cell_h * f64::from(zoom)).round() as i32;
            let x1 = (f64::from(col + 1) * cell_w * f64::from(zoom)).round() as i32;
            let y1 = (f64::from(row + 1) * cell_h * f64::from(zoom)).round() as i32;
            let cell = Rect::new(x0, y0, x1 - x0, y1 - y0);
            imgproc::rectangle(
                &mut canvas,
                cell,
                colour,
                imgproc::FILLED,
                imgproc::LINE_8,
                0,
            )
            .map_err(cv("rectangle"))?;
            imgproc::rectangle(
                &mut canvas,
                cell,
                Scalar::new(90.0, 90.0, 90.0, 0.0),
                1,
                imgproc::LINE_8,
                0,
            )
            .map_err(cv("rectangle"))?;
            imgproc::put_text(
                &mut canvas,
                &count.to_string(),
                Point::new(x0 + 4, y0 + 18),
                imgproc::FONT_HERSHEY_SIMPLEX,
                0.5,
                Scalar::new(230.0, 230.0, 230.0, 0.0),
                1,
                imgproc::LINE_AA,
                false,
            )
            .map_err(cv("putText"))?;
        }
    }
    for corner in corners_px {
        imgproc::circle(
            &mut canvas,
            fixed(*corner, zoom),
            (3 << SHIFT) / 2,
            Scalar::new(255.0, 255.0, 255.0, 0.0),
            imgproc::FILLED,
            imgproc::LINE_AA,
            SHIFT,
        )
        .map_err(cv("circle"))?;
    }
    if let Some(circle) = circle {
        let axes = circle.radii_px * f64::from(zoom) * f64::from(1 << SHIFT);
        imgproc::ellipse(
            &mut canvas,
            fixed(circle.centre_px, zoom),
            Size::new(axes.x.round() as i32, axes.y.round() as i32),
            0.0,
            0.0,
            360.0,
            Scalar::new(0.0, 200.0, 255.0, 0.0),
            2,
            imgproc::LINE_AA,
            SHIFT,
        )
        .map_err(cv("ellipse"))?;
    }
    let mut lines = vec![format!(
        "{} corners; {:.0}% of {}x{} cells hold one",
        corners_px.len(),
        100.0 * coverage.covered_fraction(),
        coverage.cols,
        coverage.rows
    )];
    if circle.is_some() {
        lines.push("orange: the lens's image circle".to_owned());
    }
    write_png(path, &with_legend(&canvas, &lines)?)
}

/// Plots the inverse response (log of relative exposure against code) and writes the PNG.
pub fn write_response_png(
    path: &Path,
    calibration: &ResponseCalibration,
) -> Result<(), ReportError> {
    let (w, h) = (768, 512);
    let (left, right, top, bottom) = (60.0, 20.0, 20.0, 40.0);
    let mut canvas =
        Mat::new_rows_cols_with_default(h, w, opencv::core::CV_8UC3, Scalar::all(24.0))
            .map_err(cv("canvas"))?;
    let table = &calibration.inverse_response;
    let logs: Vec<f64> = table
        .iter()
        .skip(1)
        .map(|&v| f64::from(v).max(1e-6).log10())
        .collect();
    let (lo, hi) = logs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if !(lo.is_finite() && hi > lo) {
        return Err(ReportError::Empty("a flat response curve"));
    }
    let at = |code: usize, log: f64| {
        DVec2::new(
            left + (f64::from(w) - left - right) * code as f64 / 255.0,
            f64::from(h) - bottom - (f64::from(h) - top - bottom) * (log - lo) / (hi - lo),
        )
    };
    let usable = calibration.usable_codes.clone();
    for code in [usize::from(*usable.start()), usize::from(*usable.end())] {
        imgproc::line(
            &mut canvas,
            fixed(at(code, lo), 1),
            fixed(at(code, hi), 1),
            Scalar::new(80.0, 80.0, 80.0, 0.0),
            1,
            imgproc::LINE_AA,
            SHIFT,
        )
        .map_err(cv("line"))?;
    }
    let mut points = Vector::<Point>::new();
    for (i, &log) in logs.iter().enumerate() {
        points.push(fixed(at(i + 1, log), 1));
    }
    let mut curves = Vector::<Vector<Point>>::new();
    curves.push(points);
    imgproc::polylines(
        &mut canvas,
        &curves,
        false,
        Scalar::new(80.0, 220.0, 255.0, 0.0),
        2,
        imgproc::LINE_AA,
        SHIFT,
    )
    .map_err(cv("polylines"))?;
    let canvas = with_legend(
        &canvas,
        &[
            format!(
                "inverse response, log10 relative exposure {lo:.2} .. {hi:.2} over codes 1..255"
            ),
            format!(
                "usable codes {}..{} (grey lines), {} samples",
                usable.start(),
                usable.end(),
                calibration.samples
            ),
        ],
    )?;
    write_png(path, &canvas)
}

/// Text summary of a response calibration.
pub fn response_summary(calibration: &ResponseCalibration) -> String {
    let mut text = String::new();
    let usable = &calibration.usable_codes;
    let mut times = calibration.exposures_s.clone();
    times.sort_by(f64::total_cmp);
    let exposures: Vec<String> = times.iter().map(|t| format!("{:.3} ms", t * 1e3)).collect();
    let _ = writeln!(text, "response (OpenCV CalibrateRobertson)");
    let _ = writeln!(text, "  exposures: {}", exposures.join(", "));
    let _ = writeln!(
        text,
        "  samples: {} pixel-channels well exposed in two or more exposures",
        calibration.samples
    );
    let _ = writeln!(
        text,
        "  usable codes: {}..={} (outside: interpolated or quantisation-limited)",
        usable.start(),
        usable.end()
    );
    let table = &calibration.inverse_response;
    let _ = writeln!(
        text,
        "  I(1) = {:.5}, I(64) = {:.4}, I(128) = 1, I(192) = {:.4}, I(254) = {:.4}",
        table[1], table[64], table[192], table[254]
    );
    match calibration.channel_spread {
        Some(spread) => {
            let _ = writeln!(
                text,
                "  channels: each channel's own curve within {:.2}% of the shared one{}",
                100.0 * spread,
                if spread > 0.05 {
                    " — more than noise: the channels may not share one curve"
                } else {
                    ""
                }
            );
        }
        None => {
            let _ = writeln!(text, "  channels: no single channel reaches code 128");
        }
    }
    text
}

/// Text summary of a vignetting fit.
pub fn vignetting_summary(fit: &VignettingFit) -> String {
    let v = &fit.vignetting;
    let [a1, a2, a3] = v.coefficients;
    let mut text = String::new();
    let _ = writeln!(
        text,
        "vignetting V(r) = 1 + a1 r² + a2 r⁴ + a3 r⁶ about ({:.2}, {:.2}), r in focal lengths",
        v.cx, v.cy
    );
    let _ = writeln!(text, "  a1 = {a1:.6}, a2 = {a2:.6}, a3 = {a3:.6}");
    let _ = writeln!(
        text,
        "  fitted to r = {:.3} ({} pixels, {} outliers); V there = {:.3}",
        fit.max_radius,
        fit.pixels,
        fit.outliers,
        v.factor(fit.max_radius)
    );
    let _ = writeln!(
        text,
        "  residuals: σ = {:.3}% of the level (robust)",
        100.0 * fit.residual_sigma
    );
    text
}

/// Text summary of a camera model.
pub fn camera_summary(name: &str, model: &CameraModel) -> String {
    let mut text = String::new();
    match model {
        CameraModel::Pinhole(p) => {
            let _ = writeln!(
                text,
                "{name}: pinhole {}x{}, fx {:.3}, fy {:.3}, cx {:.3}, cy {:.3}, k1 {:.5}, k2 {:.5}, \
                 p1 {:.6}, p2 {:.6}, k3 {:.5}",
                p.width, p.height, p.fx, p.fy, p.cx, p.cy, p.k1, p.k2, p.p1, p.p2, p.k3
            );
        }
        CameraModel::KannalaBrandt(k) => {
            let _ = writeln!(
                text,
                "{name}: Kannala–Brandt {}x{}, fx {:.3}, fy {:.3}, cx {:.3}, cy {:.3}, k1 {:.6}, \
                 k2 {:.6}, k3 {:.6}, k4 {:.6}",
                k.width, k.height, k.fx, k.fy, k.cx, k.cy, k.k1, k.k2, k.k3, k.k4
            );
        }
    }
    text
}

/// Writes `text` to `<dir>/summary.txt` (creating `dir`); returns the path.
pub fn write_summary(dir: &Path, text: &str) -> Result<PathBuf, ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Io {
        path: dir.to_owned(),
        source,
    })?;
    let path = dir.join("summary.txt");
    std::fs::write(&path, text).map_err(|source| ReportError::Io {
        path: path.clone(),
        source,
    })?;
    Ok(path)
}

/// A BGR canvas `zoom` times the image size: the image dimmed to 40%, or mid-grey.
fn canvas(width: u32, height: u32, background: Option<&Image>) -> Result<(Mat, u32), ReportError> {
    let zoom = MIN_CANVAS_WIDTH.div_ceil(width.max(1)).max(1);
    let size = Size::new((width * zoom) as i32, (height * zoom) as i32);
    let Some(image) = background else {
        let grey = Mat::new_size_with_default(size, opencv::core::CV_8UC3, Scalar::all(48.0))
            .map_err(cv("canvas"))?;
        return Ok((grey, zoom));
    };
    let source = mat_from_image(image).map_err(|e| {
        ReportError::Empty(match e {
            crate::input::InputError::Unsupported { .. } => "a background that is not 8-bit",
            _ => "a background OpenCV cannot wrap",
        })
    })?;
    let mut colour = Mat::default();
    if source.channels() == 1 {
        imgproc::cvt_color_def(&source, &mut colour, imgproc::COLOR_GRAY2BGR)
            .map_err(cv("grey to BGR"))?;
    } else {
        colour = source;
    }
    let mut resized = Mat::default();
    imgproc::resize(
        &colour,
        &mut resized,
        size,
        0.0,
        0.0,
        imgproc::INTER_NEAREST,
    )
    .map_err(cv("resize"))?;
    let mut dimmed = Mat::default();
    resized
        .convert_to(&mut dimmed, -1, 0.4, 0.0)
        .map_err(cv("dimming"))?;
    Ok((dimmed, zoom))
}

/// A pixel (OpenCV convention) of the image as a fixed-point point of the zoomed canvas. Pixel
/// centre `(i, j)` covers `[i − ½, i + ½]`, which the canvas shows as `[zoom·i, zoom·(i + 1)]`.
fn fixed(pixel: DVec2, zoom: u32) -> Point {
    let z = f64::from(zoom);
    let scaled = (pixel + 0.5) * z - 0.5;
    let f = f64::from(1 << SHIFT);
    Point::new((scaled.x * f).round() as i32, (scaled.y * f).round() as i32)
}

fn cross(canvas: &mut Mat, pixel: DVec2, zoom: u32, colour: Scalar) -> Result<(), ReportError> {
    let arm = 3.0 / f64::from(zoom);
    for (a, b) in [
        (DVec2::new(-arm, -arm), DVec2::new(arm, arm)),
        (DVec2::new(-arm, arm), DVec2::new(arm, -arm)),
    ] {
        imgproc::line(
            canvas,
            fixed(pixel + a, zoom),
            fixed(pixel + b, zoom),
            colour,
            1,
            imgproc::LINE_AA,
            SHIFT,
        )
        .map_err(cv("line"))?;
    }
    Ok(())
}

/// Green (0) → yellow (½) → red (1), BGR.
fn ramp(t: f64) -> Scalar {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let red = (2.0 * t).min(1.0) * 255.0;
    let green = (2.0 * (1.0 - t)).min(1.0) * 255.0;
    Scalar::new(0.0, green, red, 0.0)
}

/// The canvas below a dark band holding the text lines (so the legend hides nothing).
fn with_legend(canvas: &Mat, lines: &[String]) -> Result<Mat, ReportError> {
    let band = 8 + 20 * lines.len() as i32;
    let mut out = Mat::new_rows_cols_with_default(
        canvas.rows() + band,
        canvas.cols(),
        canvas.typ(),
        Scalar::all(0.0),
    )
    .map_err(cv("canvas"))?;
    {
        let mut below = out
            .roi_mut(Rect::new(0, band, canvas.cols(), canvas.rows()))
            .map_err(cv("roi"))?;
        canvas.copy_to(&mut below).map_err(cv("copyTo"))?;
    }
    for (i, line) in lines.iter().enumerate() {
        imgproc::put_text(
            &mut out,
            line,
            Point::new(8, 20 + 20 * i as i32),
            imgproc::FONT_HERSHEY_SIMPLEX,
            0.5,
            Scalar::all(235.0),
            1,
            imgproc::LINE_AA,
            false,
        )
        .map_err(cv("putText"))?;
    }
    Ok(out)
}

/// Writes `image` as PNG, creating the directory.
pub fn write_png(path: &Path, image: &Mat) -> Result<(), ReportError> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| ReportError::Io {
            path: dir.to_owned(),
            source,
        })?;
    }
    let written = imgcodecs::imwrite(path, image, &Vector::new()).map_err(cv("imwrite"))?;
    if written {
        Ok(())
    } else {
        Err(ReportError::Encode {
            path: path.to_owned(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn views() -> Vec<ViewResiduals> {
        vec![ViewResiduals {
            view: "a.png".into(),
            detected_px: vec![DVec2::new(10.0, 10.0), DVec2::new(50.0, 30.0)],
            reprojected_px: vec![DVec2::new(10.3, 10.4), DVec2::new(50.0, 30.0)],
        }]
    }

    #[test]
    fn error_statistics() {
        let (rms, max) = error_stats(&views());
        assert!((max - 0.5).abs() < 1e-12);
        assert!((rms - (0.25f64 / 2.0).sqrt()).abs() < 1e-12);
        assert_eq!(error_stats(&[]), (0.0, 0.0));
    }

    #[test]
    fn reprojection_and_coverage_pictures_are_written_and_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("reprojection.png");
        let scale =
            write_reprojection_png(&path, 64, 48, None, &views(), &ReprojectionPlot::default())
                .unwrap();
        assert!(scale > 1.0);
        let png = imgcodecs::imread(&path, imgcodecs::IMREAD_COLOR).unwrap();
        // Zoomed 15× (to 960 px wide) below a legend band of two lines (48 px).
        let band = 48;
        assert_eq!((png.cols(), png.rows()), (64 * 15, 48 * 15 + band));
        // The detected corner at (10, 10) is drawn white in the zoomed canvas.
        let centre = png
            .at_2d::<opencv::core::Vec3b>(band + 10 * 15 + 7, 10 * 15 + 7)
            .unwrap();
        assert_eq!(centre.0, [255, 255, 255]);

        let mut coverage = CoverageMap::new(64, 48, 4, 3);
        let corners = [DVec2::new(5.0, 5.0), DVec2::new(60.0, 40.0)];
        coverage.add(&corners);
        let circle = ImageCircle {
            centre_px: DVec2::new(31.5, 23.5),
            radii_px: DVec2::new(20.0, 20.0),
        };
        let path = dir.path().join("coverage.png");
        write_coverage_png(&path, &coverage, &corners, Some(&circle)).unwrap();
        assert!(
            imgcodecs::imread(&path, imgcodecs::IMREAD_COLOR)
                .unwrap()
                .cols()
                > 0
        );
        assert!(matches!(
            write_reprojection_png(&path, 64, 48, None, &[], &ReprojectionPlot::default()),
            Err(ReportError::Empty(_))
        ));
    }

    #[test]
    fn the_ramp_runs_from_green_to_red() {
        assert_eq!(ramp(0.0), Scalar::new(0.0, 255.0, 0.0, 0.0));
        assert_eq!(ramp(0.5), Scalar::new(0.0, 255.0, 255.0, 0.0));
        assert_eq!(ramp(1.0), Scalar::new(0.0, 0.0, 255.0, 0.0));
        assert_eq!(ramp(f64::NAN), ramp(1.0));
    }
}
