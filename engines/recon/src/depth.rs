//! Depth frames → a clean depth map: invalid-depth handling, the sensor's noise model, the
//! guided filter with the colour image as guide (He, Sun & Tang, *Guided Image Filtering*,
//! ECCV 2010 / TPAMI 2013), and the decision to fall back to the scene's proxy mesh.
//!
//! # Invalid depth
//!
//! A pixel holds depth when its value is finite, positive and inside the sensor's working range;
//! anything else (0 as drivers report holes, NaN, ±∞, negative, out of range) is stored as `0.0`
//! and stays `0.0` through every step of this crate: no filter, merge or normal estimate ever
//! invents geometry in a hole. Functions that take a [`DepthMap`] re-check each value with
//! [`is_valid_depth`], so a map whose public `metres` were filled by hand with NaN is safe too.
//!
//! # The CPU path as an oracle
//!
//! Everything here is written per pixel, in a fixed order, so that the GPU port
//! (`relight_engines::recon_gpu`) can match it to float tolerance: every window sum is a
//! [`box_sum_weighted`], two separable passes (horizontal, then vertical) that add the window's
//! values in ascending offset order with weights 1, d/r or (d/r)²; windows are clipped at the
//! image border (pixels outside the image contribute nothing and are not counted), so every
//! mean is a sum divided by the number of valid pixels it summed; the per-window 5 × 5 system
//! is solved by an unpivoted Cholesky decomposition in f32.

use std::ops::RangeInclusive;

use glam::Vec3;
use rayon::prelude::*;
use relight_core::{Image, PixelFormat};

/// Why a depth step cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DepthError {
    #[error("depth image is {format:?}; expected DepthU16Mm or DepthF32M")]
    NotDepth { format: PixelFormat },
    #[error("guide image is {format:?}; expected Rgb8 or Mono8")]
    BadGuide { format: PixelFormat },
    #[error("{what} is {actual_width}×{actual_height}, but the depth map is {width}×{height}")]
    SizeMismatch {
        what: &'static str,
        width: u32,
        height: u32,
        actual_width: u32,
        actual_height: u32,
    },
    #[error("depth map holds {actual} values, but {width}×{height} needs {expected}")]
    BadLength {
        width: u32,
        height: u32,
        expected: usize,
        actual: usize,
    },
    #[error("depth setting `{setting}` {reason}")]
    Setting {
        setting: &'static str,
        reason: &'static str,
    },
}

/// Whether a stored depth value is geometry: finite and positive.
pub fn is_valid_depth(depth_m: f32) -> bool {
    depth_m.is_finite() && depth_m > 0.0
}

/// The range of depths a sensor measures reliably, metres (both ends inclusive).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthRange {
    pub min_m: f32,
    pub max_m: f32,
}

impl Default for DepthRange {
    /// Kinect v1's working range (0.5–4.5 m), the simulator's too.
    fn default() -> Self {
        Self {
            min_m: 0.5,
            max_m: 4.5,
        }
    }
}

impl From<RangeInclusive<f32>> for DepthRange {
    fn from(range: RangeInclusive<f32>) -> Self {
        Self {
            min_m: *range.start(),
            max_m: *range.end(),
        }
    }
}

impl DepthRange {
    fn validate(&self) -> Result<(), DepthError> {
        if self.min_m.is_finite() && self.max_m.is_finite() && 0.0 < self.min_m {
            if self.min_m <= self.max_m {
                return Ok(());
            }
            return Err(DepthError::Setting {
                setting: "valid_range",
                reason: "must have min_m ≤ max_m",
            });
        }
        Err(DepthError::Setting {
            setting: "valid_range",
            reason: "must be finite with a positive minimum",
        })
    }
}

/// How the pixels of one depth frame were classified by [`DepthMap::from_image_with_census`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DepthCensus {
    /// Finite and inside the range: geometry.
    pub valid: usize,
    /// Zero (the driver's "no measurement") or negative.
    pub missing: usize,
    /// NaN or ±∞.
    pub non_finite: usize,
    /// Positive but nearer than the range's minimum.
    pub too_near: usize,
    /// Beyond the range's maximum.
    pub too_far: usize,
}

impl DepthCensus {
    pub fn total(&self) -> usize {
        self.valid + self.missing + self.non_finite + self.too_near + self.too_far
    }

    /// Share of the frame's pixels that are geometry; 0 for an empty frame.
    pub fn valid_fraction(&self) -> f32 {
        match self.total() {
            0 => 0.0,
            total => self.valid as f32 / total as f32,
        }
    }
}

/// Depth along the optical axis (z, metres) per pixel, row-major; `0.0` = no geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    pub width: u32,
    pub height: u32,
    pub metres: Vec<f32>,
}

