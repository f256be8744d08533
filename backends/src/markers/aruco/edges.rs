//! A marker's four sides as straight lines fitted to sub-pixel edge points, and the corners
//! where they meet: a check on (and optionally a refinement of) OpenCV's corners.
//!
//! `cornerSubPix` and the contour polygon look at the few pixels around each corner, so
//! anything there — a fingertip, a cable, the blur of a defocused lens — moves the corner and,
//! through it, the pose. The sides carry the same information over their whole length: each
//! side's edge is located at many stations along its middle (the gradient centroid across the
//! edge, which symmetric blur does not move), a line is fitted to those points, and adjacent
//! lines are intersected — the idea of the AprilTag library's `refine_edges` step (apriltag.c),
//! applied to OpenCV's quads, with the lines fitted on the camera's undistorted image plane.

use glam::{DVec2, Vec2};
use relight_core::camera::CameraModel;

/// Read access to an 8-bit grey image (row-major, tightly packed).
#[derive(Debug, Clone, Copy)]
pub(crate) struct GreyView<'a> {
    pub pixels: &'a [u8],
    pub width: usize,
    pub height: usize,
}

impl GreyView<'_> {
    /// Bilinear interpolation at a pixel position (pixel centres at integers); `None` when the
    /// 2 × 2 neighbourhood leaves the image.
    fn sample(&self, at: DVec2) -> Option<f64> {
        let (x0, y0) = (at.x.floor(), at.y.floor());
        if !(x0 >= 0.0 && y0 >= 0.0) {
            return None;
        }
        let (x, y) = (x0 as usize, y0 as usize);
        if x + 1 >= self.width || y + 1 >= self.height {
            return None;
        }
        let (fx, fy) = (at.x - x0, at.y - y0);
        let at = |x: usize, y: usize| self.pixels.get(y * self.width + x).map(|&v| f64::from(v));
        let top = at(x, y)? * (1.0 - fx) + at(x + 1, y)? * fx;
        let bottom = at(x, y + 1)? * (1.0 - fx) + at(x + 1, y + 1)? * fx;
        Some(top * (1.0 - fy) + bottom * fy)
    }
}

/// The fitted sides of one marker.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct EdgeFit {
    /// Intersections of adjacent side lines, in the order of the input corners.
    pub corners_px: [Vec2; 4],
    /// Largest distance between an input corner and the intersection replacing it, pixels.
    pub max_corner_shift_px: f64,
    /// Largest RMS distance of a side's edge points from its line, pixels.
    pub max_side_rms_px: f64,
}

/// Fraction of each side (from each end) left out of the fit: the corners' surroundings, where
/// the neighbouring side's edge and whatever hides a corner would bias the points.
const SIDE_END_FRACTION: f64 = 0.15;
/// Edge stations per side at most (one per pixel of side on small markers).
const MAX_STATIONS: usize = 48;
/// Fewest edge points a side's line is fitted to.
const MIN_STATIONS: usize = 6;
/// Step of the intensity profile across an edge, pixels.
const PROFILE_STEP_PX: f64 = 0.25;
/// Re-centrings of the profiles on the previous line.
const PASSES: usize = 2;

