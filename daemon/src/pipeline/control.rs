//! The control surface: what the control socket's requests do to the running pipeline. An
//! engine is built here, on the control thread, and handed to the render thread through the
//! [`EngineSlot`](super::render::EngineSlot); snapshots are served by the render thread between frames.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use crossbeam_channel::bounded;
use serde_json::{Map, Value, json};

use super::outputs::SnapshotRequest;
use super::render::Pending;
use super::sources::core_sync_config;
use super::{Shared, params_map, recording_path};
use crate::config::Config;
use crate::control::lights::LightsBoard;
use crate::control::types::{ControlError, ControlTarget, EngineInfo, OutputRequest, StatusReport};
use crate::lock;
use crate::sinks::exr_out::write_exr_as;
use crate::sinks::recorder::RecorderError;
use crate::sinks::safe_file::{Existing, resolve_output};
use crate::sinks::writer::WriteFailure;

/// How long a control request waits for the render thread to serve a snapshot.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(3);

fn recorder_error(error: RecorderError) -> ControlError {
    match error {
        RecorderError::Busy(message) => ControlError::busy(message),
        RecorderError::Failed(message) => ControlError::failed(message),
        RecorderError::File { ref path, .. } => ControlError::file(path, error.to_string()),
    }
}

/// A client's output path, resolved under `base` ([`resolve_output`]); a refusal is −32003.
fn resolve(requested: Option<&Path>, base: &Path) -> Result<Option<PathBuf>, ControlError> {
    requested.map(|path| resolve_one(path, base)).transpose()
}

fn resolve_one(requested: &Path, base: &Path) -> Result<PathBuf, ControlError> {
    resolve_output(requested, base).map_err(|e| ControlError::file(requested, e.to_string()))
}

/// Creates `base`, the daemon's own output directory, when `path` lies in it (a path elsewhere
/// must name a directory that exists).
fn create_base_for(path: &Path, base: &Path) -> Result<(), ControlError> {
    if path.starts_with(base) {
        std::fs::create_dir_all(base).map_err(|e| {
            ControlError::file(base, format!("cannot create {}: {e}", base.display()))
        })?;
    }
    Ok(())
}

/// The pipeline as the control socket sees it.
pub(super) struct PipelineControl {
    pub(super) shared: Arc<Shared>,
}

impl PipelineControl {
    fn build_engine(
        &self,
        name: &str,
        params: &Map<String, Value>,
    ) -> Result<Pending, ControlError> {
        let built = self
            .shared
            .registry
            .build(name, params)
            .map_err(|e| match e {
                relight_engines::registry::RegistryError::UnknownEngine { .. } => {
                    ControlError::engine_unknown(name)
                        .with_data(json!({ "known": self.shared.registry.names() }))
                }
                other => ControlError::invalid_params(other.to_string()),
            })?;
        Ok(Pending::Engine {
            engine: built.engine,
            name: name.to_owned(),
            params: built.params,
        })
    }
}

impl ControlTarget for PipelineControl {
    fn status(&self) -> StatusReport {
        super::status::report(&self.shared)
    }

    fn lights(&self) -> Option<&LightsBoard> {
        Some(&self.shared.lights)
    }

    /// Written on the control connection's own thread (a 128 × 64 map is 100 kB), never the
    /// render thread's.
    fn lights_export(&self, path: &Path, overwrite: bool) -> Result<Value, ControlError> {
        let environment = self.shared.lights.environment().ok_or_else(|| {
            ControlError::failed(
                "no HDR environment yet: the probe has not merged a bracket and the scene file has no environment map",
            )
        })?;
        let base = lock(&self.shared.config).snapshot.dir.clone();
        let path = resolve_one(path, &base)?;
        create_base_for(&path, &base)?;
        write_exr_as(
            &path,
            environment.width,
            environment.height,
            &environment.radiance,
            Existing::from_overwrite(overwrite),
        )
        .map_err(|error| ControlError::file(&path, error.to_string()))?;
        Ok(json!({
            "path": path,
            "width": environment.width,
            "height": environment.height,
        }))
    }

    fn engine_list(&self) -> Vec<EngineInfo> {
        self.shared
            .registry
            .specs()
            .iter()
            .map(|spec| EngineInfo {
                name: spec.name.to_owned(),
                description: spec.description.to_owned(),
                params_schema: serde_json::to_value(&spec.schema).unwrap_or(Value::Null),
            })
            .collect()
    }

    fn engine_set(&self, name: &str) -> Result<(), ControlError> {
        let pending = self.build_engine(name, &Map::new())?;
        *lock(&self.shared.engine.pending) = Some(pending);
        Ok(())
    }

    fn engine_params_get(&self) -> Value {
        json!({
            "engine": *lock(&self.shared.engine.name),
            "params": Value::Object(lock(&self.shared.engine.params).clone()),
        })
    }

