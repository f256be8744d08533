//! Vignetting of a lens: the radial fall-off of the light it passes, fitted from images of a
//! uniform field (a diffuse dome, an integrating sphere, an evenly lit white sheet filling the
//! view) or from a merged bracket of such a scene.
//!
//! The model is the even polynomial of Goldman & Chen ("Vignette and exposure calibration and
//! compensation", ICCV 2005; Kang & Weiss, ECCV 2000 use the same form):
//!
//! `V(r) = 1 + a1 r² + a2 r⁴ + a3 r⁶`, with `r² = ((u − cx) / fx)² + ((v − cy) / fy)²`
//!
//! about the principal point of the camera's model, in units of the focal length, so the same
//! coefficients hold at any resolution the model is resized to. For a Kannala–Brandt lens `r` is
//! the distorted angle θ_d (radians), for a pinhole the distorted radius on the normalised plane.
//! A pixel that sees radiance `L` records `L · V(r)` (linear, before the response curve).
//!
//! The fit is linear least squares of `L₀ (1 + a1 r² + a2 r⁴ + a3 r⁶)` (unknowns `L₀`, `L₀ a_k`)
//! over the pixels that carry information: a code in 1–254 in every channel of every image, inside
//! the model's valid field, and at least [`VignettingSettings::edge_margin_px`] pixels from any
//! pixel that is not (which drops the black outside a fish-eye's image circle and the partly
//! covered pixels on its rim). It is made robust to dust, specks and hot pixels by iteratively
//! reweighted least squares with Tukey's biweight on the relative residuals (scale: 1.4826 × their
//! median absolute deviation).
//!
//! The probe's coefficients `[a1, a2, a3]` go to the rig calibration's `probe_vignetting`, which
//! the daemon's light probe divides out before it merges a bracket. The model itself
//! ([`Vignetting`]) lives in relight-recon, which applies it.

use glam::DVec2;
use relight_core::camera::CameraModel;
use relight_core::{Image, PixelFormat};
use relight_recon::hdr::{HdrImage, Response};
pub use relight_recon::vignetting::Vignetting;

/// Rec. 709 luminance weights: the fit runs on the luminance of linear RGB.
const LUMINANCE: [f64; 3] = [0.2126, 0.7152, 0.0722];
/// Tukey's biweight tuning constant (95% efficiency under Gaussian noise).
const TUKEY_C: f64 = 4.685;
/// MAD → standard deviation under Gaussian noise.
const MAD_TO_SIGMA: f64 = 1.4826;
/// Fewest pixels a fit accepts: far more than its four unknowns, so that the robust scale means
/// something.
const MIN_PIXELS: usize = 200;

/// Why vignetting could not be fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VignettingError {
    #[error("no flat-field images given")]
    NoImages,
    #[error("image {index} is {actual:?}, only Rgb8 and Mono8 flat fields are supported")]
    Format { index: usize, actual: PixelFormat },
    #[error(
        "image {index} is {width}×{height}, the camera model is {expected_width}×{expected_height}"
    )]
    SizeMismatch {
        index: usize,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error(
        "only {found} pixels are usable (codes 1–254 in every image, inside the valid field, \
         away from its edge), at least {MIN_PIXELS} are needed"
    )]
    TooFewPixels { found: usize },
    #[error(
        "the usable pixels reach only r = {max_radius:.3} (focal-length units) from the \
         principal point: too little of the field to fit a fall-off"
    )]
    TooNarrow { max_radius: f64 },
    #[error("the least-squares system is singular (all usable pixels at one radius?)")]
    Singular,
    #[error("the fitted fall-off is not positive over the fitted field (at r = {radius:.3})")]
    NotPositive { radius: f64 },
    #[error("camera model: {0}")]
    Camera(#[from] relight_core::camera::CameraError),
}

/// Linear (pre-response) values of a uniform field, one per pixel; `None` where a pixel carries
/// no information (black, saturated, non-finite).
#[derive(Debug, Clone, PartialEq)]
pub struct FlatField {
    pub width: u32,
    pub height: u32,
    pub linear: Vec<Option<f64>>,
}

