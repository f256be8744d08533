//! Motion-JPEG frames → `Rgb8`.
//!
//! UVC cameras send each frame as a baseline JPEG, often without its Huffman tables: MJPEG
//! streams (OpenDML AVI File Format Extensions, "MJPEG DHT segment") omit the DHT segment and
//! rely on the standard tables of ITU-T T.81 Annex K.3. `jpeg-decoder` substitutes those only
//! when the frame carries the AVI1 APP0 marker, which many cameras leave out too, so a frame
//! with neither DHT nor AVI1 gets an AVI1 marker inserted after its SOI before decoding.

use jpeg_decoder::{Decoder, PixelFormat as JpegFormat};
use relight_core::Image;

use crate::pixel_convert::{ConvertError, grey_to_rgb, rgb24_to_rgb};

#[derive(Debug, thiserror::Error)]
pub enum MjpegError {
    #[error("not a JPEG frame: {0}")]
    Structure(&'static str),
    #[error("JPEG decode failed: {0}")]
    Decode(#[from] jpeg_decoder::Error),
    #[error("JPEG frame is {actual:?}, the stream was negotiated at {expected:?}")]
    Size {
        expected: (u32, u32),
        actual: (u32, u32),
    },
    #[error("JPEG pixel format {0:?} is not a camera format")]
    Format(JpegFormat),
    #[error(transparent)]
    Convert(#[from] ConvertError),
}

const SOI: u8 = 0xD8;
const SOS: u8 = 0xDA;
const DHT: u8 = 0xC4;
const APP0: u8 = 0xE0;
/// APP0 segment marking an AVI MJPEG frame: marker, length 7 (itself + "AVI1\0").
const AVI1_SEGMENT: [u8; 9] = [0xFF, APP0, 0x00, 0x07, b'A', b'V', b'I', b'1', 0x00];

/// Whether the headers (up to the first SOS) hold a DHT segment or an AVI1 marker.
fn has_huffman_tables(data: &[u8]) -> Result<bool, MjpegError> {
    if data.len() < 4 || data[0] != 0xFF || data[1] != SOI {
        return Err(MjpegError::Structure("no SOI marker"));
    }
    let mut at = 2;
    loop {
        // Markers may be preceded by any number of 0xFF fill bytes (T.81 B.1.1.2).
        while data.get(at) == Some(&0xFF) && data.get(at + 1) == Some(&0xFF) {
            at += 1;
        }
        let (Some(&0xFF), Some(&marker)) = (data.get(at), data.get(at + 1)) else {
            return Err(MjpegError::Structure("headers end without a scan"));
        };
        if marker == SOS {
            return Ok(false);
        }
        let length = match (data.get(at + 2), data.get(at + 3)) {
            (Some(&hi), Some(&lo)) => usize::from(u16::from_be_bytes([hi, lo])),
            _ => return Err(MjpegError::Structure("truncated segment header")),
        };
        if length < 2 || at + 2 + length > data.len() {
            return Err(MjpegError::Structure("segment runs past the frame"));
        }
        let payload = &data[at + 4..at + 2 + length];
        if marker == DHT || (marker == APP0 && payload.starts_with(b"AVI1\0")) {
            return Ok(true);
        }
        at += 2 + length;
    }
}

/// Decode one MJPEG frame of the negotiated `width × height` into `out` (`Rgb8`). `scratch`
/// holds the frame when a marker must be inserted.
pub fn decode_mjpeg(
    data: &[u8],
    width: u32,
    height: u32,
    scratch: &mut Vec<u8>,
    out: &mut Image,
) -> Result<(), MjpegError> {
    let input = if has_huffman_tables(data)? {
        data
    } else {
        scratch.clear();
        scratch.extend_from_slice(&data[..2]);
        scratch.extend_from_slice(&AVI1_SEGMENT);
        scratch.extend_from_slice(&data[2..]);
        scratch.as_slice()
    };
    let mut decoder = Decoder::new(input);
    let pixels = decoder.decode()?;
    let info = decoder
        .info()
        .ok_or(MjpegError::Structure("decoder returned no frame header"))?;
    let actual = (u32::from(info.width), u32::from(info.height));
    if actual != (width, height) {
        return Err(MjpegError::Size {
            expected: (width, height),
            actual,
        });
    }
    match info.pixel_format {
        JpegFormat::RGB24 => rgb24_to_rgb(&pixels, width, height, width as usize * 3, false, out)?,
        JpegFormat::L8 => grey_to_rgb(&pixels, width, height, width as usize, out)?,
        other => return Err(MjpegError::Format(other)),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_scan_finds_tables_markers_and_garbage() {
        let sos = [0xFF, SOS, 0x00, 0x02];
        let dht = [0xFF, DHT, 0x00, 0x03, 0x00];
        let app0_jfif = [0xFF, APP0, 0x00, 0x07, b'J', b'F', b'I', b'F', 0x00];
        let frame = |segments: &[&[u8]]| {
            let mut f = vec![0xFF, SOI];
            segments.iter().for_each(|s| f.extend_from_slice(s));
            f
        };
        assert!(has_huffman_tables(&frame(&[&app0_jfif, &dht, &sos])).unwrap());
        assert!(has_huffman_tables(&frame(&[&AVI1_SEGMENT, &sos])).unwrap());
        assert!(!has_huffman_tables(&frame(&[&app0_jfif, &sos])).unwrap());
        assert!(
            !has_huffman_tables(&frame(&[&[0xFF], &sos])).unwrap(),
            "fill byte"
        );
        assert!(has_huffman_tables(b"not a jpeg").is_err());
        assert!(has_huffman_tables(&frame(&[&[0xFF, APP0, 0x10, 0x00]])).is_err());
        assert!(
            has_huffman_tables(&frame(&[&app0_jfif])).is_err(),
            "no scan"
        );
    }
}