impl DepthMap {
    /// A map with no geometry.
    pub fn invalid(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            metres: vec![0.0; width as usize * height as usize],
        }
    }

    /// Depth from a `DepthU16Mm` or `DepthF32M` image; values outside `valid_range` (and 0,
    /// NaN, ±∞, negative) become 0.
    pub fn from_image(image: &Image, valid_range: DepthRange) -> Result<Self, DepthError> {
        Self::from_image_with_census(image, valid_range).map(|(map, _)| map)
    }

    /// [`Self::from_image`], and how many pixels were dropped for which reason (what
    /// [`ProxySwitch`] decides on).
    pub fn from_image_with_census(
        image: &Image,
        valid_range: DepthRange,
    ) -> Result<(Self, DepthCensus), DepthError> {
        valid_range.validate()?;
        let raw: Vec<f32> = match (image.format(), image.as_u16(), image.as_f32()) {
            (PixelFormat::DepthU16Mm, Some(mm), _) => {
                mm.iter().map(|&v| f32::from(v) / 1000.0).collect()
            }
            (PixelFormat::DepthF32M, _, Some(m)) => m.to_vec(),
            (format, ..) => return Err(DepthError::NotDepth { format }),
        };
        let mut census = DepthCensus::default();
        let metres = raw
            .into_iter()
            .map(|z| {
                let counter = if z.is_nan() || z.is_infinite() {
                    &mut census.non_finite
                } else if z <= 0.0 {
                    &mut census.missing
                } else if z < valid_range.min_m {
                    &mut census.too_near
                } else if z > valid_range.max_m {
                    &mut census.too_far
                } else {
                    census.valid += 1;
                    return z;
                };
                *counter += 1;
                0.0
            })
            .collect();
        let map = Self {
            width: image.width(),
            height: image.height(),
            metres,
        };
        Ok((map, census))
    }

    /// The map as a `DepthF32M` image (what `relight_engines::live_scene::depth_mesh` reads).
    pub fn to_image(&self) -> Image {
        let mut image = Image::new(self.width, self.height, PixelFormat::DepthF32M);
        if let Some(out) = image.as_f32_mut() {
            for (o, &z) in out.iter_mut().zip(&self.metres) {
                *o = if is_valid_depth(z) { z } else { 0.0 };
            }
        }
        image
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Depth at (x, y), `None` where there is no geometry or off the map.
    pub fn get(&self, x: u32, y: u32) -> Option<f32> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let z = *self
            .metres
            .get(y as usize * self.width as usize + x as usize)?;
        is_valid_depth(z).then_some(z)
    }

    pub fn valid_count(&self) -> usize {
        self.metres.iter().filter(|z| is_valid_depth(**z)).count()
    }

    /// Every `step`-th sample per axis (sample (x, y) is this map's (x·step, y·step), as
    /// `Image::subsampled`), each averaged with the opposite pairs of its 3 × 3 neighbours
    /// that measure the same surface: both valid, and within `max_sigmas` of the sensor's
    /// `noise` of it plus one quantisation step (a disparity staircase is one surface). The
    /// mean is taken in disparity (1/z), which is linear in the pixel on a plane, and a pair
    /// is centred on the sample, so a plane keeps its depth exactly at the image's border and
    /// beside a depth edge too, and only the noise shrinks (by up to 3). A sample without
    /// depth stays without; a neighbour across a depth edge is left out, with its partner,
    /// rather than blended in. `step` 1 is the map itself.
    pub fn grid_samples(&self, step: u32, noise: &DepthNoise, max_sigmas: f32) -> DepthMap {
        let step = step.max(1);
        if step == 1 {
            return self.clone();
        }
        let (width, height) = (self.width.div_ceil(step), self.height.div_ceil(step));
        let mut metres = Vec::with_capacity(width as usize * height as usize);
        for y in 0..height {
            for x in 0..width {
                let (cx, cy) = (x * step, y * step);
                let Some(z0) = self.get(cx, cy) else {
                    metres.push(0.0);
                    continue;
                };
                let tolerance = max_sigmas * noise.sigma_m(z0) + noise.quantum_m(z0);
                let same_surface = |dx: i32, dy: i32| {
                    let (nx, ny) = (cx.checked_add_signed(dx)?, cy.checked_add_signed(dy)?);
                    self.get(nx, ny).filter(|z| (z - z0).abs() <= tolerance)
                };
                let (mut disparity, mut n) = (1.0 / z0, 1.0f32);
                for (dx, dy) in [(1, 0), (0, 1), (1, 1), (1, -1)] {
                    if let (Some(a), Some(b)) = (same_surface(dx, dy), same_surface(-dx, -dy)) {
                        disparity += 1.0 / a + 1.0 / b;
                        n += 2.0;
                    }
                }
                metres.push(n / disparity);
            }
        }
        DepthMap {
            width,
            height,
            metres,
        }
    }

    /// Share of pixels holding geometry; 0 for an empty map.
    pub fn valid_fraction(&self) -> f32 {
        match self.pixel_count() {
            0 => 0.0,
            n => self.valid_count() as f32 / n as f32,
        }
    }

    /// Checks that `metres` holds `width × height` values.
    pub fn check(&self) -> Result<(), DepthError> {
        let expected = self.pixel_count();
        if self.metres.len() == expected {
            Ok(())
        } else {
            Err(DepthError::BadLength {
                width: self.width,
                height: self.height,
                expected,
                actual: self.metres.len(),
            })
        }
    }

    pub(crate) fn check_size(
        &self,
        what: &'static str,
        width: u32,
        height: u32,
    ) -> Result<(), DepthError> {
        self.check()?;
        if (width, height) == (self.width, self.height) {
            Ok(())
        } else {
            Err(DepthError::SizeMismatch {
                what,
                width: self.width,
                height: self.height,
                actual_width: width,
                actual_height: height,
            })
        }
    }
}

