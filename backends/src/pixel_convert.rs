//! Camera pixel formats → `Rgb8`: packed YUV 4:2:2 (YUYV, UYVY), Bayer mosaics (bilinear
//! demosaic), grey, RGB/BGR with any row stride; and RGB → YUYV for sinks that feed V4L2
//! outputs. Shared by the V4L2 and uEye backends; pure, so every conversion is tested against
//! known images.
//!
//! Every converter takes the source rows with their stride (bytes per row, ≥ the packed row
//! size, as drivers pad rows) and reshapes `out` to `width × height` `Rgb8`, reusing its buffer.

use relight_core::{Image, PixelFormat};

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConvertError {
    #[error(
        "{format}: {width}×{height} needs {needed} bytes at stride {stride}, the frame holds {actual}"
    )]
    ShortFrame {
        format: &'static str,
        width: u32,
        height: u32,
        stride: usize,
        needed: usize,
        actual: usize,
    },
    #[error(
        "{format}: stride {stride} is shorter than one row of {width} pixels ({row_bytes} bytes)"
    )]
    BadStride {
        format: &'static str,
        width: u32,
        stride: usize,
        row_bytes: usize,
    },
    #[error("{format}: {width}×{height} is not a valid size ({reason})")]
    BadSize {
        format: &'static str,
        width: u32,
        height: u32,
        reason: &'static str,
    },
}

/// Checks that `src` holds `height` rows of `row_bytes` at `stride` (the last row may be unpadded,
/// as some drivers set `bytesused` to exactly that).
fn check_layout(
    format: &'static str,
    src: &[u8],
    width: u32,
    height: u32,
    stride: usize,
    row_bytes: usize,
) -> Result<(), ConvertError> {
    if stride < row_bytes {
        return Err(ConvertError::BadStride {
            format,
            width,
            stride,
            row_bytes,
        });
    }
    let needed = match height {
        0 => 0,
        h => stride * (h as usize - 1) + row_bytes,
    };
    if src.len() < needed {
        return Err(ConvertError::ShortFrame {
            format,
            width,
            height,
            stride,
            needed,
            actual: src.len(),
        });
    }
    Ok(())
}

/// Rows of `src` (each `row_bytes` long) zipped with the packed rows of `out`.
fn rows<'a>(
    src: &'a [u8],
    stride: usize,
    row_bytes: usize,
    out: &'a mut [u8],
    out_row_bytes: usize,
) -> impl Iterator<Item = (&'a [u8], &'a mut [u8])> {
    // chunks(stride) also yields the unpadded last row; `check_layout` guaranteed its length.
    src.chunks(stride.max(1))
        .map(move |row| &row[..row_bytes])
        .zip(out.chunks_exact_mut(out_row_bytes.max(1)))
}

fn rgb_out(out: &mut Image, width: u32, height: u32) -> &mut [u8] {
    out.reshape(width, height, PixelFormat::Rgb8);
    out.as_u8_mut().unwrap_or_default()
}

/// Which Y′CbCr ↔ R′G′B′ matrix and quantisation range a YUV stream uses (V4L2 "Colorspaces":
/// `V4L2_YCBCR_ENC_601` / `_709`, `V4L2_QUANTIZATION_LIM_RANGE` / `_FULL_RANGE`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct YuvEncoding {
    pub matrix: YuvMatrix,
    /// Limited ("studio") range: Y′ in 16–235, Cb/Cr in 16–240. Full range: all in 0–255
    /// (JPEG/JFIF).
    pub limited_range: bool,
}

impl YuvEncoding {
    /// What UVC webcams send unless they say otherwise: BT.601, limited range.
    pub const BT601_LIMITED: YuvEncoding = YuvEncoding {
        matrix: YuvMatrix::Bt601,
        limited_range: true,
    };
}

