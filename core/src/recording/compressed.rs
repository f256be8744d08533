//! Compressed 8-bit images: JPEG (lossy, `jpeg-encoder` / `jpeg-decoder`) and PNG (lossless,
//! `png`), as `sensor_msgs/msg/CompressedImage` carries them in recordings and the live view
//! sends them.

use crate::frame::{Image, PixelFormat};

/// How a recording stores colour images ([`super::RecordingOptions::color_encoding`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ColorEncoding {
    /// `sensor_msgs/msg/Image`, `rgb8`: exact, and the largest.
    #[default]
    Raw,
    /// `sensor_msgs/msg/CompressedImage`, format `png`: exact.
    Png,
    /// `sensor_msgs/msg/CompressedImage`, format `jpeg`, at this quality (1–100): lossy.
    Jpeg { quality: u8 },
}

#[derive(Debug, thiserror::Error)]
pub enum CompressError {
    #[error("a {0:?} image cannot be compressed (8-bit RGB or mono only)")]
    Format(PixelFormat),
    #[error("an image of {0}×{1} is too large for JPEG")]
    Size(u32, u32),
    #[error("an empty image")]
    Empty,
    #[error(transparent)]
    Jpeg(#[from] jpeg_encoder::EncodingError),
    #[error(transparent)]
    Png(#[from] png::EncodingError),
}

fn eight_bit(image: &Image) -> Result<&[u8], CompressError> {
    if !matches!(image.format(), PixelFormat::Rgb8 | PixelFormat::Mono8) {
        return Err(CompressError::Format(image.format()));
    }
    if image.pixel_count() == 0 {
        return Err(CompressError::Empty);
    }
    image.as_u8().ok_or(CompressError::Format(image.format()))
}

/// An `Rgb8` or `Mono8` image as JPEG at `quality` (1–100).
pub fn jpeg(image: &Image, quality: u8) -> Result<Vec<u8>, CompressError> {
    let pixels = eight_bit(image)?;
    let color = match image.format() {
        PixelFormat::Mono8 => jpeg_encoder::ColorType::Luma,
        _ => jpeg_encoder::ColorType::Rgb,
    };
    let (Ok(width), Ok(height)) = (u16::try_from(image.width()), u16::try_from(image.height()))
    else {
        return Err(CompressError::Size(image.width(), image.height()));
    };
    let mut out = Vec::with_capacity(image.pixel_count() / 4);
    jpeg_encoder::Encoder::new(&mut out, quality).encode(pixels, width, height, color)?;
    Ok(out)
}

/// An `Rgb8` or `Mono8` image as PNG, with the fast filter and compression (a recorder writes
/// 30 of them a second).
pub fn png(image: &Image) -> Result<Vec<u8>, CompressError> {
    let pixels = eight_bit(image)?;
    let mut out = Vec::with_capacity(image.pixel_count());
    let mut encoder = png::Encoder::new(&mut out, image.width(), image.height());
    encoder.set_color(match image.format() {
        PixelFormat::Mono8 => png::ColorType::Grayscale,
        _ => png::ColorType::Rgb,
    });
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(pixels)?;
    writer.finish()?;
    Ok(out)
}

/// `image` in `encoding`, with the `format` a `sensor_msgs/msg/CompressedImage` names it by
/// (`png`, `jpeg`); `None` for [`ColorEncoding::Raw`].
pub fn compress(
    image: &Image,
    encoding: ColorEncoding,
) -> Option<Result<(&'static str, Vec<u8>), CompressError>> {
    match encoding {
        ColorEncoding::Raw => None,
        ColorEncoding::Png => Some(png(image).map(|data| ("png", data))),
        ColorEncoding::Jpeg { quality } => Some(jpeg(image, quality).map(|data| ("jpeg", data))),
    }
}

const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];

/// Decode a JPEG or PNG (told apart by their first bytes, whatever the message's `format`
/// says) into `Rgb8`, or `Mono8` when it is grey.
pub fn decompress(data: &[u8]) -> Result<Image, String> {
    let (width, height, pixels, grey) = if data.starts_with(&PNG_SIGNATURE) {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(data));
        decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
        let mut reader = decoder.read_info().map_err(|e| format!("PNG: {e}"))?;
        let size = reader
            .output_buffer_size()
            .ok_or("PNG: the image is too large")?;
        if size > super::MAX_IMAGE_BYTES {
            return Err(format!("PNG: {size} bytes of pixels is too many"));
        }
        let mut pixels = vec![0; size];
        let frame = reader
            .next_frame(&mut pixels)
            .map_err(|e| format!("PNG: {e}"))?;
        pixels.truncate(frame.buffer_size());
        let grey = match frame.color_type {
            png::ColorType::Grayscale => true,
            png::ColorType::Rgb => false,
            png::ColorType::Rgba => {
                pixels = pixels
                    .chunks_exact(4)
                    .flat_map(|p| [p[0], p[1], p[2]])
                    .collect();
                false
            }
            other => return Err(format!("PNG: {other:?} pixels are not read")),
        };
        (frame.width, frame.height, pixels, grey)
    } else if data.starts_with(&[0xFF, 0xD8]) {
        let mut decoder = jpeg_decoder::Decoder::new(data);
        decoder.read_info().map_err(|e| format!("JPEG: {e}"))?;
        let info = decoder.info().ok_or("JPEG: no frame header")?;
        let grey = match info.pixel_format {
            jpeg_decoder::PixelFormat::L8 => true,
            jpeg_decoder::PixelFormat::RGB24 => false,
            other => return Err(format!("JPEG: {other:?} pixels are not read")),
        };
        let size = usize::from(info.width) * usize::from(info.height) * 3;
        if size > super::MAX_IMAGE_BYTES {
            return Err(format!("JPEG: {size} bytes of pixels is too many"));
        }
        let pixels = decoder.decode().map_err(|e| format!("JPEG: {e}"))?;
        (u32::from(info.width), u32::from(info.height), pixels, grey)
    } else {
        return Err("the compressed image is neither PNG nor JPEG".into());
    };
    let format = if grey {
        PixelFormat::Mono8
    } else {
        PixelFormat::Rgb8
    };
    Image::from_bytes(width, height, format, &pixels).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient() -> Image {
        let mut image = Image::new(32, 16, PixelFormat::Rgb8);
        for (i, px) in image.as_u8_mut().unwrap().chunks_exact_mut(3).enumerate() {
            px.copy_from_slice(&[(i % 32 * 8) as u8, 128, (i / 32 * 16) as u8]);
        }
        image
    }

