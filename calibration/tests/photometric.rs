//! Photometric calibration against the simulator's truth: the probe's response curve recovered
//! with OpenCV's Robertson against the simulated camera's and against relight-recon's own
//! Robertson, the refusal of ladder brackets, the absolute radiance scale, and vignetting fitted
//! from synthetic flat fields with known fall-off.

use glam::{DVec2, Quat, Vec3};
use relight_calibrate::photometric::{
    PhotometricError, PixelRect, ResponseSettings, calibrate_response, radiance_scale,
};
use relight_calibrate::vignetting::{
    FlatField, Vignetting, VignettingError, VignettingSettings, fit_vignetting,
};
use relight_core::camera::CameraModel;
use relight_core::{Image, PixelFormat, Pose, ProbeImage};
use relight_recon::hdr::{HdrError, RecoverySettings, Response, merge, recover_response};
use relight_sim::probe::{ProbeLens, render_probe};
use relight_sim::response::CameraResponse;
use relight_sim::rig::equidistant_probe;

/// A smooth, coloured world spanning four decades (1e-3 … 10): every code occurs.
fn wide_range_world(d: Vec3) -> Vec3 {
    let u = 0.5 + 0.25 * ((4.0 * d.x).sin() + (3.0 * d.z + 1.0).cos());
    Vec3::new(1.0, 0.8, 0.6) * 10f32.powf(4.0 * u - 3.0)
}

/// A calibration bracket: ratios ×3, ×3.7, ×5.8, not powers of one ratio.
const CALIBRATION_US: [u32; 4] = [1_000, 3_000, 11_000, 64_000];
/// Another uneven bracket, five exposures.
const FIVE_US: [u32; 5] = [1_000, 2_700, 6_400, 19_000, 64_000];
/// The brightest direction (10) lands at 0.9 of full scale in the shortest exposure.
const EXPOSURE_SCALE: f32 = 90.0;

fn upward_probe() -> Pose {
    Pose::new(
        Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        Vec3::ZERO,
    )
}

fn bracket(
    radiance: &(dyn Fn(Vec3) -> Vec3 + Sync),
    lens: &ProbeLens,
    exposures_us: &[u32],
    exposure_scale: f32,
) -> Vec<ProbeImage> {
    exposures_us
        .iter()
        .map(|&t| {
            render_probe(
                radiance,
                lens,
                &upward_probe(),
                t,
                exposure_scale,
                &CameraResponse::default(),
            )
        })
        .collect()
}

/// The simulator's inverse response normalised like a recovered one (code 128 ↦ 1).
fn true_normalised() -> Vec<f32> {
    let table = CameraResponse::default().inverse_table();
    table.iter().map(|v| v / table[128]).collect()
}

/// Worst relative difference of `a` from `b` over `codes`, and where.
fn worst_difference(a: &[f32], b: &[f32], codes: impl Iterator<Item = u8>) -> (f32, u8) {
    codes
        .map(|m| {
            let m_ = usize::from(m);
            ((a[m_] - b[m_]).abs() / b[m_], m)
        })
        .fold((0.0, 0), |x, y| if y.0 > x.0 { y } else { x })
}

#[test]
fn robertson_recovers_the_simulated_response_within_two_percent() {
    let lens = equidistant_probe(128, 185.0);
    let truth = true_normalised();
    for exposures in [&CALIBRATION_US[..], &FIVE_US[..]] {
        let brackets = bracket(&wide_range_world, &lens, exposures, EXPOSURE_SCALE);
        let calibration = calibrate_response(&brackets, &ResponseSettings::default()).unwrap();
        let table = &calibration.inverse_response;
        let usable = calibration.usable_codes.clone();
        let (worst, code) = worst_difference(table, &truth, usable.clone());
        let (worst_all, code_all) = worst_difference(table, &truth, 1..=254);
        println!(
            "{exposures:?} µs: {} samples, usable codes {usable:?}: worst relative error \
             {worst:.4} (code {code}); over 1..=254 {worst_all:.4} (code {code_all}); \
             channel spread {:?}",
            calibration.samples, calibration.channel_spread
        );
        assert_eq!(table.len(), 256);
        assert_eq!((table[0], table[128]), (0.0, 1.0));
        assert!(table.windows(2).all(|w| w[1] >= w[0]), "non-decreasing");
        assert!(Response::from_table(table).is_ok());
        // The quantisation rule on a γ = 2.2 curve admits codes from 9 (module docs of
        // `photometric`); the bracket reaches every code up to 254.
        assert!(*usable.start() <= 10 && *usable.end() >= 250, "{usable:?}");
        assert!(worst < 0.02, "relative error {worst} at code {code}");
        // The channels share the simulator's curve: their own curves differ from the shared
        // one only by noise, well inside the 2% each is held to.
        let spread = calibration.channel_spread.unwrap();
        assert!(spread < 0.02, "channel spread {spread}");
        assert_eq!(calibration.exposures_s.len(), exposures.len());
    }
}