/// Fits the four sides of the quad `corners_px` (a marker whose side is `cells` cells, border
/// included, in cyclic order). The edge is searched within half a cell (measured across the
/// side) either side of the current side, at most 6 px: the border is one cell wide, so the
/// inner edge of the border stays out of reach.
///
/// With a `lens`, the edge points are undistorted onto its normalised image plane and the lines
/// fitted and intersected there, where a straight edge is straight whatever the distortion; the
/// corners are projected back to pixels. `None` when a side has too few usable stations, a
/// point has no ray, or two lines are parallel.
pub(crate) fn fit_sides(
    view: &GreyView<'_>,
    corners_px: &[Vec2; 4],
    cells: u32,
    lens: Option<&CameraModel>,
) -> Option<EdgeFit> {
    let input = corners_px.map(|c| c.as_dvec2());
    let to_plane = |pixel: DVec2| match lens {
        Some(camera) => camera
            .unproject(pixel)
            .filter(|ray| ray.z > 1e-9)
            .map(|ray| ray.truncate() / ray.z),
        None => Some(pixel),
    };
    let to_pixel = |point: DVec2| match lens {
        Some(camera) => camera.project(point.extend(1.0)),
        None => Some(point),
    };
    let mut corners = input;
    let mut max_side_rms_px: f64 = 0.0;
    for _ in 0..PASSES {
        max_side_rms_px = 0.0;
        let centroid = corners.iter().sum::<DVec2>() / 4.0;
        let mut lines = [(DVec2::ZERO, DVec2::ZERO); 4];
        for (k, line) in lines.iter_mut().enumerate() {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            let length = a.distance(b);
            // The border's width across this side is a cell of the two sides next to it.
            let across =
                0.5 * (corners[(k + 3) % 4].distance(a) + b.distance(corners[(k + 2) % 4]));
            let reach = (0.5 * across / f64::from(cells)).min(6.0);
            if reach.is_nan() || reach < 1.0 {
                return None;
            }
            let mut normal = ((b - a) / length).perp();
            if normal.dot((a + b) / 2.0 - centroid) < 0.0 {
                normal = -normal;
            }
            let stations = (length * (1.0 - 2.0 * SIDE_END_FRACTION)).floor() as usize;
            let stations = stations.clamp(MIN_STATIONS, MAX_STATIONS);
            let mut points = Vec::with_capacity(stations);
            for i in 0..stations {
                let t = SIDE_END_FRACTION
                    + (1.0 - 2.0 * SIDE_END_FRACTION) * (i as f64 + 0.5) / stations as f64;
                let on_side = a + (b - a) * t;
                if let Some(offset) = edge_offset(view, on_side, normal, reach) {
                    points.push(to_plane(on_side + normal * offset)?);
                }
            }
            if points.len() < MIN_STATIONS {
                return None;
            }
            let (fit, rms) = fit_line(&points)?;
            // Pixels per plane unit along this side, to report the residual in pixels.
            let scale = length / to_plane(a)?.distance(to_plane(b)?);
            max_side_rms_px = max_side_rms_px.max(rms * scale);
            *line = fit;
        }
        let meeting = intersections(&lines)?;
        for (corner, point) in corners.iter_mut().zip(meeting) {
            *corner = to_pixel(point)?;
        }
    }
    let max_corner_shift_px = corners
        .iter()
        .zip(&input)
        .map(|(c, i)| c.distance(*i))
        .fold(0.0, f64::max);
    Some(EdgeFit {
        corners_px: corners.map(|c| c.as_vec2()),
        max_corner_shift_px,
        max_side_rms_px,
    })
}

/// Where, along `normal` (pointing out of the marker) from `on_line`, the edge is: the centroid
/// of the intensity gradient within `±reach`, taking the gradient's dominant sign (dark to light
/// for a printed marker, light to dark for an inverted one). `None` when the profile leaves the
/// image or is flat.
fn edge_offset(view: &GreyView<'_>, on_line: DVec2, normal: DVec2, reach: f64) -> Option<f64> {
    let steps = (reach / PROFILE_STEP_PX).floor() as i32;
    let mut previous = view.sample(on_line - normal * (f64::from(steps) * PROFILE_STEP_PX))?;
    // (weight, moment) of the rising and of the falling parts of the profile.
    let (mut rising, mut falling) = ((0.0, 0.0), (0.0, 0.0));
    for i in -steps + 1..=steps {
        let s = f64::from(i) * PROFILE_STEP_PX;
        let value = view.sample(on_line + normal * s)?;
        let change = value - previous;
        previous = value;
        // The difference between s − step and s estimates the gradient at their midpoint.
        let at = s - PROFILE_STEP_PX / 2.0;
        let part = if change > 0.0 {
            &mut rising
        } else {
            &mut falling
        };
        part.0 += change.abs();
        part.1 += change.abs() * at;
    }
    let (weight, moment) = if rising.0 >= falling.0 {
        rising
    } else {
        falling
    };
    (weight > 0.0).then(|| moment / weight)
}

