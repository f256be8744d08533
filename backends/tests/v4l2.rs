//! The V4L2 backend without a camera: MJPEG frames made by a small baseline JPEG encoder
//! below (ITU-T T.81) decoded within the error the encoding allows, with and without their
//! Huffman tables as UVC cameras send them; raw formats through the backend's dispatch with
//! padded rows; and open() on paths that are not cameras. Live capture needs a V4L2 device
//! (or the vivid / v4l2loopback modules), which CI containers do not have.
#![cfg(feature = "v4l2")]

use std::f64::consts::{PI, SQRT_2};

use relight_backends::DeviceError;
use relight_backends::pixel_convert::{YuvEncoding, rgb_to_yuyv};
use relight_backends::sources::FrameSource;
use relight_backends::v4l2::mjpeg::{MjpegError, decode_mjpeg};
use relight_backends::v4l2::{
    Negotiated, V4l2Color, V4l2Config, V4l2PixelFormat, V4l2Probe, frame_to_rgb,
};
use relight_core::{Image, PixelFormat};

// ---- a baseline JPEG encoder (T.81 Annex A, F.1; tables of Annex K.3) ------------------------

/// Table K.3: luminance DC code lengths (counts per length 1–16) and symbols.
const DC_LUMA: ([u8; 16], &[u8]) = (
    [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0],
    &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11],
);
/// Table K.4: chrominance DC.
const DC_CHROMA: ([u8; 16], &[u8]) = (
    [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0],
    &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11],
);
/// Table K.5: luminance AC.
const AC_LUMA: ([u8; 16], &[u8]) = (
    [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7D],
    &[
        0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61,
        0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xA1, 0x08, 0x23, 0x42, 0xB1, 0xC1, 0x15, 0x52,
        0xD1, 0xF0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0A, 0x16, 0x17, 0x18, 0x19, 0x1A, 0x25,
        0x26, 0x27, 0x28, 0x29, 0x2A, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3A, 0x43, 0x44, 0x45,
        0x46, 0x47, 0x48, 0x49, 0x4A, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5A, 0x63, 0x64,
        0x65, 0x66, 0x67, 0x68, 0x69, 0x6A, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7A, 0x83,
        0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8A, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99,
        0x9A, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7, 0xA8, 0xA9, 0xAA, 0xB2, 0xB3, 0xB4, 0xB5, 0xB6,
        0xB7, 0xB8, 0xB9, 0xBA, 0xC2, 0xC3, 0xC4, 0xC5, 0xC6, 0xC7, 0xC8, 0xC9, 0xCA, 0xD2, 0xD3,
        0xD4, 0xD5, 0xD6, 0xD7, 0xD8, 0xD9, 0xDA, 0xE1, 0xE2, 0xE3, 0xE4, 0xE5, 0xE6, 0xE7, 0xE8,
        0xE9, 0xEA, 0xF1, 0xF2, 0xF3, 0xF4, 0xF5, 0xF6, 0xF7, 0xF8, 0xF9, 0xFA,
    ],
);
/// Table K.6: chrominance AC.
const AC_CHROMA: ([u8; 16], &[u8]) = (
    [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77],
    &[
        0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61,
        0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xA1, 0xB1, 0xC1, 0x09, 0x23, 0x33,
        0x52, 0xF0, 0x15, 0x62, 0x72, 0xD1, 0x0A, 0x16, 0x24, 0x34, 0xE1, 0x25, 0xF1, 0x17, 0x18,
        0x19, 0x1A, 0x26, 0x27, 0x28, 0x29, 0x2A, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3A, 0x43, 0x44,
        0x45, 0x46, 0x47, 0x48, 0x49, 0x4A, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5A, 0x63,
        0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6A, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7A,
        0x82, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8A, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97,
        0x98, 0x99, 0x9A, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7, 0xA8, 0xA9, 0xAA, 0xB2, 0xB3, 0xB4,
        0xB5, 0xB6, 0xB7, 0xB8, 0xB9, 0xBA, 0xC2, 0xC3, 0xC4, 0xC5, 0xC6, 0xC7, 0xC8, 0xC9, 0xCA,
        0xD2, 0xD3, 0xD4, 0xD5, 0xD6, 0xD7, 0xD8, 0xD9, 0xDA, 0xE2, 0xE3, 0xE4, 0xE5, 0xE6, 0xE7,
        0xE8, 0xE9, 0xEA, 0xF2, 0xF3, 0xF4, 0xF5, 0xF6, 0xF7, 0xF8, 0xF9, 0xFA,
    ],
);

