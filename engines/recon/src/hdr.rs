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
//! [`recover_response`] computes the minimiser of that objective directly rather than by
//! alternating (see there), and needs a *calibration* bracket: at least three exposures whose
//! ratios are not all powers of one ratio — an evenly spaced bracket (×4, ×4, ×4) leaves the
//! curve undetermined ([`HdrError::CommensurateExposures`]). [`merge`] works with any bracket.
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

/// How [`recover_response`] samples and regularises.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecoverySettings {
    /// At most this many pixel-channels enter the estimation, spread evenly over those that are
    /// well exposed in at least two exposures.
    pub max_samples: usize,
    /// Weight of the second-difference penalty `Σ (I_{m−1} − 2 I_m + I_{m+1})²`, relative to the
    /// mean diagonal of the data term. It only matters for codes no sample shows (they are
    /// interpolated smoothly) and keeps the system definite.
    pub smoothness: f64,
}

impl Default for RecoverySettings {
    fn default() -> Self {
        Self {
            max_samples: 30_000,
            smoothness: 1e-3,
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

/// Recovers the probe's inverse response from a bracket of the same (static) view: the
/// minimiser of Robertson's objective `Σ_ij w(y_ij) (I(y_ij) − t_i x_j)²` under `I_128 = 1`.
///
/// Robertson et al. minimise it by alternating the two updates of the module docs. That
/// iteration converges very slowly in the curve's low-frequency modes (after 500 iterations a
/// 4-exposure bracket still showed 20% steps), so the same minimiser is computed directly: the
/// `x`-update is linear in `I`, so substituting it makes every residual
/// `I(y_ij) − t_i Σ_k w_kj t_k I(y_kj) / Σ_k w_kj t_k²` linear in `I`, and the objective a linear
/// least-squares problem in the 254 inner codes, solved through its normal equations (Cholesky,
/// f64) with `I_128` moved to the right-hand side.
///
/// The bracket must not be a ladder of one ratio ([`HdrError::CommensurateExposures`], e.g.
/// 250/2000/16000 µs; 1000/3000/11000/64000 µs works). Only pixel-channels with codes in
/// 1–254 in at least two exposures tell anything about the curve; up to [`RecoverySettings::max_samples`] of them, evenly spread, are used. A small
/// second-difference penalty interpolates codes no sample shows. Then the curve is made
/// non-decreasing (weighted pool-adjacent-violators regression, weights = sample counts) and
/// two codes are pinned: `I_0 = 0`, and `I_255`, the exposure where the sensor reaches full
/// scale, extrapolated linearly from codes 253 and 254 (the saturated code's own samples only
/// bound it from below).
pub fn recover_response<B: Borrow<ProbeImage>>(
    brackets: &[B],
    settings: &RecoverySettings,
) -> Result<Response, HdrError> {
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
    let samples = informative_samples(&exposures, settings.max_samples);
    if samples.is_empty() {
        return Err(HdrError::NoOverlap);
    }

    // Normal equations over the inner codes 1..=254 (unknown k is code k + 1).
    const INNER: usize = RESPONSE_LEN - 2;
    let mut normal = vec![0.0f64; INNER * INNER];
    let mut counts = [0.0f64; RESPONSE_LEN];
    let mut codes = vec![0u8; times.len()];
    let mut residual: Vec<(usize, f64)> = Vec::with_capacity(times.len());
    for &k in &samples {
        for (code, e) in codes.iter_mut().zip(&exposures) {
            *code = e.codes[k];
        }
        let weights: Vec<f64> = codes.iter().map(|&c| certainty(c)).collect();
        let denominator: f64 = weights.iter().zip(&times).map(|(w, t)| w * t * t).sum();
        for (i, (&code_i, &w_i)) in codes.iter().zip(&weights).enumerate() {
            if w_i == 0.0 {
                continue;
            }
            counts[usize::from(code_i)] += 1.0;
            // r = I(y_i) − t_i Σ_k (w_k t_k / D) I(y_k), as sparse coefficients on codes.
            residual.clear();
            residual.push((usize::from(code_i) - 1, 1.0));
            for (&code_k, (&w_k, &t_k)) in codes.iter().zip(weights.iter().zip(&times)) {
                if w_k > 0.0 {
                    let c = -times[i] * w_k * t_k / denominator;
                    match residual
                        .iter_mut()
                        .find(|(u, _)| *u == usize::from(code_k) - 1)
                    {
                        Some((_, v)) => *v += c,
                        None => residual.push((usize::from(code_k) - 1, c)),
                    }
                }
            }
            for &(a, ca) in &residual {
                for &(b, cb) in &residual {
                    normal[a * INNER + b] += w_i * ca * cb;
                }
            }
        }
    }
    let mean_diagonal = (0..INNER).map(|k| normal[k * INNER + k]).sum::<f64>() / INNER as f64;
    let lambda = settings.smoothness.max(0.0) * mean_diagonal.max(f64::MIN_POSITIVE);
    for k in 1..INNER - 1 {
        let stencil = [(k - 1, 1.0), (k, -2.0), (k + 1, 1.0)];
        for &(a, ca) in &stencil {
            for &(b, cb) in &stencil {
                normal[a * INNER + b] += lambda * ca * cb;
            }
        }
    }
    // Fix I_128 = 1: drop its row and column, move its column to the right-hand side.
    let pinned = Response::MID_CODE - 1;
    let free: Vec<usize> = (0..INNER).filter(|&k| k != pinned).collect();
    let n = free.len();
    let mut system = vec![0.0f64; n * n];
    let mut rhs = vec![0.0f64; n];
    for (r, &a) in free.iter().enumerate() {
        rhs[r] = -normal[a * INNER + pinned];
        for (c, &b) in free.iter().enumerate() {
            system[r * n + c] = normal[a * INNER + b];
        }
    }
    let solution = cholesky_solve(&mut system, &mut rhs, n).ok_or(HdrError::NoOverlap)?;
    let mut estimate = [0.0f64; RESPONSE_LEN];
    for (&k, &v) in free.iter().zip(&solution) {
        estimate[k + 1] = v;
    }
    estimate[Response::MID_CODE] = 1.0;
    let curve = regularised(&estimate, &counts);
    tracing::debug!(
        samples = samples.len(),
        "recovered the probe response (Robertson's objective)"
    );
    Ok(Response {
        inverse: curve.iter().map(|&v| v as f32).collect(),
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

/// Solves the symmetric positive definite `n × n` system in place (Cholesky); `None` when it is
/// not numerically positive definite or the solution is not finite.
fn cholesky_solve(a: &mut [f64], b: &mut [f64], n: usize) -> Option<Vec<f64>> {
    for j in 0..n {
        let mut diagonal = a[j * n + j];
        for k in 0..j {
            diagonal -= a[j * n + k] * a[j * n + k];
        }
        if !(diagonal > 0.0 && diagonal.is_finite()) {
            return None;
        }
        let diagonal = diagonal.sqrt();
        a[j * n + j] = diagonal;
        for i in j + 1..n {
            let mut value = a[i * n + j];
            for k in 0..j {
                value -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = value / diagonal;
        }
    }
    for i in 0..n {
        let mut value = b[i];
        for k in 0..i {
            value -= a[i * n + k] * b[k];
        }
        b[i] = value / a[i * n + i];
    }
    for i in (0..n).rev() {
        let mut value = b[i];
        for k in i + 1..n {
            value -= a[k * n + i] * b[k];
        }
        b[i] = value / a[i * n + i];
    }
    b.iter().all(|v| v.is_finite()).then(|| b.to_vec())
}

/// Indices (into the interleaved RGB codes) of at most `max_samples` pixel-channels that are
/// well exposed in two or more exposures, evenly spread over all such pixel-channels.
fn informative_samples(exposures: &[Exposure<'_>], max_samples: usize) -> Vec<usize> {
    let len = exposures.first().map_or(0, |e| e.codes.len());
    let informative: Vec<usize> = (0..len)
        .filter(|&k| {
            exposures
                .iter()
                .filter(|e| certainty(e.codes[k]) > 0.0)
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
fn robertson_radiance(codes: &[u8], times: &[f64], inverse: &[f64]) -> Option<f64> {
    let (mut numerator, mut denominator) = (0.0, 0.0);
    for (&code, &t) in codes.iter().zip(times) {
        let w = certainty(code);
        numerator += w * t * inverse[usize::from(code)];
        denominator += w * t * t;
    }
    (denominator > 0.0).then(|| numerator / denominator)
}

/// A solved curve made valid: non-decreasing over the inner codes (weights: sample counts, a
/// small floor for codes no sample shows), non-negative, `I_0 = 0`, `I_255` extrapolated,
/// `I_128 = 1`.
fn regularised(estimate: &[f64; RESPONSE_LEN], counts: &[f64; RESPONSE_LEN]) -> Vec<f64> {
    let last = RESPONSE_LEN - 1;
    let weights: Vec<f64> = counts[1..last].iter().map(|c| c.max(1e-3)).collect();
    let monotone = pool_adjacent_violators(&estimate[1..last], &weights);
    let mut curve = vec![0.0f64; RESPONSE_LEN];
    for (value, fitted) in curve[1..last].iter_mut().zip(monotone) {
        *value = fitted.max(0.0);
    }
    curve[last] = (2.0 * curve[last - 1] - curve[last - 2]).max(curve[last - 1]);
    let mid = curve[Response::MID_CODE];
    if mid > 0.0 && mid.is_finite() {
        for v in &mut curve {
            *v /= mid;
        }
    }
    curve
}

/// Weighted isotonic (non-decreasing) regression: the pool-adjacent-violators algorithm.
fn pool_adjacent_violators(values: &[f64], weights: &[f64]) -> Vec<f64> {
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
                    let value = match robertson_radiance(codes, &times, &inverse) {
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
