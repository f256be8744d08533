//! Photometric calibration of the fish-eye probe: its inverse response curve from a bracket of
//! exposures of a static scene, and its absolute radiance scale from a patch of known radiance.
//!
//! # Response
//!
//! A pixel-channel `j` of exposure `i` (effective time `t_i`) records `y_ij = f(t_i x_j)`. The
//! inverse response `I_m = f⁻¹(m)` is recovered with OpenCV's photo module,
//! `cv::createCalibrateRobertson`: Robertson, Borman & Stevenson, "Estimation-theoretic approach
//! to dynamic range enhancement using multiple exposures", J. Electronic Imaging 12(2), 2003 — the
//! method relight's own `relight_recon::hdr::recover_response` implements, so the two
//! cross-check each other.
//!
//! `cv::createCalibrateDebevec` (Debevec & Malik, SIGGRAPH 1997) is not offered: on the
//! simulator's 1/3/11/64 ms bracket it took 2.3 s with 70 sample locations (40 s with 400, the
//! SVD grows with the cube) and erred by 28% at code 250 and 1.7% on codes 16–240, where
//! Robertson took 1 s and erred by under 0.7% on codes 8–254: its triangle weights and
//! smoothness term leave the ends of the curve to the regulariser.
//!
//! One curve is recovered for the three channels together, as
//! [`RigCalibration::probe_response`](relight_core::rig::RigCalibration::probe_response) holds
//! one: a camera applies the same tone curve to every channel after white balance, and white
//! balance only scales `x`, which the curve's shape does not see. Every informative pixel-channel
//! (a code in 1–254 in at least two exposures) is one sample of that curve; OpenCV is handed the
//! samples as a grey image replicated into three channels, and once per channel alone to measure
//! how far the channels disagree ([`ResponseCalibration::channel_spread`]).
//!
//! OpenCV's curve is then made a valid relight table, the convention of `relight_recon::hdr`:
//! non-decreasing (weighted pool-adjacent-violators, weights = sample counts), codes without
//! samples interpolated, `I_0 = 0`, `I_255` extrapolated linearly from codes 253 and 254 (the
//! saturated code's samples only bound it from below), normalised to `I_128 = 1`.
//!
//! # Usable codes
//!
//! Robertson's `I_m` is the mean exposure of the samples that fell into code `m`'s quantisation
//! bin, `[I(m − ½), I(m + ½)]`, of relative width `w_m ≈ (I_{m+1} − I_{m−1}) / (2 I_m)`. When the
//! samples' density `p` varies across the bin, that mean is off the curve by about
//! `(d ln p / d ln E) · w_m² / 12` (first moment of a linearly varying density over the bin). At
//! the dark end the bins are wide (`w_m ≈ γ / m` for a gamma curve: 0.5 at code 4 for γ = 2.2) and
//! the scene's darkest radiance cuts the density off sharply, so a code there can be 10% off
//! although thousands of samples show it. A code is therefore usable only when
//! `w_m² / 12 ≤` [`ResponseSettings::max_bin_bias`] (0.005 bounds the error at 2% for density
//! log-slopes up to 4; with γ = 2.2 it starts at code 9) and at least
//! [`ResponseSettings::min_samples_per_code`] samples show it; the black and saturated codes never
//! are. [`ResponseCalibration::usable_codes`] is the run of usable codes around 128.
//!
//! # Brackets
//!
//! A calibration bracket needs at least three exposures whose ratios are not all powers of one
//! ratio: with a ladder (250/2000/16000 µs, ×8 each) every constraint compares exposures a power
//! of 8 apart, and the curve is determined only up to a factor periodic in log exposure
//! (Grossberg & Nayar, "What can be known about the radiometric response from images?", ECCV
//! 2002). Such brackets are refused with relight-recon's own check
//! ([`HdrError::CommensurateExposures`]), so the two tools accept the same brackets. Use an
//! uneven bracket, e.g. 1/3/11/64 ms.
//!
//! # Absolute scale
//!
//! Merged HDR values are in response units per second. [`radiance_scale`] turns them into
//! W/(m²·sr) from a patch of known radiance (a calibrated luminance standard or a patch measured
//! with a spot radiometer); without one the scale stays 1 (relative units), as
//! [`RigCalibration::probe_radiance_scale`](relight_core::rig::RigCalibration::probe_radiance_scale)
//! documents.

use std::ops::RangeInclusive;

