//! Finding a target's points in an image.
//!
//! - **Chessboard**: `findChessboardCorners` (adaptive threshold, fast); if it finds nothing,
//!   `findChessboardCornersSB` (Duda & Frese, "Accurate Detection and Localization of
//!   Checkerboard Corners for Calibration", BMVC 2018), which copes with stronger distortion and
//!   blur. OpenCV orders the corners row by row but may start at either end; the order is fixed
//!   here by the print (the square beyond corner 0 is black, the one beyond the last corner white
//!   on a board with one even count), so that a point id always names the same printed corner.
//! - **ChArUco**: `aruco::detectMarkers`, then `aruco::interpolateCornersCharuco` (local
//!   homographies from the markers).
//! - **AprilTag grid**: `aruco::detectMarkers` with `DICT_APRILTAG_36h11`; the four corners of
//!   every tag of the grid.
//!
//! OpenCV's positions are then refined here, in the largest window that holds only that
//! corner at the local scale: saddles (chessboard, ChArUco) by [`refine_saddle`], tag corners by
//! [`refine_quad`]. On the synthetic views of the tests (640 × 480, planned poses) the points
//! land 0.009 px (chessboard), 0.018 px (ChArUco) and 0.065 px (AprilTag grid) RMS from the
//! truth, where OpenCV's own sub-pixel steps left 0.044 px (`cornerSubPix`; 0.10–0.18 px from
//! `findChessboardCornersSB` with `CALIB_CB_ACCURACY`), 0.7 px (ChArUco: OpenCV 4.6 shifts its
//! corners by half a pixel around `cornerSubPix` and back, opencv/opencv#28380) and 0.2 px
//! (tag corners pulled inwards by `cornerSubPix`).
//!
//! [`Detection`] and the size check are plain Rust; the detector itself needs the `opencv`
//! feature.

use glam::{DVec2, DVec3};
use relight_core::{Image, PixelFormat};

use crate::error::CalibrationError;

/// A target's points found in one view.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    /// Which view (a file name, a frame number): named in reports and errors.
    pub view: String,
    pub width: u32,
    pub height: u32,
    /// Point ids ([`crate::target::TargetGeometry::ids`]), one per point below.
    pub ids: Vec<u32>,
    /// Pixels, OpenCV convention (centre of the top-left pixel at (0, 0)).
    pub image_points: Vec<DVec2>,
    /// The same points in the target frame, metres.
    pub object_points: Vec<DVec3>,
}

impl Detection {
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// The pixel of point `id`, if it was found.
    pub fn pixel_of(&self, id: u32) -> Option<DVec2> {
        self.ids
            .iter()
            .position(|&i| i == id)
            .and_then(|index| self.image_points.get(index).copied())
    }
}

/// The common image size of a camera's detections; names the first view that differs.
pub fn common_size(detections: &[Detection]) -> Result<(u32, u32), CalibrationError> {
    let Some(first) = detections.first() else {
        return Err(CalibrationError::TooFewViews {
            what: "a calibration",
            found: 0,
            minimum: 1,
        });
    };
    for d in detections {
        if (d.width, d.height) != (first.width, first.height) {
            return Err(CalibrationError::MixedImageSizes {
                first_view: first.view.clone(),
                first_width: first.width,
                first_height: first.height,
                view: d.view.clone(),
                width: d.width,
                height: d.height,
            });
        }
    }
    Ok((first.width, first.height))
}

/// 8-bit luma of a `Mono8` or `Rgb8` image (Rec. 601 weights), row-major.
pub fn luma(view: &str, image: &Image) -> Result<Vec<u8>, CalibrationError> {
    let unsupported = || CalibrationError::UnsupportedFormat {
        view: view.to_owned(),
        format: image.format(),
    };
    let bytes = image.as_u8().ok_or_else(unsupported)?;
    match image.format() {
        PixelFormat::Mono8 => Ok(bytes.to_vec()),
        PixelFormat::Rgb8 => Ok(bytes
            .chunks_exact(3)
            .map(|p| {
                ((77 * u32::from(p[0]) + 150 * u32::from(p[1]) + 29 * u32::from(p[2]) + 128) >> 8)
                    as u8
            })
            .collect()),
        _ => Err(unsupported()),
    }
}

