//! Images as the views send them: JPEG for the composite and the camera, Δ in false colour,
//! depth in the encodings ROS and Foxglove read (`16UC1` millimetres, `32FC1` metres).

use relight_core::{Image, PixelFormat};

pub use relight_core::recording::compressed::{CompressError as ImageEncodeError, jpeg};

/// Rec. 709 luminance of Δ's linear RGB.
fn luminance(r: f32, g: f32, b: f32) -> f32 {
    0.2126 * r + 0.7152 * g + 0.0722 * b
}

/// Δ's luminance in false colour, `Rgb8`: black where Δ = 0, red where the object darkens
/// the real scene (shadow, Δ < 0), blue where it brightens it (bleeding, Δ > 0), full at
/// `±scale`. Returns the image and the scale used: `scale`, or without one the 99th
/// percentile of |Δ| over the pixels Δ touches, so one hot pixel does not wash the rest out.
pub fn delta_false_colour(delta: &Image, scale: Option<f32>) -> Option<(Image, f32)> {
    if delta.format() != PixelFormat::Rgba16F || delta.pixel_count() == 0 {
        return None;
    }
    let bits = delta.as_u16()?;
    let f = |i: usize| half::f16::from_bits(bits[i]).to_f32();
    let lum: Vec<f32> = (0..delta.pixel_count())
        .map(|p| luminance(f(4 * p), f(4 * p + 1), f(4 * p + 2)))
        .map(|l| if l.is_finite() { l } else { 0.0 })
        .collect();
    let scale = scale
        .unwrap_or_else(|| percentile_abs(&lum, 0.99))
        .max(1e-6);
    let mut out = Image::new(delta.width(), delta.height(), PixelFormat::Rgb8);
    let rgb = out.as_u8_mut()?;
    for (px, l) in rgb.chunks_exact_mut(3).zip(&lum) {
        let v = (l / scale).clamp(-1.0, 1.0);
        let level = (v.abs() * 255.0).round() as u8;
        px.copy_from_slice(&if v < 0.0 {
            [level, 0, 0]
        } else {
            [0, 0, level]
        });
    }
    Some((out, scale))
}

/// The `q` quantile of |v| over the non-zero entries (0 when all are zero).
fn percentile_abs(values: &[f32], q: f32) -> f32 {
    let mut magnitudes: Vec<f32> = values
        .iter()
        .map(|v| v.abs())
        .filter(|&m| m > 0.0)
        .collect();
    if magnitudes.is_empty() {
        return 0.0;
    }
    let k = ((magnitudes.len() - 1) as f32 * q).round() as usize;
    *magnitudes.select_nth_unstable_by(k, f32::total_cmp).1
}

/// A depth image's ROS encoding and little-endian bytes: `16UC1` millimetres (0 = invalid) or
/// `32FC1` metres (NaN = invalid), as REP 118 has them. `None` for other formats.
pub fn depth_raw(depth: &Image) -> Option<(&'static str, Vec<u8>)> {
    match depth.format() {
        PixelFormat::DepthU16Mm => Some((
            "16UC1",
            depth
                .as_u16()?
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect(),
        )),
        PixelFormat::DepthF32M => Some((
            "32FC1",
            depth
                .as_f32()?
                .iter()
                .map(|&m| {
                    if m > 0.0 && m.is_finite() {
                        m
                    } else {
                        f32::NAN
                    }
                })
                .flat_map(f32::to_le_bytes)
                .collect(),
        )),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn delta_of(values: &[[f32; 3]], width: u32) -> Image {
        let mut delta = Image::new(width, values.len() as u32 / width, PixelFormat::Rgba16F);
        let bits = delta.as_u16_mut().unwrap();
        for (px, v) in bits.chunks_exact_mut(4).zip(values) {
            for c in 0..3 {
                px[c] = half::f16::from_f32(v[c]).to_bits();
            }
        }
        delta
    }

    #[test]
    fn shadow_is_red_bleeding_is_blue_and_zero_is_black() {
        let delta = delta_of(
            &[
                [-0.5, -0.5, -0.5],
                [0.0, 0.0, 0.0],
                [0.25, 0.25, 0.25],
                [1.0, 1.0, 1.0],
            ],
            4,
        );
        let (image, scale) = delta_false_colour(&delta, Some(0.5)).unwrap();
        assert_eq!(scale, 0.5);
        let rgb = image.as_u8().unwrap();
        assert_eq!(&rgb[0..3], &[255, 0, 0]);
        assert_eq!(&rgb[3..6], &[0, 0, 0]);
        assert_eq!(&rgb[6..9], &[0, 0, 128]);
        assert_eq!(&rgb[9..12], &[0, 0, 255], "clamped at the scale");
    }

    #[test]
    fn the_automatic_scale_ignores_untouched_pixels_and_one_hot_pixel() {
        let mut values = vec![[0.0; 3]; 300];
        for v in values.iter_mut().take(200) {
            *v = [-0.1; 3];
        }
        values[250] = [1e4; 3];
        let (_, scale) = delta_false_colour(&delta_of(&values, 20), None).unwrap();
        assert!((scale - 0.1).abs() < 1e-3, "scale {scale}");
    }

    #[test]
    fn invalid_metric_depth_becomes_nan() {
        let mut depth = Image::new(3, 1, PixelFormat::DepthF32M);
        depth
            .as_f32_mut()
            .unwrap()
            .copy_from_slice(&[1.5, 0.0, f32::INFINITY]);
        let (encoding, bytes) = depth_raw(&depth).unwrap();
        assert_eq!(encoding, "32FC1");
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(values[0], 1.5);
        assert!(values[1].is_nan() && values[2].is_nan());
    }
}
