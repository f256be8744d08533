//! relight-engines: relighting engines behind one [`Engine`] trait, and the registry that builds
//! them by name with validated parameters.
//!
//! This crate starts with the two diagnostic engines that need no GPU (`passthrough`,
//! `depth_preview`); the GPU context, reconstruction and the paper engines (differential, DLPV,
//! DVCT, DIR, IBL) plug into the same trait and registry.

pub mod auto;
pub mod change;
pub mod deferred;
pub mod differential;
pub mod dir;
pub mod dlpv;
pub mod dvct;
pub mod engine;
pub mod gbuffer;
pub mod gpu;
pub mod gpu_scene;
pub mod ibl;
pub mod live_scene;
pub mod offline;
pub mod params;
pub mod pt;
pub mod recon_gpu;
pub mod reference_cache;
pub mod registry;
pub mod roofline;
pub mod shaders;
pub mod shadow_proxy;
pub mod shadow_reach;
mod strided;
pub mod surface_albedo;
pub mod timer;
mod volume;

mod depth_preview;
mod passthrough;

pub use engine::{Engine, EngineError, PassTiming, RelitFrame, SceneFrame};

/// One of the repository's scenes (`tests/scenes/<name>`), for the unit tests.
#[cfg(test)]
pub(crate) fn test_scene(name: &str) -> relight_core::scene::Scene {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/scenes")
        .join(name);
    relight_core::scene::Scene::load(&dir).expect("the scene loads")
}
pub use params::{ParamError, ParamKind, ParamSpec, ParamsSchema};
pub use registry::{BuiltEngine, EngineRegistry, EngineSpec};
/// The CPU path tracer every engine is scored against (its own crate so that the simulator can
/// share it without the GPU engines).
pub use relight_reference as reference;
