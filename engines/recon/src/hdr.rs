//! HDR radiance from a bracket of 8-bit probe exposures, after Robertson, Borman & Stevenson,
//! "Estimation-theoretic approach to dynamic range enhancement using multiple exposures"
//! (J. Electronic Imaging 12(2), 2003) — the method the reflection-map paper (Kan et al.) uses
//! for its environment map.
//!
//! A pixel `j` of exposure `i` (effective exposure time `t_i`) records the code
//! `y_ij = f(t_i x_j)`, where `x_j` is the pixel's radiance and `f` the camera's response. Robertson
//! et al. estimate the inverse response `I_m = f⁻¹(m)` and the radiances together by minimising
//! `Σ_ij w(y_ij) (I(y_ij) − t_i x_j)²`, alternating the two closed-form minimisers
//!
//! - `x_j = Σ_i w(y_ij) t_i I(y_ij) / Σ_i w(y_ij) t_i²` (the HDR merge, also used on its own), and
//! - `I_m = mean of t_i x_j over the samples with y_ij = m` (the response update),
//!
//! with `w` the Gaussian certainty `exp(−4 (y − 127.5)² / 127.5²)`. The response is only known up
//! to a scale; this module fixes it at `I_128 = 1` ([`Response::MID_CODE`]).
//!
//! [`recover_response`] needs a *calibration* bracket: at least three exposures whose ratios are
//! not all powers of one ratio. With an evenly spaced bracket (×4, ×4, ×4) every constraint
//! compares exposures a power of 4 apart, so the curve is determined only up to a factor periodic
//! in log exposure (Grossberg & Nayar, "What can be known about the radiometric response from
//! images?", 2003): on the simulator such a bracket left 20–30% errors however the objective was
//! minimised, and it is refused ([`HdrError::CommensurateExposures`]). [`merge`] works with any
//! bracket.
//!
//! Units: effective exposure is `exposure_us · 10⁻⁶ · 10^(gain_db / 20)` seconds (gain is an
//! amplitude gain in dB), so merged radiance is in response units per second. A photometric
//! calibration (or the simulator's `exposure_scale`) turns that into W/(m²·sr).

use std::borrow::Borrow;

use glam::Vec3;
use rayon::prelude::*;
use relight_core::rig::RigCalibration;
use relight_core::{PixelFormat, ProbeImage};

/// Entries of an 8-bit inverse response.
pub const RESPONSE_LEN: usize = 256;
/// The saturated code: only a lower bound on the exposure that produced it.
const SATURATED: u8 = 255;
/// The black code: carries no information beyond "below code 1".
const BLACK: u8 = 0;

/// Why a bracket cannot be merged, or a response not recovered.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HdrError {
    #[error("no exposures given")]
    NoBrackets,
    #[error("exposure {index} is {actual:?}, only Rgb8 probe images are supported")]
    Format { index: usize, actual: PixelFormat },
    #[error(
        "exposure {index} is {width}×{height}, exposure 0 is {expected_width}×{expected_height}"
    )]
    SizeMismatch {
        index: usize,
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error(
        "exposure {index} has exposure {exposure_us} µs at gain {gain_db} dB, not a positive time"
    )]
    InvalidExposure {
        index: usize,
        exposure_us: u32,
        gain_db: f32,
    },
    #[error("recovering a response needs at least two different exposures")]
    EqualExposures,
    #[error(
        "every exposure time is the shortest times a power of {ratio:.3}: such a bracket fixes \
         the response only up to a factor periodic in log exposure (Grossberg & Nayar 2003); \
         add an exposure off that ladder (e.g. at ×{half:.3})",
        half = ratio.sqrt()
    )]
    CommensurateExposures { ratio: f64 },
    #[error(
        "no pixel is well exposed (codes 1–254) in two exposures: the bracket carries no \
         information about the response"
    )]
    NoOverlap,
    #[error("an inverse response has {RESPONSE_LEN} entries, got {len}")]
    ResponseLength { len: usize },
    #[error(
        "inverse response entry {code} is {value}: entries must be finite, non-negative and \
         non-decreasing, and code {mid} must map to a positive value",
        mid = Response::MID_CODE
    )]
    ResponseValue { code: usize, value: f32 },
}

