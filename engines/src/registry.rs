//! Engines by name: what the control socket lists, and how a new engine is built off the render
//! thread with validated parameters before it is swapped in.

use std::sync::Arc;

use serde_json::{Map, Value};

use crate::auto::Auto;
use crate::depth_preview::DepthPreview;
use crate::differential::Differential;
use crate::dir::Dir;
use crate::dlpv::Dlpv;
use crate::dvct::Dvct;
use crate::engine::Engine;
use crate::gpu::{GpuError, SharedGpu};
use crate::ibl::Ibl;
use crate::params::{ParamError, ParamsSchema};
use crate::passthrough::Passthrough;
use crate::pt::Pt;

/// One registered engine: its name, what it does, its parameters, and how to build it.
#[derive(Debug, Clone)]
pub struct EngineSpec {
    pub name: &'static str,
    pub description: &'static str,
    pub schema: ParamsSchema,
    /// Whether it runs on the GPU (and so needs an adapter).
    pub gpu: bool,
    build: fn(&EngineRegistry) -> Result<Box<dyn Engine>, GpuError>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RegistryError {
    #[error("unknown engine `{name}`; known engines: {known}")]
    UnknownEngine { name: String, known: String },
    #[error(transparent)]
    Params(#[from] ParamError),
    #[error("engine `{name}`: {source}")]
    Gpu {
        name: String,
        #[source]
        source: GpuError,
    },
}

/// An engine built by the registry, with the full parameter set it runs with.
pub struct BuiltEngine {
    pub engine: Box<dyn Engine>,
    pub params: Map<String, Value>,
}

impl std::fmt::Debug for BuiltEngine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BuiltEngine")
            .field("engine", &self.engine.name())
            .field("params", &self.params)
            .finish()
    }
}

/// All engines this build knows, and the GPU context they share (created when the first GPU
/// engine is built, recreated after a device loss).
#[derive(Debug, Clone)]
pub struct EngineRegistry {
    specs: Vec<EngineSpec>,
    gpu: Arc<SharedGpu>,
}

impl Default for EngineRegistry {
    fn default() -> Self {
        Self::new()
    }
}

impl EngineRegistry {
    pub fn new() -> Self {
        Self {
            specs: vec![
                EngineSpec {
                    name: Passthrough::NAME,
                    description: "camera image unchanged (Δ = 0); the pipeline's reference path",
                    schema: Passthrough::schema(),
                    gpu: false,
                    build: |_| Ok(Box::new(Passthrough::default())),
                },
                EngineSpec {
                    name: DepthPreview::NAME,
                    description: "depth colour-mapped over the camera image (Δ = 0); checks registration",
                    schema: DepthPreview::schema(),
                    gpu: false,
                    build: |_| Ok(Box::new(DepthPreview::default())),
                },
                EngineSpec {
                    name: Differential::NAME,
                    description: "direct light only, shadow maps with and without the object (the no-indirect baseline)",
                    schema: Differential::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Differential::new(registry.gpu()?)?)),
                },
                EngineSpec {
                    name: Dlpv::NAME,
                    description: "Delta Light Propagation Volumes: V^Δ from R^ρ − R^μ injection and propagation (Franke 2013)",
                    schema: Dlpv::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Dlpv::new(registry.gpu()?)?)),
                },
                EngineSpec {
                    name: Dvct::NAME,
                    description: "Delta Voxel Cone Tracing: split-injected V^Δ/V^ρ mip chains, 9 diffuse + 1 glossy cone, shadow cones as antiradiance (Franke 2014)",
                    schema: Dvct::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Dvct::new(registry.gpu()?)?)),
                },
                EngineSpec {
                    name: Dir::NAME,
                    description: "Differential Instant Radiosity: real/virtual-flagged VPLs from the RSMs, imperfect shadow maps, L_rv − L_r in one gather (Knecht 2012)",
                    schema: Dir::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Dir::new(registry.gpu()?)?)),
                },
                EngineSpec {
                    name: Ibl::NAME,
                    description: "reflection-map convolution: full convolution of the HDR environment into diffuse and Phong maps, median-cut shadow lights for Δ and ambient occlusion (Kan et al.)",
                    schema: Ibl::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Ibl::new(registry.gpu()?)?)),
                },
                EngineSpec {
                    name: Auto::NAME,
                    description: "chooses the engine: the least predicted error (from the scene's shadow, bleeding, occlusion and gloss) among the candidates whose measured frame time fits budget_ms, or the cheapest that meets max_error; switches with hysteresis, builds off the render thread",
                    schema: Auto::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Auto::new(registry)?)),
                },
                EngineSpec {
                    name: Pt::NAME,
                    description: "progressive differential path tracing: the reference's estimator on the GPU, correlated L^ρ/L^μ paths, accumulated while the scene and camera hold still, samples per frame fitted to budget_ms",
                    schema: Pt::schema(),
                    gpu: true,
                    build: |registry| Ok(Box::new(Pt::new(registry.gpu()?)?)),
                },
            ],
            gpu: Arc::new(SharedGpu::default()),
        }
    }

    /// The GPU context the engines share (created on first use), for other GPU work of the
    /// pipeline such as the depth reconstruction.
    pub fn gpu(&self) -> Result<Arc<crate::gpu::GpuContext>, GpuError> {
        self.gpu.get()
    }

    pub fn specs(&self) -> &[EngineSpec] {
        &self.specs
    }

    pub fn names(&self) -> Vec<&'static str> {
        self.specs.iter().map(|s| s.name).collect()
    }

    pub fn spec(&self, name: &str) -> Result<&EngineSpec, RegistryError> {
        self.specs
            .iter()
            .find(|s| s.name == name)
            .ok_or_else(|| RegistryError::UnknownEngine {
                name: name.to_owned(),
                known: self.names().join(", "),
            })
    }

    /// Validate `params` (a partial update over the defaults) and build the engine with them.
    pub fn build(
        &self,
        name: &str,
        params: &Map<String, Value>,
    ) -> Result<BuiltEngine, RegistryError> {
        let spec = self.spec(name)?;
        let params = spec.schema.validate(&spec.schema.defaults(), params)?;
        let mut engine = (spec.build)(self).map_err(|source| RegistryError::Gpu {
            name: name.to_owned(),
            source,
        })?;
        engine.set_params(&params);
        Ok(BuiltEngine { engine, params })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_engine_lists_the_known_ones() {
        let err = EngineRegistry::new()
            .build("dlvp", &Map::new())
            .err()
            .unwrap();
        assert_eq!(
            err.to_string(),
            "unknown engine `dlvp`; known engines: passthrough, depth_preview, differential, dlpv, dvct, dir, ibl, auto, pt"
        );
    }

    #[test]
    fn every_engine_builds_with_defaults() {
        let registry = EngineRegistry::new();
        for name in registry.names() {
            let built = registry.build(name, &Map::new()).unwrap();
            assert_eq!(built.engine.name(), name);
            assert_eq!(built.params, registry.spec(name).unwrap().schema.defaults());
        }
    }
}
