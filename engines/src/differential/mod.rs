//! `differential`: differential rendering with direct light only (Debevec 1998): Δ is the
//! shadow-mapped direct light of the scene with the virtual object (R^ρ) minus without it (R^μ),
//! virtual pixels show their own direct light. No indirect light at all: the baseline every
//! other engine must beat.

use std::sync::Arc;

use serde_json::{Map, Value};

use crate::deferred::{Deferred, MapSizes, RealIndirect, ShadeOptions};
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
            crate::deferred::indirect_param(),
        ])
    }

    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let mut deferred = Deferred::new(ctx);
        deferred.set_real_indirect(RealIndirect::Nowhere);
        Ok(Self {
            deferred,
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
        self.deferred.set_shared_params(&schema, params);
    }
}

#[cfg(test)]
impl crate::shadow_reach::tests::WithDeferred for Differential {
    fn deferred_mut(&mut self) -> &mut Deferred {
        &mut self.deferred
    }
}
