//! sRGB transfer functions (IEC 61966-2-1) for 8-bit camera images: decoding camera pixels to
//! linear radiance and encoding at sinks.

/// 8-bit sRGB code value → linear [0, 1].
pub fn srgb_to_linear(code: u8) -> f32 {
    let c = f32::from(code) / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear radiance (clamped to [0, 1]) → nearest 8-bit sRGB code value.
pub fn linear_to_srgb(linear: f32) -> u8 {
    let l = if linear.is_finite() {
        linear.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let c = if l <= 0.003_130_8 {
        l * 12.92
    } else {
        1.055 * l.powf(1.0 / 2.4) - 0.055
    };
    (c * 255.0).round() as u8
}

/// Table mapping an sRGB code to the code after scaling linear radiance by 2^ev.
pub fn exposure_lut(ev: f64) -> [u8; 256] {
    let gain = 2f32.powf(ev as f32);
    std::array::from_fn(|code| linear_to_srgb(srgb_to_linear(code as u8) * gain))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_round_trips() {
        for code in 0..=255u8 {
            assert_eq!(linear_to_srgb(srgb_to_linear(code)), code);
        }
        assert_eq!(exposure_lut(0.0), std::array::from_fn(|c| c as u8));
    }
}
