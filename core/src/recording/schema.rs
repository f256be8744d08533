//! CDR, the ROS 2 wire format (OMG XCDR1 as ROS 2 writes it: a 4-byte encapsulation header,
//! then fields aligned to their own size relative to the end of that header), written and read
//! by hand, and its `sensor_msgs/msg/Image` codec. The other messages are in [`super::ros_msgs`]
//! and [`super::camera_info`].

use crate::frame::{Image, PixelFormat, Pixels};

/// MCAP message encoding of JSON messages (format 1's markers, lamp and truth state).
pub const JSON_MESSAGE_ENCODING: &str = "json";

/// ROS 2 type name of the image schema.
pub const IMAGE_SCHEMA_NAME: &str = "sensor_msgs/msg/Image";
/// MCAP schema encoding of ROS 2 message definitions.
pub const ROS2MSG_SCHEMA_ENCODING: &str = "ros2msg";
/// MCAP message encoding of ROS 2 CDR.
pub const CDR_MESSAGE_ENCODING: &str = "cdr";

/// The definitions of `std_msgs/Header` and `builtin_interfaces/Time` a ROS 2 schema that has
/// a header appends, as a literal for `concat!`.
macro_rules! header_definitions {
    () => {
        "\
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"
    };
}
pub(super) use header_definitions;

/// `sensor_msgs/msg/Image` with its dependencies, in the concatenated form of ROS 2 bags
/// (`rosbag2` / `mcap-ros2-support`).
pub const IMAGE_SCHEMA: &str = concat!(
    "\
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
",
    header_definitions!()
);

/// CDR encapsulation header of little-endian plain CDR (`CDR_LE`).
const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Appends CDR fields, aligning each to its size relative to the end of the encapsulation header.
pub(super) struct CdrWriter<'a> {
    out: &'a mut Vec<u8>,
    body_start: usize,
}

impl<'a> CdrWriter<'a> {
    pub(super) fn new(out: &'a mut Vec<u8>) -> Self {
        out.extend_from_slice(&CDR_LE_HEADER);
        let body_start = out.len();
        Self { out, body_start }
    }

    fn align(&mut self, size: usize) {
        let pos = self.out.len() - self.body_start;
        let padding = (size - pos % size) % size;
        self.out.resize(self.out.len() + padding, 0);
    }

    pub(super) fn u8(&mut self, value: u8) {
        self.out.push(value);
    }

    pub(super) fn u32(&mut self, value: u32) {
        self.align(4);
        self.out.extend_from_slice(&value.to_le_bytes());
    }

    pub(super) fn i32(&mut self, value: i32) {
        self.align(4);
        self.out.extend_from_slice(&value.to_le_bytes());
    }

    pub(super) fn u64(&mut self, value: u64) {
        self.align(8);
        self.out.extend_from_slice(&value.to_le_bytes());
    }

    pub(super) fn f32(&mut self, value: f32) {
        self.align(4);
        self.out.extend_from_slice(&value.to_le_bytes());
    }

    pub(super) fn f64(&mut self, value: f64) {
        self.align(8);
        self.out.extend_from_slice(&value.to_le_bytes());
    }

    pub(super) fn bool(&mut self, value: bool) {
        self.out.push(u8::from(value));
    }

    /// A `uint8[]`: its length, then the bytes.
    pub(super) fn bytes(&mut self, value: &[u8]) -> Result<(), String> {
        let len = u32::try_from(value.len())
            .map_err(|_| format!("{} bytes are too many for a CDR sequence", value.len()))?;
        self.u32(len);
        self.out.extend_from_slice(value);
        Ok(())
    }

    /// `header.stamp` (seconds saturating at `i32::MAX`, nanoseconds) and `header.frame_id`.
    pub(super) fn header(&mut self, stamp_ns: u64, frame_id: &str) -> Result<(), String> {
        let sec = i32::try_from(stamp_ns / 1_000_000_000).unwrap_or(i32::MAX);
        self.i32(sec);
        self.u32((stamp_ns % 1_000_000_000) as u32);
        self.string(frame_id)
    }

    /// A CDR string: length including the terminating NUL, bytes, NUL.
    pub(super) fn string(&mut self, value: &str) -> Result<(), String> {
        let len = u32::try_from(value.len() + 1)
            .map_err(|_| format!("string of {} bytes is too long for CDR", value.len()))?;
        self.u32(len);
        self.out.extend_from_slice(value.as_bytes());
        self.out.push(0);
        Ok(())
    }
}