use glam::Vec3;
use opencv::core::{Mat, Vector};
use opencv::photo::{self, CalibrateCRFTrait};
use opencv::prelude::*;
use relight_core::ProbeImage;
use relight_recon::hdr::{
    HdrError, HdrImage, RESPONSE_LEN, Response, piecewise_linear, pool_adjacent_violators,
};

use crate::vignetting::Vignetting;

/// The code at which a recovered curve is normalised, `I_128 = 1` (relight-recon's convention).
pub const MID_CODE: usize = Response::MID_CODE;
const BLACK: u8 = 0;
const SATURATED: u8 = 255;

/// Why a response or scale could not be calibrated.
#[derive(Debug, thiserror::Error)]
pub enum PhotometricError {
    /// The bracket fails relight-recon's checks (sizes, formats, exposure times, a ladder of one
    /// ratio, no overlap).
    #[error("bracket: {0}")]
    Bracket(#[from] HdrError),
    #[error("OpenCV {operation}: {source}")]
    OpenCv {
        operation: &'static str,
        #[source]
        source: opencv::Error,
    },
    #[error(
        "no sample shows code {MID_CODE} well exposed: the bracket does not reach mid-grey, so \
         the curve cannot be normalised; add a longer or shorter exposure"
    )]
    MidCodeUnobserved,
    #[error(
        "only {found} informative pixel-channels (a code in 1–254 in two exposures), at least \
         {needed} are needed: the scene lacks texture or the exposures do not overlap"
    )]
    TooFewSamples { found: usize, needed: usize },
    #[error("the recovered response is not finite at code {code}")]
    NonFinite { code: usize },
    #[error("reference patch {patch:?} lies outside the {width}×{height} HDR image")]
    PatchOutside {
        patch: PixelRect,
        width: u32,
        height: u32,
    },
    #[error(
        "reference patch {patch:?} has no usable pixel (all saturated, black or outside the \
         image circle)"
    )]
    PatchUnusable { patch: PixelRect },
    #[error("known radiance must be finite and positive, got {0} W/(m²·sr)")]
    KnownRadiance(f32),
}

fn cv(operation: &'static str) -> impl FnOnce(opencv::Error) -> PhotometricError {
    move |source| PhotometricError::OpenCv { operation, source }
}

/// How [`calibrate_response`] samples and iterates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResponseSettings {
    /// At most this many informative pixel-channels are used, spread evenly over all of them.
    pub max_samples: usize,
    /// Iterations of Robertson's alternating minimisation. OpenCV starts from a linear curve
    /// and cannot stop early when some code has no sample (its entry stays NaN, so the change it
    /// measures is NaN), so this many always run.
    pub iterations: i32,
    /// A code is usable (module docs) when at least this many samples show it …
    pub min_samples_per_code: u32,
    /// … and its bin's `w² / 12` is at most this (module docs).
    pub max_bin_bias: f64,
}

impl Default for ResponseSettings {
    fn default() -> Self {
        Self {
            max_samples: 60_000,
            iterations: 120,
            min_samples_per_code: 16,
            max_bin_bias: 0.005,
        }
    }
}

/// A recovered inverse response and what the data say about it.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseCalibration {
    /// 256 entries, code → relative exposure, non-decreasing, `I_0 = 0`, `I_128 = 1`: the table
    /// for [`RigCalibration::probe_response`](relight_core::rig::RigCalibration::probe_response).
    pub inverse_response: Vec<f32>,
    /// The codes the data determine to within the quantisation bound of the module docs: the
    /// run of usable codes around 128, never the black (0) or saturated (255) code. Entries
    /// outside are less certain (interpolated, extrapolated, or biased by wide bins).
    pub usable_codes: RangeInclusive<u8>,
    /// Informative samples per code (all channels).
    pub samples_per_code: Vec<u32>,
    /// Informative pixel-channels used.
    pub samples: usize,
    /// Effective exposure times, seconds, in bracket order.
    pub exposures_s: Vec<f64>,
    /// Largest relative difference over the usable codes between the curve recovered from one
    /// channel alone and the shared curve; `None` when no channel alone reaches code 128. A few
    /// percent is noise; tens of percent mean the channels do not share a curve.
    pub channel_spread: Option<f32>,
}

impl ResponseCalibration {
    /// The curve as relight-recon's [`Response`] (for merging brackets).
    pub fn response(&self) -> Result<Response, PhotometricError> {
        Ok(Response::from_table(&self.inverse_response)?)
    }
}