impl FlatField {
    /// The mean linear luminance of 8-bit images of the same uniform field through the camera's
    /// inverse response. A pixel is unusable if any channel of any image is 0 or 255.
    pub fn from_codes(images: &[Image], response: &Response) -> Result<Self, VignettingError> {
        let first = images.first().ok_or(VignettingError::NoImages)?;
        let (width, height) = (first.width(), first.height());
        let pixels = first.pixel_count();
        let mut sums = vec![Some(0.0f64); pixels];
        for (index, image) in images.iter().enumerate() {
            if (image.width(), image.height()) != (width, height) {
                return Err(VignettingError::SizeMismatch {
                    index,
                    width: image.width(),
                    height: image.height(),
                    expected_width: width,
                    expected_height: height,
                });
            }
            let format_error = VignettingError::Format {
                index,
                actual: image.format(),
            };
            let channels = match image.format() {
                PixelFormat::Rgb8 => 3,
                PixelFormat::Mono8 => 1,
                _ => return Err(format_error),
            };
            let codes = image.as_u8().ok_or(format_error)?;
            for (sum, px) in sums.iter_mut().zip(codes.chunks_exact(channels)) {
                let Some(s) = sum else { continue };
                if px.iter().any(|&c| c == 0 || c == 255) {
                    *sum = None;
                    continue;
                }
                *s += if let [r, g, b] = px {
                    LUMINANCE[0] * f64::from(response.exposure(*r))
                        + LUMINANCE[1] * f64::from(response.exposure(*g))
                        + LUMINANCE[2] * f64::from(response.exposure(*b))
                } else {
                    f64::from(response.exposure(px[0]))
                };
            }
        }
        let n = images.len() as f64;
        Ok(Self {
            width,
            height,
            linear: sums.into_iter().map(|s| s.map(|s| s / n)).collect(),
        })
    }

    /// The luminance of a merged bracket of a uniform field; saturated and black pixels are
    /// unusable.
    pub fn from_hdr(hdr: &HdrImage) -> Self {
        let linear = hdr
            .radiance
            .iter()
            .zip(&hdr.saturated)
            .map(|(rgb, &saturated)| {
                let y = LUMINANCE[0] * f64::from(rgb.x)
                    + LUMINANCE[1] * f64::from(rgb.y)
                    + LUMINANCE[2] * f64::from(rgb.z);
                (!saturated && y.is_finite() && y > 0.0).then_some(y)
            })
            .collect();
        Self {
            width: hdr.width,
            height: hdr.height,
            linear,
        }
    }
}

/// How [`fit_vignetting`] selects pixels and iterates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VignettingSettings {
    /// Pixels closer than this (Chebyshev distance, pixels) to an unusable pixel or the image
    /// border are left out: the rim of a fish-eye's image circle is only partly lit.
    pub edge_margin_px: u32,
    /// Iterations of reweighted least squares at most.
    pub max_iterations: usize,
    /// Every `stride`-th pixel in each direction enters the fit (1: all).
    pub stride: u32,
}

impl Default for VignettingSettings {
    fn default() -> Self {
        Self {
            edge_margin_px: 2,
            max_iterations: 20,
            stride: 1,
        }
    }
}

/// A fitted vignetting and how well the flat field fits it.
#[derive(Debug, Clone, PartialEq)]
pub struct VignettingFit {
    pub vignetting: Vignetting,
    /// `L₀`: the field's linear level on the optical axis.
    pub level: f64,
    /// Pixels in the fit.
    pub pixels: usize,
    /// Pixels given zero weight by the biweight (outliers).
    pub outliers: usize,
    /// Robust standard deviation of the relative residuals (1.4826 × MAD).
    pub residual_sigma: f64,
    /// Largest normalised radius of a pixel in the fit: the coefficients are extrapolated
    /// beyond it.
    pub max_radius: f64,
}