/// An inverse camera response `I_m`: 8-bit code `m` → relative exposure (radiance × time), one
/// curve shared by the three channels, as [`RigCalibration::probe_response`] stores it.
///
/// Invariants: 256 finite, non-negative, non-decreasing entries with `I_128 > 0`. Curves
/// recovered by [`recover_response`] are normalised to `I_128 = 1`; tables read with
/// [`Response::from_table`] keep their scale (a table calibrated in absolute units stays so).
#[derive(Debug, Clone, PartialEq)]
pub struct Response {
    inverse: Vec<f32>,
}

impl Response {
    /// The code whose exposure normalises a recovered curve: `I_128 = 1`.
    pub const MID_CODE: usize = 128;

    /// A linear camera, `I_m = m / 128`.
    pub fn linear() -> Self {
        Self {
            inverse: (0..RESPONSE_LEN)
                .map(|m| m as f32 / Self::MID_CODE as f32)
                .collect(),
        }
    }

    /// A response from its 256-entry inverse table, checked against the invariants.
    pub fn from_table(table: &[f32]) -> Result<Self, HdrError> {
        if table.len() != RESPONSE_LEN {
            return Err(HdrError::ResponseLength { len: table.len() });
        }
        let mut previous = 0.0f32;
        for (code, &value) in table.iter().enumerate() {
            let mid_ok = code != Self::MID_CODE || value > 0.0;
            if !value.is_finite() || value < previous || !mid_ok {
                return Err(HdrError::ResponseValue { code, value });
            }
            previous = value;
        }
        Ok(Self {
            inverse: table.to_vec(),
        })
    }

    /// The probe's response from a rig calibration.
    pub fn from_calibration(rig: &RigCalibration) -> Result<Self, HdrError> {
        Self::from_table(&rig.probe_response)
    }

    /// The 256 entries, code order.
    pub fn table(&self) -> &[f32] {
        &self.inverse
    }

    /// Relative exposure of `code`.
    pub fn exposure(&self, code: u8) -> f32 {
        self.inverse[usize::from(code)]
    }

    /// The same curve scaled so that `I_128 = 1`.
    pub fn normalized(&self) -> Self {
        let mid = self.inverse[Self::MID_CODE];
        Self {
            inverse: self.inverse.iter().map(|v| v / mid).collect(),
        }
    }
}

/// Robertson's certainty of a code: `exp(−4 (y − 127.5)² / 127.5²)`, and zero for the black and
/// saturated codes, which only bound the exposure.
pub fn certainty(code: u8) -> f64 {
    if code == BLACK || code == SATURATED {
        return 0.0;
    }
    let d = (f64::from(code) - 127.5) / 127.5;
    (-4.0 * d * d).exp()
}

/// [`certainty`] of every code.
fn certainty_table() -> [f64; RESPONSE_LEN] {
    std::array::from_fn(|m| certainty(m as u8))
}

/// A merged HDR probe image.
#[derive(Debug, Clone, PartialEq)]
pub struct HdrImage {
    pub width: u32,
    pub height: u32,
    /// Row-major linear radiance, response units per second (see the module docs).
    pub radiance: Vec<Vec3>,
    /// Pixels where a channel was saturated in every exposure that was not black: their
    /// radiance there is a lower bound (see [`merge`]).
    pub saturated: Vec<bool>,
}

/// How [`recover_response`] samples and iterates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecoverySettings {
    /// At most this many pixel-channels enter the estimation, spread evenly over those that are
    /// well exposed in at least two exposures.
    pub max_samples: usize,
    /// Iterations of the alternating minimisation at most.
    pub max_iterations: usize,
    /// Stop when no entry of the normalised curve moves by more than this (`I_128 = 1`).
    pub tolerance: f64,
}

impl Default for RecoverySettings {
    fn default() -> Self {
        Self {
            max_samples: 30_000,
            max_iterations: 200,
            tolerance: 1e-4,
        }
    }
}

/// One checked exposure: its codes (RGB interleaved) and effective exposure time, seconds.
struct Exposure<'a> {
    codes: &'a [u8],
    time_s: f64,
}

