//! Which views to calibrate from: blurred and redundant views out, and a map of which parts of
//! the image hold corners.
//!
//! - **Blur** is measured where it matters, across the printed edges between detected points:
//!   the intensity profile across each edge's midpoint gives the edge spread
//!   σ = C / (√(2π) · max |dI/dx|) (for a step of contrast C blurred by a Gaussian of σ px,
//!   the steepest slope is C / (σ√(2π))); a view's blur is the median over its edges. Unlike
//!   the variance of the Laplacian it does not depend on the target's size, contrast or
//!   distance. A perfectly focused view measures about 0.5 px (the pixel's own footprint).
//! - **Redundant** views show the target where an accepted view already showed it: most points
//!   shared and the shared points on average within `redundant_px` of where they were. They
//!   add no information and weigh the fit towards one pose. Of near-duplicates the sharpest
//!   is kept.
//! - **Coverage**: a grid over the image counting accepted points per cell; distortion is only
//!   known where corners were seen, so the advice names the parts of the image still empty.

use std::fmt;

use glam::DVec2;
use relight_core::Image;

use crate::detect::{Detection, luma, sample_bilinear};
use crate::error::CalibrationError;
use crate::target::TargetGeometry;

/// Thresholds of [`select_views`].
#[derive(Debug, Clone, PartialEq)]
pub struct SelectionSettings {
    /// Largest edge spread (σ, pixels) a view may have.
    pub max_blur_px: f64,
    /// Views whose shared points moved less than this on average are redundant, pixels.
    pub redundant_px: f64,
    /// Fewest points a view must have.
    pub min_points: usize,
    /// Coverage grid cells across and down the image.
    pub grid_cols: u32,
    pub grid_rows: u32,
}

impl Default for SelectionSettings {
    fn default() -> Self {
        Self {
            max_blur_px: 2.0,
            redundant_px: 6.0,
            min_points: 8,
            grid_cols: 8,
            grid_rows: 6,
        }
    }
}

/// Why a view was left out.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    TooFewPoints {
        found: usize,
        minimum: usize,
    },
    Blurred {
        blur_px: f64,
        max_px: f64,
    },
    Redundant {
        similar_to: String,
        mean_shift_px: f64,
    },
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rejection::TooFewPoints { found, minimum } => {
                write!(f, "{found} points, at least {minimum} needed")
            }
            Rejection::Blurred { blur_px, max_px } => write!(
                f,
                "blurred: edges spread over σ = {blur_px:.2} px (at most {max_px:.2}); hold the \
                 target still and in focus"
            ),
            Rejection::Redundant {
                similar_to,
                mean_shift_px,
            } => write!(
                f,
                "redundant: the target sits within {mean_shift_px:.1} px of where `{similar_to}` \
                 showed it"
            ),
        }
    }
}

/// A view left out, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct RejectedView {
    /// Index into the views given to [`select_views`].
    pub index: usize,
    pub view: String,
    pub reason: Rejection,
}

/// What [`select_views`] decided.
#[derive(Debug, Clone, PartialEq)]
pub struct Selection {
    /// Indices of the accepted views, in input order.
    pub accepted: Vec<usize>,
    pub rejected: Vec<RejectedView>,
    /// Edge spread of every view (σ, px), `None` where no edge could be measured.
    pub blur_px: Vec<Option<f64>>,
    /// Coverage of the accepted views' points.
    pub coverage: CoverageMap,
}

/// One view to select from: its detection and the image it was found in.
#[derive(Debug, Clone, Copy)]
pub struct Candidate<'a> {
    pub detection: &'a Detection,
    pub image: &'a Image,
}

