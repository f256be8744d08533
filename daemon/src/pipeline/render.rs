//! The render stage: the running engine (and the passthrough shown while the camera is
//! untracked), swapped at frame boundaries for one the control threads built, rebuilt after a
//! GPU device loss, and timed per frame and per pass.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use relight_engines::gpu::GpuError;
use relight_engines::{Engine, EngineError, EngineRegistry, RelitFrame};
use serde_json::{Map, Value};

use super::live_frame::LiveFrame;
use super::status::Counters;
use crate::lock;
use crate::timing::{PassTimers, StageTimer, Timings};

/// A change the render thread applies at the next frame boundary.
pub enum Pending {
    Engine {
        engine: Box<dyn Engine>,
        name: String,
        params: Map<String, Value>,
    },
    Params(Map<String, Value>),
}

/// The engine as the control threads see it: its name and full parameters, and a change that
/// waits for the next frame boundary. An engine is built on the control thread and only
/// swapped in by the render thread, so a slow build never stalls a frame.
#[derive(Debug)]
pub struct EngineSlot {
    pub name: Mutex<String>,
    pub params: Mutex<Map<String, Value>>,
    pub pending: Mutex<Option<Pending>>,
}

impl std::fmt::Debug for Pending {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Engine { name, .. } => f.debug_struct("Engine").field("name", name).finish(),
            Self::Params(params) => f.debug_tuple("Params").field(params).finish(),
        }
    }
}

/// What a render left.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rendered {
    Composite,
    /// The frame failed (counted and logged); nothing to output.
    Failed,
}

pub struct RenderStage {
    engine: Box<dyn Engine>,
    /// Shows the camera image while the camera is untracked (no Δ rather than a wrong one).
    passthrough: Box<dyn Engine>,
    relit: RelitFrame,
    /// Sleep this long in every render, standing in for a slow engine (tests).
    delay: Option<Duration>,
    timer: StageTimer,
    /// The engine's passes as `render.<pass>`.
    passes: PassTimers,
}

impl std::fmt::Debug for RenderStage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RenderStage")
            .field("seq", &self.relit.seq)
            .finish_non_exhaustive()
    }
}

impl RenderStage {
    pub fn new(
        engine: Box<dyn Engine>,
        passthrough: Box<dyn Engine>,
        delay: Option<Duration>,
        timings: Arc<Timings>,
    ) -> Self {
        Self {
            engine,
            passthrough,
            relit: RelitFrame::default(),
            delay,
            timer: timings.stage("render"),
            passes: PassTimers::new("render", timings),
        }
    }

    /// The last frame rendered (empty before the first).
    pub fn relit(&self) -> &RelitFrame {
        &self.relit
    }

    /// The slowest recent render, milliseconds.
    pub fn slowest_ms(&self) -> f64 {
        self.timer.stats().max_ms()
    }

    /// Take up a change from the control threads; true when a new engine came in (its first
    /// frame compiles its pipelines).
    ///
    /// The slot's `pending` stays locked until its name and parameters name the engine taken
    /// up: `engine.params.set` validates against the pending engine or else the named one, and
    /// in between it would have checked a switch's parameters against the engine it replaces
    /// (`relightctl engine set pt` then `params set spp=1` failed now and then).
    pub fn apply_pending(&mut self, slot: &EngineSlot) -> bool {
        let mut pending = lock(&slot.pending);
        let Some(taken) = pending.take() else {
            return false;
        };
        match taken {
            Pending::Engine {
                engine,
                name,
                params,
            } => {
                let replaced = std::mem::replace(&mut self.engine, engine);
                *lock(&slot.params) = params;
                tracing::info!(engine = %name, "engine switched");
                *lock(&slot.name) = name;
                drop(pending);
                // Its GPU resources are freed with the control threads no longer waiting.
                drop(replaced);
                true
            }
            Pending::Params(params) => {
                self.engine.set_params(&params);
                *lock(&slot.params) = params;
                false
            }
        }
    }

    /// Render `frame` with the engine, or with the passthrough when the camera is untracked.
    /// After a GPU device loss, the same engine is rebuilt with the same parameters on a new
    /// device (the registry's shared context is recreated once lost): until that works, frames
    /// keep failing and counting as render errors; the daemon stays up. Returns whether an
    /// engine was rebuilt along with the outcome.
    pub fn render(
        &mut self,
        frame: &LiveFrame,
        counters: &Counters,
        slot: &EngineSlot,
        registry: &EngineRegistry,
    ) -> (Rendered, bool) {
        let tracked = frame.tracking.is_usable();
        let engine = if tracked {
            &mut self.engine
        } else {
            &mut self.passthrough
        };
        let start = Instant::now();
        if let Some(delay) = self.delay {
            std::thread::sleep(delay);
        }
        let rendered = engine.render(&frame.scene, &mut self.relit);
        self.timer.record(start.elapsed().as_secs_f64() * 1e3);
        if tracked {
            counters.engine_status(engine.status());
        }
        match rendered {
            Ok(()) => {
                self.passes.record(&self.relit.timings);
                (Rendered::Composite, false)
            }
            Err(error) => {
                let (errors, log) = counters.render_failed();
                if log {
                    tracing::warn!(%error, errors, "frame not rendered");
                }
                let lost = matches!(error, EngineError::Gpu(GpuError::Lost { .. }));
                (Rendered::Failed, lost && self.rebuild(slot, registry))
            }
        }
    }

    fn rebuild(&mut self, slot: &EngineSlot, registry: &EngineRegistry) -> bool {
        let name = lock(&slot.name).clone();
        let params = lock(&slot.params).clone();
        match registry.build(&name, &params) {
            Ok(built) => {
                tracing::warn!(engine = %name, "GPU device lost; engine rebuilt on a new device");
                self.engine = built.engine;
                true
            }
            Err(error) => {
                tracing::error!(engine = %name, %error, "rebuilding the engine failed");
                false
            }
        }
    }
}
