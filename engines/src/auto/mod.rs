//! `auto`: the engine that chooses the engine. It runs one of a list of candidates (engines
//! with parameters, [`governor::candidates`]) and switches between them, per scene and adapter,
//! to meet a frame budget (`budget_ms`) with the least predicted error, or, with `max_error`,
//! at the least cost that is predicted to meet it ([`governor`] says how).
//!
//! Per frame it renders with the running candidate and times it; tracks whether the picture's
//! inputs held (the camera within a quarter pixel, the scene's content unchanged:
//! [`crate::change`]), since a still scene lets engines keep work and `pt` accumulate; and
//! re-estimates the scene's features ([`features`]) when the scene's content changes or the
//! camera has moved far. Candidates are built the way the daemon's hot-swap builds an engine:
//! off the render thread (a builder thread here), and swapped in at a frame boundary once
//! built, while the running candidate goes on rendering, so no frame is dropped or stalled by a
//! build. Built candidates are kept, so switching back costs no build.
//!
//! [`Engine::status`] reports the choice and why: the features, each candidate's predicted
//! error and measured cost, the probe under way, the number of switches.

pub mod features;
pub mod governor;

use std::sync::Arc;
use std::sync::mpsc::{Receiver, channel};
use std::time::Instant;

use relight_core::scene::{Scene, SceneCamera};
use serde_json::{Map, Value, json};

use self::features::scene_features;
use self::governor::{Action, Governor, Motion, PtFrame, Settings};
use crate::change::{STILL_PX, image_shift_px, scene_focus_depth_m, scene_key};
use crate::engine::{Engine, EngineError, RelitFrame, SceneFrame};
use crate::gpu::GpuError;
use crate::params::{ParamSpec, ParamsSchema};
use crate::registry::{EngineRegistry, RegistryError};

/// The camera must move this far (pixels) before the features are estimated again.
const FEATURES_MOVED_PX: f32 = 20.0;
/// ... and at most this often, in frames.
const FEATURES_EVERY: u32 = 10;

type Built = (usize, Result<Box<dyn Engine>, String>);

/// Builds the candidates off the render thread, all of them, one after another, from the
/// start: a probe or a switch then waits for no build (pipelines compile for seconds on
/// lavapipe), and pipelines are all an unused candidate holds (engines allocate their buffers
/// on their first frame).
struct Builder {
    built: Receiver<Built>,
    /// Candidates not built yet.
    unbuilt: usize,
}

impl Builder {
    fn new(registry: EngineRegistry, jobs: Vec<(usize, &'static str, Map<String, Value>)>) -> Self {
        let unbuilt = jobs.len();
        let (done, built) = channel();
        let spawned = std::thread::Builder::new()
            .name("auto-builder".into())
            .spawn(move || {
                for (candidate, engine, params) in jobs {
                    let result = registry
                        .build(engine, &params)
                        .map(|b| b.engine)
                        .map_err(|e| e.to_string());
                    if done.send((candidate, result)).is_err() {
                        break;
                    }
                }
            });
        if let Err(error) = spawned {
            tracing::warn!(%error, "auto: no builder thread; only the first candidate runs");
        }
        Self { built, unbuilt }
    }
}

/// Whether the picture's inputs held from frame to frame.
#[derive(Debug, Default)]
struct Stillness {
    last: Option<(u64, SceneCamera)>,
}

impl Stillness {
    fn update(&mut self, key: u64, camera: SceneCamera, height: u32, depth_m: f32) -> Motion {
        let still = self.last.is_some_and(|(last_key, last_camera)| {
            last_key == key && image_shift_px(&last_camera, &camera, height, depth_m) <= STILL_PX
        });
        self.last = Some((key, camera));
        if still { Motion::Still } else { Motion::Moving }
    }
}

pub struct Auto {
    governor: Governor,
    engines: Vec<Option<Box<dyn Engine>>>,
    builder: Builder,
    /// The candidate to switch to once it is built.
    wanted: Option<usize>,
    /// Frames the running candidate has rendered since it was switched in, and their time (ms).
    frames_on_current: u32,
    ms_on_current: f64,
    stillness: Stillness,
    /// The last scene and its key: hashing a scene (an environment map's every texel) each
    /// frame costs milliseconds, and an unchanged scene is the same `Arc`.
    scene_key: Option<(Arc<Scene>, u64)>,
    motion: Motion,
    /// The scene key and camera the features were estimated for, and frames since.
    features_for: Option<(u64, SceneCamera)>,
    frames_since_features: u32,
    size: (u32, u32),
    status: Value,
}

impl std::fmt::Debug for Auto {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Auto")
            .field("governor", &self.governor)
            .finish_non_exhaustive()
    }
}

impl Auto {
    pub const NAME: &'static str = "auto";