impl Default for YuvEncoding {
    fn default() -> Self {
        Self::BT601_LIMITED
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum YuvMatrix {
    /// ITU-R BT.601: Kr = 0.299, Kb = 0.114.
    Bt601,
    /// ITU-R BT.709: Kr = 0.2126, Kb = 0.0722.
    Bt709,
}

impl YuvMatrix {
    fn kr_kb(self) -> (f64, f64) {
        match self {
            YuvMatrix::Bt601 => (0.299, 0.114),
            YuvMatrix::Bt709 => (0.2126, 0.0722),
        }
    }
}

/// Fixed-point (Q16) coefficients of Y′CbCr → R′G′B′ for one encoding.
#[derive(Debug, Clone, Copy)]
struct YuvToRgb {
    y_offset: i32,
    y_gain: i32,
    r_cr: i32,
    g_cb: i32,
    g_cr: i32,
    b_cb: i32,
}

const Q16: f64 = 65536.0;

impl YuvToRgb {
    /// R′ = Y′ + 2(1 − Kr)·Cr′, B′ = Y′ + 2(1 − Kb)·Cb′,
    /// G′ = Y′ − 2Kb(1 − Kb)/Kg·Cb′ − 2Kr(1 − Kr)/Kg·Cr′ (BT.601 §2.5), with Y′, Cb′, Cr′ the
    /// codes rescaled to 0–255 / ±127.5 (limited range: ×255/219 and ×255/224).
    fn new(encoding: YuvEncoding) -> Self {
        let (kr, kb) = encoding.matrix.kr_kb();
        let kg = 1.0 - kr - kb;
        let (y_offset, y_scale, c_scale) = if encoding.limited_range {
            (16, 255.0 / 219.0, 255.0 / 224.0)
        } else {
            (0, 1.0, 1.0)
        };
        let q = |v: f64| (v * Q16).round() as i32;
        Self {
            y_offset,
            y_gain: q(y_scale),
            r_cr: q(2.0 * (1.0 - kr) * c_scale),
            g_cb: q(2.0 * kb * (1.0 - kb) / kg * c_scale),
            g_cr: q(2.0 * kr * (1.0 - kr) / kg * c_scale),
            b_cb: q(2.0 * (1.0 - kb) * c_scale),
        }
    }

    #[inline]
    fn chroma(&self, cb: u8, cr: u8) -> (i32, i32, i32) {
        let (cb, cr) = (i32::from(cb) - 128, i32::from(cr) - 128);
        (
            self.r_cr * cr,
            -self.g_cb * cb - self.g_cr * cr,
            self.b_cb * cb,
        )
    }

    #[inline]
    fn pixel(&self, y: u8, (r, g, b): (i32, i32, i32), out: &mut [u8]) {
        let y = self.y_gain * (i32::from(y) - self.y_offset) + (1 << 15);
        let clamp = |v: i32| (v >> 16).clamp(0, 255) as u8;
        out[0] = clamp(y + r);
        out[1] = clamp(y + g);
        out[2] = clamp(y + b);
    }
}

/// Byte order of a packed 4:2:2 stream: where Y0, Cb, Y1, Cr sit in each 4-byte macropixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Packed422 {
    /// Y0 Cb Y1 Cr (`V4L2_PIX_FMT_YUYV`, "YUY2").
    Yuyv,
    /// Cb Y0 Cr Y1 (`V4L2_PIX_FMT_UYVY`).
    Uyvy,
}

impl Packed422 {
    fn offsets(self) -> [usize; 4] {
        match self {
            Packed422::Yuyv => [0, 1, 2, 3],
            Packed422::Uyvy => [1, 0, 3, 2],
        }
    }
    fn name(self) -> &'static str {
        match self {
            Packed422::Yuyv => "YUYV",
            Packed422::Uyvy => "UYVY",
        }
    }
}

