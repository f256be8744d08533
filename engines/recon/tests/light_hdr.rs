//! HDR merge of probe brackets (Robertson et al. 2003) against the simulator's truth: the
//! recovered response curve against the camera's, merged radiance against the radiance each
//! pixel integrated, and the hard cases (all dark, saturated in every exposure, bad input).

mod light_support;

use glam::Vec3;
use light_support::*;
use relight_core::rig::RigCalibration;
use relight_core::{Image, PixelFormat, ProbeImage};
use relight_recon::hdr::{HdrError, RecoverySettings, Response, merge, recover_response};
use relight_sim::response::CameraResponse;
use relight_sim::rig::equidistant_probe;

/// A smooth, coloured world spanning four decades (1e-3 … 10): every code occurs.
fn wide_range_world(d: Vec3) -> Vec3 {
    let u = 0.5 + 0.25 * ((4.0 * d.x).sin() + (3.0 * d.z + 1.0).cos());
    Vec3::new(1.0, 0.8, 0.6) * 10f32.powf(4.0 * u - 3.0)
}

/// A calibration bracket: ratios ×3, ×3.7, ×5.8, not powers of one ratio.
const CALIBRATION_US: [u32; 4] = [1_000, 3_000, 11_000, 64_000];
/// The brightest direction (10) lands at 0.9 of full scale in the shortest exposure.
const EXPOSURE_SCALE: f32 = 90.0;

/// The true inverse response, normalised like a recovered one (code 128 ↦ 1).
fn true_normalised() -> Vec<f32> {
    let table = CameraResponse::default().inverse_table();
    table.iter().map(|v| v / table[128]).collect()
}

fn worst_error(recovered: &[f32], codes: std::ops::RangeInclusive<usize>) -> (f32, usize) {
    let truth = true_normalised();
    codes
        .map(|m| ((recovered[m] - truth[m]).abs() / truth[m], m))
        .fold((0.0, 0), |a, b| if b.0 > a.0 { b } else { a })
}

#[test]
fn robertson_recovers_the_simulated_response_within_two_percent() {
    let lens = equidistant_probe(128, 185.0);
    for exposures in [&CALIBRATION_US[..], &[1_000, 2_700, 6_400, 19_000, 64_000]] {
        let brackets = bracket(
            &wide_range_world,
            &lens,
            &upward_probe(),
            exposures,
            EXPOSURE_SCALE,
        );
        let start = std::time::Instant::now();
        let response = recover_response(&brackets, &RecoverySettings::default()).unwrap();
        let elapsed = start.elapsed();
        let recovered = response.table();
        assert_eq!(recovered[128], 1.0);
        assert!(recovered.windows(2).all(|w| w[1] >= w[0]), "non-decreasing");
        assert!(recovered.iter().all(|v| v.is_finite()));
        for (lo, hi) in [(1, 254), (2, 254), (4, 254), (8, 250), (16, 240)] {
            let (worst, code) = worst_error(recovered, lo..=hi);
            println!(
                "{exposures:?} µs, codes {lo}..={hi}: worst relative error {worst:.4} (code {code})"
            );
        }
        println!("{exposures:?} µs: recovery took {elapsed:?}");
        let (worst, code) = worst_error(recovered, 8..=250);
        assert!(worst < 0.02, "relative error {worst} at code {code}");
    }
}

#[test]
fn an_evenly_spaced_bracket_is_refused_as_ambiguous() {
    // The rig's default ×8 ladder: every constraint compares exposures a power of 8 apart.
    let lens = equidistant_probe(64, 185.0);
    let brackets = bracket(
        &wide_range_world,
        &lens,
        &upward_probe(),
        &[250, 2_000, 16_000],
        EXPOSURE_SCALE * 4.0,
    );
    match recover_response(&brackets, &RecoverySettings::default()) {
        Err(HdrError::CommensurateExposures { ratio }) => assert!((ratio - 8.0).abs() < 1e-6),
        other => panic!("expected CommensurateExposures, got {other:?}"),
    }
}

/// Relative errors of merged radiance (divided by `scale`) against what each pixel integrated,
/// over pixels that saw light and were not saturated everywhere.
fn merge_errors(response: &Response, scale: f32) -> Vec<f32> {
    let lens = equidistant_probe(128, 185.0);
    let pose = upward_probe();
    let brackets = bracket(
        &wide_range_world,
        &lens,
        &pose,
        &CALIBRATION_US,
        EXPOSURE_SCALE,
    );
    let merged = merge(&brackets, response).unwrap();
    assert_finite(&merged.radiance, "merged radiance");
    let truth = true_probe_radiance(&wide_range_world, &lens, &pose);
    merged
        .radiance
        .iter()
        .zip(&truth.radiance)
        .zip(&merged.saturated)
        .filter(|((_, t), saturated)| t.min_element() > 0.0 && !**saturated)
        .flat_map(|((m, t), _)| (0..3).map(move |c| (m[c] / scale - t[c]).abs() / t[c]))
        .collect()
}