/// Canonical Huffman codes (T.81 Annex C): symbol → (code, length).
fn huffman_codes((bits, values): ([u8; 16], &[u8])) -> [(u16, u8); 256] {
    let mut codes = [(0, 0); 256];
    let (mut code, mut k) = (0u16, 0);
    for (length, &count) in (1..=16u8).zip(&bits) {
        for _ in 0..count {
            codes[usize::from(values[k])] = (code, length);
            code += 1;
            k += 1;
        }
        code <<= 1;
    }
    codes
}

#[derive(Default)]
struct BitWriter {
    bytes: Vec<u8>,
    acc: u8,
    used: u8,
}

impl BitWriter {
    fn put(&mut self, value: u16, length: u8) {
        for i in (0..length).rev() {
            self.acc = (self.acc << 1) | ((value >> i) & 1) as u8;
            self.used += 1;
            if self.used == 8 {
                self.bytes.push(self.acc);
                if self.acc == 0xFF {
                    self.bytes.push(0x00); // byte stuffing, F.1.2.3
                }
                (self.acc, self.used) = (0, 0);
            }
        }
    }

    fn finish(mut self) -> Vec<u8> {
        while self.used != 0 {
            self.put(1, 1);
        }
        self.bytes
    }
}

/// Natural (row-major) index of each zig-zag position (Figure A.6).
fn zigzag() -> [usize; 64] {
    let mut order = [0; 64];
    let mut i = 0;
    for s in 0..15usize {
        let rows: Vec<usize> = (s.saturating_sub(7)..=s.min(7)).collect();
        let rows: Box<dyn Iterator<Item = usize>> = if s % 2 == 0 {
            Box::new(rows.into_iter().rev())
        } else {
            Box::new(rows.into_iter())
        };
        for row in rows {
            order[i] = row * 8 + (s - row);
            i += 1;
        }
    }
    order
}

/// Orthonormal 8 × 8 DCT-II of level-shifted samples (A.3.3), quantised with step 1.
fn fdct(block: &[f64; 64]) -> [i32; 64] {
    let c = |u: usize| if u == 0 { 1.0 / SQRT_2 } else { 1.0 };
    let mut out = [0; 64];
    for v in 0..8 {
        for u in 0..8 {
            let mut sum = 0.0;
            for y in 0..8 {
                for x in 0..8 {
                    sum += (block[y * 8 + x] - 128.0)
                        * (((2 * x + 1) as f64 * u as f64 * PI) / 16.0).cos()
                        * (((2 * y + 1) as f64 * v as f64 * PI) / 16.0).cos();
                }
            }
            out[v * 8 + u] = (0.25 * c(u) * c(v) * sum).round() as i32;
        }
    }
    out
}

fn magnitude(v: i32) -> (u16, u8) {
    let size = (32 - v.unsigned_abs().leading_zeros()) as u8;
    let bits = if v >= 0 { v } else { v + (1 << size) - 1 };
    (bits as u16, size)
}

struct Component {
    /// Samples, `width × height` of this component (after subsampling).
    samples: Vec<f64>,
    width: usize,
    h_sampling: usize,
    chroma: bool,
    prev_dc: i32,
}