/// Total-least-squares line through `points`: (centroid, unit direction) and the RMS distance
/// of the points from it.
fn fit_line(points: &[DVec2]) -> Option<((DVec2, DVec2), f64)> {
    let n = points.len() as f64;
    let mean = points.iter().sum::<DVec2>() / n;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in points {
        let d = *p - mean;
        sxx += d.x * d.x;
        sxy += d.x * d.y;
        syy += d.y * d.y;
    }
    // Principal axis of the 2 × 2 scatter matrix.
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let direction = DVec2::new(angle.cos(), angle.sin());
    if !direction.is_finite() {
        return None;
    }
    let normal = direction.perp();
    let residual = points
        .iter()
        .map(|p| (*p - mean).dot(normal).powi(2))
        .sum::<f64>();
    Some(((mean, direction), (residual / n).sqrt()))
}

/// Corner k is where side k − 1 (ending at it) meets side k (starting at it).
fn intersections(lines: &[(DVec2, DVec2); 4]) -> Option<[DVec2; 4]> {
    let mut corners = [DVec2::ZERO; 4];
    for (k, corner) in corners.iter_mut().enumerate() {
        let (p, u) = lines[(k + 3) % 4];
        let (q, v) = lines[k];
        let denominator = u.perp_dot(v);
        if denominator.abs() < 1e-6 {
            return None;
        }
        let t = (q - p).perp_dot(v) / denominator;
        *corner = p + u * t;
    }
    corners.iter().all(|c| c.is_finite()).then_some(corners)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dark square on a light ground, anti-aliased by area coverage (supersampled).
    fn square_image(corners: [DVec2; 4], width: usize, height: usize) -> Vec<u8> {
        let side =
            |p: DVec2, k: usize| (corners[(k + 1) % 4] - corners[k]).perp_dot(p - corners[k]);
        let inside =
            |p: DVec2| (0..4).all(|k| side(p, k) >= 0.0) || (0..4).all(|k| side(p, k) <= 0.0);
        let n = 8;
        (0..width * height)
            .map(|i| {
                let (x, y) = ((i % width) as f64, (i / width) as f64);
                let covered = (0..n * n)
                    .filter(|s| {
                        let o = DVec2::new(
                            ((s % n) as f64 + 0.5) / n as f64 - 0.5,
                            ((s / n) as f64 + 0.5) / n as f64 - 0.5,
                        );
                        inside(DVec2::new(x, y) + o)
                    })
                    .count();
                (220.0 - 200.0 * covered as f64 / (n * n) as f64).round() as u8
            })
            .collect()
    }

    #[test]
    fn sides_of_a_clean_square_meet_at_its_corners() {
        let truth = [
            DVec2::new(20.3, 60.7),
            DVec2::new(70.9, 55.2),
            DVec2::new(66.1, 12.4),
            DVec2::new(24.6, 18.8),
        ];
        let pixels = square_image(truth, 96, 80);
        let view = GreyView {
            pixels: &pixels,
            width: 96,
            height: 80,
        };
        // Start from corners a pixel off, as a contour polygon gives them.
        let start = truth.map(|c| (c + DVec2::new(0.8, -0.6)).as_vec2());
        let fit = fit_sides(&view, &start, 6, None).expect("four sides");
        for (found, expected) in fit.corners_px.iter().zip(&truth) {
            assert!(
                found.as_dvec2().distance(*expected) < 0.1,
                "{found} vs {expected}"
            );
        }
        assert!(fit.max_side_rms_px < 0.05, "{}", fit.max_side_rms_px);
        assert!(fit.max_corner_shift_px > 0.9);
    }

    #[test]
    fn a_quad_off_the_image_has_no_fit() {
        let pixels = vec![128u8; 16 * 16];
        let view = GreyView {
            pixels: &pixels,
            width: 16,
            height: 16,
        };
        let quad = [
            Vec2::new(-5.0, -5.0),
            Vec2::new(30.0, -5.0),
            Vec2::new(30.0, 30.0),
            Vec2::new(-5.0, 30.0),
        ];
        assert_eq!(fit_sides(&view, &quad, 6, None), None);
    }
}
