//! Frames: a timestamped, sequence-numbered payload, and the image payload most streams carry.

use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

/// When a frame was captured: the device's own clock and the host clock at arrival, both in ns.
///
/// Device clocks are monotonic per device but unrelated across devices; the synchroniser matches
/// streams on `host_ns`, and `device_ns` is kept for drop detection and jitter analysis.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize,
)]
pub struct Timestamp {
    pub device_ns: u64,
    pub host_ns: u64,
}

impl Timestamp {
    pub fn new(device_ns: u64, host_ns: u64) -> Self {
        Self { device_ns, host_ns }
    }

    /// A timestamp whose device and host clocks are both the host's wall clock now.
    pub fn now() -> Self {
        let host_ns = host_now_ns();
        Self {
            device_ns: host_ns,
            host_ns,
        }
    }
}

/// Host wall clock in ns since the Unix epoch (0 if the clock is before 1970).
pub fn host_now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// A payload with its capture time and its per-stream sequence number.
///
/// Sequence numbers are assigned by the producer and increase by one per captured frame, so a
/// gap tells a consumer how many frames were lost upstream.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Frame<T> {
    pub seq: u64,
    pub stamp: Timestamp,
    pub payload: T,
}

impl<T> Frame<T> {
    pub fn new(seq: u64, stamp: Timestamp, payload: T) -> Self {
        Self {
            seq,
            stamp,
            payload,
        }
    }
}

/// How pixels are laid out. Rows are tightly packed (stride = width × bytes per pixel).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PixelFormat {
    /// Depth in millimetres, 0 = invalid (what Kinect-class sensors deliver).
    DepthU16Mm,
    /// Depth in metres, 0 or non-finite = invalid (after the backend).
    DepthF32M,
    /// 8-bit sRGB-encoded RGB.
    Rgb8,
    /// Linear RGBA in IEEE half floats.
    Rgba16F,
    /// 8-bit single channel.
    Mono8,
}

impl PixelFormat {
    pub const ALL: [PixelFormat; 5] = [
        PixelFormat::DepthU16Mm,
        PixelFormat::DepthF32M,
        PixelFormat::Rgb8,
        PixelFormat::Rgba16F,
        PixelFormat::Mono8,
    ];

    /// Scalars (channels) per pixel.
    pub fn channels(self) -> usize {
        match self {
            PixelFormat::DepthU16Mm | PixelFormat::DepthF32M | PixelFormat::Mono8 => 1,
            PixelFormat::Rgb8 => 3,
            PixelFormat::Rgba16F => 4,
        }
    }

    /// Bytes per pixel when serialised.
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            PixelFormat::Mono8 => 1,
            PixelFormat::DepthU16Mm => 2,
            PixelFormat::Rgb8 => 3,
            PixelFormat::DepthF32M => 4,
            PixelFormat::Rgba16F => 8,
        }
    }

    /// The encoding name used by Foxglove's RawImage schema (ROS `sensor_msgs/Image` names).
    pub fn ros_encoding(self) -> &'static str {
        match self {
            PixelFormat::DepthU16Mm => "16UC1",
            PixelFormat::DepthF32M => "32FC1",
            PixelFormat::Rgb8 => "rgb8",
            PixelFormat::Rgba16F => "rgba16f",
            PixelFormat::Mono8 => "mono8",
        }
    }

    pub fn from_ros_encoding(encoding: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.ros_encoding() == encoding)
    }

    fn empty_pixels(self) -> Pixels {
        match self {
            PixelFormat::Rgb8 | PixelFormat::Mono8 => Pixels::U8(Vec::new()),
            PixelFormat::DepthU16Mm | PixelFormat::Rgba16F => Pixels::U16(Vec::new()),
            PixelFormat::DepthF32M => Pixels::F32(Vec::new()),
        }
    }
}

/// Pixel storage, typed so that u16 and f32 images are always aligned. `Rgba16F` is stored as
/// the raw bits of `half::f16` in `U16`.
#[derive(Debug, Clone, PartialEq)]
pub enum Pixels {
    U8(Vec<u8>),
    U16(Vec<u16>),
    F32(Vec<f32>),
}

impl Pixels {
    fn len(&self) -> usize {
        match self {
            Pixels::U8(v) => v.len(),
            Pixels::U16(v) => v.len(),
            Pixels::F32(v) => v.len(),
        }
    }

