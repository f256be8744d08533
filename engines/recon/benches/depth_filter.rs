//! The live depth stage's CPU filter: [`guided_filter`] at the mesh grid's size (160 × 120,
//! radius 2: `[scene] depth_stride = 2` of a 320 × 240 sensor) and at the full 320 × 240
//! (radius 4), on a desk under a box with the sensor's noise and a textured colour guide.
//!
//! `cargo bench -p relight-recon --bench depth_filter`; under `cargo test` it runs a small
//! smoke version.

use std::hint::black_box;

use criterion::{Criterion, Throughput};
use relight_core::{Image, PixelFormat};
use relight_recon::depth::{DepthMap, GuidedFilterSettings, guided_filter};

/// A slanted desk 1–2 m away with a box 0.3 m in front of its middle, noisy as a Kinect v1
/// (a fixed pseudo-random pattern), some pixels missing, and a colour image with a texture and
/// the box darker.
fn frame(width: u32, height: u32) -> (DepthMap, Image) {
    let mut state = 0x9e37_79b9_u32;
    let mut noise = move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        state as f32 / u32::MAX as f32 - 0.5
    };
    let mut colour = Image::new(width, height, PixelFormat::Rgb8);
    let bytes = colour.as_u8_mut().expect("an RGB8 image");
    let mut metres = Vec::with_capacity((width * height) as usize);
    for y in 0..height {
        for x in 0..width {
            let (u, v) = (x as f32 / width as f32, y as f32 / height as f32);
            let on_box = (0.35..0.65).contains(&u) && (0.4..0.8).contains(&v);
            let z = 1.0 + v + if on_box { -0.3 } else { 0.0 };
            let missing = noise() > 0.48;
            metres.push(if missing {
                0.0
            } else {
                z + 0.0028 * z * z * noise()
            });
            let shade = if on_box { 60.0 } else { 170.0 } + 30.0 * ((x / 8 + y / 8) % 2) as f32;
            let i = 3 * (y * width + x) as usize;
            bytes[i..i + 3].copy_from_slice(&[
                shade as u8,
                (shade * 0.9) as u8,
                (shade * 0.8) as u8,
            ]);
        }
    }
    (
        DepthMap {
            width,
            height,
            metres,
        },
        colour,
    )
}

fn main() {
    // `cargo bench` passes --bench; anything else (cargo test) gets a quick smoke run.
    let full = std::env::args().any(|arg| arg == "--bench");
    let cases: &[(u32, u32, u32)] = if full {
        &[(160, 120, 2), (320, 240, 4)]
    } else {
        &[(40, 30, 2)]
    };
    let mut criterion = Criterion::default().configure_from_args();
    let mut group = criterion.benchmark_group("depth_filter");
    group.sample_size(20);
    for &(width, height, radius_px) in cases {
        let (depth, colour) = frame(width, height);
        let settings = GuidedFilterSettings {
            radius_px,
            ..GuidedFilterSettings::kinect_v1(285.0 * width as f32 / 320.0)
        };
        group.throughput(Throughput::Elements(u64::from(width * height)));
        group.bench_function(format!("guided {width}x{height} r{radius_px}"), |b| {
            b.iter(|| black_box(guided_filter(&depth, &colour, &settings).expect("valid")));
        });
    }
    group.finish();
    criterion.final_summary();
}