/// Fits `V(r)` to a flat field seen by `model` (module docs).
pub fn fit_vignetting(
    field: &FlatField,
    model: &CameraModel,
    settings: &VignettingSettings,
) -> Result<VignettingFit, VignettingError> {
    model.validate()?;
    if (field.width, field.height) != (model.width(), model.height()) {
        return Err(VignettingError::SizeMismatch {
            index: 0,
            width: field.width,
            height: field.height,
            expected_width: model.width(),
            expected_height: model.height(),
        });
    }
    let unit = Vignetting::new(model, &[]);
    let (width, height) = (field.width as usize, field.height as usize);
    let usable: Vec<bool> = (0..width * height)
        .map(|i| {
            let pixel = DVec2::new((i % width) as f64, (i / width) as f64);
            field.linear.get(i).copied().flatten().is_some() && model.unproject(pixel).is_some()
        })
        .collect();
    let inner = eroded(&usable, width, height, settings.edge_margin_px as usize);
    let stride = settings.stride.max(1) as usize;
    let mut samples: Vec<(f64, f64)> = Vec::new();
    for y in (0..height).step_by(stride) {
        for x in (0..width).step_by(stride) {
            let i = y * width + x;
            if let (true, Some(value)) = (inner[i], field.linear[i]) {
                samples.push((unit.radius(DVec2::new(x as f64, y as f64)), value));
            }
        }
    }
    if samples.len() < MIN_PIXELS {
        return Err(VignettingError::TooFewPixels {
            found: samples.len(),
        });
    }
    let max_radius = samples.iter().map(|s| s.0).fold(0.0, f64::max);
    // Below this reach the r⁶ term is not separable from r² and r⁴ at 8-bit precision.
    const MIN_REACH: f64 = 0.1;
    if max_radius < MIN_REACH {
        return Err(VignettingError::TooNarrow { max_radius });
    }

    let mut weights = vec![1.0f64; samples.len()];
    let mut beta = [0.0f64; 4];
    let mut sigma = 0.0;
    for _ in 0..settings.max_iterations.max(1) {
        let next = weighted_fit(&samples, &weights, max_radius)?;
        let relative: Vec<f64> = samples
            .iter()
            .map(|&(r, y)| {
                let model = polynomial(&next, r);
                (y - model) / model.abs().max(f64::MIN_POSITIVE)
            })
            .collect();
        sigma = MAD_TO_SIGMA * median_abs(&relative);
        let scale = (TUKEY_C * sigma).max(f64::EPSILON);
        for (w, e) in weights.iter_mut().zip(&relative) {
            let u = e / scale;
            *w = if u.abs() < 1.0 {
                (1.0 - u * u).powi(2)
            } else {
                0.0
            };
        }
        let converged = next
            .iter()
            .zip(&beta)
            .all(|(a, b)| (a - b).abs() <= 1e-9 * next[0].abs());
        beta = next;
        if converged {
            break;
        }
    }
    let level = beta[0];
    if !(level.is_finite() && level > 0.0) {
        return Err(VignettingError::NotPositive { radius: 0.0 });
    }
    let vignetting = Vignetting {
        coefficients: [beta[1] / level, beta[2] / level, beta[3] / level],
        ..unit
    };
    const CHECKS: usize = 64;
    for k in 0..=CHECKS {
        let radius = max_radius * k as f64 / CHECKS as f64;
        if vignetting.factor(radius) <= 0.0 {
            return Err(VignettingError::NotPositive { radius });
        }
    }
    Ok(VignettingFit {
        vignetting,
        level,
        pixels: samples.len(),
        outliers: weights.iter().filter(|&&w| w == 0.0).count(),
        residual_sigma: sigma,
        max_radius,
    })
}

/// `β₀ + β₁ r² + β₂ r⁴ + β₃ r⁶`.
fn polynomial(beta: &[f64; 4], r: f64) -> f64 {
    let r2 = r * r;
    beta[0] + r2 * (beta[1] + r2 * (beta[2] + r2 * beta[3]))
}

