//! Deterministic rig traffic for the recording tests: every stream, every pixel format, large
//! sequence numbers and device clocks, random floats.
#![allow(dead_code)]

use std::io::Cursor;
use std::sync::Arc;

use glam::{Quat, Vec2, Vec3};
use relight_core::camera::{CameraModel, KannalaBrandt, Pinhole};
use relight_core::recording::{RecordingMeta, RecordingOptions, RecordingWriter};
use relight_core::rig::RigCalibration;
use relight_core::{
    Frame, Image, LampState, MarkerDetection, MarkerSet, PixelFormat, Pose, ProbeImage,
    StreamMessage, Timestamp,
};

/// xorshift64*: reproducible noise without a dependency.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed.max(1))
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    /// Any finite f32 bit pattern, so the round trip is tested on awkward values too.
    pub fn finite_f32(&mut self) -> f32 {
        loop {
            let value = f32::from_bits(self.next_u64() as u32);
            if value.is_finite() {
                return value;
            }
        }
    }
    pub fn unit_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

pub fn noisy_image(rng: &mut Rng, width: u32, height: u32, format: PixelFormat) -> Image {
    let mut image = Image::new(width, height, format);
    if let Some(v) = image.as_u8_mut() {
        v.iter_mut().for_each(|p| *p = rng.next_u64() as u8);
    } else if let Some(v) = image.as_u16_mut() {
        // Half floats travel widened to f32, which keeps every value but not NaN payloads.
        let half_float = format == PixelFormat::Rgba16F;
        v.iter_mut().for_each(|p| {
            *p = rng.next_u64() as u16;
            if half_float && half::f16::from_bits(*p).is_nan() {
                *p = half::f16::INFINITY.to_bits();
            }
        });
    } else if let Some(v) = image.as_f32_mut() {
        // Any bit pattern but NaN (NaN != NaN would fail the equality, not the recording).
        v.iter_mut().for_each(|p| {
            *p = f32::from_bits(rng.next_u64() as u32);
            if p.is_nan() {
                *p = f32::INFINITY;
            }
        });
    }
    image
}

pub fn calibration() -> RigCalibration {
    RigCalibration {
        name: "desk-7".into(),
        depth: Some(CameraModel::Pinhole(Pinhole {
            width: 320,
            height: 240,
            fx: 285.5,
            fy: 285.25,
            cx: 160.0,
            cy: 120.0,
            k1: 0.01,
            k2: -0.002,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })),
        probe: Some(CameraModel::KannalaBrandt(KannalaBrandt {
            width: 640,
            height: 640,
            fx: 200.0,
            fy: 200.0,
            cx: 320.0,
            cy: 320.0,
            k1: 0.1,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        })),
        color_from_depth: Pose::from_translation(Vec3::new(0.025, 0.0, 0.0)),
        probe_response: (0..256).map(|i| i as f32 / 255.0).collect(),
        ..Default::default()
    }
}

pub fn meta() -> RecordingMeta {
    RecordingMeta {
        calibration: Some(calibration()),
        source: "relight-tests 0.1.0".into(),
    }
}

/// `frames` rounds of depth, color, probe, markers and lamp with strictly increasing host time
/// (1 ms apart). Images rotate through every pixel format; one stream's seq crosses `u32::MAX`
/// and device clocks reach past what a ROS header stamp holds.
pub fn traffic(frames: usize, width: u32, height: u32, seed: u64) -> Vec<StreamMessage> {
    let mut rng = Rng::new(seed);
    let mut host_ns = 1_700_000_000_000_000_000u64;
    let mut stamp = |device_ns: u64| {
        host_ns += 1_000_000;
        Timestamp::new(device_ns, host_ns)
    };
    let mut messages = Vec::new();
    for i in 0..frames {
        let n = i as u64;
        let depth_format = [PixelFormat::DepthU16Mm, PixelFormat::DepthF32M][i % 2];
        messages.push(StreamMessage::Depth(Arc::new(Frame::new(
            n,
            stamp(n * 33_333_333),
            noisy_image(&mut rng, width, height, depth_format),
        ))));
        let color_format = [PixelFormat::Rgb8, PixelFormat::Rgba16F, PixelFormat::Mono8][i % 3];
        messages.push(StreamMessage::Color(Arc::new(Frame::new(
            u64::from(u32::MAX) - 2 + n,
            stamp(u64::MAX - 1000 + n),
            noisy_image(&mut rng, width, height, color_format),
        ))));
        let probe_format = [PixelFormat::Mono8, PixelFormat::Rgb8][i % 2];
        messages.push(StreamMessage::Probe(Arc::new(Frame::new(
            n * 3,
            stamp(rng.next_u64()),
            ProbeImage {
                image: noisy_image(&mut rng, width / 2, height / 2, probe_format),
                exposure_us: rng.next_u64() as u32,
                gain_db: rng.finite_f32(),
            },
        ))));
        let detections = (0..i % 4)
            .map(|d| MarkerDetection {
                family: if d % 2 == 0 {
                    "tag36h11"
                } else {
                    "aruco_4x4_50"
                }
                .into(),
                marker_id: rng.next_u64() as u32,
                corners_px: [(); 4].map(|_| Vec2::new(rng.finite_f32(), rng.unit_f32() * 640.0)),
                camera_from_marker: Pose {
                    rotation: Quat::from_xyzw(
                        rng.unit_f32(),
                        rng.unit_f32(),
                        rng.unit_f32(),
                        rng.unit_f32(),
                    ),
                    translation: Vec3::new(rng.finite_f32(), rng.unit_f32(), -rng.unit_f32()),
                },
                reprojection_rms_px: rng.unit_f32(),
            })
            .collect();
        messages.push(StreamMessage::Markers(Arc::new(Frame::new(
            u64::MAX - n,
            stamp(n),
            MarkerSet { detections },
        ))));
        messages.push(StreamMessage::Lamp(Arc::new(Frame::new(
            n,
            stamp(rng.next_u64()),
            LampState {
                on: i % 3 != 0,
                position_in_world: Vec3::new(rng.finite_f32(), rng.unit_f32(), rng.unit_f32()),
                intensity: Vec3::new(rng.unit_f32(), rng.finite_f32(), 0.0),
            },
        ))));
    }
    messages
}

/// Options with small chunks so that a few dozen small frames span many chunks.
pub fn small_chunks() -> RecordingOptions {
    RecordingOptions {
        chunk_size_bytes: 32 * 1024,
        ..Default::default()
    }
}

/// Record `messages` into memory.
pub fn record(messages: &[StreamMessage], options: &RecordingOptions) -> Vec<u8> {
    let mut writer =
        RecordingWriter::with_options(Cursor::new(Vec::new()), &meta(), options).unwrap();
    for msg in messages {
        writer.write(msg).unwrap();
    }
    let (summary, cursor) = writer.finish_into_inner().unwrap();
    assert_eq!(summary.total_messages(), messages.len() as u64);
    cursor.into_inner()
}