fn encode_block(
    component: &mut Component,
    bx: usize,
    by: usize,
    writer: &mut BitWriter,
    dc: &[(u16, u8); 256],
    ac: &[(u16, u8); 256],
    zz: &[usize; 64],
) {
    let mut block = [0.0; 64];
    for y in 0..8 {
        for x in 0..8 {
            block[y * 8 + x] = component.samples[(by * 8 + y) * component.width + bx * 8 + x];
        }
    }
    let coeffs = fdct(&block);
    let diff = coeffs[0] - component.prev_dc;
    component.prev_dc = coeffs[0];
    let (bits, size) = magnitude(diff);
    let (code, length) = dc[usize::from(size)];
    writer.put(code, length);
    writer.put(bits, size);
    let mut run = 0;
    for &index in &zz[1..] {
        let v = coeffs[index];
        if v == 0 {
            run += 1;
            continue;
        }
        while run > 15 {
            let (code, length) = ac[0xF0];
            writer.put(code, length);
            run -= 16;
        }
        let (bits, size) = magnitude(v);
        let (code, length) = ac[(run << 4) | usize::from(size)];
        writer.put(code, length);
        writer.put(bits, size);
        run = 0;
    }
    if run > 0 {
        let (code, length) = ac[0x00];
        writer.put(code, length);
    }
}

fn segment(out: &mut Vec<u8>, marker: u8, payload: &[u8]) {
    out.extend_from_slice(&[0xFF, marker]);
    out.extend_from_slice(&((payload.len() + 2) as u16).to_be_bytes());
    out.extend_from_slice(payload);
}

/// Encode `rgb` (`width × height`, multiples of 16 × 8) as a baseline JPEG with quantisation
/// step 1 and the standard Huffman tables. `chroma_422`: Cb/Cr halved horizontally (UVC
/// MJPEG); `grey`: one luminance component only; `with_tables`: write DHT (and JFIF) segments,
/// else leave them out as MJPEG cameras do.
fn encode_jpeg(
    rgb: &[u8],
    width: usize,
    height: usize,
    chroma_422: bool,
    grey: bool,
    with_tables: bool,
) -> Vec<u8> {
    let px = |i: usize| [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]].map(f64::from);
    let n = width * height;
    let luma: Vec<f64> = (0..n)
        .map(|i| {
            let [r, g, b] = px(i);
            0.299 * r + 0.587 * g + 0.114 * b
        })
        .collect();
    let cb: Vec<f64> = (0..n)
        .map(|i| {
            let [r, g, b] = px(i);
            128.0 - 0.168736 * r - 0.331264 * g + 0.5 * b
        })
        .collect();
    let cr: Vec<f64> = (0..n)
        .map(|i| {
            let [r, g, b] = px(i);
            128.0 + 0.5 * r - 0.418688 * g - 0.081312 * b
        })
        .collect();
    let halve =
        |c: &[f64]| -> Vec<f64> { c.chunks_exact(2).map(|p| (p[0] + p[1]) / 2.0).collect() };
    let chroma_width = if chroma_422 { width / 2 } else { width };
    let h = if chroma_422 { 2 } else { 1 };
    let mut components = vec![Component {
        samples: luma,
        width,
        h_sampling: h,
        chroma: false,
        prev_dc: 0,
    }];
    if !grey {
        for c in [cb, cr] {
            let samples = if chroma_422 { halve(&c) } else { c };
            components.push(Component {
                samples,
                width: chroma_width,
                h_sampling: 1,
                chroma: true,
                prev_dc: 0,
            });
        }
    }

    let mut out = vec![0xFF, 0xD8];
    if with_tables {
        segment(
            &mut out,
            0xE0,
            b"JFIF\0\x01\x01\x00\x00\x01\x00\x01\x00\x00",
        );
    }
    for table in 0..2u8 {
        let mut dqt = vec![table];
        dqt.extend_from_slice(&[1; 64]);
        segment(&mut out, 0xDB, &dqt);
    }
    let mut sof = vec![8];
    sof.extend_from_slice(&(height as u16).to_be_bytes());
    sof.extend_from_slice(&(width as u16).to_be_bytes());
    sof.push(components.len() as u8);
    for (i, c) in components.iter().enumerate() {
        sof.extend_from_slice(&[
            i as u8 + 1,
            ((c.h_sampling as u8) << 4) | 1,
            u8::from(c.chroma),
        ]);
    }
    segment(&mut out, 0xC0, &sof);
    if with_tables {
        for (class_and_id, (bits, values)) in [
            (0x00, DC_LUMA),
            (0x10, AC_LUMA),
            (0x01, DC_CHROMA),
            (0x11, AC_CHROMA),
        ] {
            let mut dht = vec![class_and_id];
            dht.extend_from_slice(&bits);
            dht.extend_from_slice(values);
            segment(&mut out, 0xC4, &dht);
        }
    }
    let mut sos = vec![components.len() as u8];
    for (i, c) in components.iter().enumerate() {
        let t = u8::from(c.chroma);
        sos.extend_from_slice(&[i as u8 + 1, (t << 4) | t]);
    }
    sos.extend_from_slice(&[0, 63, 0]);
    segment(&mut out, 0xDA, &sos);

    let tables = [
        (huffman_codes(DC_LUMA), huffman_codes(AC_LUMA)),
        (huffman_codes(DC_CHROMA), huffman_codes(AC_CHROMA)),
    ];
    let zz = zigzag();
    let mut writer = BitWriter::default();
    let mcu_width = 8 * h;
    for my in 0..height / 8 {
        for mx in 0..width / mcu_width {
            for c in &mut components {
                let (dc, ac) = &tables[usize::from(c.chroma)];
                for k in 0..c.h_sampling {
                    encode_block(c, mx * c.h_sampling + k, my, &mut writer, dc, ac, &zz);
                }
            }
        }
    }
    out.extend_from_slice(&writer.finish());
    out.extend_from_slice(&[0xFF, 0xD9]);
    out
}