/// Effective exposure time of a probe frame, seconds: `exposure_us · 10⁻⁶ · 10^(gain_db / 20)`
/// (gain as an amplitude gain), relight-recon's convention.
pub fn effective_exposure_s(probe: &ProbeImage) -> f64 {
    f64::from(probe.exposure_us) * 1e-6 * 10f64.powf(f64::from(probe.gain_db) / 20.0)
}

/// Checks a calibration bracket exactly as `relight_recon::hdr::recover_response` does (sizes,
/// `Rgb8`, positive exposure times, at least two different times, no ladder of one ratio, some
/// overlap).
pub fn check_bracket(brackets: &[ProbeImage]) -> Result<(), PhotometricError> {
    Ok(relight_recon::hdr::check_bracket(brackets)?)
}

/// Recovers the probe's inverse response from a bracket of one static view (module docs).
pub fn calibrate_response(
    brackets: &[ProbeImage],
    settings: &ResponseSettings,
) -> Result<ResponseCalibration, PhotometricError> {
    check_bracket(brackets)?;
    let exposures_s: Vec<f64> = brackets.iter().map(effective_exposure_s).collect();
    let codes: Vec<&[u8]> = brackets
        .iter()
        .map(|b| b.image.as_u8().unwrap_or_default())
        .collect();
    let informative = informative_samples(&codes, settings.max_samples);
    const MIN_SAMPLES: usize = 64;
    if informative.len() < MIN_SAMPLES {
        return Err(PhotometricError::TooFewSamples {
            found: informative.len(),
            needed: MIN_SAMPLES,
        });
    }
    let samples = |keep: &dyn Fn(usize) -> bool| -> Vec<Vec<u8>> {
        codes
            .iter()
            .map(|c| {
                informative
                    .iter()
                    .filter(|&&k| keep(k))
                    .map(|&k| c[k])
                    .collect()
            })
            .collect()
    };
    let shared = samples(&|_| true);
    let counts = code_counts(&shared);
    if counts[MID_CODE] == 0 {
        return Err(PhotometricError::MidCodeUnobserved);
    }
    let raw = opencv_response(&shared, &exposures_s, settings)?;
    let inverse_response = regularised(&raw, &counts)?;
    let usable_codes = usable_codes(&inverse_response, &counts, settings);

    let mut channel_spread: Option<f32> = None;
    for channel in 0..3 {
        let own = samples(&|k| k % 3 == channel);
        let own_counts = code_counts(&own);
        if own_counts[MID_CODE] == 0 || own.first().is_none_or(|s| s.len() < MIN_SAMPLES) {
            continue;
        }
        let raw = opencv_response(&own, &exposures_s, settings)?;
        let Ok(curve) = regularised(&raw, &own_counts) else {
            continue;
        };
        let own_usable = self::usable_codes(&curve, &own_counts, settings);
        let worst = usable_codes
            .clone()
            .filter(|m| own_usable.contains(m))
            .map(usize::from)
            .map(|m| (curve[m] - inverse_response[m]).abs() / inverse_response[m])
            .fold(0.0f32, f32::max);
        channel_spread = Some(channel_spread.map_or(worst, |s| s.max(worst)));
    }

    Ok(ResponseCalibration {
        inverse_response,
        usable_codes,
        samples_per_code: counts.to_vec(),
        samples: informative.len(),
        exposures_s,
        channel_spread,
    })
}

/// Indices (into the interleaved RGB codes) of at most `max_samples` pixel-channels with a code
/// in 1–254 in at least two exposures, evenly spread over all such pixel-channels.
fn informative_samples(codes: &[&[u8]], max_samples: usize) -> Vec<usize> {
    let len = codes.iter().map(|c| c.len()).min().unwrap_or(0);
    let informative: Vec<usize> = (0..len)
        .filter(|&k| {
            codes
                .iter()
                .filter(|c| c[k] != BLACK && c[k] != SATURATED)
                .count()
                >= 2
        })
        .collect();
    let keep = max_samples.max(1);
    if informative.len() <= keep {
        return informative;
    }
    (0..keep)
        .map(|s| informative[s * informative.len() / keep])
        .collect()
}

/// How many samples show each code in any exposure.
fn code_counts(samples: &[Vec<u8>]) -> [u32; RESPONSE_LEN] {
    let mut counts = [0u32; RESPONSE_LEN];
    for &code in samples.iter().flatten() {
        counts[usize::from(code)] += 1;
    }
    counts
}

/// Relative width of code `m`'s quantisation bin, `(I_{m+1} − I_{m−1}) / (2 I_m)`, for
/// `m` in 1–254.
fn bin_width(table: &[f32], m: usize) -> f64 {
    let (below, here, above) = (table[m - 1], table[m], table[m + 1]);
    f64::from(above - below) / (2.0 * f64::from(here))
}