/// Noise of a structured-light depth sensor, from which the filters' tolerances follow.
///
/// Kinect v1 reports z = f·b / d from a disparity d measured in 1/8 px. Its depth error has two
/// parts: Gaussian noise σ_z(z) = a + b·(z − z0)² (Nguyen, Izadi & Lovell 2012, measured
/// head-on) and the quantisation of d, whose depth step is z²·step / (f·b) (Khoshelham &
/// Elberink 2012). [`Self::sigma_m`] combines them: σ² = σ_z² + step²/12. The defaults are the
/// model the simulator draws from (`relight_sim::kinect::KinectModel`), with the focal
/// length of the depth camera *at the resolution used*, since the disparity is measured in its
/// pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthNoise {
    pub sigma_a_m: f32,
    pub sigma_b_per_m: f32,
    pub sigma_z0_m: f32,
    /// Depth camera focal length at the depth map's resolution, pixels.
    pub focal_px: f32,
    /// Camera–projector baseline, metres.
    pub baseline_m: f32,
    /// Disparity quantisation step, pixels.
    pub disparity_step_px: f32,
}

impl DepthNoise {
    /// Kinect v1 (b = 7.5 cm, 1/8 px disparity steps, σ_z = 1.2 mm + 1.9 mm·(z − 0.4 m)²) whose
    /// depth camera has focal length `focal_px` at the working resolution.
    pub fn kinect_v1(focal_px: f32) -> Self {
        Self {
            sigma_a_m: 0.0012,
            sigma_b_per_m: 0.0019,
            sigma_z0_m: 0.4,
            focal_px,
            baseline_m: 0.075,
            disparity_step_px: 1.0 / 8.0,
        }
    }

    /// Random noise σ_z at depth z, metres.
    pub fn sigma_z_m(&self, z_m: f32) -> f32 {
        self.sigma_a_m + self.sigma_b_per_m * (z_m - self.sigma_z0_m).powi(2)
    }

    /// Depth step of one disparity quantum at z, metres.
    pub fn quantum_m(&self, z_m: f32) -> f32 {
        z_m * z_m * self.disparity_step_px / (self.focal_px * self.baseline_m)
    }

    /// Standard deviation of a raw measurement at z: √(σ_z² + step²/12).
    pub fn sigma_m(&self, z_m: f32) -> f32 {
        let quantum = self.quantum_m(z_m);
        (self.sigma_z_m(z_m).powi(2) + quantum * quantum / 12.0).sqrt()
    }

    pub(crate) fn validate(&self) -> Result<(), DepthError> {
        let positive = [self.focal_px, self.baseline_m, self.disparity_step_px]
            .iter()
            .all(|v| v.is_finite() && *v > 0.0);
        let finite = [self.sigma_a_m, self.sigma_b_per_m, self.sigma_z0_m]
            .iter()
            .all(|v| v.is_finite() && *v >= 0.0);
        if positive && finite {
            Ok(())
        } else {
            Err(DepthError::Setting {
                setting: "noise",
                reason: "needs a positive focal length, baseline and step and finite, \
                         non-negative σ coefficients",
            })
        }
    }
}

/// Largest window radius [`guided_filter`] accepts (a 129 × 129 window; far beyond any useful
/// depth filter, it keeps a typo from costing minutes per frame).
pub const MAX_RADIUS_PX: u32 = 64;

/// Settings of [`guided_filter`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuidedFilterSettings {
    /// Window radius r: windows are (2r + 1)² pixels.
    pub radius_px: u32,
    /// Regularisation ε of the colour coefficients of a_k, in the guide's units squared (guide
    /// values in [0, 1]). Colour variations much weaker than √ε are smoothed over; stronger
    /// colour edges shape the output. It must exceed the colour image's noise variance, or
    /// the noise is copied into the depth.
    pub eps: f32,
    /// Regularisation of the position coefficients (offsets in units of the radius). Small: a
    /// slope is not penalised; it only keeps windows whose valid pixels lie on a line regular.
    pub eps_position: f32,
    /// The sensor's noise, for the deviation guard.
    pub noise: DepthNoise,
    /// Deviation guard: where the filtered depth differs from the raw depth by more than this
    /// many [`DepthNoise::sigma_m`], the raw depth is kept. The filter averages across a depth
    /// edge whose two sides have the same colour; the guard keeps such a blend (a "flying
    /// pixel" between the surfaces) from becoming geometry. `f32::INFINITY` disables it.
    pub max_deviation_sigmas: f32,
}