/// Reads CDR fields with bounds checks; every failure is a reason string.
pub(super) struct CdrReader<'a> {
    body: &'a [u8],
    pos: usize,
}

impl<'a> CdrReader<'a> {
    pub(super) fn new(data: &'a [u8]) -> Result<Self, String> {
        let (header, body) = data
            .split_first_chunk::<4>()
            .ok_or_else(|| format!("{} bytes is too short for a CDR header", data.len()))?;
        match header {
            [0x00, 0x01, _, _] => Ok(Self { body, pos: 0 }),
            [0x00, 0x00, _, _] => Err("big-endian CDR is not supported".into()),
            other => Err(format!("unknown CDR encapsulation {other:02x?}")),
        }
    }

    pub(super) fn take(&mut self, len: usize) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(len)
            .filter(|&end| end <= self.body.len())
            .ok_or_else(|| {
                format!(
                    "CDR field of {len} bytes at body offset {} runs past the {}-byte message",
                    self.pos,
                    self.body.len()
                )
            })?;
        let bytes = self.body.get(self.pos..end).unwrap_or_default();
        self.pos = end;
        Ok(bytes)
    }

    fn align(&mut self, size: usize) {
        self.pos += (size - self.pos % size) % size;
    }

    pub(super) fn u8(&mut self) -> Result<u8, String> {
        let bytes = self.take(1)?;
        Ok(bytes.first().copied().unwrap_or_default())
    }

    pub(super) fn u32(&mut self) -> Result<u32, String> {
        self.align(4);
        let bytes = self.take(4)?;
        let array: [u8; 4] = bytes.try_into().map_err(|_| "short u32".to_string())?;
        Ok(u32::from_le_bytes(array))
    }

    pub(super) fn i32(&mut self) -> Result<i32, String> {
        self.u32().map(|v| v as i32)
    }

    pub(super) fn u64(&mut self) -> Result<u64, String> {
        self.align(8);
        let bytes = self.take(8)?;
        let array: [u8; 8] = bytes.try_into().map_err(|_| "short u64".to_string())?;
        Ok(u64::from_le_bytes(array))
    }

    pub(super) fn f32(&mut self) -> Result<f32, String> {
        self.u32().map(f32::from_bits)
    }

    pub(super) fn f64(&mut self) -> Result<f64, String> {
        self.u64().map(f64::from_bits)
    }

    pub(super) fn bool(&mut self) -> Result<bool, String> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            other => Err(format!("bool byte {other}")),
        }
    }

    /// A `uint8[]`.
    pub(super) fn bytes(&mut self) -> Result<&'a [u8], String> {
        let len = self.u32()? as usize;
        self.take(len)
    }

    /// The length of a sequence whose elements take at least `min_element_bytes` each, checked
    /// against what is left, so a lying length cannot make the caller reserve memory.
    pub(super) fn sequence_len(&mut self, min_element_bytes: usize) -> Result<usize, String> {
        let len = self.u32()? as usize;
        let left = self.body.len().saturating_sub(self.pos);
        if len.saturating_mul(min_element_bytes.max(1)) > left {
            return Err(format!(
                "sequence of {len} elements does not fit in the {left} bytes left"
            ));
        }
        Ok(len)
    }

    /// `header.stamp` in ns (negative seconds clamp to 0) and `header.frame_id`.
    pub(super) fn header(&mut self) -> Result<(u64, &'a str), String> {
        let sec = self.i32()?;
        let nanosec = self.u32()?;
        let frame_id = self.string("header.frame_id")?;
        let stamp_ns = u64::try_from(sec).unwrap_or(0) * 1_000_000_000 + u64::from(nanosec);
        Ok((stamp_ns, frame_id))
    }

    pub(super) fn string(&mut self, field: &str) -> Result<&'a str, String> {
        let len = self.u32()? as usize;
        let bytes = self.take(len)?;
        let text = match bytes.split_last() {
            Some((0, text)) => text,
            Some(_) => return Err(format!("{field}: string is not NUL-terminated")),
            None => &[],
        };
        std::str::from_utf8(text).map_err(|e| format!("{field}: {e}"))
    }
}

