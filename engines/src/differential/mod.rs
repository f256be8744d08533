//! `differential`: differential rendering with direct light only (Debevec 1998): Δ is the
//! shadow-mapped direct light of the scene with the virtual object (R^ρ) minus without it (R^μ),
//! virtual pixels show their own direct light. No indirect light at all: the baseline every
//! other engine must beat.

use std::sync::Arc;

use serde_json::{Map, Value};

use crate::deferred::{Deferred, MapSizes, ShadeOptions};
use crate::engine::{Engine, EngineError, RelitFrame, SceneFrame};
use crate::gpu::{GpuContext, GpuError};
use crate::params::{ParamSpec, ParamsSchema};

#[derive(Debug)]
pub struct Differential {
    deferred: Deferred,
    rsm_size: u32,
    shadow_bias_texels: f32,
}

impl Differential {
    pub const NAME: &'static str = "differential";

    pub fn schema() -> ParamsSchema {
        ParamsSchema::new(vec![
            ParamSpec::int(
                "rsm_size",
                "shadow-map edge in texels, per light face",
                64,
                4096,
                512,
            ),
            ParamSpec::float(
                "shadow_bias",
                "shadow-map depth bias in texel footprints (grows with the surface slope)",
                0.0,
                8.0,
                1.5,
            ),
            crate::deferred::env_lights_param(8),
            crate::deferred::accumulate_param(),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        Ok(Self {
            deferred: Deferred::new(ctx),
            rsm_size: 512,
            shadow_bias_texels: 1.5,
        })
    }
}

impl Engine for Differential {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, scene: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        let Some(_) =
            self.deferred
                .prepare(Self::NAME, scene, out, MapSizes::shadows(self.rsm_size))?
        else {
            return Ok(());
        };
        self.deferred.finish(
            ShadeOptions {
                shadow_bias_texels: self.shadow_bias_texels,
                direct_delta: true,
            },
            out,
        )
    }

    fn set_params(&mut self, params: &Map<String, Value>) {
        let schema = Self::schema();
        self.rsm_size = schema.int(params, "rsm_size") as u32;
        self.shadow_bias_texels = schema.float(params, "shadow_bias") as f32;
        self.deferred
            .set_environment_light_count(schema.int(params, "env_lights") as u32);
        self.deferred
            .set_accumulate(schema.int(params, "accumulate") as u32);
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use glam::Vec3;
    use relight_core::light::Light;
    use relight_core::scene::Scene;
    use relight_core::{Frame, Image, PixelFormat, Timestamp};

    use super::*;
    use crate::offline::delta_pixels;

    fn render(scene: &Arc<Scene>, cull: bool) -> Vec<Vec3> {
        let ctx = Arc::new(GpuContext::new().expect("a GPU adapter (lavapipe in CI)"));
        let mut engine = Differential::new(ctx).expect("the engine builds");
        if !cull {
            engine.deferred.without_shadow_reach_cull();
        }
        let color = Image::new(96, 72, PixelFormat::Rgb8);
        let frame = SceneFrame {
            stamp: Timestamp::new(0, 0),
            seq: 0,
            color: Some(Arc::new(Frame::new(0, Timestamp::new(0, 0), color))),
            depth: None,
            scene: Some(scene.clone()),
        };
        let mut out = RelitFrame::default();
        engine.render(&frame, &mut out).expect("it renders");
        delta_pixels(&out.delta)
    }

    /// Skipping the shadow-map lookups of pixels the object cannot shadow changes no pixel:
    /// under the scene's own light, and under a low one whose long shadows graze the floor
    /// and reach the wall.
    #[test]
    fn the_shadow_reach_cull_changes_no_pixel() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box");
        let desk = Scene::load(&dir).expect("the scene loads");
        let mut low = desk.clone();
        low.lights = vec![Light::Point {
            position_in_world: Vec3::new(0.9, 0.35, 0.6),
            intensity: Vec3::splat(2.0),
        }];
        for (name, scene) in [("desk_box", desk), ("low light", low)] {
            let scene = Arc::new(scene);
            let culled = render(&scene, true);
            let full = render(&scene, false);
            let shadowed = full.iter().filter(|d| d.x < -1e-4).count();
            assert!(
                shadowed > 50,
                "{name}: the object shadows {shadowed} pixels"
            );
            for (i, (a, b)) in culled.iter().zip(&full).enumerate() {
                assert_eq!(
                    a.to_array().map(f32::to_bits),
                    b.to_array().map(f32::to_bits),
                    "{name}: pixel {i}"
                );
            }
        }
    }
}