#[test]
fn opencv_and_relight_robertson_agree() {
    let lens = equidistant_probe(128, 185.0);
    let brackets = bracket(&wide_range_world, &lens, &CALIBRATION_US, EXPOSURE_SCALE);
    let opencv = calibrate_response(&brackets, &ResponseSettings::default()).unwrap();
    let relight = recover_response(&brackets, &RecoverySettings::default()).unwrap();
    let (worst, code) = worst_difference(
        &opencv.inverse_response,
        relight.table(),
        opencv.usable_codes.clone(),
    );
    println!(
        "OpenCV vs relight-recon Robertson: worst relative difference {worst:.4} (code {code})"
    );
    // Each is within 2% of the truth on these codes, so they are within 4% of each other.
    assert!(worst < 0.04, "{worst} at code {code}");
}

#[test]
fn a_ladder_bracket_is_refused_as_ambiguous() {
    let lens = equidistant_probe(64, 185.0);
    let brackets = bracket(
        &wide_range_world,
        &lens,
        &[250, 2_000, 16_000],
        EXPOSURE_SCALE * 4.0,
    );
    match calibrate_response(&brackets, &ResponseSettings::default()) {
        Err(PhotometricError::Bracket(HdrError::CommensurateExposures { ratio })) => {
            assert!((ratio - 8.0).abs() < 1e-6, "{ratio}");
        }
        other => panic!("expected CommensurateExposures, got {other:?}"),
    }
}

#[test]
fn a_bracket_without_information_is_refused() {
    let lens = equidistant_probe(64, 185.0);
    let dark = bracket(&|_| Vec3::ZERO, &lens, &CALIBRATION_US, EXPOSURE_SCALE);
    assert!(matches!(
        calibrate_response(&dark, &ResponseSettings::default()),
        Err(PhotometricError::Bracket(HdrError::NoOverlap))
    ));
    // A flat grey world: every pixel shows the same four codes, none of them 128.
    let flat = bracket(
        &|_| Vec3::splat(0.02),
        &lens,
        &CALIBRATION_US,
        EXPOSURE_SCALE,
    );
    let error = calibrate_response(&flat, &ResponseSettings::default()).unwrap_err();
    assert!(
        matches!(error, PhotometricError::MidCodeUnobserved),
        "{error}"
    );
}

#[test]
fn the_radiance_scale_turns_merged_values_into_radiance() {
    let lens = equidistant_probe(96, 185.0);
    let calibration_bracket = bracket(&wide_range_world, &lens, &CALIBRATION_US, EXPOSURE_SCALE);
    let calibration =
        calibrate_response(&calibration_bracket, &ResponseSettings::default()).unwrap();
    let response = calibration.response().unwrap();

    // A reference scene of known, uniform radiance, bracketed the same way.
    let known = 0.04f32;
    let reference = bracket(
        &|_| Vec3::splat(known),
        &lens,
        &CALIBRATION_US,
        EXPOSURE_SCALE,
    );
    let hdr = merge(&reference, &response).unwrap();
    let patch = PixelRect {
        x: 40,
        y: 40,
        width: 16,
        height: 16,
    };
    let scale = radiance_scale(&hdr, patch, known, None).unwrap();
    // Merged = radiance × exposure_scale / I_true(128) for a curve normalised to I(128) = 1.
    let expected = CameraResponse::default().inverse_table()[128] / EXPOSURE_SCALE;
    let error = (scale / expected - 1.0).abs();
    println!("radiance scale {scale:.6e}, expected {expected:.6e}, relative error {error:.4}");
    // The curve's error on the codes this radiance produces (< 2%) plus half a quantisation
    // bin of the mid-grey codes (2.2 / 128 / 2 < 0.9%).
    assert!(error < 0.03, "{error}");

    // With vignetting, each pixel of the patch is read as if on the axis (divided by its V).
    let vignetting = Vignetting {
        fx: 48.0,
        fy: 48.0,
        cx: 47.5,
        cy: 47.5,
        coefficients: [-5.0, 0.0, 0.0],
    };
    let corrected = radiance_scale(&hdr, patch, known, Some(&vignetting)).unwrap();
    let mut inverse_sum = 0.0;
    for y in patch.y..patch.y + patch.height {
        for x in patch.x..patch.x + patch.width {
            inverse_sum += 1.0 / vignetting.factor_at(f64::from(x), f64::from(y)).unwrap();
        }
    }
    let mean_inverse = inverse_sum / f64::from(patch.width * patch.height);
    println!("mean 1/V over the patch {mean_inverse:.4}");
    assert!(mean_inverse > 1.1);
    let expected_corrected = f64::from(scale) / mean_inverse;
    assert!((f64::from(corrected) / expected_corrected - 1.0).abs() < 1e-4);

    let outside = PixelRect { x: 90, ..patch };
    assert!(matches!(
        radiance_scale(&hdr, outside, known, None),
        Err(PhotometricError::PatchOutside { .. })
    ));
    let corner = PixelRect {
        x: 0,
        y: 0,
        width: 4,
        height: 4,
    };
    assert!(matches!(
        radiance_scale(&hdr, corner, known, None),
        Err(PhotometricError::PatchUnusable { .. })
    ));
    assert!(matches!(
        radiance_scale(&hdr, patch, f32::NAN, None),
        Err(PhotometricError::KnownRadiance(_))
    ));
}