fn checked<B: Borrow<ProbeImage>>(
    brackets: &[B],
) -> Result<(u32, u32, Vec<Exposure<'_>>), HdrError> {
    let first = brackets.first().ok_or(HdrError::NoBrackets)?.borrow();
    let (width, height) = (first.image.width(), first.image.height());
    let mut out = Vec::with_capacity(brackets.len());
    for (index, probe) in brackets.iter().enumerate() {
        let probe = probe.borrow();
        let image = &probe.image;
        if image.format() != PixelFormat::Rgb8 {
            return Err(HdrError::Format {
                index,
                actual: image.format(),
            });
        }
        if (image.width(), image.height()) != (width, height) {
            return Err(HdrError::SizeMismatch {
                index,
                width: image.width(),
                height: image.height(),
                expected_width: width,
                expected_height: height,
            });
        }
        let time_s =
            f64::from(probe.exposure_us) * 1e-6 * 10f64.powf(f64::from(probe.gain_db) / 20.0);
        let codes = image.as_u8().ok_or(HdrError::Format {
            index,
            actual: image.format(),
        })?;
        if !(time_s.is_finite() && time_s > 0.0) || codes.len() != 3 * image.pixel_count() {
            return Err(HdrError::InvalidExposure {
                index,
                exposure_us: probe.exposure_us,
                gain_db: probe.gain_db,
            });
        }
        out.push(Exposure { codes, time_s });
    }
    Ok((width, height, out))
}

/// The checks [`recover_response`] makes of a bracket before estimating anything: sizes, `Rgb8`,
/// positive exposure times, at least two different times, no ladder of one ratio
/// ([`HdrError::CommensurateExposures`]) and some pixel-channel well exposed in two exposures.
pub fn check_bracket<B: Borrow<ProbeImage>>(brackets: &[B]) -> Result<(), HdrError> {
    let exposures = calibration_bracket(brackets)?;
    if informative_samples(&exposures, 1).is_empty() {
        return Err(HdrError::NoOverlap);
    }
    Ok(())
}

/// The bracket's exposures when its times can determine a response curve.
fn calibration_bracket<B: Borrow<ProbeImage>>(
    brackets: &[B],
) -> Result<Vec<Exposure<'_>>, HdrError> {
    let (_, _, exposures) = checked(brackets)?;
    let (shortest, longest) = exposures
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), e| {
            (lo.min(e.time_s), hi.max(e.time_s))
        });
    if longest <= shortest * (1.0 + 1e-9) {
        return Err(HdrError::EqualExposures);
    }
    let times: Vec<f64> = exposures.iter().map(|e| e.time_s).collect();
    if let Some(ratio) = common_ratio(&times) {
        return Err(HdrError::CommensurateExposures { ratio });
    }
    Ok(exposures)
}

