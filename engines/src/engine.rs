//! The engine contract: a scene frame in, a relit frame (Δ, composite, per-pass timings) out.

use std::sync::Arc;
use std::time::Instant;

use relight_core::scene::Scene;
use relight_core::{Frame, Image, PixelFormat, Timestamp};

use crate::gpu::GpuError;
use crate::roofline::PassWork;

/// What every engine renders from: the synchronised sensor data of one instant.
///
/// The reconstruction issue extends this with the G-buffer, normals, albedo and lights; the
/// daemon, `relightd render` and the bench all build it the same way, so an error measured
/// offline is the error live.
#[derive(Debug, Clone, Default)]
pub struct SceneFrame {
    pub stamp: Timestamp,
    /// Sequence number of the frame set this scene frame was built from.
    pub seq: u64,
    /// The camera image the composite is built on (the background B of DLPV Algorithm 1).
    pub color: Option<Arc<Frame<Image>>>,
    /// Depth registered to the colour camera, metres or millimetres.
    pub depth: Option<Arc<Frame<Image>>>,
    /// The scene the GPU engines relight: the real geometry (a scene's meshes offline, the
    /// depth-derived surface live), the virtual object(s), the lights and the camera (its pose
    /// and vertical field of view; the image size is the colour image's). Engines cache their
    /// upload by `Arc` identity, so share one `Arc` while the scene does not change.
    pub scene: Option<Arc<Scene>>,
}

/// How long one pass of an engine took, wall clock (GPU timestamp queries where available).
#[derive(Debug, Clone, PartialEq)]
pub struct PassTiming {
    pub pass: &'static str,
    pub ms: f64,
}

impl PassTiming {
    /// Time `f` and record it under `pass`.
    pub fn measure<T>(
        timings: &mut Vec<PassTiming>,
        pass: &'static str,
        f: impl FnOnce() -> T,
    ) -> T {
        let start = Instant::now();
        let out = f();
        timings.push(PassTiming {
            pass,
            ms: start.elapsed().as_secs_f64() * 1e3,
        });
        out
    }
}

/// An engine's output for one frame.
#[derive(Debug, Clone, Default)]
pub struct RelitFrame {
    pub stamp: Timestamp,
    pub seq: u64,
    /// Δ = L^ρ − L^μ, linear HDR RGBA f16 (may be negative); zero-sized when the engine has none.
    pub delta: Image,
    /// Background + Δ on real pixels, L^ρ on virtual pixels (DLPV Algorithm 1), 8-bit RGB.
    pub composite: Image,
    pub timings: Vec<PassTiming>,
    /// What each GPU pass run this frame had to do, for the roofline (`bench --roofline`);
    /// a pass kept from an earlier frame has no entry.
    pub work: Vec<PassWork>,
    /// Δ values (pixels × channels) the engine computed as NaN or ±∞ (written as 0) or beyond
    /// f16's range (clamped to it): no non-finite value reaches a sink, and this says one was
    /// computed (0 on a healthy frame).
    pub non_finite: usize,
    /// The engine's own estimate of its Δ's relative L2 error over real pixels, where it has
    /// one: `pt`'s Monte Carlo standard error. `None` for the engines whose error is bias.
    pub estimated_relative_error: Option<f64>,
    /// Path samples per pixel in this frame's picture (`pt`'s running means), and those traced
    /// this frame, averaged over the pixels (a frame may trace a sample for a share of them);
    /// 0 for the engines that trace none.
    pub path_samples: f64,
    pub path_samples_traced: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("engine `{engine}` needs a {stream} image and the frame has none")]
    MissingInput {
        engine: &'static str,
        stream: &'static str,
    },
    #[error("engine `{engine}`: unsupported {stream} format {format:?}")]
    UnsupportedFormat {
        engine: &'static str,
        stream: &'static str,
        format: PixelFormat,
    },
    #[error(transparent)]
    Params(#[from] crate::params::ParamError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("engine `{engine}`: the lights need {faces} shadow-map faces, at most {max} fit")]
    TooManyLights {
        engine: &'static str,
        faces: u32,
        max: u32,
    },
    #[error("internal: shading before the frame was prepared")]
    NotPrepared,
}

/// A relighting engine. Built off the render thread by the registry and swapped in between
/// frames, so `render` is the only method called per frame.
pub trait Engine: Send {
    fn name(&self) -> &'static str;
    /// Render one frame into `out`, whose buffers are reused from frame to frame (no
    /// allocation per frame in steady state). Never panics on bad input; returns an error.
    fn render(&mut self, scene: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError>;
    /// Apply already-validated parameters (see [`crate::ParamsSchema::validate`]).
    fn set_params(&mut self, params: &serde_json::Map<String, serde_json::Value>);
    /// What the engine decided and why, for the daemon's status (`auto`: the engine it chose,
    /// the scene's features, the predicted error and cost). `None` for an engine with no
    /// decisions of its own.
    fn status(&self) -> Option<serde_json::Value> {
        None
    }
}

impl RelitFrame {
    /// Start a frame for an engine that composites over the camera image: check the image,
    /// size Δ (zeroed) and the composite to it, and reset the timings. Buffers are reused.
    pub fn begin<'s>(
        &mut self,
        engine: &'static str,
        scene: &'s SceneFrame,
    ) -> Result<&'s Image, EngineError> {
        let color = &scene
            .color
            .as_ref()
            .ok_or(EngineError::MissingInput {
                engine,
                stream: "color",
            })?
            .payload;
        if color.format() != PixelFormat::Rgb8 {
            return Err(EngineError::UnsupportedFormat {
                engine,
                stream: "color",
                format: color.format(),
            });
        }
        let (width, height) = (color.width(), color.height());
        self.stamp = scene.stamp;
        self.seq = scene.seq;
        self.timings.clear();
        self.work.clear();
        self.non_finite = 0;
        self.estimated_relative_error = None;
        self.path_samples = 0.0;
        self.path_samples_traced = 0.0;
        self.composite.reshape(width, height, PixelFormat::Rgb8);
        self.delta.reshape(width, height, PixelFormat::Rgba16F);
        if let Some(delta) = self.delta.as_u16_mut() {
            delta.fill(0);
        }
        Ok(color)
    }
}