impl GuidedFilterSettings {
    /// r = 4 px, ε = 0.063² (colour edges of about 16 codes and more shape the depth; the
    /// simulator's 4-spp colour noise stays below), ε_pos = 10⁻⁴ and the guard at 3 σ, for a
    /// Kinect v1 whose depth camera has `focal_px` at the working resolution (the
    /// `depth_pipeline` tests measure the errors at 160 × 120; scale the radius with the
    /// resolution).
    pub fn kinect_v1(focal_px: f32) -> Self {
        Self {
            radius_px: 4,
            eps: 4e-3,
            eps_position: 1e-4,
            noise: DepthNoise::kinect_v1(focal_px),
            max_deviation_sigmas: 3.0,
        }
    }

    /// The checks [`guided_filter`] makes of its settings.
    pub fn validate(&self) -> Result<(), DepthError> {
        if self.radius_px > MAX_RADIUS_PX {
            return Err(DepthError::Setting {
                setting: "radius_px",
                reason: "must be at most 64",
            });
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(DepthError::Setting {
                setting: "eps",
                reason: "must be a positive number",
            });
        }
        if !(self.eps_position.is_finite() && self.eps_position > 0.0) {
            return Err(DepthError::Setting {
                setting: "eps_position",
                reason: "must be a positive number",
            });
        }
        if self.max_deviation_sigmas.is_nan() || self.max_deviation_sigmas <= 0.0 {
            return Err(DepthError::Setting {
                setting: "max_deviation_sigmas",
                reason: "must be positive (∞ disables the guard)",
            });
        }
        self.noise.validate()
    }
}

/// Guide colour per pixel in [0, 1]: sRGB code / 255 (the perceptual scale He et al. filter
/// on); grey is replicated to three channels for `Mono8` (ε keeps the 3 × 3 system regular).
fn guide_values(guide: &Image) -> Result<Vec<Vec3>, DepthError> {
    let n = guide.pixel_count();
    let code = |c: u8| f32::from(c) / 255.0;
    let values: Option<Vec<Vec3>> = match guide.format() {
        PixelFormat::Rgb8 => guide.as_u8().map(|px| {
            px.chunks_exact(3)
                .map(|c| Vec3::new(code(c[0]), code(c[1]), code(c[2])))
                .collect()
        }),
        PixelFormat::Mono8 => guide
            .as_u8()
            .map(|px| px.iter().map(|&c| Vec3::splat(code(c))).collect()),
        format => return Err(DepthError::BadGuide { format }),
    };
    match values {
        Some(values) if values.len() == n => Ok(values),
        _ => Err(DepthError::BadGuide {
            format: guide.format(),
        }),
    }
}

/// Weight of a pixel in a window by its offset d from the window's centre along one axis
/// (in units of the radius, so d/r ∈ [−1, 1]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BoxWeight {
    One,
    /// d / r
    Offset,
    /// (d / r)²
    OffsetSquared,
}

impl BoxWeight {
    fn at(self, offset: i64, radius: usize) -> f32 {
        let d = offset as f32 / radius.max(1) as f32;
        match self {
            BoxWeight::One => 1.0,
            BoxWeight::Offset => d,
            BoxWeight::OffsetSquared => d * d,
        }
    }
}

/// Weighted sum over the (2r + 1)² window around every pixel k, clipped at the border:
/// `out[k] = Σ_{i ∈ ω_k} w_x(x_i − x_k) · w_y(y_i − y_k) · values[i]`. Computed as a horizontal
/// pass, then a vertical one, each adding offsets −r..=r in ascending order (what the GPU
/// port does, so the two agree to float rounding).
pub fn box_sum_weighted(
    values: &[f32],
    width: usize,
    height: usize,
    radius: usize,
    (weight_x, weight_y): (BoxWeight, BoxWeight),
) -> Vec<f32> {
    let mut rows = vec![0.0f32; values.len()];
    if width == 0 || values.len() != width * height {
        return rows;
    }
    let kernel = |weight: BoxWeight| -> Vec<f32> {
        (-(radius as i64)..=radius as i64)
            .map(|d| weight.at(d, radius))
            .collect()
    };
    let (kernel_x, kernel_y) = (kernel(weight_x), kernel(weight_y));
    // Offset by offset over whole lines, each output still adding its in-range offsets in
    // ascending order: the same sums as one output at a time, in a loop that vectorises.
    let r = radius as isize;
    rows.par_chunks_mut(width)
        .zip(values.par_chunks(width))
        .with_min_len(ROWS_PER_TASK)
        .for_each(|(out, row)| {
            for (d, k) in (-r..=r).zip(&kernel_x) {
                // Outputs whose offset `d` lies in the line: first..end.
                let first = (-d).max(0) as usize;
                let end = (width as isize - d.max(0)).max(0) as usize;
                if first >= end {
                    continue;
                }
                let shifted = &row[(first as isize + d) as usize..(end as isize + d) as usize];
                for (o, v) in out[first..end].iter_mut().zip(shifted) {
                    *o += k * v;
                }
            }
        });
    let mut out = vec![0.0f32; values.len()];
    out.par_chunks_mut(width)
        .enumerate()
        .with_min_len(ROWS_PER_TASK)
        .for_each(|(y, out_row)| {
            let y = y as isize;
            for (d, k) in (-r..=r).zip(&kernel_y) {
                let yy = y + d;
                if yy < 0 || yy >= height as isize {
                    continue;
                }
                let row = &rows[yy as usize * width..(yy as usize + 1) * width];
                for (o, v) in out_row.iter_mut().zip(row) {
                    *o += k * v;
                }
            }
        });
    out
}

