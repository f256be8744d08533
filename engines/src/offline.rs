//! Offline scene frames: the same [`SceneFrame`] the daemon builds live, made from a scene file,
//! so that `relightd render`, `relightd bench` and the tests measure exactly what runs live.

use std::sync::Arc;

use glam::Vec3;
use relight_core::scene::Scene;
use relight_core::srgb::linear_to_srgb;
use relight_core::{Frame, Image, PixelFormat, Timestamp};

use crate::engine::SceneFrame;
use crate::reference::{ReferenceError, ReferenceImages, ReferenceSettings, render_reference};

/// What the engines are judged against: the reference with full light transport, `spp` samples
/// at pixel centres (as the engines' rasteriser samples, so silhouettes agree pixel for pixel).
pub fn reference(
    scene: &Scene,
    width: u32,
    height: u32,
    spp: u32,
) -> Result<ReferenceImages, ReferenceError> {
    render_reference(
        scene,
        ReferenceSettings {
            spp,
            pixel_jitter: false,
            size: Some((width, height)),
            ..ReferenceSettings::default()
        },
    )
}

/// The camera image of an offline scene: the reference's L^μ, sRGB-encoded and clipped, as a
/// camera without tone curve would record it.
pub fn background(reference: &ReferenceImages) -> Image {
    srgb_image(reference.width, reference.height, &reference.l_mu)
}

/// Linear RGB pixels (row-major) as an 8-bit sRGB image, clipped.
pub fn srgb_image(width: u32, height: u32, linear: &[Vec3]) -> Image {
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    if let Some(px) = image.as_u8_mut() {
        for (rgb, l) in px.chunks_exact_mut(3).zip(linear) {
            for (c, v) in rgb.iter_mut().zip(l.to_array()) {
                *c = linear_to_srgb(v);
            }
        }
    }
    image
}

/// A scene frame of `scene` over `background` (its size is the render size).
pub fn scene_frame(scene: Arc<Scene>, background: Image) -> SceneFrame {
    let stamp = Timestamp::new(0, 0);
    SceneFrame {
        stamp,
        seq: 0,
        color: Some(Arc::new(Frame::new(0, stamp, background))),
        depth: None,
        scene: Some(scene),
    }
}

/// Δ of a [`RelitFrame`](crate::RelitFrame) (Rgba16F) as linear RGB per pixel; empty for other
/// formats.
pub fn delta_pixels(delta: &Image) -> Vec<Vec3> {
    let Some(bits) = delta
        .as_u16()
        .filter(|_| delta.format() == PixelFormat::Rgba16F)
    else {
        return Vec::new();
    };
    bits.chunks_exact(4)
        .map(|px| {
            Vec3::new(
                half::f16::from_bits(px[0]).to_f32(),
                half::f16::from_bits(px[1]).to_f32(),
                half::f16::from_bits(px[2]).to_f32(),
            )
        })
        .collect()
}

/// The error every engine is judged by: ‖Δ − Δ_ref‖₂ / ‖Δ_ref‖₂ over real pixels (where the
/// reference's camera ray hits no virtual object), and max |Δ − Δ_ref| there. A missing or
/// mis-sized Δ is an error of NaN.
pub fn delta_error(delta: &[Vec3], reference: &[Vec3], virtual_mask: &[bool]) -> (f64, f64) {
    if delta.len() != reference.len() {
        return (f64::NAN, f64::NAN);
    }
    let (mut err, mut norm, mut max_abs) = (0.0f64, 0.0f64, 0.0f64);
    for ((d, r), v) in delta.iter().zip(reference).zip(virtual_mask) {
        if *v {
            continue;
        }
        let e = *d - *r;
        err += f64::from(e.length_squared());
        norm += f64::from(r.length_squared());
        max_abs = max_abs.max(f64::from(e.abs().max_element()));
    }
    ((err / norm.max(1e-30)).sqrt(), max_abs)
}
