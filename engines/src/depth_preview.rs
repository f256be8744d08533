//! `depth_preview`: depth colour-mapped and blended over the camera image, Δ = 0. A quick visual
//! check that depth is registered to colour, and a second engine to switch to live.

use serde_json::{Map, Value};

use relight_core::PixelFormat;

use crate::engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::params::{ParamSpec, ParamsSchema};

#[derive(Debug)]
pub struct DepthPreview {
    near_m: f32,
    far_m: f32,
    opacity: f32,
}

impl Default for DepthPreview {
    fn default() -> Self {
        Self {
            near_m: 0.5,
            far_m: 4.0,
            opacity: 0.5,
        }
    }
}

impl DepthPreview {
    pub const NAME: &'static str = "depth_preview";

    pub fn schema() -> ParamsSchema {
        ParamsSchema::new(vec![
            ParamSpec::float(
                "near_m",
                "depth mapped to the first colour of the ramp, metres",
                0.0,
                20.0,
                0.5,
            ),
            ParamSpec::float(
                "far_m",
                "depth mapped to the last colour of the ramp, metres",
                0.01,
                20.0,
                4.0,
            ),
            ParamSpec::float(
                "opacity",
                "weight of the depth colour over the camera image",
                0.0,
                1.0,
                0.5,
            ),
        ])
    }

    /// Blue (near) → green → red (far).
    fn ramp(&self, depth_m: f32) -> [f32; 3] {
        let span = (self.far_m - self.near_m).max(1e-3);
        let t = ((depth_m - self.near_m) / span).clamp(0.0, 1.0);
        [
            (2.0 * t - 1.0).max(0.0),
            1.0 - (2.0 * t - 1.0).abs(),
            (1.0 - 2.0 * t).max(0.0),
        ]
    }
}

impl Engine for DepthPreview {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, scene: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let color = out.begin(Self::NAME, scene)?;
        let depth = &scene
            .depth
            .as_ref()
            .ok_or(EngineError::MissingInput {
                engine: Self::NAME,
                stream: "depth",
            })?
            .payload;
        if !matches!(
            depth.format(),
            PixelFormat::DepthU16Mm | PixelFormat::DepthF32M
        ) {
            return Err(EngineError::UnsupportedFormat {
                engine: Self::NAME,
                stream: "depth",
                format: depth.format(),
            });
        }
        let (width, height) = (color.width(), color.height());
        let this = &*self;
        PassTiming::measure(&mut out.timings, "blend", || {
            let (Some(src), Some(dst)) = (color.as_u8(), out.composite.as_u8_mut()) else {
                return;
            };
            for y in 0..height {
                // Nearest-neighbour lookup so depth of another resolution still lines up.
                let dy =
                    (u64::from(y) * u64::from(depth.height()) / u64::from(height.max(1))) as u32;
                for x in 0..width {
                    let dx =
                        (u64::from(x) * u64::from(depth.width()) / u64::from(width.max(1))) as u32;
                    let i = 3 * (y as usize * width as usize + x as usize);
                    let (Some(s), Some(d)) = (src.get(i..i + 3), dst.get_mut(i..i + 3)) else {
                        continue;
                    };
                    match depth.depth_m(dx, dy) {
                        Some(depth_m) => {
                            let ramp = this.ramp(depth_m);
                            for c in 0..3 {
                                let mixed = f32::from(s[c]) * (1.0 - this.opacity)
                                    + ramp[c] * 255.0 * this.opacity;
                                d[c] = mixed.round().clamp(0.0, 255.0) as u8;
                            }
                        }
                        None => d.copy_from_slice(s),
                    }
                }
            }
        });
        Ok(())
    }

    fn set_params(&mut self, params: &Map<String, Value>) {
        let schema = Self::schema();
        self.near_m = schema.float(params, "near_m") as f32;
        self.far_m = schema.float(params, "far_m") as f32;
        self.opacity = schema.float(params, "opacity") as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::{Frame, Image, Timestamp};
    use std::sync::Arc;

    #[test]
    fn holes_keep_the_camera_colour_and_valid_depth_is_tinted() {
        let mut color = Image::new(2, 1, PixelFormat::Rgb8);
        color.as_u8_mut().unwrap().fill(100);
        let mut depth = Image::new(2, 1, PixelFormat::DepthU16Mm);
        depth.as_u16_mut().unwrap().copy_from_slice(&[0, 500]);
        let scene = SceneFrame {
            color: Some(Arc::new(Frame::new(0, Timestamp::default(), color))),
            depth: Some(Arc::new(Frame::new(0, Timestamp::default(), depth))),
            ..Default::default()
        };
        let mut engine = DepthPreview::default();
        let mut out = RelitFrame::default();
        engine.render(&scene, &mut out).unwrap();
        let px = out.composite.as_u8().unwrap();
        assert_eq!(&px[0..3], &[100, 100, 100]);
        // 0.5 m is `near_m`: pure blue at opacity 0.5.
        assert_eq!(&px[3..6], &[50, 50, 178]);
    }
}