/// Recovers the probe's inverse response from a bracket of the same (static) view by
/// Robertson's alternating minimisation (module docs), normalised to `I_128 = 1`, starting from
/// a linear curve.
///
/// The bracket must not be a ladder of one ratio ([`HdrError::CommensurateExposures`], e.g.
/// 250/2000/16000 µs; 1000/3000/11000/64000 µs works). Only pixel-channels with codes in 1–254
/// in at least two exposures tell anything about the curve; up to
/// [`RecoverySettings::max_samples`] of them, evenly spread, are used. After every response
/// update the curve is made non-decreasing (weighted pool-adjacent-violators regression,
/// weights = sample counts), codes no sample shows are interpolated linearly between their
/// neighbours (extrapolated linearly above the highest), and two codes are pinned: `I_0 = 0`,
/// and `I_255`, the exposure where the sensor reaches full scale, extrapolated linearly from codes
/// 253 and 254 (the saturated code's own samples only bound it from below). On the simulator's
/// curve it is within 1% of the truth after about 30 iterations and meets the default tolerance
/// after about 120; if it has not met the tolerance after
/// [`RecoverySettings::max_iterations`], the last curve is returned (and logged).
pub fn recover_response<B: Borrow<ProbeImage>>(
    brackets: &[B],
    settings: &RecoverySettings,
) -> Result<Response, HdrError> {
    let exposures = calibration_bracket(brackets)?;
    let times: Vec<f64> = exposures.iter().map(|e| e.time_s).collect();
    let samples = informative_samples(&exposures, settings.max_samples);
    if samples.is_empty() {
        return Err(HdrError::NoOverlap);
    }
    // codes[s * stride + i]: code of sample s in exposure i.
    let stride = times.len();
    let codes: Vec<u8> = samples
        .iter()
        .flat_map(|&k| exposures.iter().map(move |e| e.codes[k]))
        .collect();
    let weights = certainty_table();
    let mut counts = [0.0f64; RESPONSE_LEN];
    for &code in &codes {
        if weights[usize::from(code)] > 0.0 {
            counts[usize::from(code)] += 1.0;
        }
    }

    let mut inverse: Vec<f64> = (0..RESPONSE_LEN)
        .map(|m| m as f64 / Response::MID_CODE as f64)
        .collect();
    let mut iterations = 0;
    let mut change = f64::INFINITY;
    while iterations < settings.max_iterations && change > settings.tolerance {
        iterations += 1;
        let mut sums = [0.0f64; RESPONSE_LEN];
        for sample in codes.chunks_exact(stride) {
            let Some(x) = robertson_radiance(sample, &times, &inverse, &weights) else {
                continue;
            };
            for (&code, &t) in sample.iter().zip(&times) {
                if weights[usize::from(code)] > 0.0 {
                    sums[usize::from(code)] += t * x;
                }
            }
        }
        let mut estimate = [0.0f64; RESPONSE_LEN];
        for ((e, sum), count) in estimate.iter_mut().zip(sums).zip(counts) {
            if count > 0.0 {
                *e = sum / count;
            }
        }
        let updated = regularised(&estimate, &counts);
        change = updated
            .iter()
            .zip(&inverse)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        inverse = updated;
    }
    if change > settings.tolerance {
        tracing::debug!(
            iterations,
            change,
            "response recovery stopped before converging"
        );
    }
    tracing::debug!(
        iterations,
        samples = samples.len(),
        "recovered the probe response (Robertson)"
    );
    Ok(Response {
        inverse: inverse.iter().map(|&v| v as f32).collect(),
    })
}

/// Smallest ladder ratio searched for: finer ladders fit any three exposures by chance.
const MIN_AMBIGUOUS_RATIO: f64 = 1.5;
/// How far (in steps of the ladder) an exposure may sit from a rung and still count as on it:
/// 1/3.3/11/36 ms (off by < 0.01 step) recovered the simulated curve with 14% errors, 1/3/11 ms
/// (0.08 step) within 4%.
const RUNG_TOLERANCE: f64 = 0.05;

/// The largest ratio `r ≥ 1.5` such that every exposure time is `t_min · r^k` for an integer `k`
/// (within 0.05 of a step), if there is one; with only two distinct times, their ratio.
///
/// With such a ladder, if `I` explains the data then so does `I · p(ln I)` for any `p` periodic
/// with period `ln r`: the constraints only ever compare exposures a power of `r` apart. Only
/// 8-bit quantisation then separates the true curve from its distortions, which in practice
/// leaves errors of tens of percent.
fn common_ratio(times: &[f64]) -> Option<f64> {
    let shortest = times.iter().copied().fold(f64::INFINITY, f64::min);
    let mut logs: Vec<f64> = times
        .iter()
        .map(|t| (t / shortest).ln())
        .filter(|&l| l > 1e-9)
        .collect();
    logs.sort_by(f64::total_cmp);
    logs.dedup_by(|a, b| (*a - *b).abs() <= 1e-9);
    if let [single] = logs.as_slice() {
        return Some(single.exp());
    }
    let min_period = MIN_AMBIGUOUS_RATIO.ln();
    let mut best: Option<f64> = None;
    for &l in &logs {
        for steps in 1..=64 {
            let period = l / f64::from(steps);
            if period < min_period {
                break;
            }
            let on_ladder = logs.iter().all(|&m| {
                let rungs = m / period;
                (rungs - rungs.round()).abs() <= RUNG_TOLERANCE
            });
            if on_ladder && best.is_none_or(|b| period > b) {
                best = Some(period);
            }
        }
    }
    best.map(f64::exp)
}