    #[test]
    fn png_is_exact_and_jpeg_close() {
        let image = gradient();
        assert_eq!(decompress(&png(&image).unwrap()).unwrap(), image);
        let grey =
            Image::from_bytes(4, 2, PixelFormat::Mono8, &[0, 9, 80, 255, 3, 4, 5, 6]).unwrap();
        assert_eq!(decompress(&png(&grey).unwrap()).unwrap(), grey);
        let decoded = decompress(&jpeg(&image, 95).unwrap()).unwrap();
        let original = image.as_u8().unwrap();
        let mean_error = decoded
            .as_u8()
            .unwrap()
            .iter()
            .zip(original)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / original.len() as f64;
        assert!(mean_error < 3.0, "mean error {mean_error} at quality 95");
    }

    #[test]
    fn what_cannot_be_compressed_or_decoded_is_an_error() {
        assert!(jpeg(&Image::new(0, 0, PixelFormat::Rgb8), 80).is_err());
        assert!(png(&Image::new(4, 4, PixelFormat::DepthF32M)).is_err());
        let bytes = png(&gradient()).unwrap();
        for len in [0, 4, 8, 40, bytes.len() / 2] {
            assert!(decompress(&bytes[..len]).is_err(), "prefix of {len}");
        }
        let bytes = jpeg(&gradient(), 80).unwrap();
        assert!(decompress(&bytes[..bytes.len() / 2]).is_err());
    }
}
