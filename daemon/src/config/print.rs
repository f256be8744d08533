//! A [`Config`] written back as a configuration file: what `check-config` prints, so a user sees
//! every default and every resolved path in the form they would write them. Parsing the printed
//! text yields the same `Config` (tested as a property in `tests/config_errors.rs`).
//!
//! Paths are printed as resolved (relative ones already joined to the file's directory), so the
//! text means the same wherever it is saved; non-UTF-8 bytes in a path are replaced (`U+FFFD`).

use std::path::Path;
use std::time::Duration;

use relight_engines::live_scene::{LightSource, RealGeometry};
use toml::{Table, Value};

use super::{Config, GroupSpec, ImageEncoding, SourceConfig};

fn path(p: &Path) -> Value {
    Value::String(p.to_string_lossy().into_owned())
}

/// Milliseconds to the nanosecond, as `[sync]` and `[tracking]` write them.
fn ms(d: Duration) -> Value {
    Value::Float(d.as_nanos() as f64 / 1e6)
}

fn integer(n: impl TryInto<i64>) -> Value {
    // Every count in a Config was checked against a maximum far below i64::MAX.
    Value::Integer(n.try_into().unwrap_or(i64::MAX))
}

/// A JSON object that was a TOML table when it was read (engine params, device and `[sim]`
/// settings), back as one.
fn table_from_json(json: &serde_json::Value) -> Table {
    Table::try_from(json).unwrap_or_default()
}

fn section(entries: impl IntoIterator<Item = (&'static str, Option<Value>)>) -> Value {
    Value::Table(
        entries
            .into_iter()
            .filter_map(|(key, value)| Some((key.to_owned(), value?)))
            .collect(),
    )
}

impl Config {
    /// The configuration as TOML text that [`Config::parse`] reads back to `self` (its `path`
    /// aside).
    pub fn to_toml(&self) -> String {
        let mut file = Table::new();
        let daemon = &self.daemon;
        file.insert(
            "daemon".into(),
            section([
                ("socket", Some(path(&daemon.socket))),
                (
                    "socket_mode",
                    Some(Value::String(format!("{:04o}", daemon.socket_mode))),
                ),
                (
                    "socket_group",
                    daemon.socket_group.as_ref().map(|group| match group {
                        GroupSpec::Name(name) => Value::String(name.clone()),
                        GroupSpec::Gid(gid) => integer(*gid),
                    }),
                ),
                ("max_request_bytes", Some(integer(daemon.max_request_bytes))),
                ("watchdog", Some(Value::Boolean(daemon.watchdog))),
            ]),
        );
        match &self.source {
            SourceConfig::Replay(replay) => {
                file.insert(
                    "replay".into(),
                    section([
                        ("path", Some(path(&replay.path))),
                        ("mode", Some(Value::String(replay.mode.name().into()))),
                        ("loop", Some(Value::Boolean(replay.loop_playback))),
                        ("speed", Some(Value::Float(replay.speed))),
                        (
                            "topics",
                            (!replay.topics.is_empty()).then(|| {
                                Value::Table(
                                    replay
                                        .topics
                                        .iter()
                                        .map(|(stream, topic)| {
                                            (stream.name().to_owned(), Value::String(topic.clone()))
                                        })
                                        .collect(),
                                )
                            }),
                        ),
                    ]),
                );
            }
            SourceConfig::Sim(sim) => {
                file.insert("sim".into(), Value::Table(table_from_json(&sim.settings)));
            }
            SourceConfig::Devices(devices) => {
                for (stream, device) in devices {
                    let mut table = table_from_json(&device.settings);
                    table.insert(
                        "backend".into(),
                        Value::String(device.backend.name().into()),
                    );
                    file.insert(stream.name().into(), Value::Table(table));
                }
            }
        }
        let sync = &self.sync;
        file.insert(
            "sync".into(),
            section([
                ("tolerance_ms", Some(ms(sync.tolerance))),
                ("max_wait_ms", Some(ms(sync.max_wait))),
                (
                    "streams",
                    Some(Value::Array(
                        sync.streams
                            .iter()
                            .map(|s| Value::String(s.name().into()))
                            .collect(),
                    )),
                ),
                (
                    "reference",
                    Some(Value::String(sync.reference.name().into())),
                ),
            ]),
        );
        file.insert(
            "engine".into(),
            section([
                ("name", Some(Value::String(self.engine.name.clone()))),
                (
                    "params",
                    Some(Value::Table(table_from_json(&self.engine.params))),
                ),
            ]),
        );
        let scene = &self.scene;
        let word = |s: &str| Some(Value::String(s.into()));
        file.insert(
            "scene".into(),
            section([
                ("dir", scene.dir.as_deref().map(path)),
                (
                    "real",
                    word(match scene.real {
                        RealGeometry::Depth => "depth",
                        RealGeometry::Scene => "scene",
                    }),
                ),
                // Exactly the f32 held, so that reading it back rounds to the same f32.
                (
                    "real_albedo",
                    Some(Value::Float(f64::from(scene.real_albedo))),
                ),
                (
                    "albedo",
                    word(if scene.measure_albedo {
                        "measured"
                    } else {
                        "fixed"
                    }),
                ),
                ("albedo_every", Some(integer(scene.albedo_every))),
                ("depth_stride", Some(integer(scene.depth_stride))),
                (
                    "lighting",
                    word(match scene.lighting {
                        LightSource::Scene => "scene",
                        LightSource::Probe => "probe",
                    }),
                ),
                ("depth_filter", Some(Value::Boolean(scene.depth_filter))),
                ("probe_lights", Some(integer(scene.probe_lights))),
            ]),
        );
        file.insert(
            "recorder".into(),
            section([
                ("dir", Some(path(&self.recorder.dir))),
                ("autostart", Some(Value::Boolean(self.recorder.autostart))),
                ("queue_frames", Some(integer(self.recorder.queue_frames))),
            ]),
        );
        file.insert(
            "snapshot".into(),
            section([("dir", Some(path(&self.snapshot.dir)))]),
        );
        file.insert(
            "output".into(),
            section([
                ("dir", self.output.dir.as_deref().map(path)),
                ("every_n", Some(integer(self.output.every_n))),
            ]),
        );
        file.insert(
            "rig".into(),
            section([(
                "calibration",
                self.rig.calibration_path.as_deref().map(path),
            )]),
        );
        let tracking = &self.tracking;
        file.insert(
            "tracking".into(),
            section([
                (
                    "source",
                    tracking.source.map(|s| Value::String(s.name().into())),
                ),
                ("max_age_ms", Some(ms(tracking.max_age))),
                ("max_rms_px", Some(Value::Float(tracking.max_rms_px))),
                (
                    "board",
                    tracking
                        .board
                        .as_ref()
                        .and_then(|b| Value::try_from(b).ok()),
                ),
                ("smoothing", Value::try_from(tracking.smoothing).ok()),
            ]),
        );
        let live = &self.live_view;
        file.insert(
            "live_view".into(),
            section([
                ("bind", live.foxglove.map(|a| Value::String(a.to_string()))),
                ("page", live.page.map(|a| Value::String(a.to_string()))),
                (
                    "image",
                    Some(Value::String(
                        match live.image {
                            ImageEncoding::Jpeg => "jpeg",
                            ImageEncoding::Raw => "raw",
                        }
                        .into(),
                    )),
                ),
                ("jpeg_quality", Some(integer(live.jpeg_quality))),
                ("max_rate_hz", Some(Value::Float(live.max_rate_hz))),
            ]),
        );
        toml::to_string(&file).expect("a table of strings, numbers, booleans and tables")
    }
}