/// Weighted least squares of `y ≈ β₀ + β₁ r² + β₂ r⁴ + β₃ r⁶`, solved in the scaled variable
/// `s = (r / reach)²` for conditioning, then converted back.
fn weighted_fit(
    samples: &[(f64, f64)],
    weights: &[f64],
    reach: f64,
) -> Result<[f64; 4], VignettingError> {
    let mut normal = [[0.0f64; 4]; 4];
    let mut rhs = [0.0f64; 4];
    for (&(r, y), &w) in samples.iter().zip(weights) {
        if w == 0.0 {
            continue;
        }
        let s = (r / reach).powi(2);
        let basis = [1.0, s, s * s, s * s * s];
        for (i, bi) in basis.iter().enumerate() {
            rhs[i] += w * bi * y;
            for (j, bj) in basis.iter().enumerate() {
                normal[i][j] += w * bi * bj;
            }
        }
    }
    let gamma = crate::linalg::solve(normal, rhs).ok_or(VignettingError::Singular)?;
    let r2 = reach * reach;
    Ok([
        gamma[0],
        gamma[1] / r2,
        gamma[2] / (r2 * r2),
        gamma[3] / (r2 * r2 * r2),
    ])
}

/// Median of `|values|` (0 for none).
fn median_abs(values: &[f64]) -> f64 {
    let mut abs: Vec<f64> = values.iter().map(|v| v.abs()).collect();
    if abs.is_empty() {
        return 0.0;
    }
    let mid = abs.len() / 2;
    let (_, median, _) = abs.select_nth_unstable_by(mid, f64::total_cmp);
    *median
}

/// Pixels whose whole `(2 margin + 1)²` neighbourhood is set and inside the image.
fn eroded(mask: &[bool], width: usize, height: usize, margin: usize) -> Vec<bool> {
    if margin == 0 {
        return mask.to_vec();
    }
    // Separable: rows, then columns (a square structuring element).
    let run = |line: &[bool]| -> Vec<bool> {
        let n = line.len();
        (0..n)
            .map(|i| {
                i >= margin && i + margin < n && line[i - margin..=i + margin].iter().all(|&b| b)
            })
            .collect()
    };
    let mut rows = vec![false; mask.len()];
    for y in 0..height {
        let line = run(&mask[y * width..(y + 1) * width]);
        rows[y * width..(y + 1) * width].copy_from_slice(&line);
    }
    let mut out = vec![false; mask.len()];
    for x in 0..width {
        let column: Vec<bool> = (0..height).map(|y| rows[y * width + x]).collect();
        for (y, keep) in run(&column).into_iter().enumerate() {
            out[y * width + x] = keep;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erosion_drops_the_rim_and_the_border() {
        let (w, h) = (7, 5);
        let mut mask = vec![true; w * h];
        mask[2 * w + 5] = false;
        let out = eroded(&mask, w, h, 1);
        let set: Vec<(usize, usize)> = (0..w * h)
            .filter(|&i| out[i])
            .map(|i| (i % w, i / w))
            .collect();
        assert_eq!(
            set,
            vec![
                (1, 1),
                (2, 1),
                (3, 1),
                (1, 2),
                (2, 2),
                (3, 2),
                (1, 3),
                (2, 3),
                (3, 3)
            ]
        );
    }

    #[test]
    fn an_exact_polynomial_is_recovered_exactly() {
        let truth = [2.0, -0.3, 0.05, -0.004];
        let samples: Vec<(f64, f64)> = (0..500)
            .map(|i| {
                let r = 1.5 * f64::from(i) / 499.0;
                (r, polynomial(&truth, r))
            })
            .collect();
        let beta = weighted_fit(&samples, &vec![1.0; samples.len()], 1.5).unwrap();
        for (b, t) in beta.iter().zip(truth) {
            assert!((b - t).abs() < 1e-9, "{beta:?}");
        }
    }
}