/// The ROS encoding a half-float RGBA image is written in: `rgba16f` is relight's own, which
/// neither ROS nor Foxglove knows, so the values go out widened to f32 (exactly).
pub const RGBA16F_WIRE_ENCODING: &str = "32FC4";

/// Encode `image` as a CDR `sensor_msgs/msg/Image` into `out` (cleared first). `header.stamp` is
/// `stamp_ns` split into seconds (saturating at `i32::MAX`) and nanoseconds. Encodings are
/// [`PixelFormat::ros_encoding`]'s, except `Rgba16F`, written as [`RGBA16F_WIRE_ENCODING`].
pub fn encode_image(
    out: &mut Vec<u8>,
    stamp_ns: u64,
    frame_id: &str,
    image: &Image,
) -> Result<(), String> {
    out.clear();
    let format = image.format();
    let (encoding, bytes_per_pixel) = match format {
        PixelFormat::Rgba16F => (RGBA16F_WIRE_ENCODING, 16),
        _ => (format.ros_encoding(), format.bytes_per_pixel()),
    };
    let data_len = image.pixel_count() * bytes_per_pixel;
    let data_len_u32 = u32::try_from(data_len)
        .map_err(|_| format!("image of {data_len} bytes is too large for sensor_msgs/Image"))?;
    let row = image.width() as usize * bytes_per_pixel;
    let step = u32::try_from(row).map_err(|_| format!("row of {row} bytes is too large"))?;
    out.reserve(data_len + 64 + frame_id.len());

    let mut cdr = CdrWriter::new(out);
    cdr.header(stamp_ns, frame_id)?;
    cdr.u32(image.height());
    cdr.u32(image.width());
    cdr.string(encoding)?;
    cdr.u8(0);
    cdr.u32(step);
    cdr.u32(data_len_u32);
    match (format, image.pixels()) {
        (PixelFormat::Rgba16F, Pixels::U16(halves)) => {
            let start = cdr.out.len();
            cdr.out.resize(start + halves.len() * 4, 0);
            for (dst, bits) in cdr.out[start..].chunks_exact_mut(4).zip(halves) {
                dst.copy_from_slice(&half::f16::from_bits(*bits).to_f32().to_le_bytes());
            }
        }
        (_, pixels) => append_le_pixels(cdr.out, pixels),
    }
    Ok(())
}

/// Append pixels as packed little-endian scalars, writing into a pre-sized tail so the loop
/// compiles to plain stores.
fn append_le_pixels(out: &mut Vec<u8>, pixels: &Pixels) {
    match pixels {
        Pixels::U8(values) => out.extend_from_slice(values),
        Pixels::U16(values) => {
            let start = out.len();
            out.resize(start + values.len() * 2, 0);
            for (dst, value) in out[start..].chunks_exact_mut(2).zip(values) {
                dst.copy_from_slice(&value.to_le_bytes());
            }
        }
        Pixels::F32(values) => {
            let start = out.len();
            out.resize(start + values.len() * 4, 0);
            for (dst, value) in out[start..].chunks_exact_mut(4).zip(values) {
                dst.copy_from_slice(&value.to_le_bytes());
            }
        }
    }
}

/// A decoded `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedImage {
    /// `header.stamp` in ns (negative seconds clamp to 0).
    pub stamp_ns: u64,
    pub frame_id: String,
    pub image: Image,
}