#[test]
fn merged_radiance_matches_what_each_pixel_integrated() {
    // With the camera's true inverse table, merged radiance is radiance × exposure_scale.
    let true_table = CameraResponse::default().inverse_table();
    let calibrated = Response::from_table(&true_table).unwrap();
    let errors = merge_errors(&calibrated, EXPOSURE_SCALE);
    let (median, p99, worst) = (
        quantile(&errors, 0.5),
        quantile(&errors, 0.99),
        quantile(&errors, 1.0),
    );
    println!(
        "true response: {} channel samples, relative error median {median:.5}, p99 {p99:.5}, max {worst:.5}",
        errors.len()
    );
    // Quantisation-limited: the darkest pixels reach only code ~19 in the longest exposure,
    // where half a code is 2.2 × 0.5 / 19 ≈ 5.8% of radiance.
    assert!(median < 0.005 && p99 < 0.04 && worst < 0.12);

    // With the recovered (normalised) curve the unknown scale is 1 / I_true(128).
    let lens = equidistant_probe(128, 185.0);
    let brackets = bracket(
        &wide_range_world,
        &lens,
        &upward_probe(),
        &CALIBRATION_US,
        EXPOSURE_SCALE,
    );
    let recovered = recover_response(&brackets, &RecoverySettings::default()).unwrap();
    let errors = merge_errors(&recovered, EXPOSURE_SCALE / true_table[128]);
    let (median, p99) = (quantile(&errors, 0.5), quantile(&errors, 0.99));
    println!("recovered response: relative error median {median:.5}, p99 {p99:.5}");
    assert!(median < 0.01 && p99 < 0.04);
}

fn rgb8(width: u32, height: u32, fill: u8, exposure_us: u32) -> ProbeImage {
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    image.as_u8_mut().unwrap().fill(fill);
    ProbeImage {
        image,
        exposure_us,
        gain_db: 0.0,
    }
}

#[test]
fn an_all_dark_bracket_merges_to_zero_and_cannot_calibrate() {
    let dark: Vec<ProbeImage> = CALIBRATION_US
        .into_iter()
        .map(|t| rgb8(32, 32, 0, t))
        .collect();
    let merged = merge(&dark, &Response::linear()).unwrap();
    assert!(merged.radiance.iter().all(|&l| l == Vec3::ZERO));
    assert!(merged.saturated.iter().all(|&s| !s));
    assert_eq!(
        recover_response(&dark, &RecoverySettings::default()),
        Err(HdrError::NoOverlap)
    );
}

#[test]
fn pixels_saturated_in_every_exposure_get_the_shortest_exposures_lower_bound() {
    // A sun of 1e6 beside a sky of 1: far beyond full scale even in the shortest exposure.
    let sun = Vec3::new(0.3, 0.9, -0.2).normalize();
    let world = |d: Vec3| {
        if d.dot(sun) > 0.995 {
            Vec3::splat(1e6)
        } else {
            Vec3::splat(1.0)
        }
    };
    let lens = equidistant_probe(64, 185.0);
    let pose = upward_probe();
    let scale = 20.0;
    let brackets = bracket(&world, &lens, &pose, &CALIBRATION_US, scale);
    let table = CameraResponse::default().inverse_table();
    let response = Response::from_table(&table).unwrap();
    let merged = merge(&brackets, &response).unwrap();
    assert_finite(&merged.radiance, "merged radiance");
    let truth = true_probe_radiance(&world, &lens, &pose);
    let codes: Vec<&[u8]> = brackets.iter().map(|b| b.image.as_u8().unwrap()).collect();
    let bound = table[255] / (CALIBRATION_US[0] as f32 * 1e-6);
    let mut saturated_pixels = 0;
    for (p, &saturated) in merged.saturated.iter().enumerate() {
        let all_saturated = codes.iter().all(|c| c[3 * p] == 255);
        assert_eq!(saturated, all_saturated, "pixel {p}");
        if all_saturated {
            saturated_pixels += 1;
            assert!((merged.radiance[p].x - bound).abs() <= 1e-3 * bound);
            assert!(
                merged.radiance[p].x / scale <= truth.radiance[p].x,
                "a lower bound"
            );
        }
    }
    println!(
        "{saturated_pixels} pixels saturated in every exposure, each merged to the bound {:.1} \
         (radiance {:.1}; truth up to 1e6)",
        bound,
        bound / scale
    );
    assert!(saturated_pixels > 0);
}

#[test]
fn bad_brackets_are_refused_with_typed_errors() {
    let none: [ProbeImage; 0] = [];
    assert_eq!(merge(&none, &Response::linear()), Err(HdrError::NoBrackets));
    let a = rgb8(8, 8, 100, 1_000);
    let small = rgb8(8, 4, 100, 3_000);
    assert!(matches!(
        merge(&[&a, &small], &Response::linear()),
        Err(HdrError::SizeMismatch { index: 1, .. })
    ));
    let mut mono = a.clone();
    mono.image = Image::new(8, 8, PixelFormat::Mono8);
    assert!(matches!(
        merge(&[&a, &mono], &Response::linear()),
        Err(HdrError::Format { index: 1, .. })
    ));
    let zero_time = rgb8(8, 8, 100, 0);
    assert!(matches!(
        merge(&[&zero_time], &Response::linear()),
        Err(HdrError::InvalidExposure { index: 0, .. })
    ));
    let mut nan_gain = a.clone();
    nan_gain.gain_db = f32::NAN;
    assert!(matches!(
        merge(&[&nan_gain], &Response::linear()),
        Err(HdrError::InvalidExposure { .. })
    ));
    assert_eq!(
        recover_response(&[&a, &a], &RecoverySettings::default()),
        Err(HdrError::EqualExposures)
    );
    assert!(Response::from_calibration(&RigCalibration::default()).is_err());
}

#[test]
fn gain_counts_as_exposure() {
    // 6.0206 dB of gain doubles the signal: the same codes at half the time merge the same.
    let a = rgb8(4, 4, 150, 2_000);
    let mut b = rgb8(4, 4, 150, 1_000);
    b.gain_db = 20.0 * 2f32.log10();
    let response = Response::linear();
    let (ma, mb) = (
        merge(&[a], &response).unwrap(),
        merge(&[b], &response).unwrap(),
    );
    assert!((ma.radiance[0] - mb.radiance[0]).abs().max_element() < 1e-4 * ma.radiance[0].x);
}