/// Packed Y′CbCr 4:2:2 → RGB: each pixel pair shares one Cb/Cr sample. `width` must be even.
pub fn yuv422_to_rgb(
    src: &[u8],
    width: u32,
    height: u32,
    stride: usize,
    order: Packed422,
    encoding: YuvEncoding,
    out: &mut Image,
) -> Result<(), ConvertError> {
    let format = order.name();
    if !width.is_multiple_of(2) {
        return Err(ConvertError::BadSize {
            format,
            width,
            height,
            reason: "4:2:2 needs an even width",
        });
    }
    let row_bytes = width as usize * 2;
    check_layout(format, src, width, height, stride, row_bytes)?;
    let [y0, cb, y1, cr] = order.offsets();
    let coef = YuvToRgb::new(encoding);
    let dst = rgb_out(out, width, height);
    for (src_row, dst_row) in rows(src, stride, row_bytes, dst, width as usize * 3) {
        for (m, px) in src_row.chunks_exact(4).zip(dst_row.chunks_exact_mut(6)) {
            let chroma = coef.chroma(m[cb], m[cr]);
            let (first, second) = px.split_at_mut(3);
            coef.pixel(m[y0], chroma, first);
            coef.pixel(m[y1], chroma, second);
        }
    }
    Ok(())
}

/// Packed RGB → YUYV (for V4L2 output sinks and loopback tests): BT.601/709 in the given
/// range, Cb/Cr of each pixel pair the mean of the pair's (the usual 4:2:2 decimation), all
/// rounded to nearest. `out` is cleared and filled with `width × height × 2` bytes.
pub fn rgb_to_yuyv(
    rgb: &[u8],
    width: u32,
    height: u32,
    encoding: YuvEncoding,
    out: &mut Vec<u8>,
) -> Result<(), ConvertError> {
    if !width.is_multiple_of(2) {
        return Err(ConvertError::BadSize {
            format: "YUYV",
            width,
            height,
            reason: "4:2:2 needs an even width",
        });
    }
    let row_bytes = width as usize * 3;
    check_layout("RGB24", rgb, width, height, row_bytes, row_bytes)?;
    let (kr, kb) = encoding.matrix.kr_kb();
    let kg = 1.0 - kr - kb;
    let (y_off, y_range, c_range) = if encoding.limited_range {
        (16.0, 219.0, 224.0)
    } else {
        (0.0, 255.0, 255.0)
    };
    let code = |v: f64| v.round().clamp(0.0, 255.0) as u8;
    out.clear();
    out.reserve(width as usize * height as usize * 2);
    for pair in rgb[..row_bytes * height as usize].chunks_exact(6) {
        let mut cb_sum = 0.0;
        let mut cr_sum = 0.0;
        let mut ys = [0u8; 2];
        for (px, y_code) in pair.chunks_exact(3).zip(&mut ys) {
            let [r, g, b] = [px[0], px[1], px[2]].map(|v| f64::from(v) / 255.0);
            let y = kr * r + kg * g + kb * b;
            *y_code = code(y_off + y_range * y);
            cb_sum += (b - y) / (2.0 * (1.0 - kb));
            cr_sum += (r - y) / (2.0 * (1.0 - kr));
        }
        let cb = code(128.0 + c_range * cb_sum / 2.0);
        let cr = code(128.0 + c_range * cr_sum / 2.0);
        out.extend_from_slice(&[ys[0], cb, ys[1], cr]);
    }
    Ok(())
}

/// Packed 8-bit RGB (or BGR when `bgr`) rows → `Rgb8`.
pub fn rgb24_to_rgb(
    src: &[u8],
    width: u32,
    height: u32,
    stride: usize,
    bgr: bool,
    out: &mut Image,
) -> Result<(), ConvertError> {
    let format = if bgr { "BGR24" } else { "RGB24" };
    let row_bytes = width as usize * 3;
    check_layout(format, src, width, height, stride, row_bytes)?;
    let dst = rgb_out(out, width, height);
    for (src_row, dst_row) in rows(src, stride, row_bytes, dst, row_bytes) {
        if bgr {
            for (s, d) in src_row.chunks_exact(3).zip(dst_row.chunks_exact_mut(3)) {
                d.copy_from_slice(&[s[2], s[1], s[0]]);
            }
        } else {
            dst_row.copy_from_slice(src_row);
        }
    }
    Ok(())
}