// ---- error bounds ---------------------------------------------------------------------------

/// Worst-case error of a decoded sample for quantisation step 1: each coefficient is off by at
/// most ½, and an orthonormal 8-point basis function is at most 1/(2√2) (DC) or ½ (AC) in
/// magnitude, so a sample is off by at most ½·(1/(2√2) + 7·½)² ≈ 7.4; plus ½ for rounding the
/// sample and 1 for the decoder's fixed-point IDCT. Y′CbCr → RGB (JFIF) then multiplies by at
/// most 1 + 1.772 (B from Cb), and rounds once more.
fn worst_case_rgb_error() -> f64 {
    let basis_sum = 1.0 / (2.0 * SQRT_2) + 7.0 * 0.5;
    let sample = 0.5 * basis_sum * basis_sum + 0.5 + 1.0;
    sample * (1.0 + 1.772) + 0.5
}

/// Expected RMS error: coefficient errors uniform on [−½, ½] (variance 1/12) pass through the
/// orthonormal IDCT unchanged in variance; sample rounding adds 1/12; R′G′B′ mixes up to
/// 1 + 1.772² of that; output rounding adds 1/12. Allowed: twice that RMS.
fn rms_bound() -> f64 {
    let sample_var: f64 = 2.0 / 12.0;
    2.0 * (sample_var * (1.0 + 1.772 * 1.772) + 1.0 / 12.0).sqrt()
}

fn errors(decoded: &Image, original: &[u8]) -> (f64, f64) {
    let d = decoded.as_u8().unwrap();
    assert_eq!(d.len(), original.len());
    let diffs: Vec<f64> = d
        .iter()
        .zip(original)
        .map(|(a, b)| f64::from(*a) - f64::from(*b))
        .collect();
    let max = diffs.iter().fold(0.0f64, |m, e| m.max(e.abs()));
    let rms = (diffs.iter().map(|e| e * e).sum::<f64>() / diffs.len() as f64).sqrt();
    (max, rms)
}

/// A smooth colour scene, away from clipping.
fn smooth_scene(width: usize, height: usize) -> Vec<u8> {
    let mut rgb = Vec::with_capacity(width * height * 3);
    for y in 0..height {
        for x in 0..width {
            let (xf, yf) = (x as f64, y as f64);
            rgb.push((128.0 + 80.0 * (xf / 9.0).sin() * (yf / 7.0).cos()).round() as u8);
            rgb.push((120.0 + 60.0 * ((xf + yf) / 11.0).cos()).round() as u8);
            rgb.push((110.0 + 70.0 * (yf / 6.0 - xf / 13.0).sin()).round() as u8);
        }
    }
    rgb
}