    pub fn schema() -> ParamsSchema {
        ParamsSchema::new(vec![
            ParamSpec::float(
                "budget_ms",
                "frame time to stay within (33: a 30 Hz sensor)",
                1.0,
                60_000.0,
                33.0,
            ),
            ParamSpec::float(
                "max_error",
                "predicted relative L2 of Δ to meet at the least cost (0: the least error the budget allows)",
                0.0,
                10.0,
                0.0,
            ),
            ParamSpec::float(
                "horizon_ms",
                "how long a still camera is expected to stay still: what accumulates over frames (pt's samples, edges) is judged at this age",
                1.0,
                3_600_000.0,
                2000.0,
            ),
        ])
    }

    /// Starts on the cheapest candidate (`differential`), built here; the others are built
    /// when the governor first wants them.
    pub fn new(registry: &EngineRegistry) -> Result<Self, GpuError> {
        let candidates = governor::candidates();
        let first = &candidates[0];
        let engine = match registry.build(first.engine, &first.params) {
            Ok(built) => built.engine,
            Err(RegistryError::Gpu { source, .. }) => return Err(source),
            Err(other) => return Err(GpuError::Validation(format!("auto: {other}"))),
        };
        let mut engines: Vec<Option<Box<dyn Engine>>> = std::iter::repeat_with(|| None)
            .take(candidates.len())
            .collect();
        engines[0] = Some(engine);
        let settings = Settings {
            budget_ms: 33.0,
            max_error: None,
            horizon_ms: 2000.0,
        };
        let jobs = candidates
            .iter()
            .enumerate()
            .skip(1)
            .map(|(i, c)| (i, c.engine, c.params.clone()))
            .collect();
        let mut auto = Self {
            governor: Governor::new(candidates, 0, settings),
            engines,
            builder: Builder::new(registry.clone(), jobs),
            wanted: None,
            frames_on_current: 0,
            ms_on_current: 0.0,
            stillness: Stillness::default(),
            scene_key: None,
            motion: Motion::Moving,
            features_for: None,
            frames_since_features: 0,
            size: (0, 0),
            status: Value::Null,
        };
        auto.refresh_status(None);
        Ok(auto)
    }

    /// Block until every candidate is built (the builder works in the background from
    /// [`Auto::new`] on): for measurements that should not count the builds, which a running
    /// daemon does not wait for.
    pub fn wait_for_builds(&mut self) {
        while self.builder.unbuilt > 0 {
            match self.builder.built.recv() {
                Ok(built) => self.take_built(built),
                Err(_) => break,
            }
        }
    }

    /// A candidate's parameters under this budget: `pt` fits its samples to it.
    fn params_for(&self, candidate: usize) -> Map<String, Value> {
        let mut params = self.governor.candidates()[candidate].params.clone();
        if self.governor.candidates()[candidate].is_path_traced() {
            params.insert(
                "budget_ms".into(),
                json!(self.governor.settings().budget_ms),
            );
        }
        params
    }

    /// Give a built candidate the parameters it runs with here (`pt` its share of the budget).
    fn configure(&self, candidate: usize, engine: &mut dyn Engine) {
        if !self.governor.candidates()[candidate].is_path_traced() {
            return;
        }
        let schema = crate::pt::Pt::schema();
        if let Ok(params) = schema.validate(&schema.defaults(), &self.params_for(candidate)) {
            engine.set_params(&params);
        }
    }

    fn switch_to(&mut self, candidate: usize) {
        self.governor.switched(candidate);
        self.frames_on_current = 0;
        self.ms_on_current = 0.0;
    }

    /// Start running `candidate`: at once when it is built, else once the builder has it.
    fn want(&mut self, candidate: usize) {
        if self.engines[candidate].is_some() {
            self.wanted = None;
            self.switch_to(candidate);
        } else {
            self.wanted = Some(candidate);
        }
    }

    /// Take up the candidates the builder finished; switch to the wanted one when it is there.
    fn collect_built(&mut self) {
        while let Ok(built) = self.builder.built.try_recv() {
            self.take_built(built);
        }
        if let Some(candidate) = self.wanted
            && self.engines[candidate].is_some()
        {
            self.want(candidate);
        }
    }

    fn take_built(&mut self, (candidate, result): Built) {
        self.builder.unbuilt = self.builder.unbuilt.saturating_sub(1);
        match result {
            Ok(mut engine) => {
                self.configure(candidate, engine.as_mut());
                self.engines[candidate] = Some(engine);
            }
            Err(error) => {
                tracing::warn!(candidate = %self.governor.candidates()[candidate].label, %error, "auto: candidate not built; left out");
                self.governor.mark_unavailable(candidate);
                if self.wanted == Some(candidate) {
                    self.wanted = None;
                }
            }
        }
    }