/// 8-bit grey → `Rgb8` (R = G = B).
pub fn grey_to_rgb(
    src: &[u8],
    width: u32,
    height: u32,
    stride: usize,
    out: &mut Image,
) -> Result<(), ConvertError> {
    let row_bytes = width as usize;
    check_layout("GREY", src, width, height, stride, row_bytes)?;
    let dst = rgb_out(out, width, height);
    for (src_row, dst_row) in rows(src, stride, row_bytes, dst, row_bytes * 3) {
        for (&v, d) in src_row.iter().zip(dst_row.chunks_exact_mut(3)) {
            d.fill(v);
        }
    }
    Ok(())
}

/// The colour filter array, named by its top-left 2 × 2 block read row by row
/// (`V4L2_PIX_FMT_SRGGB8` = RGGB, `SBGGR8` = BGGR, `SGRBG8` = GRBG, `SGBRG8` = GBRG).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BayerPattern {
    Rggb,
    Bggr,
    Grbg,
    Gbrg,
}

impl BayerPattern {
    pub const ALL: [BayerPattern; 4] = [
        BayerPattern::Rggb,
        BayerPattern::Bggr,
        BayerPattern::Grbg,
        BayerPattern::Gbrg,
    ];

    /// Channel (0 = R, 1 = G, 2 = B) sampled at (x, y).
    pub fn channel_at(self, x: usize, y: usize) -> usize {
        let block = match self {
            BayerPattern::Rggb => [0, 1, 1, 2],
            BayerPattern::Bggr => [2, 1, 1, 0],
            BayerPattern::Grbg => [1, 0, 2, 1],
            BayerPattern::Gbrg => [1, 2, 0, 1],
        };
        block[(y & 1) * 2 + (x & 1)]
    }

    pub fn name(self) -> &'static str {
        match self {
            BayerPattern::Rggb => "RGGB",
            BayerPattern::Bggr => "BGGR",
            BayerPattern::Grbg => "GRBG",
            BayerPattern::Gbrg => "GBRG",
        }
    }
}

/// Index of `i ± 1` reflected at the borders without repeating the edge (…, 1, 0, 1, …):
/// keeps the Bayer parity, so a reflected neighbour carries the same colour as the missing one.
#[inline]
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let i = if i < 0 { -i } else { i };
    (if i >= n { 2 * (n - 1) - i } else { i }) as usize
}