/// Luma varying in x and y plus a colour cast varying in y only: Cb and Cr are then constant
/// along each row, so 4:2:2 subsampling loses nothing and the 4:4:4 bound holds.
fn row_chroma_scene(width: usize, height: usize) -> Vec<u8> {
    let mut rgb = Vec::with_capacity(width * height * 3);
    for y in 0..height {
        let cast = [
            30.0 * (y as f64 / 5.0).sin(),
            -20.0 * (y as f64 / 4.0).cos(),
            25.0 * (y as f64 / 6.0).cos(),
        ];
        for x in 0..width {
            let grey = 128.0 + 60.0 * (x as f64 / 8.0 + y as f64 / 10.0).sin();
            rgb.extend(cast.map(|c| (grey + c).round() as u8));
        }
    }
    rgb
}

fn decode(jpeg: &[u8], width: u32, height: u32) -> Result<Image, MjpegError> {
    let mut out = Image::default();
    decode_mjpeg(jpeg, width, height, &mut Vec::new(), &mut out).map(|()| out)
}

#[test]
fn a_jpeg_with_its_tables_decodes_within_the_quantisation_bound() {
    let (w, h) = (48, 32);
    let scene = smooth_scene(w, h);
    let jpeg = encode_jpeg(&scene, w, h, false, false, true);
    let decoded = decode(&jpeg, w as u32, h as u32).unwrap();
    assert_eq!(
        (decoded.width(), decoded.height(), decoded.format()),
        (48, 32, PixelFormat::Rgb8)
    );
    let (max, rms) = errors(&decoded, &scene);
    assert!(
        max <= worst_case_rgb_error(),
        "max error {max:.2} > {:.2}",
        worst_case_rgb_error()
    );
    assert!(
        rms <= rms_bound(),
        "rms error {rms:.3} > {:.3}",
        rms_bound()
    );
}

/// UVC MJPEG: 4:2:2, no JFIF, no DHT — the standard tables must be assumed. Decoding it at
/// all shows they were; matching the original shows they were the right ones.
#[test]
fn an_mjpeg_frame_without_huffman_tables_decodes_with_the_standard_ones() {
    let (w, h) = (64, 24);
    let scene = row_chroma_scene(w, h);
    let frame = encode_jpeg(&scene, w, h, true, false, false);
    assert!(
        !frame.windows(2).any(|m| m == [0xFF, 0xC4]),
        "no DHT in the frame"
    );
    let decoded = decode(&frame, w as u32, h as u32).unwrap();
    let (max, rms) = errors(&decoded, &scene);
    assert!(max <= worst_case_rgb_error(), "max error {max:.2}");
    assert!(
        rms <= rms_bound(),
        "rms error {rms:.3} > {:.3}",
        rms_bound()
    );

    // The same frame with its tables decodes to the same image.
    let with_tables = encode_jpeg(&scene, w, h, true, false, true);
    assert_eq!(decode(&with_tables, w as u32, h as u32).unwrap(), decoded);
}

#[test]
fn a_greyscale_jpeg_becomes_grey_rgb() {
    let (w, h) = (16, 16);
    let grey: Vec<u8> = (0..w * h)
        .map(|i| (40 + (i % w) * 5 + (i / w) * 3) as u8)
        .collect();
    let rgb: Vec<u8> = grey.iter().flat_map(|&g| [g; 3]).collect();
    let decoded = decode(
        &encode_jpeg(&rgb, w, h, false, true, true),
        w as u32,
        h as u32,
    )
    .unwrap();
    let px = decoded.as_u8().unwrap();
    assert!(px.chunks_exact(3).all(|p| p[0] == p[1] && p[1] == p[2]));
    // One component: no colour conversion, so the sample bound applies directly.
    let (max, _) = errors(&decoded, &rgb);
    assert!(
        max <= 0.5 * (1.0 / (2.0 * SQRT_2) + 3.5f64).powi(2) + 1.5,
        "max error {max}"
    );
}

#[test]
fn broken_mjpeg_frames_are_errors() {
    let (w, h) = (16, 8);
    let jpeg = encode_jpeg(&smooth_scene(w, h), w, h, true, false, false);
    assert!(matches!(
        decode(b"\x00\x01garbage", 16, 8),
        Err(MjpegError::Structure(_))
    ));
    assert!(
        decode(&jpeg[..jpeg.len() / 2], 16, 8).is_err(),
        "truncated frame"
    );
    assert!(
        matches!(decode(&jpeg, 32, 8), Err(MjpegError::Size { .. })),
        "size differs from the stream's"
    );
}