    fn refresh_status(&mut self, estimated: Option<f64>) {
        let current = self.governor.current();
        let candidates = self.governor.candidates();
        let motion = self.motion;
        let assessments = self.governor.assess(motion);
        let chosen = &assessments[current];
        self.status = json!({
            "engine": candidates[current].engine,
            "chosen": candidates[current].label,
            "params": Value::Object(self.params_for(current)),
            "reason": self.governor.reason(),
            "motion": motion,
            "budget_ms": self.governor.settings().budget_ms,
            "max_error": self.governor.settings().max_error,
            "predicted_error": chosen.predicted_error,
            "predicted_ms": chosen.cost_ms.or(chosen.estimated_cost_ms),
            "estimated_error": estimated,
            "features": self.governor.features(),
            "indirect_share": self.governor.features().indirect_share(),
            "probing": self.governor.probing().map(|c| candidates[c].label.clone()),
            "waiting_for": self.wanted.map(|c| candidates[c].label.clone()),
            "unbuilt": self.builder.unbuilt,
            "switches": self.governor.switches(),
            "candidates": assessments,
        });
    }
}

impl Engine for Auto {
    fn name(&self) -> &'static str {
        Self::NAME
    }

    fn render(&mut self, frame: &SceneFrame, out: &mut RelitFrame) -> Result<(), EngineError> {
        self.collect_built();
        let scene = frame.scene.as_ref().ok_or(EngineError::MissingInput {
            engine: Self::NAME,
            stream: "scene",
        })?;
        let size = frame
            .color
            .as_ref()
            .map_or((0, 0), |c| (c.payload.width(), c.payload.height()));
        if size != self.size {
            self.size = size;
            self.governor.forget_costs();
        }
        let key = match &self.scene_key {
            Some((held, key)) if Arc::ptr_eq(held, scene) => *key,
            _ => {
                let key = scene_key(scene);
                self.scene_key = Some((scene.clone(), key));
                key
            }
        };
        let depth = scene_focus_depth_m(scene);
        self.motion = self.stillness.update(key, scene.camera, size.1, depth);
        self.frames_since_features = self.frames_since_features.saturating_add(1);
        let stale = self.features_for.is_none_or(|(k, camera)| {
            k != key || image_shift_px(&camera, &scene.camera, size.1, depth) > FEATURES_MOVED_PX
        });
        if stale && (self.features_for.is_none() || self.frames_since_features >= FEATURES_EVERY) {
            self.governor.set_features(scene_features(scene));
            self.features_for = Some((key, scene.camera));
            self.frames_since_features = 0;
        }

        let current = self.governor.current();
        let Some(engine) = self.engines[current].as_mut() else {
            return Err(EngineError::NotPrepared);
        };
        let started = Instant::now();
        engine.render(frame, out)?;
        let ms = started.elapsed().as_secs_f64() * 1e3;
        let steady = self.frames_on_current > 0
            && (self.ms_on_current >= governor::WARM_UP_MS
                || self.frames_on_current >= governor::WARM_UP_FRAMES);
        self.frames_on_current = self.frames_on_current.saturating_add(1);
        self.ms_on_current += ms;
        let pt = self.governor.candidates()[current]
            .is_path_traced()
            .then_some(PtFrame {
                path_samples: out.path_samples,
                samples_added: out.path_samples_traced,
                estimated_error: out.estimated_relative_error,
            });
        self.governor.observe(current, self.motion, ms, steady, pt);
        match self.governor.decide(self.motion, self.wanted.is_some()) {
            Action::Stay => {}
            Action::Switch(candidate) | Action::Probe(candidate) => {
                tracing::info!(
                    to = %self.governor.candidates()[candidate].label,
                    motion = ?self.motion,
                    budget_ms = self.governor.settings().budget_ms,
                    reason = %self.governor.reason(),
                    "auto: switching"
                );
                self.want(candidate);
            }
        }
        self.refresh_status(out.estimated_relative_error);
        Ok(())
    }

    fn set_params(&mut self, params: &Map<String, Value>) {
        let schema = Self::schema();
        let max_error = schema.float(params, "max_error");
        self.governor.set_settings(Settings {
            budget_ms: schema.float(params, "budget_ms"),
            max_error: (max_error > 0.0).then_some(max_error),
            horizon_ms: schema.float(params, "horizon_ms"),
        });
        for candidate in 0..self.engines.len() {
            if let Some(mut engine) = self.engines[candidate].take() {
                self.configure(candidate, engine.as_mut());
                self.engines[candidate] = Some(engine);
            }
        }
        self.refresh_status(None);
    }

    fn status(&self) -> Option<Value> {
        Some(self.status.clone())
    }
}