    /// Resize to `len` scalars (zero-filled where grown), reusing capacity: no allocation when
    /// the buffer already held that many.
    fn resize(&mut self, len: usize) {
        match self {
            Pixels::U8(v) => v.resize(len, 0),
            Pixels::U16(v) => v.resize(len, 0),
            Pixels::F32(v) => v.resize(len, 0.0),
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ImageError {
    #[error("image data holds {actual} bytes, but {width}×{height} {format:?} needs {expected}")]
    SizeMismatch {
        width: u32,
        height: u32,
        format: PixelFormat,
        expected: usize,
        actual: usize,
    },
    #[error("image is {actual:?}, expected {expected:?}")]
    WrongFormat {
        expected: PixelFormat,
        actual: PixelFormat,
    },
}

/// A tightly packed image.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    width: u32,
    height: u32,
    format: PixelFormat,
    pixels: Pixels,
}

impl Default for Image {
    fn default() -> Self {
        Image::new(0, 0, PixelFormat::Mono8)
    }
}

impl Image {
    /// A zero-filled image.
    pub fn new(width: u32, height: u32, format: PixelFormat) -> Self {
        let mut image = Image {
            width: 0,
            height: 0,
            format,
            pixels: format.empty_pixels(),
        };
        image.reshape(width, height, format);
        image
    }

    /// Change size and format in place. Reuses the buffer when the format's storage type stays
    /// the same, so a pooled image that is reshaped to the same size allocates nothing.
    pub fn reshape(&mut self, width: u32, height: u32, format: PixelFormat) {
        if std::mem::discriminant(&self.pixels) != std::mem::discriminant(&format.empty_pixels()) {
            self.pixels = format.empty_pixels();
        }
        self.width = width;
        self.height = height;
        self.format = format;
        self.pixels
            .resize(width as usize * height as usize * format.channels());
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn format(&self) -> PixelFormat {
        self.format
    }
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
    pub fn pixels(&self) -> &Pixels {
        &self.pixels
    }

    /// Bytes of one packed row.
    pub fn stride(&self) -> usize {
        self.width as usize * self.format.bytes_per_pixel()
    }

    fn expect(&self, expected: PixelFormat) -> Result<(), ImageError> {
        if self.format == expected {
            Ok(())
        } else {
            Err(ImageError::WrongFormat {
                expected,
                actual: self.format,
            })
        }
    }

    /// 8-bit scalars of an `Rgb8` or `Mono8` image.
    pub fn as_u8(&self) -> Option<&[u8]> {
        match &self.pixels {
            Pixels::U8(v) => Some(v),
            _ => None,
        }
    }
    pub fn as_u8_mut(&mut self) -> Option<&mut [u8]> {
        match &mut self.pixels {
            Pixels::U8(v) => Some(v),
            _ => None,
        }
    }
    /// 16-bit scalars of a `DepthU16Mm` image (or the f16 bits of `Rgba16F`).
    pub fn as_u16(&self) -> Option<&[u16]> {
        match &self.pixels {
            Pixels::U16(v) => Some(v),
            _ => None,
        }
    }
    pub fn as_u16_mut(&mut self) -> Option<&mut [u16]> {
        match &mut self.pixels {
            Pixels::U16(v) => Some(v),
            _ => None,
        }
    }
    pub fn as_f32(&self) -> Option<&[f32]> {
        match &self.pixels {
            Pixels::F32(v) => Some(v),
            _ => None,
        }
    }
    pub fn as_f32_mut(&mut self) -> Option<&mut [f32]> {
        match &mut self.pixels {
            Pixels::F32(v) => Some(v),
            _ => None,
        }
    }

    /// Depth in metres at (x, y), `None` where invalid (0, non-finite) or off the image.
    pub fn depth_m(&self, x: u32, y: u32) -> Option<f32> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = y as usize * self.width as usize + x as usize;
        let depth_m = match (self.format, &self.pixels) {
            (PixelFormat::DepthU16Mm, Pixels::U16(v)) => f32::from(v[i]) / 1000.0,
            (PixelFormat::DepthF32M, Pixels::F32(v)) => v[i],
            _ => return None,
        };
        (depth_m.is_finite() && depth_m > 0.0).then_some(depth_m)
    }

    /// Every `step`-th pixel along each axis from (0, 0): pixel (x, y) of the result is pixel
    /// (x·step, y·step) of this one, ⌈width/step⌉ × ⌈height/step⌉ of them. Samples, not
    /// averages: a depth value stays one measurement, never a blend across an edge.
    pub fn subsampled(&self, step: u32) -> Image {
        fn pick<T: Copy>(src: &[T], dst: &mut [T], width: usize, channels: usize, step: usize) {
            let out_width = width.div_ceil(step);
            for (row, out_row) in dst.chunks_exact_mut(out_width * channels).enumerate() {
                let src_row = &src[row * step * width * channels..][..width * channels];
                for (x, out) in out_row.chunks_exact_mut(channels).enumerate() {
                    out.copy_from_slice(&src_row[x * step * channels..][..channels]);
                }
            }
        }
        let step = step.max(1);
        let mut out = Image::new(
            self.width.div_ceil(step),
            self.height.div_ceil(step),
            self.format,
        );
        if out.pixel_count() == 0 {
            return out;
        }
        let (width, channels) = (self.width as usize, self.format.channels());
        let step = step as usize;
        match (&self.pixels, &mut out.pixels) {
            (Pixels::U8(s), Pixels::U8(d)) => pick(s, d, width, channels, step),
            (Pixels::U16(s), Pixels::U16(d)) => pick(s, d, width, channels, step),
            (Pixels::F32(s), Pixels::F32(d)) => pick(s, d, width, channels, step),
            _ => unreachable!("an image and its subsample share the format's storage"),
        }
        out
    }

    /// Convert a `DepthU16Mm` image into `out` as `DepthF32M` (0 stays 0 = invalid).
    pub fn depth_mm_to_m(&self, out: &mut Image) -> Result<(), ImageError> {
        self.expect(PixelFormat::DepthU16Mm)?;
        out.reshape(self.width, self.height, PixelFormat::DepthF32M);
        if let (Pixels::U16(src), Pixels::F32(dst)) = (&self.pixels, &mut out.pixels) {
            for (d, s) in dst.iter_mut().zip(src) {
                *d = f32::from(*s) / 1000.0;
            }
        }
        Ok(())
    }

    /// Serialise the pixels as packed little-endian bytes into `out` (cleared first).
    pub fn write_bytes(&self, out: &mut Vec<u8>) {
        out.clear();
        out.reserve(self.pixel_count() * self.format.bytes_per_pixel());
        match &self.pixels {
            Pixels::U8(v) => out.extend_from_slice(v),
            Pixels::U16(v) => v
                .iter()
                .for_each(|s| out.extend_from_slice(&s.to_le_bytes())),
            Pixels::F32(v) => v
                .iter()
                .for_each(|s| out.extend_from_slice(&s.to_le_bytes())),
        }
    }

    /// Parse packed little-endian bytes; the length must match the size and format exactly.
    pub fn from_bytes(
        width: u32,
        height: u32,
        format: PixelFormat,
        bytes: &[u8],
    ) -> Result<Image, ImageError> {
        let expected = width as usize * height as usize * format.bytes_per_pixel();
        if bytes.len() != expected {
            return Err(ImageError::SizeMismatch {
                width,
                height,
                format,
                expected,
                actual: bytes.len(),
            });
        }
        let pixels = match format.empty_pixels() {
            Pixels::U8(_) => Pixels::U8(bytes.to_vec()),
            Pixels::U16(_) => Pixels::U16(
                bytes
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            ),
            Pixels::F32(_) => Pixels::F32(
                bytes
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
            ),
        };
        debug_assert_eq!(
            pixels.len(),
            width as usize * height as usize * format.channels()
        );
        Ok(Image {
            width,
            height,
            format,
            pixels,
        })
    }
}

/// A rectangle of pixels: columns `x..x + width`, rows `y..y + height` (no pixel when either is
/// 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl PixelRect {
    /// Every pixel of a `width` × `height` image.
    pub fn full(width: u32, height: u32) -> Self {
        Self {
            x: 0,
            y: 0,
            width,
            height,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.width == 0 || self.height == 0
    }

    pub fn area(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// Whether every pixel of `other` is in this rectangle.
    pub fn contains(&self, other: Self) -> bool {
        other.is_empty()
            || (other.x >= self.x
                && other.y >= self.y
                && other.x + other.width <= self.x + self.width
                && other.y + other.height <= self.y + self.height)
    }

    /// The rectangle grown by `by` pixels on every side, within a `width` × `height` image.
    pub fn grown(self, by: u32, width: u32, height: u32) -> Self {
        if self.is_empty() {
            return self;
        }
        let (x, y) = (self.x.saturating_sub(by), self.y.saturating_sub(by));
        let right = (self.x + self.width + by).min(width);
        let bottom = (self.y + self.height + by).min(height);
        Self {
            x,
            y,
            width: right - x,
            height: bottom - y,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_round_trip_every_format() {
        for format in PixelFormat::ALL {
            let mut image = Image::new(5, 3, format);
            match &mut image.pixels {
                Pixels::U8(v) => v.iter_mut().enumerate().for_each(|(i, p)| *p = i as u8),
                Pixels::U16(v) => v
                    .iter_mut()
                    .enumerate()
                    .for_each(|(i, p)| *p = 1000 + i as u16),
                Pixels::F32(v) => v
                    .iter_mut()
                    .enumerate()
                    .for_each(|(i, p)| *p = i as f32 * 0.25),
            }
            let mut bytes = Vec::new();
            image.write_bytes(&mut bytes);
            assert_eq!(bytes.len(), 15 * format.bytes_per_pixel());
            let back = Image::from_bytes(5, 3, format, &bytes).unwrap();
            assert_eq!(back, image);
            assert_eq!(
                PixelFormat::from_ros_encoding(format.ros_encoding()),
                Some(format)
            );
        }
    }

    #[test]
    fn wrong_byte_count_is_an_error_not_a_panic() {
        let err = Image::from_bytes(4, 4, PixelFormat::DepthU16Mm, &[0; 31]).unwrap_err();
        assert!(matches!(
            err,
            ImageError::SizeMismatch {
                expected: 32,
                actual: 31,
                ..
            }
        ));
    }

    #[test]
    fn invalid_depth_is_none() {
        let mut depth = Image::new(2, 1, PixelFormat::DepthU16Mm);
        depth.as_u16_mut().unwrap()[1] = 1500;
        assert_eq!(depth.depth_m(0, 0), None);
        assert_eq!(depth.depth_m(1, 0), Some(1.5));
        assert_eq!(depth.depth_m(2, 0), None);
        let mut metres = Image::default();
        depth.depth_mm_to_m(&mut metres).unwrap();
        assert_eq!(metres.as_f32().unwrap(), &[0.0, 1.5]);
        let mut nan = Image::new(1, 1, PixelFormat::DepthF32M);
        nan.as_f32_mut().unwrap()[0] = f32::NAN;
        assert_eq!(nan.depth_m(0, 0), None);
    }

    #[test]
    fn a_subsample_keeps_every_steps_pixel_whole() {
        let mut colour = Image::new(5, 3, PixelFormat::Rgb8);
        colour
            .as_u8_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
            .for_each(|(i, p)| *p = i as u8);
        let half = colour.subsampled(2);
        assert_eq!(
            (half.width(), half.height(), half.format()),
            (3, 2, PixelFormat::Rgb8)
        );
        // Pixels (0, 0), (2, 0), (4, 0), then (0, 2), (2, 2), (4, 2) of the 5-wide image.
        let expected: Vec<u8> = [0, 2, 4, 10, 12, 14]
            .iter()
            .flat_map(|&p| (0..3).map(move |c| p * 3 + c))
            .collect();
        assert_eq!(half.as_u8().unwrap(), expected.as_slice());

        let mut depth = Image::new(4, 4, PixelFormat::DepthF32M);
        depth.as_f32_mut().unwrap()[2 * 4 + 2] = 1.5;
        let third = depth.subsampled(3);
        assert_eq!((third.width(), third.height()), (2, 2));
        assert_eq!(third.depth_m(0, 0), None);
        assert_eq!(depth.subsampled(2).depth_m(1, 1), Some(1.5));
        assert_eq!(depth.subsampled(1), depth);
        assert_eq!(
            Image::new(0, 0, PixelFormat::Mono8)
                .subsampled(2)
                .pixel_count(),
            0
        );
    }
}