/// Rejects views with too few points, blurred views and redundant views (see the module docs)
/// and maps the coverage of the rest.
pub fn select_views(
    geometry: &TargetGeometry,
    candidates: &[Candidate<'_>],
    settings: &SelectionSettings,
) -> Result<Selection, CalibrationError> {
    let detections: Vec<Detection> = candidates.iter().map(|c| c.detection.clone()).collect();
    let (width, height) = crate::detect::common_size(&detections)?;
    let mut blur_px = Vec::with_capacity(candidates.len());
    for candidate in candidates {
        blur_px.push(edge_blur_px(
            geometry,
            candidate.detection,
            candidate.image,
        )?);
    }
    let mut order: Vec<usize> = (0..candidates.len()).collect();
    order.sort_by(|&a, &b| {
        let key = |i: usize| blur_px[i].unwrap_or(f64::INFINITY);
        key(a).total_cmp(&key(b))
    });
    let mut accepted: Vec<usize> = Vec::new();
    let mut rejected = Vec::new();
    for index in order {
        let detection = candidates[index].detection;
        let reject = |reason| RejectedView {
            index,
            view: detection.view.clone(),
            reason,
        };
        if detection.len() < settings.min_points {
            rejected.push(reject(Rejection::TooFewPoints {
                found: detection.len(),
                minimum: settings.min_points,
            }));
            continue;
        }
        if let Some(blur) = blur_px[index].filter(|&b| b > settings.max_blur_px) {
            rejected.push(reject(Rejection::Blurred {
                blur_px: blur,
                max_px: settings.max_blur_px,
            }));
            continue;
        }
        let similar = accepted.iter().find_map(|&other| {
            let other = candidates[other].detection;
            mean_shift_px(detection, other)
                .filter(|&shift| shift < settings.redundant_px)
                .map(|shift| (other.view.clone(), shift))
        });
        if let Some((similar_to, mean_shift_px)) = similar {
            rejected.push(reject(Rejection::Redundant {
                similar_to,
                mean_shift_px,
            }));
            continue;
        }
        accepted.push(index);
    }
    accepted.sort_unstable();
    rejected.sort_by_key(|r| r.index);
    let mut coverage = CoverageMap::new(width, height, settings.grid_cols, settings.grid_rows);
    for &index in &accepted {
        coverage.add(&candidates[index].detection.image_points);
    }
    Ok(Selection {
        accepted,
        rejected,
        blur_px,
        coverage,
    })
}

/// Mean pixel distance between the points two detections share, if they share at least 80 %
/// of the smaller one's points (otherwise they show different parts of the target).
fn mean_shift_px(a: &Detection, b: &Detection) -> Option<f64> {
    let mut total = 0.0;
    let mut shared = 0usize;
    for (id, pa) in a.ids.iter().zip(&a.image_points) {
        if let Some(pb) = b.pixel_of(*id) {
            total += pa.distance(pb);
            shared += 1;
        }
    }
    let needed = (0.8 * a.len().min(b.len()) as f64).ceil() as usize;
    (shared > 0 && shared >= needed).then(|| total / shared as f64)
}

/// Median edge spread σ (pixels) across the printed edges between a detection's points; `None`
/// when no edge is long enough to measure (under 6 px).
pub fn edge_blur_px(
    geometry: &TargetGeometry,
    detection: &Detection,
    image: &Image,
) -> Result<Option<f64>, CalibrationError> {
    let bytes = luma(&detection.view, image)?;
    let (w, h) = (image.width() as usize, image.height() as usize);
    let edges: Vec<(DVec2, DVec2)> = geometry
        .edges()
        .iter()
        .filter_map(|&[a, b]| Some((detection.pixel_of(a)?, detection.pixel_of(b)?)))
        .filter(|(a, b)| a.distance(*b) >= 6.0)
        .collect();
    const MAX_EDGES: usize = 64;
    let stride = edges.len().div_ceil(MAX_EDGES).max(1);
    let mut spreads: Vec<f64> = edges
        .iter()
        .step_by(stride)
        .filter_map(|&(a, b)| edge_spread(&bytes, w, h, a, b))
        .collect();
    if spreads.is_empty() {
        return Ok(None);
    }
    spreads.sort_by(f64::total_cmp);
    Ok(Some(spreads[spreads.len() / 2]))
}

/// σ of the edge between two adjacent points, from the profile across its midpoint averaged
/// over five lines along the middle 40 % of the edge.
fn edge_spread(bytes: &[u8], w: usize, h: usize, a: DVec2, b: DVec2) -> Option<f64> {
    const STEP: f64 = 0.25;
    let length = a.distance(b);
    let along = (b - a) / length;
    let across = along.perp();
    let middle = 0.5 * (a + b);
    let reach = (0.45 * length).clamp(2.5, 10.0);
    let samples = (reach / STEP).round() as i32;
    let profile: Vec<f64> = (-samples..=samples)
        .map(|k| {
            let t = f64::from(k) * STEP;
            (-2..=2)
                .map(|l| {
                    let s = f64::from(l) * 0.1 * length;
                    sample_bilinear(bytes, w, h, middle + across * t + along * s)
                })
                .sum::<f64>()
                / 5.0
        })
        .collect();
    let (lo, hi) = profile
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let contrast = hi - lo;
    let slope = profile
        .windows(3)
        .map(|w| (w[2] - w[0]).abs() / (2.0 * STEP))
        .fold(0.0, f64::max);
    // Too little contrast to tell an edge from noise.
    if contrast < 20.0 || slope <= 0.0 {
        return None;
    }
    Some(contrast / (slope * (std::f64::consts::TAU).sqrt()))
}

/// Points per cell of a grid over the image.
#[derive(Debug, Clone, PartialEq)]
pub struct CoverageMap {
    pub width: u32,
    pub height: u32,
    pub cols: u32,
    pub rows: u32,
    /// Row-major, `cols × rows`.
    pub counts: Vec<u32>,
}

/// The nine parts of an image named in advice, row-major from the top left.
const REGIONS: [&str; 9] = [
    "top-left corner",
    "top edge",
    "top-right corner",
    "left edge",
    "centre",
    "right edge",
    "bottom-left corner",
    "bottom edge",
    "bottom-right corner",
];

impl CoverageMap {
    pub fn new(width: u32, height: u32, cols: u32, rows: u32) -> Self {
        let (cols, rows) = (cols.max(1), rows.max(1));
        Self {
            width,
            height,
            cols,
            rows,
            counts: vec![0; (cols * rows) as usize],
        }
    }

    fn cell(&self, pixel: DVec2) -> Option<(u32, u32)> {
        let u = (pixel.x + 0.5) / f64::from(self.width);
        let v = (pixel.y + 0.5) / f64::from(self.height);
        if !(0.0..1.0).contains(&u) || !(0.0..1.0).contains(&v) {
            return None;
        }
        Some((
            (u * f64::from(self.cols)) as u32,
            (v * f64::from(self.rows)) as u32,
        ))
    }

    pub fn add(&mut self, pixels: &[DVec2]) {
        for &pixel in pixels {
            if let Some((c, r)) = self.cell(pixel) {
                self.counts[(r * self.cols + c) as usize] += 1;
            }
        }
    }

    /// Fraction of cells holding at least one point.
    pub fn covered_fraction(&self) -> f64 {
        let covered = self.counts.iter().filter(|&&n| n > 0).count();
        covered as f64 / self.counts.len() as f64
    }

    /// The parts of the image (of nine) where fewer than half the cells hold a point.
    pub fn empty_regions(&self) -> Vec<&'static str> {
        let region_of = |index: u32, count: u32| (index * 3 / count).min(2);
        let mut cells = [0u32; 9];
        let mut covered = [0u32; 9];
        for r in 0..self.rows {
            for c in 0..self.cols {
                let region = (region_of(r, self.rows) * 3 + region_of(c, self.cols)) as usize;
                cells[region] += 1;
                if self.counts[(r * self.cols + c) as usize] > 0 {
                    covered[region] += 1;
                }
            }
        }
        (0..9)
            .filter(|&i| cells[i] > 0 && 2 * covered[i] < cells[i])
            .map(|i| REGIONS[i])
            .collect()
    }

    /// What to do about the empty parts, if any.
    pub fn advice(&self) -> Option<String> {
        let empty = self.empty_regions();
        (!empty.is_empty()).then(|| {
            format!(
                "no corners yet near the {} of the image ({:.0} % of the image covered): add \
                 views with the target there, tilted, so the distortion is measured rather than \
                 extrapolated",
                empty.join(", "),
                100.0 * self.covered_fraction()
            )
        })
    }

    /// A text picture of the grid: `#` for a cell with points, `.` for an empty one.
    pub fn render(&self) -> String {
        let mut text = String::with_capacity(((self.cols + 1) * self.rows) as usize);
        for r in 0..self.rows {
            for c in 0..self.cols {
                text.push(if self.counts[(r * self.cols + c) as usize] > 0 {
                    '#'
                } else {
                    '.'
                });
            }
            text.push('\n');
        }
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rigid::Rigid;
    use crate::synth::{RenderSettings, SynthCamera};
    use crate::target::{Chessboard, Target};
    use glam::{DQuat, DVec3};
    use relight_core::camera::{CameraModel, Pinhole};

    fn camera() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 320,
            height: 240,
            fx: 300.0,
            fy: 300.0,
            cx: 159.5,
            cy: 119.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })
    }

    fn geometry() -> TargetGeometry {
        Target::Chessboard(Chessboard {
            inner_cols: 7,
            inner_rows: 4,
            square_m: 0.03,
        })
        .geometry()
        .unwrap()
    }

    /// The detection a perfect detector returns, and the image.
    fn view(name: &str, pose: Rigid, blur_sigma_px: f64) -> (Detection, Image) {
        let synth = SynthCamera::new(
            camera(),
            RenderSettings {
                blur_sigma_px,
                ..RenderSettings::default()
            },
        )
        .unwrap();
        let geometry = geometry();
        let image = synth.render_target(&geometry, &pose);
        let visible = synth.visible_points(&geometry, &pose);
        let detection = Detection {
            view: name.into(),
            width: 320,
            height: 240,
            ids: visible.iter().map(|(id, _)| *id).collect(),
            image_points: visible.iter().map(|(_, p)| *p).collect(),
            object_points: visible
                .iter()
                .map(|(id, _)| geometry.point(*id).unwrap())
                .collect(),
        };
        (detection, image)
    }

    fn pose(x: f64, y: f64, tilt: f64) -> Rigid {
        let rotation = DQuat::from_rotation_y(tilt);
        Rigid::new(
            rotation,
            DVec3::new(x, y, 0.6) - rotation * DVec3::new(0.09, 0.045, 0.0),
        )
    }

    #[test]
    fn edge_spread_follows_the_blur() {
        let (sharp_detection, sharp) = view("sharp", pose(0.0, 0.0, 0.3), 0.0);
        let sharp_px = edge_blur_px(&geometry(), &sharp_detection, &sharp)
            .unwrap()
            .unwrap();
        assert!(sharp_px < 0.9, "{sharp_px}");
        for sigma in [1.5, 3.0] {
            let (detection, image) = view("blurred", pose(0.0, 0.0, 0.3), sigma);
            let measured = edge_blur_px(&geometry(), &detection, &image)
                .unwrap()
                .unwrap();
            // The pixel footprint adds in quadrature.
            let expected = (sigma * sigma + sharp_px * sharp_px).sqrt();
            assert!(
                (measured - expected).abs() < 0.2 * expected,
                "σ {sigma}: measured {measured}, expected {expected}"
            );
        }
    }

    #[test]
    fn blurred_and_redundant_views_are_rejected_and_coverage_advises() {
        let views = [
            view("left.png", pose(-0.1, 0.0, 0.3), 0.0),
            view("left-again.png", pose(-0.1, 0.001, 0.3), 0.0),
            view("shaken.png", pose(0.1, 0.0, -0.3), 3.0),
            view("right.png", pose(0.1, 0.0, -0.3), 0.0),
        ];
        let candidates: Vec<Candidate<'_>> = views
            .iter()
            .map(|(detection, image)| Candidate { detection, image })
            .collect();
        let selection =
            select_views(&geometry(), &candidates, &SelectionSettings::default()).unwrap();
        assert_eq!(selection.accepted.len(), 2, "{selection:?}");
        assert!(selection.accepted.contains(&3));
        let reasons: Vec<String> = selection
            .rejected
            .iter()
            .map(|r| format!("{}: {}", r.view, r.reason))
            .collect();
        assert!(
            reasons.iter().any(|r| r.starts_with("shaken.png: blurred")),
            "{reasons:?}"
        );
        assert!(
            reasons.iter().any(|r| r.contains("redundant")),
            "{reasons:?}"
        );
        // Two views side by side in the middle band leave the top and bottom corners empty.
        let advice = selection.coverage.advice().unwrap();
        assert!(advice.contains("top-left corner"), "{advice}");
        assert!(advice.contains("bottom-right corner"), "{advice}");
    }

    #[test]
    fn coverage_grid_counts_and_names_regions() {
        let mut map = CoverageMap::new(90, 90, 3, 3);
        map.add(&[
            DVec2::new(5.0, 5.0),
            DVec2::new(44.0, 44.0),
            DVec2::new(200.0, 5.0),
        ]);
        assert_eq!(map.counts, vec![1, 0, 0, 0, 1, 0, 0, 0, 0]);
        assert_eq!(map.render(), "#..\n.#.\n...\n");
        let empty = map.empty_regions();
        assert!(!empty.contains(&"top-left corner") && empty.contains(&"top edge"));
        assert!((map.covered_fraction() - 2.0 / 9.0).abs() < 1e-12);
    }
}
