//! Offline scene frames: the same [`SceneFrame`] the daemon builds live, made from a scene file,
//! so that `relightd render`, `relightd bench` and the tests measure exactly what runs live.

use std::sync::Arc;

use relight_core::scene::Scene;
use relight_core::srgb::linear_to_srgb;
use relight_core::{Frame, Image, PixelFormat, Timestamp};

use crate::engine::SceneFrame;
use crate::reference::{ReferenceError, ReferenceSettings, render_reference};

/// The camera image of an offline scene: the reference's L^μ (`spp` samples at pixel centres),
/// sRGB-encoded and clipped, as a camera without tone curve would record it.
pub fn background(
    scene: &Scene,
    width: u32,
    height: u32,
    spp: u32,
) -> Result<Image, ReferenceError> {
    let images = render_reference(
        scene,
        ReferenceSettings {
            spp,
            pixel_jitter: false,
            size: Some((width, height)),
            ..ReferenceSettings::default()
        },
    )?;
    let mut image = Image::new(width, height, PixelFormat::Rgb8);
    if let Some(px) = image.as_u8_mut() {
        for (rgb, l) in px.chunks_exact_mut(3).zip(&images.l_mu) {
            for (c, v) in rgb.iter_mut().zip(l.to_array()) {
                *c = linear_to_srgb(v);
            }
        }
    }
    Ok(image)
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