/// Image rows one parallel task of [`box_sum_weighted`] takes: a task of a few thousand
/// multiply-adds, so the live grid's small images are not split finer than the threads' cost.
const ROWS_PER_TASK: usize = 16;

/// Plain sum over the (2r + 1)² window around every pixel, clipped at the border.
pub fn box_sum(values: &[f32], width: usize, height: usize, radius: usize) -> Vec<f32> {
    box_sum_weighted(
        values,
        width,
        height,
        radius,
        (BoxWeight::One, BoxWeight::One),
    )
}

/// Guide channels: colour (3) and the offset from the window centre (2).
const GUIDE: usize = 5;

/// Pixels one parallel task of [`guided_filter`]'s per-pixel loops takes.
const PIXELS_PER_TASK: usize = 1024;

/// Solve `m · x = rhs` for a symmetric positive definite `m` by Cholesky decomposition;
/// `None` if a pivot is not positive or the result not finite.
fn solve_spd(mut m: [[f32; GUIDE]; GUIDE], rhs: [f32; GUIDE]) -> Option<[f32; GUIDE]> {
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
    // m = L Lᵀ, L stored in the lower triangle.
    for j in 0..GUIDE {
        let row_j = m[j];
        let pivot = row_j[j] - dot(&row_j[..j], &row_j[..j]);
        if !(pivot.is_finite() && pivot > 0.0) {
            return None;
        }
        let pivot = pivot.sqrt();
        m[j][j] = pivot;
        for row_i in m.iter_mut().skip(j + 1) {
            row_i[j] = (row_i[j] - dot(&row_i[..j], &row_j[..j])) / pivot;
        }
    }
    // L y = rhs, then Lᵀ x = y.
    let mut y = [0.0f32; GUIDE];
    for i in 0..GUIDE {
        y[i] = (rhs[i] - dot(&m[i][..i], &y[..i])) / m[i][i];
    }
    let mut x = [0.0f32; GUIDE];
    for i in (0..GUIDE).rev() {
        let upper: f32 = (i + 1..GUIDE).map(|k| m[k][i] * x[k]).sum();
        x[i] = (y[i] - upper) / m[i][i];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Guided filter of `depth` with the registered colour image `guide` (He et al. 2010,
/// Sec. 3.1, with the multi-channel guide of TPAMI 2013 Sec. 3.5), restricted to valid depth.
///
/// What is filtered is disparity p = 1/z: the sensor's noise and quantisation are uniform in
/// it, and a plane's disparity is an affine function of the pixel position. The guide of pixel
/// i seen from window ω_k is g_i = (R, G, B, (x_i − x_k)/r, (y_i − y_k)/r): the colour (sRGB
/// code / 255) and the pixel's offset from the window centre. With the offset in the local
/// linear model q_i = a_k · g_i + b_k, a slanted plane is reproduced exactly however the window
/// is clipped by the border or by holes (the plain colour-guided filter pulls such pixels
/// towards the window's centroid, biasing every pixel near a border or hole on a slope).
///
/// Per window, over the n_k valid pixels i in it: μ_k = mean g, p̄_k = mean p,
/// Σ_k = mean g gᵀ − μ_k μ_kᵀ, a_k = (Σ_k + E)⁻¹ (mean g p − μ_k p̄_k), b_k = p̄_k − a_k · μ_k, with
/// E = diag(ε, ε, ε, ε_pos, ε_pos). A valid pixel's output is the mean over the windows
/// containing it of a_k · g_i + b_k, each window weighted by n_k (a window with more
/// measurements is trusted more; the paper's plain mean is the case without holes), and
/// z = 1/q. Invalid pixels stay invalid; the deviation guard of
/// [`GuidedFilterSettings::max_deviation_sigmas`] keeps the raw value where the output strays
/// beyond the sensor's noise.
///
/// Every window moment is a [`box_sum_weighted`] with weights 1, d/r or (d/r)² per axis, so
/// offsets stay small numbers and the sums well conditioned in f32.
pub fn guided_filter(
    depth: &DepthMap,
    guide: &Image,
    settings: &GuidedFilterSettings,
) -> Result<DepthMap, DepthError> {
    use BoxWeight::{Offset as D, OffsetSquared as D2, One};
    settings.validate()?;
    depth.check_size("guide image", guide.width(), guide.height())?;
    let colour = guide_values(guide)?;
    let (w, h) = (depth.width as usize, depth.height as usize);
    let r = settings.radius_px as usize;
    let n = w * h;
    let valid: Vec<bool> = depth.metres.iter().map(|z| is_valid_depth(*z)).collect();
    let boxed = |f: &(dyn Fn(usize) -> f32 + Sync), weights: (BoxWeight, BoxWeight)| {
        let masked: Vec<f32> = (0..n).map(|i| if valid[i] { f(i) } else { 0.0 }).collect();
        box_sum_weighted(&masked, w, h, r, weights)
    };
    let p = |i: usize| 1.0 / depth.metres[i];
    let one = |_: usize| 1.0;
    let colour = &colour;

    // Window moments of the mask (pixel offsets), of p, and of the colour: 27 independent
    // sums, computed side by side.
    const PAIRS: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
    type Moment<'a> = (
        Box<dyn Fn(usize) -> f32 + Sync + 'a>,
        (BoxWeight, BoxWeight),
    );
    let mut moments: Vec<Moment> = vec![
        (Box::new(one), (One, One)),
        (Box::new(one), (D, One)),
        (Box::new(one), (One, D)),
        (Box::new(one), (D2, One)),
        (Box::new(one), (One, D2)),
        (Box::new(one), (D, D)),
        (Box::new(p), (One, One)),
        (Box::new(p), (D, One)),
        (Box::new(p), (One, D)),
    ];
    for weights in [(One, One), (D, One), (One, D)] {
        moments.extend((0..3).map(|c| -> Moment { (Box::new(move |i| colour[i][c]), weights) }));
    }
    moments
        .extend((0..3).map(|c| -> Moment { (Box::new(move |i| colour[i][c] * p(i)), (One, One)) }));
    for (a, b) in PAIRS {
        moments.push((Box::new(move |i| colour[i][a] * colour[i][b]), (One, One)));
    }
    let mut sums = moments
        .par_iter()
        .map(|(f, weights)| boxed(f.as_ref(), *weights))
        .collect::<Vec<_>>()
        .into_iter();
    let mut next = || sums.next().expect("one sum per moment");
    let [m_1, m_x, m_y, m_xx, m_yy, m_xy, p_1, p_x, p_y] = std::array::from_fn(|_| next());
    let c_1: [Vec<f32>; 3] = std::array::from_fn(|_| next());
    let c_x: [Vec<f32>; 3] = std::array::from_fn(|_| next());
    let c_y: [Vec<f32>; 3] = std::array::from_fn(|_| next());
    let c_p: [Vec<f32>; 3] = std::array::from_fn(|_| next());
    let c_c: [Vec<f32>; 6] = std::array::from_fn(|_| next());

    // Per window k: n_k · a_k (5) and n_k · b_k; zero for windows without valid depth.
    let regularisation = [
        settings.eps,
        settings.eps,
        settings.eps,
        settings.eps_position,
        settings.eps_position,
    ];
    let window_coefficients = |k: usize| -> [f32; GUIDE + 1] {
        let n_k = m_1[k];
        if n_k < 1.0 {
            return [0.0; GUIDE + 1];
        }
        let mu = [
            c_1[0][k] / n_k,
            c_1[1][k] / n_k,
            c_1[2][k] / n_k,
            m_x[k] / n_k,
            m_y[k] / n_k,
        ];
        let p_mean = p_1[k] / n_k;
        let mean_gp = [
            c_p[0][k] / n_k,
            c_p[1][k] / n_k,
            c_p[2][k] / n_k,
            p_x[k] / n_k,
            p_y[k] / n_k,
        ];
        let mut mean_gg = [[0.0f32; GUIDE]; GUIDE];
        for (j, &(a, b)) in PAIRS.iter().enumerate() {
            mean_gg[a][b] = c_c[j][k] / n_k;
            mean_gg[b][a] = mean_gg[a][b];
        }
        for c in 0..3 {
            mean_gg[c][3] = c_x[c][k] / n_k;
            mean_gg[3][c] = mean_gg[c][3];
            mean_gg[c][4] = c_y[c][k] / n_k;
            mean_gg[4][c] = mean_gg[c][4];
        }
        mean_gg[3][3] = m_xx[k] / n_k;
        mean_gg[4][4] = m_yy[k] / n_k;
        mean_gg[3][4] = m_xy[k] / n_k;
        mean_gg[4][3] = mean_gg[3][4];
        let mut system = [[0.0f32; GUIDE]; GUIDE];
        let mut rhs = [0.0f32; GUIDE];
        for a in 0..GUIDE {
            for b in 0..GUIDE {
                system[a][b] = mean_gg[a][b] - mu[a] * mu[b];
            }
            system[a][a] += regularisation[a];
            rhs[a] = mean_gp[a] - mu[a] * p_mean;
        }
        let a_k = solve_spd(system, rhs).unwrap_or([0.0; GUIDE]);
        let b_k = p_mean - (0..GUIDE).map(|j| a_k[j] * mu[j]).sum::<f32>();
        let mut out = [0.0; GUIDE + 1];
        for j in 0..GUIDE {
            out[j] = n_k * a_k[j];
        }
        out[GUIDE] = n_k * b_k;
        out
    };
    let coefficients: Vec<[f32; GUIDE + 1]> = (0..n)
        .into_par_iter()
        .with_min_len(PIXELS_PER_TASK)
        .map(window_coefficients)
        .collect();
    let [a_r, a_g, a_b, a_x, a_y, weighted_b]: [Vec<f32>; GUIDE + 1] =
        std::array::from_fn(|j| coefficients.iter().map(|c| c[j]).collect());

    // Per pixel i: Σ_k n_k (a_k · g_i + b_k) over the windows k containing i. The offset of i
    // from k's centre is minus the offset of k from i's, hence the negated offset sums.
    let mut sums = [
        (&m_1, (One, One)),
        (&a_r, (One, One)),
        (&a_g, (One, One)),
        (&a_b, (One, One)),
        (&a_x, (D, One)),
        (&a_y, (One, D)),
        (&weighted_b, (One, One)),
    ]
    .par_iter()
    .map(|(values, weights)| box_sum_weighted(values, w, h, r, *weights))
    .collect::<Vec<_>>()
    .into_iter();
    let mut next = || sums.next().expect("one sum per term");
    let weight_sum = next();
    let sum_colour: [Vec<f32>; 3] = std::array::from_fn(|_| next());
    let [sum_x, sum_y, sum_b] = std::array::from_fn(|_| next());

    let metres = (0..n)
        .into_par_iter()
        .with_min_len(PIXELS_PER_TASK)
        .map(|i| {
            let raw = depth.metres[i];
            if !valid[i] || weight_sum[i] <= 0.0 {
                return 0.0;
            }
            let colour_term: f32 = (0..3).map(|c| sum_colour[c][i] * colour[i][c]).sum();
            let q = (colour_term - sum_x[i] - sum_y[i] + sum_b[i]) / weight_sum[i];
            let z = 1.0 / q;
            let limit = settings.max_deviation_sigmas * settings.noise.sigma_m(raw);
            if is_valid_depth(z) && (z - raw).abs() <= limit {
                z
            } else {
                raw
            }
        })
        .collect();
    Ok(DepthMap {
        width: depth.width,
        height: depth.height,
        metres,
    })
}

/// Where the engines take the real scene's geometry from this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GeometrySource {
    /// The reconstructed depth.
    Depth,
    /// The scene file's proxy mesh of the real scene: depth is unusable (the sensor is held too
    /// close, or sunlight or a lamp floods its IR pattern; both show as missing depth).
    Proxy,
}

/// Switches between depth and the proxy mesh on the share of valid depth, with hysteresis so a
/// frame near the threshold does not make the geometry flicker between the two.
///
/// Starts on depth; goes to the proxy when the valid fraction falls below `enter_proxy_below`,
/// and back to depth once it is at least `leave_proxy_at`.
#[derive(Debug, Clone, PartialEq)]
pub struct ProxySwitch {
    pub enter_proxy_below: f32,
    pub leave_proxy_at: f32,
    using_proxy: bool,
}

impl Default for ProxySwitch {
    /// Proxy below 25 % valid pixels, back to depth at 40 %: a Kinect v1 on a table-top scene
    /// keeps 70–90 % (projector shadows, dark and grazing surfaces are the rest).
    fn default() -> Self {
        Self::new(0.25, 0.40)
    }
}

impl ProxySwitch {
    pub fn new(enter_proxy_below: f32, leave_proxy_at: f32) -> Self {
        Self {
            enter_proxy_below,
            leave_proxy_at: leave_proxy_at.max(enter_proxy_below),
            using_proxy: false,
        }
    }

    /// The source for a frame whose census is `census`.
    pub fn update(&mut self, census: &DepthCensus) -> GeometrySource {
        self.update_fraction(census.valid_fraction())
    }

    /// The source for a frame whose share of valid depth pixels is `valid_fraction` (NaN counts
    /// as no valid depth).
    pub fn update_fraction(&mut self, valid_fraction: f32) -> GeometrySource {
        let fraction = if valid_fraction.is_nan() {
            0.0
        } else {
            valid_fraction
        };
        if self.using_proxy {
            self.using_proxy = fraction < self.leave_proxy_at;
        } else {
            self.using_proxy = fraction < self.enter_proxy_below;
        }
        self.source()
    }

    pub fn source(&self) -> GeometrySource {
        if self.using_proxy {
            GeometrySource::Proxy
        } else {
            GeometrySource::Depth
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane's disparity is linear in the pixel, so the centred mean keeps a noise-free
    /// plane's depth at every grid sample; a sample keeps its own surface across a depth edge;
    /// a hole stays a hole; noise shrinks.
    #[test]
    fn grid_samples_average_one_surface_and_keep_planes_exact() {
        let noise = DepthNoise::kinect_v1(285.0);
        let (width, height) = (9u32, 7u32);
        // A slanted wall, 1/z = 0.5 + 0.004 x + 0.006 y, and in its right three columns a
        // box face nearer by 0.3 in disparity (about 0.6 m); one hole.
        let disparity = |x: u32, y: u32| {
            0.5 + 0.004 * x as f32 + 0.006 * y as f32 + if x >= 6 { 0.3 } else { 0.0 }
        };
        let mut map = DepthMap::invalid(width, height);
        for y in 0..height {
            for x in 0..width {
                map.metres[(y * width + x) as usize] = 1.0 / disparity(x, y);
            }
        }
        map.metres[(4 * width + 2) as usize] = 0.0;
        let grid = map.grid_samples(2, &noise, 3.0);
        assert_eq!((grid.width, grid.height), (5, 4));
        for y in 0..grid.height {
            for x in 0..grid.width {
                let got = grid.metres[(y * grid.width + x) as usize];
                let (px, py) = (2 * x, 2 * y);
                let expected = map.get(px, py).unwrap_or(0.0);
                // f32 rounding of a sum of up to nine terms.
                assert!(
                    (got - expected).abs() <= 1e-5 * expected.max(1.0),
                    "sample ({x}, {y}): {got} against {expected}"
                );
            }
        }
        // Noise: a checkerboard of ± half a quantisation step averages to a ninth of it at a
        // grid sample with all eight neighbours (the border's have fewer pairs).
        let z = 2.0;
        let step = noise.quantum_m(z) / 2.0;
        let mut noisy = DepthMap::invalid(width, height);
        for (i, m) in noisy.metres.iter_mut().enumerate() {
            *m = if i % 2 == 0 { z + step } else { z - step };
        }
        let smooth = noisy.grid_samples(2, &noise, 3.0);
        let worst = (1..smooth.height - 1)
            .flat_map(|y| (1..smooth.width - 1).map(move |x| (x, y)))
            .map(|(x, y)| (smooth.metres[(y * smooth.width + x) as usize] - z).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 0.4 * step, "{worst} of a {step} m step left");
        assert_eq!(noisy.grid_samples(1, &noise, 3.0), noisy);
    }

    #[test]
    fn box_sum_clips_windows_at_the_border() {
        let ones = vec![1.0; 5 * 4];
        let counts = box_sum(&ones, 5, 4, 1);
        assert_eq!(counts[0], 4.0, "corner: 2 × 2");
        assert_eq!(counts[1], 6.0, "top edge: 3 × 2");
        assert_eq!(counts[6], 9.0, "interior: 3 × 3");
        let ramp: Vec<f32> = (0..20).map(|i| i as f32).collect();
        let sums = box_sum(&ramp, 5, 4, 1);
        let direct = |x: i32, y: i32| {
            let mut s = 0.0;
            for yy in (y - 1).max(0)..=(y + 1).min(3) {
                for xx in (x - 1).max(0)..=(x + 1).min(4) {
                    s += ramp[(yy * 5 + xx) as usize];
                }
            }
            s
        };
        for y in 0..4 {
            for x in 0..5 {
                assert_eq!(sums[(y * 5 + x) as usize], direct(x, y));
            }
        }
    }

    /// The line-at-a-time passes give exactly the sums of one output at a time adding its
    /// in-range offsets in ascending order (what the GPU port adds), for every weight and for
    /// a window wider than the image.
    #[test]
    fn weighted_box_sums_add_in_the_order_of_the_gpu_port() {
        use BoxWeight::{Offset, OffsetSquared, One};
        let (w, h) = (5usize, 4usize);
        let values: Vec<f32> = (0..w * h)
            .map(|i| ((i * 7919) % 13) as f32 * 0.37 - 2.1)
            .collect();
        for radius in [1usize, 2, 7] {
            for weights in [
                (One, One),
                (Offset, One),
                (One, OffsetSquared),
                (Offset, Offset),
            ] {
                let sums = box_sum_weighted(&values, w, h, radius, weights);
                let r = radius as i64;
                let line = |centre: i64, len: i64, weight: BoxWeight, at: &dyn Fn(i64) -> f32| {
                    let mut sum = 0.0f32;
                    for d in -r..=r {
                        if (0..len).contains(&(centre + d)) {
                            sum += weight.at(d, radius) * at(centre + d);
                        }
                    }
                    sum
                };
                for y in 0..h as i64 {
                    for x in 0..w as i64 {
                        let row = |yy: i64| {
                            line(x, w as i64, weights.0, &|xx| {
                                values[(yy * w as i64 + xx) as usize]
                            })
                        };
                        let expected = line(y, h as i64, weights.1, &row);
                        let got = sums[y as usize * w + x as usize];
                        assert_eq!(
                            got.to_bits(),
                            expected.to_bits(),
                            "r {radius} {weights:?} at ({x}, {y})"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn radius_zero_is_the_identity() {
        let depth = DepthMap {
            width: 3,
            height: 1,
            metres: vec![1.0, 0.0, 2.0],
        };
        let guide = Image::new(3, 1, PixelFormat::Rgb8);
        let settings = GuidedFilterSettings {
            radius_px: 0,
            ..GuidedFilterSettings::kinect_v1(500.0)
        };
        let out = guided_filter(&depth, &guide, &settings).unwrap();
        assert_eq!(out.metres, depth.metres);
    }

    #[test]
    fn proxy_switch_has_hysteresis() {
        let mut switch = ProxySwitch::default();
        assert_eq!(switch.update_fraction(0.8), GeometrySource::Depth);
        assert_eq!(switch.update_fraction(0.3), GeometrySource::Depth);
        assert_eq!(switch.update_fraction(0.1), GeometrySource::Proxy);
        assert_eq!(switch.update_fraction(0.3), GeometrySource::Proxy);
        assert_eq!(switch.update_fraction(f32::NAN), GeometrySource::Proxy);
        assert_eq!(switch.update_fraction(0.5), GeometrySource::Depth);
    }
}