/// Indices (into the interleaved RGB codes) of at most `max_samples` pixel-channels that are
/// well exposed in two or more exposures, evenly spread over all such pixel-channels.
fn informative_samples(exposures: &[Exposure<'_>], max_samples: usize) -> Vec<usize> {
    let len = exposures.first().map_or(0, |e| e.codes.len());
    let informative: Vec<usize> = (0..len)
        .filter(|&k| {
            exposures
                .iter()
                .filter(|e| e.codes[k] != BLACK && e.codes[k] != SATURATED)
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

/// Robertson's radiance of one pixel-channel, `Σ w t I(y) / Σ w t²`; `None` without any
/// well-exposed code.
fn robertson_radiance(
    codes: &[u8],
    times: &[f64],
    inverse: &[f64],
    weights: &[f64; RESPONSE_LEN],
) -> Option<f64> {
    let (mut numerator, mut denominator) = (0.0, 0.0);
    for (&code, &t) in codes.iter().zip(times) {
        let w = weights[usize::from(code)];
        numerator += w * t * inverse[usize::from(code)];
        denominator += w * t * t;
    }
    (denominator > 0.0).then(|| numerator / denominator)
}

/// A response update made a valid curve: non-decreasing over the observed inner codes, gaps
/// filled, `I_0 = 0`, `I_255` extrapolated, `I_128 = 1`.
fn regularised(estimate: &[f64; RESPONSE_LEN], counts: &[f64; RESPONSE_LEN]) -> Vec<f64> {
    let last = RESPONSE_LEN - 1;
    let observed: Vec<usize> = (1..last).filter(|&m| counts[m] > 0.0).collect();
    let monotone = pool_adjacent_violators(
        &observed.iter().map(|&m| estimate[m]).collect::<Vec<_>>(),
        &observed.iter().map(|&m| counts[m]).collect::<Vec<_>>(),
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
    let mid = curve[Response::MID_CODE];
    if mid > 0.0 && mid.is_finite() {
        for v in &mut curve {
            *v /= mid;
        }
    }
    curve
}

/// Weighted isotonic (non-decreasing) regression: the pool-adjacent-violators algorithm.
pub fn pool_adjacent_violators(values: &[f64], weights: &[f64]) -> Vec<f64> {
    // Blocks of (mean, weight, length).
    let mut blocks: Vec<(f64, f64, usize)> = Vec::with_capacity(values.len());
    for (&v, &w) in values.iter().zip(weights) {
        blocks.push((v, w, 1));
        while blocks.len() >= 2 {
            let (b_mean, b_weight, b_len) = blocks[blocks.len() - 1];
            let (a_mean, a_weight, a_len) = blocks[blocks.len() - 2];
            if a_mean <= b_mean {
                break;
            }
            let weight = a_weight + b_weight;
            let mean = (a_mean * a_weight + b_mean * b_weight) / weight;
            blocks.truncate(blocks.len() - 2);
            blocks.push((mean, weight, a_len + b_len));
        }
    }
    blocks
        .into_iter()
        .flat_map(|(mean, _, len)| std::iter::repeat_n(mean, len))
        .collect()
}

/// Linear interpolation through `(x, y)` anchors sorted by `x`, linear extrapolation beyond the
/// last two (flat with only one), never below the last anchor.
pub fn piecewise_linear(anchors: &[(f64, f64)], x: f64) -> f64 {
    let upper = anchors.partition_point(|&(ax, _)| ax < x);
    let below = upper.checked_sub(1).and_then(|i| anchors.get(i));
    match (below, anchors.get(upper)) {
        (_, Some(&(ax, ay))) if ax == x => ay,
        (Some(&(x0, y0)), Some(&(x1, y1))) => y0 + (y1 - y0) * (x - x0) / (x1 - x0),
        (Some(&(x1, y1)), None) => match upper.checked_sub(2).and_then(|i| anchors.get(i)) {
            Some(&(x0, y0)) if x1 > x0 => (y1 + (y1 - y0) / (x1 - x0) * (x - x1)).max(y1),
            _ => y1,
        },
        (None, Some(&(_, y1))) => y1,
        (None, None) => 0.0,
    }
}

/// Merges a bracket into HDR radiance with Robertson's estimator
/// `x = Σ_i w(y_i) t_i I(y_i) / Σ_i w(y_i) t_i²`, per pixel and channel.
///
/// Where a channel carries no well-exposed code:
/// - saturated (255) in some exposure: the best lower bound, `I_255 / t` for the shortest
///   saturated exposure `t` (the radiance that just reaches full scale there); the pixel is
///   flagged in [`HdrImage::saturated`];
/// - black (0) in every exposure: 0 (the radiance is below `I_1 / t_longest`, indistinguishable
///   from none).
///
/// Equal exposure times are fine here (they average). The result is always finite and
/// non-negative.
pub fn merge<B: Borrow<ProbeImage>>(
    brackets: &[B],
    response: &Response,
) -> Result<HdrImage, HdrError> {
    let (width, height, exposures) = checked(brackets)?;
    let inverse: Vec<f64> = response.table().iter().map(|&v| f64::from(v)).collect();
    let times: Vec<f64> = exposures.iter().map(|e| e.time_s).collect();
    let full_scale = inverse[usize::from(SATURATED)];
    let weights = certainty_table();
    let pixels = width as usize * height as usize;
    let merged: Vec<(Vec3, bool)> = (0..pixels)
        .into_par_iter()
        .map_init(
            || vec![0u8; exposures.len()],
            |codes, p| {
                let mut rgb = [0.0f32; 3];
                let mut saturated = false;
                for (c, out) in rgb.iter_mut().enumerate() {
                    for (code, e) in codes.iter_mut().zip(&exposures) {
                        *code = e.codes[3 * p + c];
                    }
                    let value = match robertson_radiance(codes, &times, &inverse, &weights) {
                        Some(x) => x,
                        None => {
                            let shortest_saturated = codes
                                .iter()
                                .zip(&times)
                                .filter(|(code, _)| **code == SATURATED)
                                .map(|(_, &t)| t)
                                .fold(f64::INFINITY, f64::min);
                            if shortest_saturated.is_finite() {
                                saturated = true;
                                full_scale / shortest_saturated
                            } else {
                                0.0
                            }
                        }
                    };
                    *out = if value.is_finite() {
                        value.max(0.0) as f32
                    } else {
                        0.0
                    };
                }
                (Vec3::from_array(rgb), saturated)
            },
        )
        .collect();
    let (radiance, saturated) = merged.into_iter().unzip();
    Ok(HdrImage {
        width,
        height,
        radiance,
        saturated,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pava_pools_violations_and_keeps_order() {
        let fitted = pool_adjacent_violators(&[1.0, 3.0, 2.0, 4.0], &[1.0, 1.0, 1.0, 1.0]);
        assert_eq!(fitted, vec![1.0, 2.5, 2.5, 4.0]);
        let weighted = pool_adjacent_violators(&[2.0, 1.0], &[3.0, 1.0]);
        assert_eq!(weighted, vec![1.75, 1.75]);
    }

    #[test]
    fn ladders_of_one_ratio_are_found() {
        let ratio = |t: &[f64]| common_ratio(t).map(|r| (r * 1e3).round() / 1e3);
        assert_eq!(ratio(&[250.0, 2000.0, 16000.0]), Some(8.0));
        assert_eq!(ratio(&[1.0, 4.0, 16.0, 64.0]), Some(4.0));
        assert_eq!(ratio(&[1.0, 4.0]), Some(4.0));
        assert_eq!(ratio(&[1.0, 1.25, 1.0]), Some(1.25));
        assert_eq!(ratio(&[1.0, 2.0, 8.0]), Some(2.0));
        assert_eq!(ratio(&[1000.0, 3000.0, 11000.0, 64000.0]), None);
        assert_eq!(ratio(&[1000.0, 2700.0, 6400.0, 19000.0, 64000.0]), None);
    }

    #[test]
    fn interpolation_fills_gaps_and_extrapolates_upwards() {
        let anchors = [(0.0, 0.0), (2.0, 2.0), (4.0, 6.0)];
        assert_eq!(piecewise_linear(&anchors, 1.0), 1.0);
        assert_eq!(piecewise_linear(&anchors, 3.0), 4.0);
        assert_eq!(piecewise_linear(&anchors, 5.0), 8.0);
        assert_eq!(piecewise_linear(&[(0.0, 0.0)], 7.0), 0.0);
    }

    #[test]
    fn tables_are_validated() {
        assert!(Response::from_table(&[0.0; 3]).is_err());
        let mut table = Response::linear().table().to_vec();
        assert!(Response::from_table(&table).is_ok());
        table[10] = f32::NAN;
        assert!(matches!(
            Response::from_table(&table),
            Err(HdrError::ResponseValue { code: 10, .. })
        ));
        table[10] = 100.0;
        assert!(Response::from_table(&table).is_err());
    }
}
