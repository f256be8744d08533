//! Kinect v1 raw disparity (libfreenect's `FREENECT_DEPTH_11BIT`) ↔ depth in millimetres.
//!
//! The sensor reports an 11-bit code that is affine in disparity, so inverse depth is affine in
//! it. We use Nicolas Burrus' least-squares fit of that line (Kinect calibration notes, 2011;
//! the formula libfreenect's examples and ROS `openni_camera` users quote):
//!
//! z(raw) = 1 / (B − C·raw) metres, B = 3.3309495161 m⁻¹, C = 0.0030711016 m⁻¹.
//!
//! A device's own calibration (what libfreenect applies in `FREENECT_DEPTH_MM` and
//! `FREENECT_DEPTH_REGISTERED`) differs from this generic fit by a few per cent per unit, so the
//! backend prefers those modes and converts only where the library offers raw codes alone — as
//! fakenect does, whose dumps hold 11-bit codes.
//!
//! Codes are valid from 0 (z = 300.2 mm) up to where z passes [`MAX_DEPTH_MM`] (code 1052);
//! [`RAW_INVALID`] (2047) marks a pixel without a measurement, as in libfreenect.
//!
//! **Round trip.** A depth written as the nearest code and read back differs from it by at
//! most [`round_trip_bound_mm`]: with raw* = (B − 1/z)/C exact and the code raw* + δ, |δ| ≤ ½,
//! z' = z / (1 − C·z·δ), so |z' − z| ≤ C·z²·½ / (1 − C·z·½), plus ½ mm for rounding z' to mm.
//! The step between neighbouring codes is C·z² (2.9 mm at 1 m, 28 mm at 3 m).

/// libfreenect's "no data" code (`FREENECT_DEPTH_RAW_NO_VALUE`).
pub const RAW_INVALID: u16 = 2047;

/// Deepest depth the conversion reports, mm (libfreenect's `FREENECT_DEPTH_MM_MAX_VALUE`);
/// farther codes read as invalid (0).
pub const MAX_DEPTH_MM: u16 = 10_000;

/// Intercept B of 1/z, m⁻¹.
pub const INVERSE_DEPTH_AT_CODE_ZERO: f64 = 3.330_949_516_1;

/// Slope C of 1/z per code, m⁻¹.
pub const INVERSE_DEPTH_PER_CODE: f64 = 0.003_071_101_6;

/// Depth in mm of a raw code; 0 (invalid) for [`RAW_INVALID`], codes beyond [`MAX_DEPTH_MM`]
/// and codes above 2047.
pub fn raw_to_mm(raw: u16) -> u16 {
    if raw >= RAW_INVALID {
        return 0;
    }
    let inverse_depth = INVERSE_DEPTH_AT_CODE_ZERO - INVERSE_DEPTH_PER_CODE * f64::from(raw);
    if inverse_depth <= 0.0 {
        return 0;
    }
    let mm = (1000.0 / inverse_depth).round();
    if mm > f64::from(MAX_DEPTH_MM) {
        0
    } else {
        mm as u16
    }
}

/// The nearest raw code of a depth in mm; [`RAW_INVALID`] for 0 (invalid) and for depths the
/// code cannot express (nearer than 301 mm, farther than [`MAX_DEPTH_MM`]).
pub fn mm_to_raw(mm: u16) -> u16 {
    if mm == 0 || mm > MAX_DEPTH_MM {
        return RAW_INVALID;
    }
    let code =
        ((INVERSE_DEPTH_AT_CODE_ZERO - 1000.0 / f64::from(mm)) / INVERSE_DEPTH_PER_CODE).round();
    if !(0.0..f64::from(RAW_INVALID)).contains(&code) {
        return RAW_INVALID;
    }
    let code = code as u16;
    if raw_to_mm(code) == 0 {
        RAW_INVALID
    } else {
        code
    }
}

/// The depth step between neighbouring codes at `mm`, mm: C·z².
pub fn code_step_mm(mm: u16) -> f64 {
    let z_m = f64::from(mm) / 1000.0;
    1000.0 * INVERSE_DEPTH_PER_CODE * z_m * z_m
}

/// The most `raw_to_mm(mm_to_raw(mm))` can differ from `mm` (see the module docs).
pub fn round_trip_bound_mm(mm: u16) -> f64 {
    let z_m = f64::from(mm) / 1000.0;
    let half_step_m =
        INVERSE_DEPTH_PER_CODE * z_m * z_m * 0.5 / (1.0 - INVERSE_DEPTH_PER_CODE * z_m * 0.5);
    1000.0 * half_step_m + 0.5
}

/// [`raw_to_mm`] for every 11-bit code, for converting whole frames.
pub fn raw_to_mm_table() -> Vec<u16> {
    (0..2048).map(raw_to_mm).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_expressible_depth_round_trips_within_the_bound() {
        let mut tightest = 0.0f64;
        for mm in 301..=MAX_DEPTH_MM {
            let raw = mm_to_raw(mm);
            assert_ne!(raw, RAW_INVALID, "{mm} mm is expressible");
            let back = raw_to_mm(raw);
            let error = (f64::from(back) - f64::from(mm)).abs();
            let bound = round_trip_bound_mm(mm);
            assert!(
                error <= bound,
                "{mm} mm → {raw} → {back} mm: {error} > {bound}"
            );
            tightest = tightest.max(error / bound);
        }
        // Far away a code spans many mm, so the bound is nearly reached: it is not slack.
        assert!(tightest > 0.9, "largest error / bound {tightest}");
    }

    #[test]
    fn depth_grows_with_the_code_by_the_stated_step() {
        let table = raw_to_mm_table();
        let valid: Vec<u16> = table.iter().copied().take_while(|&mm| mm > 0).collect();
        assert_eq!(valid.len(), 1053, "codes 0..=1052 are within 10 m");
        assert_eq!(valid[0], 300);
        assert!(valid.windows(2).all(|w| w[1] >= w[0]));
        for raw in [100usize, 500, 800, 1000] {
            let step = f64::from(valid[raw + 1]) - f64::from(valid[raw]);
            let predicted = code_step_mm(valid[raw]);
            assert!(
                (step - predicted).abs() <= 1.0 + 0.02 * predicted,
                "code {raw}: step {step} vs {predicted}"
            );
        }
        assert!(table[1053..].iter().all(|&mm| mm == 0));
    }

    #[test]
    fn invalid_and_inexpressible_depths_map_to_the_invalid_code() {
        assert_eq!(mm_to_raw(0), RAW_INVALID);
        assert_eq!(mm_to_raw(250), RAW_INVALID);
        assert_eq!(mm_to_raw(300), RAW_INVALID);
        assert_eq!(mm_to_raw(MAX_DEPTH_MM + 1), RAW_INVALID);
        assert_eq!(raw_to_mm(RAW_INVALID), 0);
        assert_eq!(raw_to_mm(u16::MAX), 0);
    }
}