    /// Validate against the engine that renders the next frame: the one waiting to be swapped
    /// in after an `engine.set`, if any (so `engine set X` then `params set` applies to X),
    /// else the running one.
    fn engine_params_set(&self, params: Map<String, Value>) -> Result<Value, ControlError> {
        let mut pending = lock(&self.shared.engine.pending);
        let (name, current) = match pending.as_ref() {
            Some(Pending::Engine { name, params, .. }) => (name.clone(), params.clone()),
            _ => (
                lock(&self.shared.engine.name).clone(),
                lock(&self.shared.engine.params).clone(),
            ),
        };
        let spec = self
            .shared
            .registry
            .spec(&name)
            .map_err(|e| ControlError::failed(e.to_string()))?;
        let merged = spec
            .schema
            .validate(&current, &params)
            .map_err(|e| ControlError::invalid_params(e.to_string()))?;
        match pending.as_mut() {
            Some(Pending::Engine { engine, params, .. }) => {
                engine.set_params(&merged);
                *params = merged.clone();
            }
            _ => {
                *lock(&self.shared.engine.params) = merged.clone();
                *pending = Some(Pending::Params(merged.clone()));
            }
        }
        Ok(Value::Object(merged))
    }

    fn record_start(&self, request: OutputRequest) -> Result<PathBuf, ControlError> {
        let (dir, settings) = {
            let config = lock(&self.shared.config);
            (config.recorder.dir.clone(), config.recorder.settings())
        };
        let path = resolve(request.path.as_deref(), &dir)?.unwrap_or_else(|| recording_path(&dir));
        create_base_for(&path, &dir)?;
        self.shared
            .recorder
            .start(path, Existing::from_overwrite(request.overwrite), settings)
            .map_err(recorder_error)
    }

    fn record_stop(&self) -> Result<Value, ControlError> {
        self.shared
            .recorder
            .stop_recording()
            .map_err(recorder_error)
    }

    fn snapshot(&self, request: OutputRequest) -> Result<Vec<PathBuf>, ControlError> {
        let base = lock(&self.shared.config).snapshot.dir.clone();
        let dir = resolve(request.path.as_deref(), &base)?.unwrap_or(base);
        let (reply, answer) = bounded(1);
        self.shared
            .snapshots
            .try_send(SnapshotRequest {
                dir: dir.clone(),
                existing: Existing::from_overwrite(request.overwrite),
                reply,
            })
            .map_err(|_| ControlError::busy("too many snapshots pending"))?;
        answer
            .recv_timeout(SNAPSHOT_TIMEOUT)
            .map_err(|_| {
                ControlError::failed(format!(
                    "no frame rendered within {} s; is a source running? (see `relightctl status`)",
                    SNAPSHOT_TIMEOUT.as_secs()
                ))
            })?
            .map_err(|failure| match failure {
                WriteFailure::Behind => ControlError::busy(failure.to_string()),
                WriteFailure::Io(message) => ControlError::file(&dir, message),
            })
    }

    fn replay_step(&self, frames: u32) -> Result<Value, ControlError> {
        if self.shared.steppers.is_empty() {
            return Err(ControlError::failed(
                "the source is not a stepped replay (set [replay] mode = \"stepped\")",
            ));
        }
        if !self.shared.steppers.iter().all(|s| s.step(frames)) {
            return Err(ControlError::failed("the replay has ended"));
        }
        Ok(json!({ "frames": frames }))
    }

    fn config_reload(&self) -> Result<Value, ControlError> {
        let path = lock(&self.shared.config).path.clone();
        let new = Config::load(&path).map_err(|e| {
            ControlError::invalid_params(format!("configuration not reloaded: {e}"))
        })?;
        let old = lock(&self.shared.config).clone();
        let mut applied = Vec::new();
        let mut restart_required = Vec::new();
        if new.engine != old.engine {
            let pending = self.build_engine(&new.engine.name, &params_map(&new.engine.params))?;
            *lock(&self.shared.engine.pending) = Some(pending);
            applied.push("engine");
        }
        if new.sync != old.sync {
            *lock(&self.shared.pending_sync) = Some(core_sync_config(&new.sync));
            applied.push("sync");
        }
        for (name, changed) in [
            ("recorder.dir", new.recorder.dir != old.recorder.dir),
            ("snapshot", new.snapshot != old.snapshot),
            ("output", new.output != old.output),
        ] {
            if changed {
                applied.push(name);
            }
        }
        for (name, changed) in [
            ("daemon", new.daemon != old.daemon),
            ("source", new.source != old.source),
            ("tracking", new.tracking != old.tracking),
            (
                "recorder.queue_frames",
                new.recorder.queue_frames != old.recorder.queue_frames,
            ),
        ] {
            if changed {
                restart_required.push(name);
            }
        }
        *lock(&self.shared.config) = new;
        tracing::info!(?applied, ?restart_required, "configuration reloaded");
        Ok(json!({ "applied": applied, "restart_required": restart_required }))
    }
}