/// Decode a CDR `sensor_msgs/msg/Image`. Rows padded beyond the packed width (`step` larger than
/// width × bytes per pixel, as some drivers write) are repacked. Besides relight's own
/// encodings ([`PixelFormat::ros_encoding`]) it reads the colour encodings other ROS drivers
/// write, `bgr8`, `rgba8` and `bgra8`, as [`PixelFormat::Rgb8`] (alpha dropped).
pub fn decode_image(data: &[u8]) -> Result<DecodedImage, String> {
    let mut cdr = CdrReader::new(data)?;
    let (stamp_ns, frame_id) = cdr.header()?;
    let frame_id = frame_id.to_owned();
    let height = cdr.u32()?;
    let width = cdr.u32()?;
    let encoding = cdr.string("encoding")?;
    let is_bigendian = cdr.u8()?;
    let step = cdr.u32()? as usize;
    let data_len = cdr.u32()? as usize;
    let pixel_bytes = cdr.take(data_len)?;

    if encoding == RGBA16F_WIRE_ENCODING {
        return decode_rgba32f(stamp_ns, frame_id, width, height, step, pixel_bytes);
    }
    let (format, source) = match PixelFormat::from_ros_encoding(encoding) {
        Some(format) => (format, None),
        None => (
            PixelFormat::Rgb8,
            Some(
                ForeignColour::of(encoding)
                    .ok_or_else(|| format!("unsupported image encoding `{encoding}`"))?,
            ),
        ),
    };
    if is_bigendian != 0 && format.bytes_per_pixel() > 1 {
        return Err("big-endian pixel data is not supported".into());
    }
    let source_bpp = source.map_or(format.bytes_per_pixel(), |s| s.bytes_per_pixel);
    let stride = width as usize * source_bpp;
    let rows = height as usize;
    let needed = step
        .checked_mul(rows.saturating_sub(1))
        .and_then(|n| n.checked_add(if rows == 0 { 0 } else { stride }))
        .ok_or_else(|| "image size overflows".to_string())?;
    if step < stride || pixel_bytes.len() < needed {
        return Err(format!(
            "{width}×{height} {encoding} with step {step} needs {needed} bytes of data (step ≥ {stride}), got {}",
            pixel_bytes.len()
        ));
    }
    let row_bytes = || {
        pixel_bytes
            .chunks(step.max(1))
            .take(rows)
            .map(|row| row.get(..stride).unwrap_or_default())
    };
    let image = match source {
        Some(colour) => {
            let packed: Vec<u8> = row_bytes()
                .flat_map(|row| row.chunks_exact(colour.bytes_per_pixel))
                .flat_map(|pixel| colour.rgb.map(|c| pixel.get(c).copied().unwrap_or(0)))
                .collect();
            Image::from_bytes(width, height, format, &packed)
        }
        None if step == stride => Image::from_bytes(
            width,
            height,
            format,
            pixel_bytes.get(..needed).unwrap_or_default(),
        ),
        None => {
            let packed: Vec<u8> = row_bytes().flatten().copied().collect();
            Image::from_bytes(width, height, format, &packed)
        }
    }
    .map_err(|e| e.to_string())?;

    Ok(DecodedImage {
        stamp_ns,
        frame_id,
        image,
    })
}

/// A `32FC4` image, narrowed to `Rgba16F` (exact for what [`encode_image`] wrote).
fn decode_rgba32f(
    stamp_ns: u64,
    frame_id: String,
    width: u32,
    height: u32,
    step: usize,
    pixel_bytes: &[u8],
) -> Result<DecodedImage, String> {
    let stride = width as usize * 16;
    let rows = height as usize;
    let needed = stride
        .checked_mul(rows)
        .ok_or_else(|| "image size overflows".to_string())?;
    if step != stride || pixel_bytes.len() < needed {
        return Err(format!(
            "{width}×{height} {RGBA16F_WIRE_ENCODING} with step {step} needs {needed} bytes (step {stride}), got {}",
            pixel_bytes.len()
        ));
    }
    let halves: Vec<u8> = pixel_bytes
        .get(..needed)
        .unwrap_or_default()
        .chunks_exact(4)
        .flat_map(|v| {
            let value = f32::from_le_bytes([v[0], v[1], v[2], v[3]]);
            half::f16::from_f32(value).to_bits().to_le_bytes()
        })
        .collect();
    let image = Image::from_bytes(width, height, PixelFormat::Rgba16F, &halves)
        .map_err(|e| e.to_string())?;
    Ok(DecodedImage {
        stamp_ns,
        frame_id,
        image,
    })
}

/// An 8-bit colour encoding of other ROS drivers, read into `rgb8`.
#[derive(Debug, Clone, Copy)]
struct ForeignColour {
    bytes_per_pixel: usize,
    /// Where red, green and blue lie in a pixel.
    rgb: [usize; 3],
}