/// Deterministic uniform numbers in [0, 1) (SplitMix64), for noise and dust.
struct Uniform(u64);

impl Uniform {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn gaussian(&mut self) -> f64 {
        let (u, v) = (self.next().max(1e-300), self.next());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// What the test fish-eye records of a uniform field: linear `level · V(r)` times the fraction
/// of the pixel inside the 185° image circle (4 × 4 sub-pixel samples, so the rim is partly
/// lit), darkened by 40% in a few dust specks, plus Gaussian noise of `noise_codes` 8-bit levels,
/// through the simulator's response; a few hot (255) and dead (0) pixels.
fn flat_field_image(
    lens: &ProbeLens,
    truth: &Vignetting,
    level: f64,
    exposure: f64,
    noise_codes: f64,
    seed: u64,
) -> Image {
    let model = lens.model;
    let camera = CameraModel::KannalaBrandt(model);
    let half_field = lens.field_of_view_deg.to_radians() / 2.0;
    let (w, h) = (model.width as usize, model.height as usize);
    let response = CameraResponse::default();
    let mut random = Uniform(seed);
    let dust: Vec<(DVec2, f64)> = (0..6)
        .map(|_| {
            let centre = DVec2::new(random.next() * w as f64, random.next() * h as f64);
            (centre, 1.5 + 1.5 * random.next())
        })
        .collect();
    let mut image = Image::new(model.width, model.height, PixelFormat::Rgb8);
    let pixels = image.as_u8_mut().unwrap();
    for (i, rgb) in pixels.chunks_exact_mut(3).enumerate() {
        let pixel = DVec2::new((i % w) as f64, (i / w) as f64);
        let n = 4;
        let inside = (0..n * n)
            .filter(|s| {
                let offset = DVec2::new(
                    (f64::from(s % n) + 0.5) / f64::from(n) - 0.5,
                    (f64::from(s / n) + 0.5) / f64::from(n) - 0.5,
                );
                camera
                    .unproject(pixel + offset)
                    .is_some_and(|ray| ray.z >= half_field.cos())
            })
            .count() as f64
            / f64::from(n * n);
        let specked = dust.iter().any(|(c, r)| c.distance(pixel) < *r);
        let linear = level
            * truth.factor_at(pixel.x, pixel.y).unwrap_or(0.0)
            * inside
            * if specked { 0.6 } else { 1.0 };
        let code = if linear > 0.0 {
            let y = f64::from(response.apply((linear * exposure) as f32)) * 255.0
                + noise_codes * random.gaussian();
            y.round().clamp(0.0, 255.0) as u8
        } else {
            0
        };
        rgb.fill(code);
    }
    for k in 0..8 {
        let i = (random.next() * (w * h) as f64) as usize;
        pixels[3 * i..3 * i + 3].fill(if k % 2 == 0 { 255 } else { 0 });
    }
    image
}

/// Largest |V_fit(r) − V_true(r)| over `[0, reach]`.
fn worst_falloff_error(fit: &Vignetting, truth: &Vignetting, reach: f64) -> f64 {
    (0..=200)
        .map(|k| reach * f64::from(k) / 200.0)
        .map(|r| (fit.factor(r) - truth.factor(r)).abs())
        .fold(0.0, f64::max)
}

/// A fish-eye losing 45% of its light at 90° off axis (r = θ_d = π/2).
fn fisheye_and_truth(size: u32) -> (ProbeLens, Vignetting) {
    let lens = equidistant_probe(size, 185.0);
    let camera = CameraModel::KannalaBrandt(lens.model);
    let truth = Vignetting::new(&camera, &[-0.3, 0.06, -0.008]);
    (lens, truth)
}

#[test]
fn vignetting_is_recovered_from_flat_fields_despite_the_black_rim_dust_and_hot_pixels() {
    let (lens, truth) = fisheye_and_truth(160);
    let camera = CameraModel::KannalaBrandt(lens.model);
    println!(
        "true fall-off at 90°: V = {:.3}",
        truth.factor(std::f64::consts::FRAC_PI_2)
    );
    let table = CameraResponse::default().inverse_table();
    let response = Response::from_table(&table).unwrap();
    let images: Vec<Image> = (0..2)
        .map(|seed| flat_field_image(&lens, &truth, 1.0, 0.8, 0.5, 7 + seed))
        .collect();
    let field = FlatField::from_codes(&images, &response).unwrap();
    let fit = fit_vignetting(&field, &camera, &VignettingSettings::default()).unwrap();
    let error = worst_falloff_error(&fit.vignetting, &truth, fit.max_radius);
    // Least squares theory: with pixels spread uniformly over a disc, s = (r / reach)² is
    // uniform on [0, 1] and a cubic in s has leverage at most 16 / N (Σ (2k + 1), k = 0..3, of
    // the orthonormal shifted Legendre basis). V = P(r) / P(0) then has a standard error of at
    // most (4 + 4) σ / √N, σ the per-pixel relative noise the fit itself measures; 5 of those.
    let tolerance = 5.0 * 8.0 * fit.residual_sigma / (fit.pixels as f64).sqrt();
    println!(
        "flat field: {} pixels ({} outliers), reach r = {:.3}, residual σ {:.5}, coefficients \
         {:?} (truth {:?}), worst |ΔV| {error:.5}, tolerance {tolerance:.5}",
        fit.pixels,
        fit.outliers,
        fit.max_radius,
        fit.residual_sigma,
        fit.vignetting.coefficients,
        truth.coefficients
    );
    assert!(fit.max_radius > 1.4, "the fit reaches 80° off axis");
    assert!(fit.outliers > 0, "dust specks are rejected");
    assert!(error < tolerance, "{error} ≥ {tolerance}");
    assert_eq!((fit.vignetting.cx, fit.vignetting.cy), (truth.cx, truth.cy));
}

#[test]
fn vignetting_is_recovered_from_a_merged_bracket_of_a_flat_scene() {
    let (lens, truth) = fisheye_and_truth(96);
    let camera = CameraModel::KannalaBrandt(lens.model);
    let table = CameraResponse::default().inverse_table();
    let response = Response::from_table(&table).unwrap();
    // Bright enough that the centre saturates in the longest exposure: the merge must fall back
    // on the shorter ones there.
    let bracket: Vec<ProbeImage> = [1_000u32, 3_000, 11_000]
        .into_iter()
        .enumerate()
        .map(|(k, t)| ProbeImage {
            image: flat_field_image(
                &lens,
                &truth,
                1.0,
                f64::from(t) / 8_000.0,
                0.5,
                20 + k as u64,
            ),
            exposure_us: t,
            gain_db: 0.0,
        })
        .collect();
    let hdr = merge(&bracket, &response).unwrap();
    let field = FlatField::from_hdr(&hdr);
    let fit = fit_vignetting(&field, &camera, &VignettingSettings::default()).unwrap();
    let error = worst_falloff_error(&fit.vignetting, &truth, fit.max_radius);
    let tolerance = 5.0 * 8.0 * fit.residual_sigma / (fit.pixels as f64).sqrt();
    println!(
        "merged bracket: {} pixels, residual σ {:.5}, worst |ΔV| {error:.5}, tolerance \
         {tolerance:.5}",
        fit.pixels, fit.residual_sigma
    );
    assert!(error < tolerance, "{error} ≥ {tolerance}");
}

#[test]
fn vignetting_refuses_fields_without_information() {
    let (lens, _) = fisheye_and_truth(64);
    let camera = CameraModel::KannalaBrandt(lens.model);
    let response = Response::linear();
    let black = Image::new(64, 64, PixelFormat::Rgb8);
    let field = FlatField::from_codes(&[black], &response).unwrap();
    assert!(matches!(
        fit_vignetting(&field, &camera, &VignettingSettings::default()),
        Err(VignettingError::TooFewPixels { found: 0 })
    ));
    let other_size = Image::new(32, 64, PixelFormat::Rgb8);
    assert!(matches!(
        FlatField::from_codes(
            &[Image::new(64, 64, PixelFormat::Rgb8), other_size],
            &response
        ),
        Err(VignettingError::SizeMismatch { index: 1, .. })
    ));
    let depth = Image::new(64, 64, PixelFormat::DepthF32M);
    assert!(matches!(
        FlatField::from_codes(&[depth], &response),
        Err(VignettingError::Format { index: 0, .. })
    ));
    assert!(matches!(
        FlatField::from_codes(&[], &response),
        Err(VignettingError::NoImages)
    ));
}
