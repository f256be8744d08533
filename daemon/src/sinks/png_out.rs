//! PNG output of images: 8-bit RGB/mono as they are, depth in millimetres as 16-bit grey.

use std::io::BufWriter;
use std::path::Path;

use relight_core::{Image, PixelFormat};

use super::safe_file::Existing;

#[derive(Debug, thiserror::Error)]
pub enum PngError {
    /// The source's message names the path and the reason.
    #[error("{source}")]
    Create {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot encode {path}: {source}")]
    Encode {
        path: String,
        source: ::png::EncodingError,
    },
    #[error("{path}: {format:?} images are not written as PNG")]
    Unsupported { path: String, format: PixelFormat },
}

/// Write `image` to `path`, a regular file ([`super::safe_file`]). Depth in metres is converted
/// to millimetres (invalid → 0).
pub fn write_png(path: &Path, image: &Image) -> Result<(), PngError> {
    write_png_as(path, image, Existing::Replace)
}

/// [`write_png`], refusing an existing file unless `existing` says to replace it.
pub fn write_png_as(path: &Path, image: &Image, existing: Existing) -> Result<(), PngError> {
    let name = path.display().to_string();
    let (color, depth, data): (_, _, Vec<u8>) = match image.format() {
        PixelFormat::Rgb8 => (
            ::png::ColorType::Rgb,
            ::png::BitDepth::Eight,
            image.as_u8().unwrap_or_default().to_vec(),
        ),
        PixelFormat::Mono8 => (
            ::png::ColorType::Grayscale,
            ::png::BitDepth::Eight,
            image.as_u8().unwrap_or_default().to_vec(),
        ),
        PixelFormat::DepthU16Mm => (
            ::png::ColorType::Grayscale,
            ::png::BitDepth::Sixteen,
            image
                .as_u16()
                .unwrap_or_default()
                .iter()
                .flat_map(|d| d.to_be_bytes())
                .collect(),
        ),
        PixelFormat::DepthF32M => (
            ::png::ColorType::Grayscale,
            ::png::BitDepth::Sixteen,
            image
                .as_f32()
                .unwrap_or_default()
                .iter()
                .map(|&m| {
                    if m.is_finite() && m > 0.0 {
                        (m * 1000.0).round().min(65535.0) as u16
                    } else {
                        0
                    }
                })
                .flat_map(u16::to_be_bytes)
                .collect(),
        ),
        format @ PixelFormat::Rgba16F => {
            return Err(PngError::Unsupported { path: name, format });
        }
    };
    let file =
        super::safe_file::create_regular(path, existing).map_err(|source| PngError::Create {
            path: name.clone(),
            source,
        })?;
    let mut encoder = ::png::Encoder::new(BufWriter::new(file), image.width(), image.height());
    encoder.set_color(color);
    encoder.set_depth(depth);
    let encode = |source| PngError::Encode {
        path: name.clone(),
        source,
    };
    let mut writer = encoder.write_header().map_err(encode)?;
    writer.write_image_data(&data).map_err(encode)?;
    writer.finish().map_err(encode)
}

/// Reinhard tone mapping (L / (1 + L) per channel) of linear radiance into 8-bit sRGB — the
/// only place HDR becomes display values (DESIGN.md: tonemapping at sinks only).
pub fn tonemap_reinhard(width: u32, height: u32, radiance: &[glam::Vec3]) -> Image {
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    if let Some(px) = image.as_u8_mut() {
        for (rgb, l) in px.chunks_exact_mut(3).zip(radiance) {
            for (c, v) in rgb.iter_mut().zip(l.to_array()) {
                let v = if v.is_finite() { v.max(0.0) } else { 0.0 };
                *c = relight_core::srgb::linear_to_srgb(v / (1.0 + v));
            }
        }
    }
    image
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs::File;

    #[test]
    fn depth_png_reads_back_in_millimetres() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("depth.png");
        let mut depth = Image::new(3, 1, PixelFormat::DepthF32M);
        depth
            .as_f32_mut()
            .unwrap()
            .copy_from_slice(&[1.234, f32::NAN, 0.5]);
        write_png(&path, &depth).unwrap();
        let decoder = ::png::Decoder::new(std::io::BufReader::new(File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        let mm: Vec<u16> = buf
            .chunks(2)
            .map(|c| u16::from_be_bytes([c[0], c[1]]))
            .collect();
        assert_eq!(mm, vec![1234, 0, 500]);
    }

    #[test]
    fn unwritable_path_is_an_error() {
        let err = write_png(
            Path::new("/nonexistent-dir/x.png"),
            &Image::new(1, 1, PixelFormat::Rgb8),
        );
        assert!(matches!(err, Err(PngError::Create { .. })));
    }
}
