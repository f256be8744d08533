//! `passthrough`: the composite is the camera image, Δ = 0. The path every frame takes before
//! any relighting, so the pipeline, sinks and timings can be checked without a GPU.

use serde_json::{Map, Value};

use crate::engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};
use crate::params::{ParamSpec, ParamsSchema};
use relight_core::srgb;

#[derive(Debug)]
pub struct Passthrough {
    /// 8-bit sRGB in → 8-bit sRGB out after an exposure change in linear space.
    lut: [u8; 256],
}

impl Default for Passthrough {
    fn default() -> Self {
        Self {
            lut: srgb::exposure_lut(0.0),
        }
    }
}

impl Passthrough {
    pub const NAME: &'static str = "passthrough";

    pub fn schema() -> ParamsSchema {
        ParamsSchema::new(vec![ParamSpec::float(
            "exposure_ev",
            "exposure change applied in linear space before re-encoding, in stops",
            -8.0,
            8.0,
            0.0,
        )])
    }
}

impl Engine for Passthrough {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, scene: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let color = out.begin(Self::NAME, scene)?;
        let lut = &self.lut;
        PassTiming::measure(&mut out.timings, "composite", || {
            if let (Some(src), Some(dst)) = (color.as_u8(), out.composite.as_u8_mut()) {
                for (d, s) in dst.iter_mut().zip(src) {
                    *d = lut[usize::from(*s)];
                }
            }
        });
        Ok(())
    }

    fn set_params(&mut self, params: &Map<String, Value>) {
        self.lut = srgb::exposure_lut(Self::schema().float(params, "exposure_ev"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::{Frame, Image, PixelFormat, Timestamp};
    use std::sync::Arc;

    fn scene() -> SceneFrame {
        let mut image = Image::new(4, 2, PixelFormat::Rgb8);
        image
            .as_u8_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
            .for_each(|(i, p)| *p = (i * 10) as u8);
        SceneFrame {
            stamp: Timestamp::new(1, 2),
            seq: 7,
            color: Some(Arc::new(Frame::new(7, Timestamp::new(1, 2), image))),
            depth: None,
            scene: None,
        }
    }

    #[test]
    fn composite_is_the_camera_image_and_delta_is_zero() {
        let mut engine = Passthrough::default();
        let mut out = RelitFrame::default();
        let scene = scene();
        engine.render(&scene, &mut out).unwrap();
        assert_eq!(&out.composite, &scene.color.as_ref().unwrap().payload);
        assert_eq!(out.delta.format(), PixelFormat::Rgba16F);
        assert!(out.delta.as_u16().unwrap().iter().all(|&h| h == 0));
        assert_eq!(out.seq, 7);
    }

    #[test]
    fn one_stop_brighter_doubles_linear_radiance() {
        let mut engine = Passthrough::default();
        let mut params = Map::new();
        params.insert("exposure_ev".into(), 1.0.into());
        engine.set_params(&params);
        let mut out = RelitFrame::default();
        engine.render(&scene(), &mut out).unwrap();
        let before = srgb::srgb_to_linear(30);
        let after = srgb::srgb_to_linear(out.composite.as_u8().unwrap()[3]);
        assert!((after / before - 2.0).abs() < 0.1, "{before} → {after}");
    }

    #[test]
    fn missing_camera_image_is_an_error() {
        let err = Passthrough::default()
            .render(&SceneFrame::default(), &mut RelitFrame::default())
            .unwrap_err();
        assert!(err.to_string().contains("needs a color image"));
    }
}