/// The run of usable codes (module docs) containing [`MID_CODE`], within 1–254 (just the mid
/// code when even it is not usable).
fn usable_codes(
    table: &[f32],
    counts: &[u32; RESPONSE_LEN],
    settings: &ResponseSettings,
) -> RangeInclusive<u8> {
    let usable = |m: usize| {
        let width = bin_width(table, m);
        counts[m] >= settings.min_samples_per_code.max(1)
            && width.is_finite()
            && width * width / 12.0 <= settings.max_bin_bias
    };
    if !usable(MID_CODE) {
        return MID_CODE as u8..=MID_CODE as u8;
    }
    let mut lo = MID_CODE;
    while lo > 1 && usable(lo - 1) {
        lo -= 1;
    }
    let mut hi = MID_CODE;
    while hi < 254 && usable(hi + 1) {
        hi += 1;
    }
    lo as u8..=hi as u8
}

/// OpenCV's raw Robertson curve (one channel of its three identical ones) from samples laid out as a
/// roughly square grey image, replicated into three channels as its estimators require.
fn opencv_response(
    samples: &[Vec<u8>],
    exposures_s: &[f64],
    settings: &ResponseSettings,
) -> Result<Vec<f32>, PhotometricError> {
    let count = samples.first().map_or(0, Vec::len);
    let cols = (count as f64).sqrt().ceil().max(1.0) as usize;
    let rows = (count / cols).max(1);
    let used = (rows * cols).min(count);
    let mut images = Vector::<Mat>::new();
    for codes in samples {
        let rgb: Vec<u8> = codes[..used].iter().flat_map(|&c| [c, c, c]).collect();
        let image = Mat::new_rows_cols_with_bytes::<opencv::core::Vec3b>(
            rows as i32,
            (used / rows) as i32,
            &rgb,
        )
        .and_then(|m| m.try_clone())
        .map_err(cv("building the sample image"))?;
        images.push(image);
    }
    let times: Vec<f32> = exposures_s.iter().map(|&t| t as f32).collect();
    let times = Mat::from_slice(&times)
        .and_then(|m| m.try_clone())
        .map_err(cv("exposure times"))?;
    let mut response = Mat::default();
    let mut calibrate = photo::create_calibrate_robertson(settings.iterations.max(1), 0.0)
        .map_err(cv("createCalibrateRobertson"))?;
    calibrate
        .process(&images, &mut response, &times)
        .map_err(cv("CalibrateRobertson::process"))?;
    let values = response
        .data_typed::<opencv::core::Vec3f>()
        .map_err(cv("reading the response"))?;
    Ok(values.iter().map(|v| v[0]).collect())
}

/// OpenCV's curve made a valid relight table (module docs): the codes that samples show keep
/// their (isotonic-regressed) values, the others are interpolated, `I_0 = 0`, `I_255` is
/// extrapolated, and the curve is normalised to `I_128 = 1`.
fn regularised(raw: &[f32], counts: &[u32; RESPONSE_LEN]) -> Result<Vec<f32>, PhotometricError> {
    let last = RESPONSE_LEN - 1;
    let observed: Vec<usize> = (1..last)
        .filter(|&m| counts[m] > 0 && raw.get(m).is_some_and(|v| v.is_finite()))
        .collect();
    if !observed.contains(&MID_CODE) {
        return Err(PhotometricError::NonFinite { code: MID_CODE });
    }
    let monotone = pool_adjacent_violators(
        &observed
            .iter()
            .map(|&m| f64::from(raw[m]))
            .collect::<Vec<_>>(),
        &observed
            .iter()
            .map(|&m| f64::from(counts[m]))
            .collect::<Vec<_>>(),
    );
    let anchors: Vec<(f64, f64)> = std::iter::once((0.0, 0.0))
        .chain(
            observed
                .iter()
                .zip(monotone)
                .map(|(&m, v)| (m as f64, v.max(0.0))),
        )
        .collect();
    let mut curve: Vec<f64> = (0..last)
        .map(|m| piecewise_linear(&anchors, m as f64))
        .collect();
    curve.push((2.0 * curve[last - 1] - curve[last - 2]).max(curve[last - 1]));
    let mid = curve[MID_CODE];
    if !(mid.is_finite() && mid > 0.0) {
        return Err(PhotometricError::NonFinite { code: MID_CODE });
    }
    let table: Vec<f32> = curve.iter().map(|v| (v / mid) as f32).collect();
    if let Some(code) = table.iter().position(|v| !v.is_finite()) {
        return Err(PhotometricError::NonFinite { code });
    }
    Ok(table)
}