/// Bilinear sample of a row-major 8-bit image at a pixel position (OpenCV convention), edges
/// clamped.
pub(crate) fn sample_bilinear(luma: &[u8], width: usize, height: usize, p: DVec2) -> f64 {
    if width == 0 || height == 0 {
        return 0.0;
    }
    let x = p.x.clamp(0.0, (width - 1) as f64);
    let y = p.y.clamp(0.0, (height - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let at = |xx: usize, yy: usize| f64::from(luma[yy * width + xx]);
    let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
    let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
    top * (1.0 - fy) + bottom * fy
}

/// Gaussian pre-smoothing of [`refine_saddle`], pixels.
const SADDLE_SMOOTHING_PX: f64 = 1.5;
/// Width of [`refine_saddle`]'s Gaussian weights as a fraction of its radius: the quadratic
/// describes a blurred X-junction only near its centre, so the fit leans on the centre.
const SADDLE_WEIGHT_SCALE: f64 = 0.3;

/// Sub-pixel centre of a chessboard saddle (an X-junction, where two black and two white squares
/// meet) near `start`, after Lucchese & Mitra, "Using saddle points for subpixel feature
/// detection in camera calibration targets" (APCCAS 2002): smooth with a Gaussian (σ = 1.5 px),
/// fit `z = a x² + b xy + c y² + d x + e y + f` by least squares to the pixels within `radius`
/// of the current estimate (Gaussian weights, σ = 0.3 radius), move to the quadratic's saddle,
/// repeat until it moves less than 10⁻⁴ px.
///
/// An X-junction is point-symmetric about its centre whatever the angle between its edges, so at
/// the centre the fit's linear terms vanish and the estimate is unbiased under perspective. On
/// synthetic views (18 planned views, 640 × 480) chessboard corners land 0.009 px RMS from the
/// truth and ChArUco corners 0.02 px, against 0.044 and 0.08 px for `cornerSubPix`; the
/// smoothing and weights were chosen on those views. `None` when the patch leaves the image, is
/// not a saddle, or the estimate wanders out of the window.
pub fn refine_saddle(
    luma: &[u8],
    width: usize,
    height: usize,
    start: DVec2,
    radius: f64,
) -> Option<DVec2> {
    let sigma = SADDLE_SMOOTHING_PX;
    let blur_reach = (3.0 * sigma).ceil() as isize;
    let reach = radius.ceil() as isize + 1;
    let weight_sigma_sq = (SADDLE_WEIGHT_SCALE * radius).powi(2);
    let mut p = start;
    for _ in 0..20 {
        let (px, py) = (p.x.round() as isize, p.y.round() as isize);
        let (x0, y0) = (px - reach - blur_reach, py - reach - blur_reach);
        let (x1, y1) = (px + reach + blur_reach, py + reach + blur_reach);
        if x0 < 0 || y0 < 0 || x1 >= width as isize || y1 >= height as isize {
            return None;
        }
        let patch = smoothed_patch(luma, width, (x0, y0), (x1, y1), sigma);
        let patch_width = (x1 - x0 + 1) as usize;
        let mut normal = [[0.0; 6]; 6];
        let mut rhs = [0.0; 6];
        for y in (py - reach)..=(py + reach) {
            for x in (px - reach)..=(px + reach) {
                let offset = DVec2::new(x as f64, y as f64) - p;
                let distance_sq = offset.length_squared();
                if distance_sq > radius * radius {
                    continue;
                }
                let weight = (-distance_sq / (2.0 * weight_sigma_sq)).exp();
                let value = patch[(y - y0) as usize * patch_width + (x - x0) as usize];
                let (u, v) = (offset.x, offset.y);
                let basis = [u * u, u * v, v * v, u, v, 1.0];
                for i in 0..6 {
                    for j in 0..6 {
                        normal[i][j] += weight * basis[i] * basis[j];
                    }
                    rhs[i] += weight * basis[i] * value;
                }
            }
        }
        let [a, b, c, d, e, _] = crate::linalg::solve(normal, rhs)?;
        // ∇z = 0: [2a b; b 2c] · offset = −[d; e]; a saddle has a negative determinant.
        let det = 4.0 * a * c - b * b;
        if det.is_nan() || det >= 0.0 {
            return None;
        }
        let step = DVec2::new(-(2.0 * c * d - b * e) / det, -(2.0 * a * e - b * d) / det);
        p += step;
        if !p.is_finite() || p.distance(start) > radius {
            return None;
        }
        if step.length() < 1e-4 {
            return Some(p);
        }
    }
    Some(p)
}

/// Sub-pixel corners of a square marker's black border from its approximate corners (in order
/// round the square): each side's edge is located about once a pixel along its middle 84 %,
/// from the profile across it within `reach_px` of the side (at most half the border's one cell
/// inside: the data bits beyond it would bias the profile) as the point that splits the profile's dark and bright
/// areas; each corner is where lines fitted (total least squares) to the halves of its two
/// sides next to it meet.
///
/// A square's corner is not a saddle: `cornerSubPix` pulls it ~0.2 px inwards along the
/// diagonal (its gradient condition is met by the blurred corner's rounded tip), where the
/// area split of a symmetrically blurred straight edge stays on the edge. `None` when a side
/// has too few clear edges or two sides are parallel.
pub fn refine_quad(
    luma: &[u8],
    width: usize,
    height: usize,
    corners: [DVec2; 4],
    reach_px: f64,
) -> Option<[DVec2; 4]> {
    // Profiles centred on the edges are symmetric, where the split is exact even when the
    // ends fall short of the plateaus: a second and third pass start from the first's corners.
    let mut refined = corners;
    for _ in 0..3 {
        let next = refine_quad_once(luma, width, height, refined, reach_px)?;
        if next
            .iter()
            .zip(&corners)
            .any(|(n, c)| n.distance(*c) > 2.0 * reach_px.max(1.0))
        {
            return None;
        }
        refined = next;
    }
    Some(refined)
}

fn refine_quad_once(
    luma: &[u8],
    width: usize,
    height: usize,
    corners: [DVec2; 4],
    reach_px: f64,
) -> Option<[DVec2; 4]> {
    const STEP: f64 = 0.25;
    const SMOOTHING_PX: f64 = 0.7;
    let centre = corners.iter().copied().sum::<DVec2>() / 4.0;
    let samples = (reach_px / STEP).round().max(2.0) as i32;
    // A lightly smoothed copy of the region: bilinear interpolation of raw pixels bends a
    // blurred edge's profile by up to 0.08 px depending on where the edge falls in a pixel;
    // smoothing (which keeps areas) makes the interpolation faithful.
    let (lo, hi) = corners.iter().fold(
        (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
        |(lo, hi), c| (lo.min(*c), hi.max(*c)),
    );
    let margin = reach_px + 2.0 + (3.0 * SMOOTHING_PX).ceil();
    let (x0, y0) = (
        (lo.x - margin).floor() as isize,
        (lo.y - margin).floor() as isize,
    );
    let (x1, y1) = (
        (hi.x + margin).ceil() as isize,
        (hi.y + margin).ceil() as isize,
    );
    if !(x0 >= 0 && y0 >= 0 && x1 < width as isize && y1 < height as isize) {
        return None;
    }
    let patch = smoothed_patch(luma, width, (x0, y0), (x1, y1), SMOOTHING_PX);
    let patch_width = (x1 - x0 + 1) as usize;
    let patch_height = (y1 - y0 + 1) as usize;
    let sample = |p: DVec2| {
        let local = p - DVec2::new(x0 as f64, y0 as f64);
        let x = local.x.clamp(0.0, (patch_width - 1) as f64);
        let y = local.y.clamp(0.0, (patch_height - 1) as f64);
        let (ix, iy) = (x.floor() as usize, y.floor() as usize);
        let (jx, jy) = (
            (ix + 1).min(patch_width - 1),
            (iy + 1).min(patch_height - 1),
        );
        let (fx, fy) = (x - ix as f64, y - iy as f64);
        let at = |xx: usize, yy: usize| patch[yy * patch_width + xx];
        let top = at(ix, iy) * (1.0 - fx) + at(jx, iy) * fx;
        let bottom = at(ix, jy) * (1.0 - fx) + at(jx, jy) * fx;
        top * (1.0 - fy) + bottom * fy
    };
    // Edge points along each side, with their place along it (0 at the side's first corner).
    let mut edges: [Vec<(f64, DVec2)>; 4] = Default::default();
    for (side, points) in edges.iter_mut().enumerate() {
        let (a, b) = (corners[side], corners[(side + 1) % 4]);
        let length = a.distance(b);
        if length.is_nan() || length <= 4.0 {
            return None;
        }
        let along = (b - a) / length;
        let mut outward = along.perp();
        if outward.dot(0.5 * (a + b) - centre) < 0.0 {
            outward = -outward;
        }
        let count = ((0.84 * length / 1.0) as usize).clamp(8, 48);
        for i in 0..count {
            let t = 0.08 + 0.84 * (i as f64 + 0.5) / count as f64;
            let base = a.lerp(b, t);
            let profile: Vec<f64> = (-samples..=samples)
                .map(|k| sample(base + outward * (f64::from(k) * STEP)))
                .collect();
            let (dark, bright) = (profile[0], profile[profile.len() - 1]);
            // A dark inside and a bright outside, clearly apart.
            if bright - dark <= 20.0 {
                continue;
            }
            // For a step at offset e, the bright fraction integrates to (reach − e) over
            // [−reach, reach]. The integral of the interpolated pixels keeps each pixel's
            // share of the edge, where the half-way crossing of the interpolation is off by up
            // to 0.08 px depending on where the edge falls within a pixel.
            let bright_share: f64 = profile
                .windows(2)
                .map(|w| 0.5 * ((w[0] - dark) + (w[1] - dark)) / (bright - dark) * STEP)
                .sum();
            let reach = f64::from(samples) * STEP;
            let offset = reach - bright_share;
            if offset.abs() < reach {
                points.push((t, base + outward * offset));
            }
        }
    }
    // Each corner from the halves of its two sides next to it: lens distortion bends a side,
    // and a line through its near half meets the other's close to where the curves meet.
    let mut refined = [DVec2::ZERO; 4];
    for (k, corner) in refined.iter_mut().enumerate() {
        let before = fit_line(edges[(k + 3) % 4].iter().filter(|(t, _)| *t >= 0.5))?;
        let after = fit_line(edges[k].iter().filter(|(t, _)| *t <= 0.5))?;
        let ((p, u), (q, v)) = (before, after);
        let denominator = u.perp_dot(v);
        if denominator.abs() < 1e-6 {
            return None;
        }
        *corner = p + u * ((q - p).perp_dot(v) / denominator);
        if !corner.is_finite() {
            return None;
        }
    }
    Some(refined)
}

/// Total-least-squares line through at least three points: a point on it and its direction.
fn fit_line<'a>(points: impl Iterator<Item = &'a (f64, DVec2)>) -> Option<(DVec2, DVec2)> {
    let points: Vec<DVec2> = points.map(|(_, p)| *p).collect();
    if points.len() < 3 {
        return None;
    }
    let mean = points.iter().copied().sum::<DVec2>() / points.len() as f64;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in &points {
        let d = *p - mean;
        sxx += d.x * d.x;
        sxy += d.x * d.y;
        syy += d.y * d.y;
    }
    // Principal direction of the scatter.
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    Some((mean, DVec2::new(angle.cos(), angle.sin())))
}

/// The image between two corners (inclusive), smoothed by a separable Gaussian; the caller
/// keeps `3σ` of margin inside the image.
fn smoothed_patch(
    luma: &[u8],
    width: usize,
    (x0, y0): (isize, isize),
    (x1, y1): (isize, isize),
    sigma: f64,
) -> Vec<f64> {
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-((k * k) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = kernel.iter().sum();
    let (w, h) = ((x1 - x0 + 1) as usize, (y1 - y0 + 1) as usize);
    let at = |x: isize, y: isize| f64::from(luma[y as usize * width + x as usize]);
    let mut rows = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (gx, gy) = (x0 + x as isize, y0 + y as isize);
            let mut sum = 0.0;
            for (k, weight) in kernel.iter().enumerate() {
                let sx = (gx + k as isize - radius).clamp(x0, x1);
                sum += weight * at(sx, gy);
            }
            rows[y * w + x] = sum / total;
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut sum = 0.0;
            for (k, weight) in kernel.iter().enumerate() {
                let sy = (y as isize + k as isize - radius).clamp(0, h as isize - 1) as usize;
                sum += weight * rows[sy * w + x];
            }
            out[y * w + x] = sum / total;
        }
    }
    out
}

#[cfg(feature = "opencv")]
pub use cv::{Detector, MarkerCorners, detect_markers};

#[cfg(feature = "opencv")]
mod cv {
    use std::fmt;

    use glam::{DVec2, DVec3};
    use opencv::aruco;
    use opencv::calib3d;
    use opencv::core::{Mat, Point2f, Ptr, Size, Vector};
    use opencv::prelude::*;
    use relight_core::Image;

    use super::{Detection, luma, refine_quad, refine_saddle, sample_bilinear};
    use crate::error::CalibrationError;
    use crate::target::{Dictionary, Target, TargetGeometry, opencv_dictionary};

    /// Finds one target's points in images.
    pub struct Detector {
        geometry: TargetGeometry,
        kind: Kind,
    }

    enum Kind {
        Chessboard {
            cols: i32,
            rows: i32,
        },
        Charuco {
            dictionary: Ptr<aruco::Dictionary>,
            board: Ptr<aruco::CharucoBoard>,
            parameters: Ptr<aruco::DetectorParameters>,
        },
        AprilGrid {
            dictionary: Ptr<aruco::Dictionary>,
            parameters: Ptr<aruco::DetectorParameters>,
            first_id: u32,
            count: u32,
        },
    }

    impl fmt::Debug for Detector {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.debug_struct("Detector")
                .field("target", self.geometry.target())
                .finish_non_exhaustive()
        }
    }

    impl Detector {
        pub fn new(geometry: &TargetGeometry) -> Result<Self, CalibrationError> {
            let kind = match geometry.target() {
                Target::Chessboard(c) => Kind::Chessboard {
                    cols: c.inner_cols as i32,
                    rows: c.inner_rows as i32,
                },
                Target::Charuco(c) => {
                    let dictionary = opencv_dictionary(c.dictionary)?;
                    let board = aruco::CharucoBoard::create(
                        c.squares_x as i32,
                        c.squares_y as i32,
                        c.square_m as f32,
                        c.marker_m as f32,
                        &dictionary,
                    )?;
                    Kind::Charuco {
                        dictionary,
                        board,
                        parameters: aruco::DetectorParameters::create()?,
                    }
                }
                Target::AprilGrid(g) => Kind::AprilGrid {
                    dictionary: opencv_dictionary(Dictionary::AprilTag36h11)?,
                    parameters: refined_parameters()?,
                    first_id: g.first_id,
                    count: g.cols * g.rows,
                },
            };
            Ok(Self {
                geometry: geometry.clone(),
                kind,
            })
        }

        pub fn geometry(&self) -> &TargetGeometry {
            &self.geometry
        }

        /// The target's points in one image; [`CalibrationError::NoTargetDetected`] when none
        /// are found.
        pub fn detect(&self, view: &str, image: &Image) -> Result<Detection, CalibrationError> {
            let gray_bytes = luma(view, image)?;
            let (width, height) = (image.width(), image.height());
            let gray = Mat::new_rows_cols_with_data(height as i32, width as i32, &gray_bytes)?
                .try_clone()?;
            let mut found: Vec<(u32, DVec2)> = match &self.kind {
                Kind::Chessboard { cols, rows } => {
                    chessboard(&gray, &gray_bytes, width, height, *cols, *rows)?
                }
                Kind::Charuco {
                    dictionary,
                    board,
                    parameters,
                } => charuco(&gray, dictionary, board, parameters)?,
                Kind::AprilGrid {
                    dictionary,
                    parameters,
                    first_id,
                    count,
                } => {
                    let Target::AprilGrid(grid) = self.geometry.target() else {
                        unreachable!("an AprilTag-grid detector holds an AprilTag grid")
                    };
                    // Half the border's one cell inside (the profile must not reach the data
                    // bits), as far outside.
                    let reach_m = 0.45 * (grid.tag_m / 8.0).min(grid.spacing_m);
                    markers(&gray, dictionary, parameters)?
                        .into_iter()
                        .filter(|m| (*first_id..first_id + count).contains(&m.marker_id))
                        .filter_map(|m| {
                            let side_px = side_length_px(&m.corners);
                            let reach_px = (reach_m * side_px / grid.tag_m).clamp(1.0, 10.0);
                            let refined = refine_quad(
                                &gray_bytes,
                                width as usize,
                                height as usize,
                                m.corners,
                                reach_px,
                            )?;
                            Some((0..4).map(move |k| (4 * m.marker_id + k as u32, refined[k])))
                        })
                        .flatten()
                        .collect()
                }
            };
            if !matches!(self.geometry.target(), Target::AprilGrid(_)) {
                refine((&gray_bytes, width, height), &self.geometry, &mut found)?;
            }
            let mut detection = Detection {
                view: view.to_owned(),
                width,
                height,
                ids: Vec::with_capacity(found.len()),
                image_points: Vec::with_capacity(found.len()),
                object_points: Vec::with_capacity(found.len()),
            };
            for (id, pixel) in found {
                if let Some(point) = self.geometry.point(id) {
                    detection.ids.push(id);
                    detection.image_points.push(pixel);
                    detection.object_points.push(point);
                }
            }
            if detection.is_empty() {
                return Err(CalibrationError::NoTargetDetected {
                    view: view.to_owned(),
                    target: self.geometry.target().describe(),
                });
            }
            Ok(detection)
        }

        /// Detects in every view; returns the detections and, separately, the views where
        /// nothing was found (or that failed) with the reason.
        pub fn detect_all<'a>(
            &self,
            views: impl IntoIterator<Item = (&'a str, &'a Image)>,
        ) -> (Vec<Detection>, Vec<(String, CalibrationError)>) {
            let mut found = Vec::new();
            let mut failed = Vec::new();
            for (view, image) in views {
                match self.detect(view, image) {
                    Ok(detection) => found.push(detection),
                    Err(error) => failed.push((view.to_owned(), error)),
                }
            }
            (found, failed)
        }
    }

    fn refined_parameters() -> Result<Ptr<aruco::DetectorParameters>, CalibrationError> {
        let mut parameters = aruco::DetectorParameters::create()?;
        parameters.set_corner_refinement_method(aruco::CORNER_REFINE_SUBPIX);
        parameters.set_corner_refinement_win_size(4);
        parameters.set_corner_refinement_max_iterations(50);
        parameters.set_corner_refinement_min_accuracy(0.005);
        Ok(parameters)
    }

    fn to_dvec2(p: Point2f) -> DVec2 {
        DVec2::new(f64::from(p.x), f64::from(p.y))
    }

    fn chessboard(
        gray: &Mat,
        bytes: &[u8],
        width: u32,
        height: u32,
        cols: i32,
        rows: i32,
    ) -> Result<Vec<(u32, DVec2)>, CalibrationError> {
        let size = Size::new(cols, rows);
        let mut corners = Vector::<Point2f>::new();
        let mut found = calib3d::find_chessboard_corners(
            gray,
            size,
            &mut corners,
            calib3d::CALIB_CB_ADAPTIVE_THRESH | calib3d::CALIB_CB_NORMALIZE_IMAGE,
        )?;
        if !found {
            // Slower, but copes with stronger distortion, blur and uneven light.
            found = calib3d::find_chessboard_corners_sb(
                gray,
                size,
                &mut corners,
                calib3d::CALIB_CB_NORMALIZE_IMAGE | calib3d::CALIB_CB_EXHAUSTIVE,
            )?;
        }
        if !found || corners.len() != (cols * rows) as usize {
            return Ok(Vec::new());
        }
        let mut grid: Vec<DVec2> = corners.iter().map(to_dvec2).collect();
        orient_chessboard(
            &mut grid,
            cols as usize,
            rows as usize,
            bytes,
            width,
            height,
        );
        Ok(grid
            .into_iter()
            .enumerate()
            .map(|(i, p)| (i as u32, p))
            .collect())
    }

    /// Refines every saddle (chessboard, ChArUco corner) with [`refine_saddle`] in the largest
    /// window that sees only that corner: the target's clear radius round a point
    /// ([`TargetGeometry::corner_clearance_m`]) at the local scale (pixels per metre to the
    /// nearest neighbours, the smaller on foreshortened axes), 2 to 12 pixels. A saddle the fit
    /// cannot settle is too small or too blurred to locate: it is left out rather than trusted
    /// to a cruder method.
    fn refine(
        image: (&[u8], u32, u32),
        geometry: &TargetGeometry,
        found: &mut Vec<(u32, DVec2)>,
    ) -> Result<(), CalibrationError> {
        let (bytes, width, height) = image;
        let object: Vec<Option<DVec3>> = found.iter().map(|(id, _)| geometry.point(*id)).collect();
        let clearance = geometry.corner_clearance_m();
        let mut kept = Vec::with_capacity(found.len());
        for (i, &(id, pixel)) in found.iter().enumerate() {
            let Some(p) = object[i] else { continue };
            let mut neighbours: Vec<(f64, f64)> = found
                .iter()
                .zip(&object)
                .filter_map(|((_, q_pixel), q)| {
                    let metres = q.as_ref()?.distance(p);
                    (metres > 1e-9).then(|| (metres, pixel.distance(*q_pixel) / metres))
                })
                .collect();
            neighbours.sort_by(|a, b| a.0.total_cmp(&b.0));
            let scale = neighbours
                .iter()
                .take(4)
                .map(|&(_, px_per_m)| px_per_m)
                .fold(f64::INFINITY, f64::min);
            if !scale.is_finite() {
                continue;
            }
            let window = (clearance * scale).clamp(2.0, 12.0);
            // The weights keep the fit near the centre, so its window may reach a little past
            // the clear radius.
            let radius = (1.3 * window).clamp(3.0, 15.0);
            if let Some(refined) =
                refine_saddle(bytes, width as usize, height as usize, pixel, radius)
            {
                kept.push((id, refined));
            }
        }
        *found = kept;
        Ok(())
    }

    /// Mean side length of a quadrilateral, pixels.
    fn side_length_px(corners: &[DVec2; 4]) -> f64 {
        (0..4)
            .map(|k| corners[k].distance(corners[(k + 1) % 4]))
            .sum::<f64>()
            / 4.0
    }

    /// Puts OpenCV's row-major corner grid into the print's order: rows seen with the print's
    /// handedness (+X then +Y turn clockwise in the image, as they do on the print seen from
    /// the front), and corner 0 next to the black outer square.
    fn orient_chessboard(
        grid: &mut [DVec2],
        cols: usize,
        rows: usize,
        bytes: &[u8],
        width: u32,
        height: u32,
    ) {
        let at = |grid: &[DVec2], c: usize, r: usize| grid[r * cols + c];
        let x_step = at(grid, 1, 0) - at(grid, 0, 0);
        let y_step = at(grid, 0, 1) - at(grid, 0, 0);
        if x_step.perp_dot(y_step) < 0.0 {
            for row in grid.chunks_mut(cols) {
                row.reverse();
            }
        }
        let (w, h) = (width as usize, height as usize);
        let level_beyond = |grid: &[DVec2], corner: (usize, usize), inward: (usize, usize)| {
            let p = at(grid, corner.0, corner.1);
            let a = at(grid, inward.0, corner.1);
            let b = at(grid, corner.0, inward.1);
            let beyond = p + 0.5 * (p - a) + 0.5 * (p - b);
            let step = 0.15 * ((p - a).length() + (p - b).length());
            let mut sum = 0.0;
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let offset = DVec2::new(f64::from(dx), f64::from(dy)) * step;
                    sum += sample_bilinear(bytes, w, h, beyond + offset);
                }
            }
            sum / 9.0
        };
        let first = level_beyond(grid, (0, 0), (1, 1));
        let last = level_beyond(grid, (cols - 1, rows - 1), (cols - 2, rows - 2));
        if first > last {
            grid.reverse();
        }
    }

    fn charuco(
        gray: &Mat,
        dictionary: &Ptr<aruco::Dictionary>,
        board: &Ptr<aruco::CharucoBoard>,
        parameters: &Ptr<aruco::DetectorParameters>,
    ) -> Result<Vec<(u32, DVec2)>, CalibrationError> {
        let mut marker_corners = Vector::<Vector<Point2f>>::new();
        let mut marker_ids = Vector::<i32>::new();
        let mut rejected = Vector::<Vector<Point2f>>::new();
        aruco::detect_markers(
            gray,
            dictionary,
            &mut marker_corners,
            &mut marker_ids,
            parameters,
            &mut rejected,
        )?;
        if marker_ids.is_empty() {
            return Ok(Vec::new());
        }
        let mut corners = Vector::<Point2f>::new();
        let mut ids = Vector::<i32>::new();
        aruco::interpolate_corners_charuco_def(
            &marker_corners,
            &marker_ids,
            gray,
            board,
            &mut corners,
            &mut ids,
        )?;
        Ok(ids
            .iter()
            .zip(corners.iter())
            .filter(|(id, _)| *id >= 0)
            .map(|(id, p)| (id as u32, to_dvec2(p)))
            .collect())
    }

    /// One square marker found in an image: its id and its corners in OpenCV's order (top-left,
    /// top-right, bottom-right, bottom-left as printed), pixels.
    #[derive(Debug, Clone, Copy, PartialEq)]
    pub struct MarkerCorners {
        pub marker_id: u32,
        pub corners: [DVec2; 4],
    }

    fn markers(
        gray: &Mat,
        dictionary: &Ptr<aruco::Dictionary>,
        parameters: &Ptr<aruco::DetectorParameters>,
    ) -> Result<Vec<MarkerCorners>, CalibrationError> {
        let mut corners = Vector::<Vector<Point2f>>::new();
        let mut ids = Vector::<i32>::new();
        let mut rejected = Vector::<Vector<Point2f>>::new();
        aruco::detect_markers(
            gray,
            dictionary,
            &mut corners,
            &mut ids,
            parameters,
            &mut rejected,
        )?;
        let mut found = Vec::with_capacity(ids.len());
        for (id, quad) in ids.iter().zip(corners.iter()) {
            if id < 0 || quad.len() != 4 {
                continue;
            }
            let mut corners = [DVec2::ZERO; 4];
            for (slot, p) in corners.iter_mut().zip(quad.iter()) {
                *slot = to_dvec2(p);
            }
            found.push(MarkerCorners {
                marker_id: id as u32,
                corners,
            });
        }
        Ok(found)
    }

    /// Every marker of a dictionary in an image, corners refined to sub-pixel accuracy
    /// ([`refine_quad`] within half a cell of each side, assuming a quiet zone of at least half
    /// a cell; OpenCV's `cornerSubPix` corners where that fails).
    pub fn detect_markers(
        view: &str,
        image: &Image,
        dictionary: Dictionary,
    ) -> Result<Vec<MarkerCorners>, CalibrationError> {
        let bytes = luma(view, image)?;
        let (width, height) = (image.width() as usize, image.height() as usize);
        let gray =
            Mat::new_rows_cols_with_data(height as i32, width as i32, &bytes)?.try_clone()?;
        let cells = f64::from(dictionary.marker_bits() + 2);
        let mut found = markers(
            &gray,
            &opencv_dictionary(dictionary)?,
            &refined_parameters()?,
        )?;
        for marker in &mut found {
            let reach_px = (0.45 * side_length_px(&marker.corners) / cells).clamp(1.0, 10.0);
            if let Some(refined) = refine_quad(&bytes, width, height, marker.corners, reach_px) {
                marker.corners = refined;
            }
        }
        Ok(found)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn detection(view: &str, width: u32, height: u32) -> Detection {
        Detection {
            view: view.into(),
            width,
            height,
            ids: vec![0],
            image_points: vec![DVec2::ZERO],
            object_points: vec![DVec3::ZERO],
        }
    }

    /// A row-major image of a dark square (level 20) on a bright ground (level 220), rotated by
    /// `angle` about `centre`, each pixel the exact mean over its footprint (64² samples).
    fn square_image(
        w: usize,
        h: usize,
        centre: DVec2,
        half: f64,
        angle: f64,
    ) -> (Vec<u8>, [DVec2; 4]) {
        let (s, c) = angle.sin_cos();
        let to_square = |p: DVec2| {
            let d = p - centre;
            DVec2::new(c * d.x + s * d.y, -s * d.x + c * d.y)
        };
        let n = 64;
        let mut image = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut inside = 0;
                for j in 0..n {
                    for i in 0..n {
                        let p = DVec2::new(
                            x as f64 - 0.5 + (i as f64 + 0.5) / n as f64,
                            y as f64 - 0.5 + (j as f64 + 0.5) / n as f64,
                        );
                        let q = to_square(p);
                        if q.x.abs() < half && q.y.abs() < half {
                            inside += 1;
                        }
                    }
                }
                let coverage = f64::from(inside) / f64::from(n * n);
                image[y * w + x] = (220.0 - 200.0 * coverage).round() as u8;
            }
        }
        let from_square = |q: DVec2| centre + DVec2::new(c * q.x - s * q.y, s * q.x + c * q.y);
        let corners = [
            from_square(DVec2::new(-half, -half)),
            from_square(DVec2::new(half, -half)),
            from_square(DVec2::new(half, half)),
            from_square(DVec2::new(-half, half)),
        ];
        (image, corners)
    }

    #[test]
    fn quad_corners_land_on_the_square() {
        for (centre, angle) in [
            (DVec2::new(30.3, 29.7), 0.0),
            (DVec2::new(31.1, 30.45), 0.3),
            (DVec2::new(29.8, 30.2), -0.7),
        ] {
            let (image, truth) = square_image(60, 60, centre, 12.0, angle);
            // Start 0.4 px off, as a detector's corners are.
            let start = truth.map(|c| c + DVec2::new(0.3, -0.25));
            let refined = refine_quad(&image, 60, 60, start, 2.5).unwrap();
            for (r, t) in refined.iter().zip(&truth) {
                assert!(r.distance(*t) < 0.02, "{r} vs {t} (angle {angle})");
            }
        }
    }

    #[test]
    fn mixed_sizes_name_both_views() {
        let views = [detection("a.png", 640, 480), detection("b.png", 1280, 960)];
        let err = common_size(&views).unwrap_err().to_string();
        assert!(err.contains("a.png") && err.contains("640x480"), "{err}");
        assert!(err.contains("b.png") && err.contains("1280x960"), "{err}");
        assert_eq!(common_size(&views[..1]).unwrap(), (640, 480));
        assert!(matches!(
            common_size(&[]),
            Err(CalibrationError::TooFewViews { .. })
        ));
    }

    #[test]
    fn luma_of_rgb_and_refusal_of_depth() {
        let mut rgb = Image::new(2, 1, PixelFormat::Rgb8);
        rgb.as_u8_mut()
            .unwrap()
            .copy_from_slice(&[255, 255, 255, 255, 0, 0]);
        assert_eq!(luma("rgb", &rgb).unwrap(), vec![255, 77]);
        let depth = Image::new(2, 1, PixelFormat::DepthU16Mm);
        assert!(matches!(
            luma("depth", &depth),
            Err(CalibrationError::UnsupportedFormat { .. })
        ));
    }
}