// ---- raw formats through the backend -----------------------------------------------------------

fn negotiated(format: V4l2PixelFormat, width: u32, height: u32, stride: usize) -> Negotiated {
    Negotiated {
        format,
        fourcc: *format.fourccs()[0],
        width,
        height,
        stride,
        yuv: YuvEncoding::BT601_LIMITED,
    }
}

/// Rows of `row_bytes` spread out to `stride` with junk in the padding.
fn pad_rows(packed: &[u8], row_bytes: usize, stride: usize) -> Vec<u8> {
    packed
        .chunks_exact(row_bytes)
        .flat_map(|row| row.iter().copied().chain((row.len()..stride).map(|_| 0xEE)))
        .collect()
}

#[test]
fn every_raw_format_reaches_rgb_through_padded_rows() {
    let (w, h) = (8u32, 4u32);
    let rgb: Vec<u8> = (0..w * h)
        .flat_map(|i| [i as u8 * 7, 200 - i as u8 * 3, 50 + i as u8])
        .collect();
    let pairs: Vec<u8> = rgb
        .chunks_exact(6)
        .flat_map(|p| [p[0], p[1], p[2], p[0], p[1], p[2]])
        .collect();
    let mut out = Image::default();
    let mut scratch = Vec::new();

    let row = w as usize * 3;
    frame_to_rgb(
        &pad_rows(&rgb, row, row + 4),
        &negotiated(V4l2PixelFormat::Rgb24, w, h, row + 4),
        &mut scratch,
        &mut out,
    )
    .unwrap();
    assert_eq!(out.as_u8().unwrap(), &rgb[..]);

    let bgr: Vec<u8> = rgb
        .chunks_exact(3)
        .flat_map(|p| [p[2], p[1], p[0]])
        .collect();
    frame_to_rgb(
        &pad_rows(&bgr, row, row + 2),
        &negotiated(V4l2PixelFormat::Bgr24, w, h, row + 2),
        &mut scratch,
        &mut out,
    )
    .unwrap();
    assert_eq!(out.as_u8().unwrap(), &rgb[..]);

    let grey: Vec<u8> = (0..w * h).map(|i| (i * 8) as u8).collect();
    frame_to_rgb(
        &pad_rows(&grey, w as usize, 16),
        &negotiated(V4l2PixelFormat::Grey, w, h, 16),
        &mut scratch,
        &mut out,
    )
    .unwrap();
    assert!(
        out.as_u8()
            .unwrap()
            .chunks_exact(3)
            .zip(&grey)
            .all(|(p, g)| p == [*g; 3])
    );

    // YUYV of pair-constant colours: within the 4:2:2 quantisation bound (2, see pixel_convert).
    let mut yuyv = Vec::new();
    rgb_to_yuyv(&pairs, w, h, YuvEncoding::BT601_LIMITED, &mut yuyv).unwrap();
    let row = w as usize * 2;
    frame_to_rgb(
        &pad_rows(&yuyv, row, row + 8),
        &negotiated(V4l2PixelFormat::Yuyv, w, h, row + 8),
        &mut scratch,
        &mut out,
    )
    .unwrap();
    assert!(
        out.as_u8()
            .unwrap()
            .iter()
            .zip(&pairs)
            .all(|(a, b)| a.abs_diff(*b) <= 2)
    );
    let uyvy: Vec<u8> = yuyv.chunks_exact(2).flat_map(|p| [p[1], p[0]]).collect();
    frame_to_rgb(
        &uyvy,
        &negotiated(V4l2PixelFormat::Uyvy, w, h, row),
        &mut scratch,
        &mut out,
    )
    .unwrap();
    assert!(
        out.as_u8()
            .unwrap()
            .iter()
            .zip(&pairs)
            .all(|(a, b)| a.abs_diff(*b) <= 2)
    );

    // A flat card through each Bayer fourcc keeps its colour.
    let card = [180u8, 90, 30];
    for (format, pattern) in [
        (V4l2PixelFormat::BayerRggb, [0, 1, 1, 2]),
        (V4l2PixelFormat::BayerBggr, [2, 1, 1, 0]),
        (V4l2PixelFormat::BayerGrbg, [1, 0, 2, 1]),
        (V4l2PixelFormat::BayerGbrg, [1, 2, 0, 1]),
    ] {
        let mosaic: Vec<u8> = (0..h as usize)
            .flat_map(|y| (0..w as usize).map(move |x| card[pattern[(y % 2) * 2 + x % 2]]))
            .collect();
        frame_to_rgb(
            &pad_rows(&mosaic, w as usize, 12),
            &negotiated(format, w, h, 12),
            &mut scratch,
            &mut out,
        )
        .unwrap();
        assert!(
            out.as_u8().unwrap().chunks_exact(3).all(|p| p == card),
            "{format:?}"
        );
    }

    // A frame shorter than the negotiated size is an error, not a panic.
    let short = frame_to_rgb(
        &yuyv[..10],
        &negotiated(V4l2PixelFormat::Yuyv, w, h, row),
        &mut scratch,
        &mut out,
    );
    assert!(short.unwrap_err().contains("needs"));
}