/// Bilinear demosaic of an 8-bit Bayer mosaic (Gunturk et al., "Demosaicking: color filter
/// array interpolation", IEEE Signal Processing Magazine 22(1), 2005, §"bilinear"): each missing
/// colour is the mean of the nearest samples of that colour — the 4 edge neighbours (G at R/B),
/// the 4 diagonal neighbours (B at R, R at B), or the 2 neighbours along the row or column
/// (R/B at G). For a smooth image f this errs by at most ½·max|∂²f/∂d²|·|d|², i.e. max|D²f| for
/// diagonals (|d|² = 2), plus ½ for rounding. Borders use mirrored neighbours.
pub fn bayer_to_rgb(
    src: &[u8],
    width: u32,
    height: u32,
    stride: usize,
    pattern: BayerPattern,
    out: &mut Image,
) -> Result<(), ConvertError> {
    let format = pattern.name();
    if width < 2 || height < 2 {
        return Err(ConvertError::BadSize {
            format,
            width,
            height,
            reason: "a Bayer mosaic needs at least 2 × 2 pixels",
        });
    }
    let (w, h) = (width as usize, height as usize);
    check_layout(format, src, width, height, stride, w)?;
    let dst = rgb_out(out, width, height);
    let at = |x: usize, y: usize| u16::from(src[y * stride + x]);
    for y in 0..h {
        let (up, down) = (reflect(y as isize - 1, h), reflect(y as isize + 1, h));
        let dst_row = &mut dst[y * w * 3..(y + 1) * w * 3];
        for (x, px) in dst_row.chunks_exact_mut(3).enumerate() {
            let (left, right) = (reflect(x as isize - 1, w), reflect(x as isize + 1, w));
            let own = pattern.channel_at(x, y);
            let mean2 = |a: u16, b: u16| ((a + b + 1) >> 1) as u8;
            let mean4 = |a: u16, b: u16, c: u16, d: u16| ((a + b + c + d + 2) >> 2) as u8;
            let cross = || mean4(at(left, y), at(right, y), at(x, up), at(x, down));
            let diagonal = || mean4(at(left, up), at(right, up), at(left, down), at(right, down));
            let horizontal = || mean2(at(left, y), at(right, y));
            let vertical = || mean2(at(x, up), at(x, down));
            let value = at(x, y) as u8;
            match own {
                0 => px.copy_from_slice(&[value, cross(), diagonal()]),
                2 => px.copy_from_slice(&[diagonal(), cross(), value]),
                _ => {
                    // A green site: the row's other colour is left/right, the column's is up/down.
                    if pattern.channel_at(x + 1, y) == 0 {
                        px.copy_from_slice(&[horizontal(), value, vertical()]);
                    } else {
                        px.copy_from_slice(&[vertical(), value, horizontal()]);
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_pcg::Pcg64;

    fn rgb(image: &Image) -> &[u8] {
        image.as_u8().unwrap()
    }

    fn max_abs_diff(a: &[u8], b: &[u8]) -> u8 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0)
    }

    /// Random colours, each repeated over a pixel pair: 4:2:2 decimation then loses nothing, and
    /// the round trip errs only by quantisation. Limited range, BT.601: a code step is 255/219
    /// in Y′ and the Cr→R gain is 2(1 − Kr)·255/224 = 1.596, Cb→B 2(1 − Kb)·255/224 = 2.018,
    /// Cb,Cr→G 0.392 + 0.813; with ½ code of rounding in each of Y′, Cb, Cr and ½ in the output,
    /// |ΔR| ≤ 0.58 + 0.80 + 0.5, |ΔG| ≤ 0.58 + 0.60 + 0.5, |ΔB| ≤ 0.58 + 1.01 + 0.5 — so every
    /// integer channel is within 2.
    #[test]
    fn rgb_yuyv_rgb_round_trip_is_within_the_quantisation_bound() {
        let mut rng = Pcg64::seed_from_u64(7);
        let (w, h) = (32u32, 8u32);
        for encoding in [
            YuvEncoding::BT601_LIMITED,
            YuvEncoding {
                matrix: YuvMatrix::Bt709,
                limited_range: true,
            },
            YuvEncoding {
                matrix: YuvMatrix::Bt601,
                limited_range: false,
            },
        ] {
            let mut original = Vec::new();
            for _ in 0..(w * h / 2) {
                let c: [u8; 3] = rng.random();
                original.extend_from_slice(&c);
                original.extend_from_slice(&c);
            }
            let mut yuyv = Vec::new();
            rgb_to_yuyv(&original, w, h, encoding, &mut yuyv).unwrap();
            assert_eq!(yuyv.len(), (w * h * 2) as usize);
            let mut back = Image::default();
            yuv422_to_rgb(
                &yuyv,
                w,
                h,
                w as usize * 2,
                Packed422::Yuyv,
                encoding,
                &mut back,
            )
            .unwrap();
            assert_eq!((back.width(), back.height()), (w, h));
            assert_eq!(back.format(), PixelFormat::Rgb8);
            let err = max_abs_diff(rgb(&back), &original);
            assert!(err <= 2, "{encoding:?}: max error {err}");
        }
    }

    /// Known codes of BT.601 limited range: black (16, 128, 128), white (235, 128, 128), and
    /// full red (81, 90, 240) — its exact Y′ of 81.5 is rounded, hence a tolerance of 1.
    #[test]
    fn limited_range_reference_codes_decode_to_their_colours() {
        let yuyv = [16, 128, 235, 128, 81, 90, 81, 240];
        let mut out = Image::default();
        yuv422_to_rgb(
            &yuyv,
            4,
            1,
            8,
            Packed422::Yuyv,
            YuvEncoding::BT601_LIMITED,
            &mut out,
        )
        .unwrap();
        let px = rgb(&out);
        assert_eq!(&px[0..3], &[0, 0, 0]);
        assert_eq!(&px[3..6], &[255, 255, 255]);
        assert!(
            max_abs_diff(&px[6..9], &[255, 0, 0]) <= 1,
            "{:?}",
            &px[6..9]
        );
        assert_eq!(&px[6..9], &px[9..12]);
    }

    #[test]
    fn uyvy_is_yuyv_with_swapped_bytes_and_row_padding_is_skipped() {
        let mut rng = Pcg64::seed_from_u64(3);
        let (w, h, stride) = (6u32, 3u32, 16usize);
        let yuyv: Vec<u8> = (0..w * h * 2).map(|_| rng.random()).collect();
        let mut uyvy = vec![0xAA; stride * h as usize];
        for (y, row) in yuyv.chunks_exact(w as usize * 2).enumerate() {
            for (m, dst) in row
                .chunks_exact(4)
                .zip(uyvy[y * stride..].chunks_exact_mut(4))
            {
                dst.copy_from_slice(&[m[1], m[0], m[3], m[2]]);
            }
        }
        let enc = YuvEncoding::BT601_LIMITED;
        let (mut a, mut b) = (Image::default(), Image::default());
        yuv422_to_rgb(&yuyv, w, h, w as usize * 2, Packed422::Yuyv, enc, &mut a).unwrap();
        yuv422_to_rgb(&uyvy, w, h, stride, Packed422::Uyvy, enc, &mut b).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn bgr_rgb_and_grey_copy_exactly_through_padding() {
        let (w, h, stride) = (3u32, 2u32, 12usize);
        let mut bgr = vec![0u8; stride * 2];
        let mut expected = Vec::new();
        for y in 0..2 {
            for x in 0..3 {
                let (r, g, b) = (10 * x as u8 + y as u8, 100 + x as u8, 200 + y as u8);
                bgr[y * stride + x * 3..][..3].copy_from_slice(&[b, g, r]);
                expected.extend_from_slice(&[r, g, b]);
            }
        }
        let mut out = Image::default();
        rgb24_to_rgb(&bgr, w, h, stride, true, &mut out).unwrap();
        assert_eq!(rgb(&out), &expected[..]);

        let mut rgb_rows = vec![0u8; stride * 2];
        for y in 0..2 {
            rgb_rows[y * stride..][..9].copy_from_slice(&expected[y * 9..][..9]);
        }
        rgb24_to_rgb(&rgb_rows, w, h, stride, false, &mut out).unwrap();
        assert_eq!(rgb(&out), &expected[..]);

        grey_to_rgb(&[1, 2, 3, 0, 4, 5, 6], w, h, 4, &mut out).unwrap();
        assert_eq!(
            rgb(&out),
            &[1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4, 5, 5, 5, 6, 6, 6]
        );
    }

    /// A smooth test scene f_c(x, y) = 128 + A·sin(kx + φ_c)·cos(ky + ψ_c) per channel. Its
    /// Hessian has eigenvalues ±A k² sin(…), so |∂²f/∂d²| ≤ A k² |d|²: a bilinear estimate from
    /// neighbours at ±d errs by ≤ ½ A k² |d|² (≤ A k² for diagonals), plus ½ for rounding the
    /// mosaic and ½ for rounding the mean. At the border a mirrored neighbour stands in for the
    /// missing one, adding the first-order term |∇f|·|d| ≤ A k √2.
    fn scene(x: usize, y: usize, c: usize, amplitude: f64, k: f64) -> f64 {
        let phase = [0.0, 1.3, 2.6][c];
        128.0 + amplitude * (k * x as f64 + phase).sin() * (k * y as f64 - phase).cos()
    }

    #[test]
    fn bilinear_demosaic_of_a_smooth_scene_is_within_the_derived_bound() {
        let (w, h) = (48usize, 40usize);
        let (amplitude, k) = (100.0, std::f64::consts::TAU / 32.0);
        let interior_bound = amplitude * k * k + 1.0;
        let border_bound = interior_bound + amplitude * k * std::f64::consts::SQRT_2;
        for pattern in BayerPattern::ALL {
            let stride = w + 5;
            let mut mosaic = vec![0u8; stride * h];
            for y in 0..h {
                for x in 0..w {
                    let c = pattern.channel_at(x, y);
                    mosaic[y * stride + x] = scene(x, y, c, amplitude, k).round() as u8;
                }
            }
            let mut out = Image::default();
            bayer_to_rgb(&mosaic, w as u32, h as u32, stride, pattern, &mut out).unwrap();
            let px = rgb(&out);
            let (mut interior_max, mut border_max) = (0.0f64, 0.0f64);
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        let err = (f64::from(px[(y * w + x) * 3 + c])
                            - scene(x, y, c, amplitude, k))
                        .abs();
                        if pattern.channel_at(x, y) == c {
                            assert!(err <= 0.5, "{pattern:?}: sampled value changed");
                        }
                        if x == 0 || y == 0 || x == w - 1 || y == h - 1 {
                            border_max = border_max.max(err);
                        } else {
                            interior_max = interior_max.max(err);
                        }
                    }
                }
            }
            assert!(
                interior_max <= interior_bound,
                "{pattern:?}: interior error {interior_max:.2} > {interior_bound:.2}"
            );
            assert!(
                border_max <= border_bound,
                "{pattern:?}: border error {border_max:.2} > {border_bound:.2}"
            );
        }
    }

    /// A flat grey card must come out grey for every pattern: a channel mix-up (wrong pattern
    /// table) would tint it.
    #[test]
    fn demosaic_keeps_each_pattern_s_colours_apart() {
        let (w, h) = (8usize, 6usize);
        let colour = [200u8, 120, 40];
        for pattern in BayerPattern::ALL {
            let mosaic: Vec<u8> = (0..w * h)
                .map(|i| colour[pattern.channel_at(i % w, i / w)])
                .collect();
            let mut out = Image::default();
            bayer_to_rgb(&mosaic, w as u32, h as u32, w, pattern, &mut out).unwrap();
            assert!(
                rgb(&out).chunks_exact(3).all(|p| p == colour),
                "{pattern:?}"
            );
        }
    }

    #[test]
    fn short_frames_and_bad_sizes_are_errors_not_panics() {
        let mut out = Image::default();
        let short = yuv422_to_rgb(
            &[0; 10],
            4,
            2,
            8,
            Packed422::Yuyv,
            YuvEncoding::default(),
            &mut out,
        );
        assert!(matches!(
            short,
            Err(ConvertError::ShortFrame { needed: 16, .. })
        ));
        let odd = yuv422_to_rgb(
            &[0; 64],
            3,
            2,
            8,
            Packed422::Yuyv,
            YuvEncoding::default(),
            &mut out,
        );
        assert!(matches!(odd, Err(ConvertError::BadSize { .. })));
        let stride = grey_to_rgb(&[0; 64], 8, 2, 4, &mut out);
        assert!(matches!(stride, Err(ConvertError::BadStride { .. })));
        let tiny = bayer_to_rgb(&[0; 4], 1, 4, 1, BayerPattern::Rggb, &mut out);
        assert!(matches!(tiny, Err(ConvertError::BadSize { .. })));
        // The last row may come unpadded: 10 + 8 bytes for two 8-pixel rows at stride 10.
        grey_to_rgb(&[0; 18], 8, 2, 10, &mut out).unwrap();
    }
}