impl ForeignColour {
    fn of(encoding: &str) -> Option<Self> {
        let (bytes_per_pixel, rgb) = match encoding {
            "bgr8" => (3, [2, 1, 0]),
            "rgba8" => (4, [0, 1, 2]),
            "bgra8" => (4, [2, 1, 0]),
            _ => return None,
        };
        Some(Self {
            bytes_per_pixel,
            rgb,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_cdr_layout_matches_ros2() {
        let mut image = Image::new(2, 1, PixelFormat::DepthU16Mm);
        image
            .as_u16_mut()
            .unwrap()
            .copy_from_slice(&[0x0102, 0x0304]);
        let mut out = Vec::new();
        encode_image(&mut out, 3_000_000_005, "ab", &image).unwrap();
        #[rustfmt::skip]
        let expected: Vec<u8> = [
            &[0x00, 0x01, 0x00, 0x00][..],      // CDR_LE
            &3i32.to_le_bytes(), &5u32.to_le_bytes(),
            &3u32.to_le_bytes(), b"ab\0", &[0],  // frame_id + pad to 4
            &1u32.to_le_bytes(), &2u32.to_le_bytes(),
            &6u32.to_le_bytes(), b"16UC1\0",     // encoding
            &[0],                                 // is_bigendian
            &[0],                                 // pad to 4
            &4u32.to_le_bytes(),                  // step
            &4u32.to_le_bytes(), &[0x02, 0x01, 0x04, 0x03],
        ]
        .concat();
        assert_eq!(out, expected);
        let decoded = decode_image(&out).unwrap();
        assert_eq!(decoded.image, image);
        assert_eq!(decoded.stamp_ns, 3_000_000_005);
        assert_eq!(decoded.frame_id, "ab");
    }

    #[test]
    fn padded_rows_are_repacked() {
        let mut out = Vec::new();
        let mut cdr = CdrWriter::new(&mut out);
        cdr.i32(0);
        cdr.u32(0);
        cdr.string("color").unwrap();
        cdr.u32(2);
        cdr.u32(1);
        cdr.string("mono8").unwrap();
        cdr.u8(0);
        cdr.u32(4);
        cdr.u32(8);
        cdr.out.extend_from_slice(&[7, 9, 9, 9, 8, 9, 9, 9]);
        let decoded = decode_image(&out).unwrap();
        assert_eq!(decoded.image.as_u8().unwrap(), &[7, 8]);
    }

    #[test]
    fn truncated_or_lying_images_are_errors() {
        let image = Image::new(4, 4, PixelFormat::Rgb8);
        let mut out = Vec::new();
        encode_image(&mut out, 0, "color", &image).unwrap();
        for len in 0..out.len() {
            assert!(
                decode_image(&out[..len]).is_err(),
                "prefix of {len} bytes decoded"
            );
        }
    }

    /// Other drivers' colour encodings, with rows padded past the packed width, read as rgb8.
    #[test]
    fn foreign_colour_encodings_read_as_rgb8() {
        let (width, height) = (2u32, 2u32);
        for (encoding, bytes_per_pixel, rgb) in [
            ("bgr8", 3, [2, 1, 0]),
            ("rgba8", 4, [0, 1, 2]),
            ("bgra8", 4, [2, 1, 0]),
        ] {
            let step = width as usize * bytes_per_pixel + 3;
            let pixels: Vec<u8> = (0..step * height as usize).map(|i| i as u8).collect();
            let mut out = Vec::new();
            let mut cdr = CdrWriter::new(&mut out);
            cdr.header(5, "camera_color_optical_frame").unwrap();
            cdr.u32(height);
            cdr.u32(width);
            cdr.string(encoding).unwrap();
            cdr.u8(0);
            cdr.u32(step as u32);
            cdr.u32(pixels.len() as u32);
            out.extend_from_slice(&pixels);
            let decoded = decode_image(&out).unwrap();
            assert_eq!(decoded.image.format(), PixelFormat::Rgb8);
            let expected: Vec<u8> = (0..height as usize)
                .flat_map(|y| (0..width as usize).map(move |x| y * step + x * bytes_per_pixel))
                .flat_map(|at| rgb.map(|c| (at + c) as u8))
                .collect();
            assert_eq!(decoded.image.as_u8().unwrap(), expected, "{encoding}");
        }
        let mut out = Vec::new();
        encode_image(&mut out, 0, "c", &Image::new(1, 1, PixelFormat::Rgb8)).unwrap();
        let at = out.windows(4).position(|w| w == b"rgb8").unwrap();
        out[at..at + 4].copy_from_slice(b"yuv8");
        assert!(decode_image(&out).unwrap_err().contains("`yuv8`"));
    }
}