// ---- opening things that are not cameras --------------------------------------------------------

fn probe_at(path: &std::path::Path) -> V4l2Probe {
    V4l2Probe::new(V4l2Config {
        device: path.to_owned(),
        ..V4l2Config::default()
    })
    .unwrap()
}

#[test]
fn a_missing_device_is_not_found() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("video7");
    match probe_at(&missing).open() {
        Err(DeviceError::NotFound { reason, .. }) => assert!(reason.contains("video7"), "{reason}"),
        other => panic!("expected NotFound, got {other:?}"),
    }
}

#[test]
fn files_that_are_not_v4l2_devices_are_configuration_errors() {
    let file = tempfile::NamedTempFile::new().unwrap();
    let dir = tempfile::tempdir().unwrap();
    for path in [std::path::Path::new("/dev/null"), file.path(), dir.path()] {
        let mut colour = V4l2Color::new(V4l2Config {
            device: path.to_owned(),
            ..V4l2Config::default()
        })
        .unwrap();
        match colour.open() {
            Err(DeviceError::Config { reason, .. }) => {
                assert!(
                    reason.contains("not a V4L2 device") || reason.contains("directory"),
                    "{path:?}: {reason}"
                );
            }
            other => panic!("{path:?}: expected a configuration error, got {other:?}"),
        }
        colour.close();
    }
}

#[test]
fn configuration_keys_parse_with_defaults_and_bad_ones_are_refused() {
    let config: V4l2Config = serde_json::from_str(
        r#"{"device": "/dev/v4l/by-id/usb-probe-video-index0", "width": 1280, "height": 960,
            "formats": ["bayer_grbg", "mjpeg"], "bracket_us": [125, 1000, 8000]}"#,
    )
    .unwrap();
    assert_eq!(
        config.formats,
        [V4l2PixelFormat::BayerGrbg, V4l2PixelFormat::Mjpeg]
    );
    assert_eq!(config.exposure_latency_frames, 2);
    assert_eq!(config.buffers, 4);
    assert!(V4l2Probe::new(config.clone()).is_ok());
    assert!(
        serde_json::from_str::<V4l2Config>(r#"{"exposure": 100}"#).is_err(),
        "unknown key"
    );
    assert!(
        serde_json::from_str::<V4l2Config>(r#"{"formats": ["nv12"]}"#).is_err(),
        "unknown format"
    );

    let refused =
        |config: V4l2Config| matches!(V4l2Probe::new(config), Err(DeviceError::Config { .. }));
    assert!(refused(V4l2Config {
        width: Some(640),
        ..V4l2Config::default()
    }));
    assert!(refused(V4l2Config {
        formats: vec![],
        ..V4l2Config::default()
    }));
    assert!(refused(V4l2Config {
        bracket_us: vec![100, 0],
        ..V4l2Config::default()
    }));
    assert!(refused(V4l2Config {
        fps: Some(0),
        ..V4l2Config::default()
    }));
    assert!(
        matches!(V4l2Color::new(config), Err(DeviceError::Config { .. })),
        "a bracket on a colour camera"
    );
}