pub use relight_core::PixelRect;

/// Rec. 709 luminance weights: the reference patch's radiance is compared with the luminance of
/// the merged RGB.
const LUMINANCE: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);

/// The probe's absolute scale, W/(m²·sr) per unit of merged HDR value (response units per
/// second), from a patch whose radiance is known: `known / mean(luminance / V)` over the patch's
/// pixels that are neither saturated nor black, with `V` the lens's vignetting when given (the
/// patch is then read as if at the optical axis). Merged values times this scale are radiance.
pub fn radiance_scale(
    hdr: &HdrImage,
    patch: PixelRect,
    known_radiance: f32,
    vignetting: Option<&Vignetting>,
) -> Result<f32, PhotometricError> {
    if !(known_radiance.is_finite() && known_radiance > 0.0) {
        return Err(PhotometricError::KnownRadiance(known_radiance));
    }
    let inside = patch.width > 0
        && patch.height > 0
        && u64::from(patch.x) + u64::from(patch.width) <= u64::from(hdr.width)
        && u64::from(patch.y) + u64::from(patch.height) <= u64::from(hdr.height);
    if !inside {
        return Err(PhotometricError::PatchOutside {
            patch,
            width: hdr.width,
            height: hdr.height,
        });
    }
    let (mut sum, mut n) = (0.0f64, 0u32);
    for y in patch.y..patch.y + patch.height {
        for x in patch.x..patch.x + patch.width {
            let i = y as usize * hdr.width as usize + x as usize;
            let (Some(rgb), Some(&saturated)) = (hdr.radiance.get(i), hdr.saturated.get(i)) else {
                continue;
            };
            let falloff = vignetting.map_or(Some(1.0), |v| v.factor_at(f64::from(x), f64::from(y)));
            let luminance = rgb.dot(LUMINANCE);
            match falloff {
                Some(v) if !saturated && luminance > 0.0 && luminance.is_finite() && v > 0.0 => {
                    sum += f64::from(luminance) / v;
                    n += 1;
                }
                _ => {}
            }
        }
    }
    if n == 0 {
        return Err(PhotometricError::PatchUnusable { patch });
    }
    Ok((f64::from(known_radiance) / (sum / f64::from(n))) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usable_codes_stop_at_sparse_codes_and_wide_bins() {
        let settings = ResponseSettings::default();
        let linear: Vec<f32> = (0..RESPONSE_LEN).map(|m| m as f32 / 128.0).collect();
        let mut counts = [100u32; RESPONSE_LEN];
        // A linear curve's bins are 1/m wide: w²/12 ≤ 0.005 from m ≥ 1/√0.06 ≈ 4.08.
        assert_eq!(usable_codes(&linear, &counts, &settings), 5..=254);
        counts[40] = 3;
        counts[200] = 0;
        assert_eq!(usable_codes(&linear, &counts, &settings), 41..=199);
        counts[MID_CODE] = 0;
        assert_eq!(usable_codes(&linear, &counts, &settings), 128..=128);
        // γ = 2.2: w ≈ 2.2 / m, usable from m ≥ 2.2 / √0.06 ≈ 9.
        let gamma: Vec<f32> = (0..RESPONSE_LEN)
            .map(|m| (m as f32 / 128.0).powf(2.2))
            .collect();
        let counts = [100u32; RESPONSE_LEN];
        assert_eq!(usable_codes(&gamma, &counts, &settings), 9..=254);
    }

    #[test]
    fn regularising_fills_gaps_pins_the_ends_and_normalises() {
        let mut counts = [0u32; RESPONSE_LEN];
        let mut raw = vec![f32::NAN; RESPONSE_LEN];
        for m in [10usize, 100, 128, 130, 200, 253, 254] {
            counts[m] = 5;
            raw[m] = m as f32 * 0.5;
        }
        raw[130] = 60.0; // a violation: pooled with 128
        let table = regularised(&raw, &counts).unwrap();
        assert_eq!(table[0], 0.0);
        assert_eq!(table[MID_CODE], 1.0);
        assert!(table.windows(2).all(|w| w[1] >= w[0]));
        assert!((table[255] - (2.0 * table[254] - table[253])).abs() < 1e-6);
        assert!((table[55] / table[10] - 5.5).abs() < 1e-3, "interpolated");
        counts[MID_CODE] = 0;
        assert!(regularised(&raw, &counts).is_err());
    }
}
