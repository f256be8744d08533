//! relightctl: command-line client of relightd's control socket.
//!
//! Exit status: 0 on success, 1 when the daemon answers with an error (or the exchange fails after
//! connecting), 2 when the command line is wrong (clap's usage error), 3 when the socket cannot
//! be reached (no daemon, wrong `--socket`, no permission).
//!
//! Every command prints a readable summary with rounded numbers; `--json` prints the daemon's
//! result as it came.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand};
use relight_daemon::config::DEFAULT_SOCKET_PATH;
use relight_daemon::control::rpc::LIGHTS_UPDATE;
use relight_daemon::control::{Client, ClientError, EngineInfo, StatusReport};
use relight_recon::estimate::LightingEstimate;
use relight_recon::sh_conventions;
use serde_json::{Map, Value, json};

#[derive(Debug, Parser)]
#[command(name = "relightctl", version, about = "Control a running relightd")]
struct Cli {
    /// The daemon's control socket (before or after the command).
    #[arg(long, global = true, value_name = "PATH", env = "RELIGHT_SOCKET", default_value = DEFAULT_SOCKET_PATH)]
    socket: PathBuf,
    /// Print the raw JSON result instead of a readable summary.
    #[arg(long, global = true)]
    json: bool,
    /// How long to wait for the daemon's answer, ms.
    #[arg(long, global = true, value_name = "N", default_value_t = 5000)]
    timeout_ms: u64,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Devices, pipeline stage timings, synchronisation and recording state.
    Status,
    /// List, switch or tune relighting engines.
    Engine {
        #[command(subcommand)]
        action: EngineAction,
    },
    /// Start or stop recording all streams to an MCAP file.
    Record {
        #[command(subcommand)]
        action: RecordAction,
    },
    /// Write the current frame set's images to the directory PATH (relative to the daemon's
    /// snapshot directory) or to that directory itself.
    Snapshot {
        path: Option<PathBuf>,
        /// Replace files that exist already (they are refused otherwise).
        #[arg(long)]
        overwrite: bool,
    },
    /// Re-read the configuration file.
    Reload,
    /// Advance a stepped replay by FRAMES frame sets (default 1): each a reference-stream frame
    /// (`[sync] reference`, depth by default) and the other streams' messages up to the next.
    Step { frames: Option<u32> },
    /// The lighting estimate: main light, SH9, extracted lights.
    Lights {
        #[command(subcommand)]
        action: LightsAction,
    },
    /// Call any JSON-RPC method; JSON is its params (an object or an array).
    Call {
        method: String,
        #[arg(value_parser = parse_json_params)]
        params: Option<Value>,
    },
}

#[derive(Debug, Subcommand)]
enum EngineAction {
    /// The registered engines.
    List,
    /// Switch to engine NAME (at the next frame boundary).
    Set { name: String },
    /// Show (default) or change the current engine's parameters.
    Params {
        #[command(subcommand)]
        action: Option<ParamsAction>,
    },
}

#[derive(Debug, Subcommand)]
enum ParamsAction {
    /// Show the current engine's parameters.
    Get,
    /// Set parameters; VALUE is read as JSON when it parses (`2.5`, `true`, `[1,2]`), else as a
    /// string.
    Set {
        #[arg(required = true, value_name = "KEY=VALUE", value_parser = parse_assignment)]
        assignments: Vec<(String, Value)>,
    },
}

#[derive(Debug, Subcommand)]
enum LightsAction {
    /// Show the current estimate (`null` with --json before the first).
    Get {
        /// Print it as JSON in a renderer's conventions instead: `unity` (SphericalHarmonicsL2
        /// coefficients `[channel][i]` and a directional light, Unity's frame and units) or
        /// `threejs` (`LightProbe.sh.fromArray` coefficients and a DirectionalLight); see
        /// docs/lighting-estimate.md.
        #[arg(long = "as", value_enum, value_name = "RENDERER")]
        renderer: Option<Renderer>,
    },
    /// Print every update as one JSON line (the first is the current estimate) until interrupted.
    Watch,
    /// Write the HDR environment the estimate comes from (equirectangular, linear RGB radiance,
    /// +y up, u from −z towards +x) as an OpenEXR file, relative to the daemon's snapshot
    /// directory (/var/lib/relightd/snapshots under the service).
    Export {
        /// The .exr file to write.
        path: PathBuf,
        /// Replace PATH if it exists (it is refused otherwise).
        #[arg(long)]
        overwrite: bool,
    },
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Renderer {
    Unity,
    Threejs,
}

#[derive(Debug, Subcommand)]
enum RecordAction {
    /// Start recording to PATH (relative to the daemon's recordings directory,
    /// /var/lib/relightd/recordings under the service), or to a new file there.
    Start {
        path: Option<PathBuf>,
        /// Replace PATH if it exists (it is refused otherwise).
        #[arg(long)]
        overwrite: bool,
    },
    /// Stop recording and show its summary.
    Stop,
}

fn parse_json_params(text: &str) -> Result<Value, String> {
    match serde_json::from_str::<Value>(text) {
        Ok(value @ (Value::Object(_) | Value::Array(_))) => Ok(value),
        Ok(_) => Err("params must be a JSON object or array".to_owned()),
        Err(err) => Err(format!("not valid JSON: {err}")),
    }
}

fn parse_assignment(text: &str) -> Result<(String, Value), String> {
    let (key, value) = relight_engines::params::parse_assignment(text)
        .ok_or_else(|| format!("expected KEY=VALUE, got {text:?}"))?;
    if key.is_empty() {
        return Err(format!("empty key in {text:?}"));
    }
    Ok((key.to_owned(), value))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let (method, params) = request(&cli.command);
    let timeout = Duration::from_millis(cli.timeout_ms);
    if matches!(
        cli.command,
        Command::Lights {
            action: LightsAction::Watch
        }
    ) {
        return exit_code(method, watch_lights(&cli.socket, timeout));
    }
    let result = Client::connect(&cli.socket, timeout)
        .and_then(|mut client| client.call(method, params))
        .map(|result| {
            let text = match &cli.command {
                Command::Lights {
                    action:
                        LightsAction::Get {
                            renderer: Some(renderer),
                        },
                } => for_renderer(*renderer, &result),
                _ if cli.json => format!("{result}\n"),
                _ => render(&cli.command, &result),
            };
            // A closed stdout (`| head`) is not the daemon's fault; nothing more to say.
            let _ = std::io::stdout().lock().write_all(text.as_bytes());
        });
    exit_code(method, result)
}

/// Subscribes to the lighting estimate and prints each `lights.update` as a JSON line. Returns
/// only on an error (the daemon went away) or when stdout is closed.
fn watch_lights(socket: &Path, timeout: Duration) -> Result<(), ClientError> {
    let mut client = Client::connect(socket, timeout)?;
    client.call("lights.subscribe", None)?;
    let mut stdout = std::io::stdout().lock();
    loop {
        let notification = match client.next_notification() {
            Ok(notification) => notification,
            // Nothing changed for a while: keep listening.
            Err(ClientError::Timeout(_)) => continue,
            Err(err) => return Err(err),
        };
        if notification.method != LIGHTS_UPDATE {
            continue;
        }
        if writeln!(stdout, "{}", notification.params)
            .and_then(|()| stdout.flush())
            .is_err()
        {
            return Ok(());
        }
    }
}

/// The socket cannot be reached; 2 is clap's usage error.
const EXIT_UNREACHABLE: u8 = 3;

/// The exit status of a finished command, after saying what went wrong.
fn exit_code(method: &str, result: Result<(), ClientError>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(ClientError::Rpc(error)) => {
            eprintln!("relightctl: {method}: {}", error.message);
            if let Some(data) = &error.data {
                eprintln!("{data:#}");
            }
            ExitCode::from(1)
        }
        Err(err @ ClientError::Connect { .. }) => {
            eprintln!("relightctl: {err}");
            ExitCode::from(EXIT_UNREACHABLE)
        }
        Err(err) => {
            eprintln!("relightctl: {method}: {err}");
            ExitCode::from(1)
        }
    }
}

/// The JSON-RPC method and params of a command.
fn request(command: &Command) -> (&str, Option<Value>) {
    match command {
        Command::Status => ("status", None),
        Command::Engine { action } => match action {
            EngineAction::List => ("engine.list", None),
            EngineAction::Set { name } => ("engine.set", Some(json!({ "name": name }))),
            EngineAction::Params {
                action: None | Some(ParamsAction::Get),
            } => ("engine.params.get", None),
            EngineAction::Params {
                action: Some(ParamsAction::Set { assignments }),
            } => {
                let params: Map<String, Value> = assignments.iter().cloned().collect();
                ("engine.params.set", Some(json!({ "params": params })))
            }
        },
        Command::Record { action } => match action {
            RecordAction::Start { path, overwrite } => {
                ("record.start", output_params(path.as_deref(), *overwrite))
            }
            RecordAction::Stop => ("record.stop", None),
        },
        Command::Snapshot { path, overwrite } => {
            ("snapshot", output_params(path.as_deref(), *overwrite))
        }
        Command::Reload => ("config.reload", None),
        Command::Step { frames } => ("replay.step", frames.map(|n| json!({ "frames": n }))),
        Command::Lights { action } => match action {
            LightsAction::Get { .. } => ("lights.get", None),
            LightsAction::Watch => ("lights.subscribe", None),
            LightsAction::Export { path, overwrite } => {
                ("lights.export", output_params(Some(path), *overwrite))
            }
        },
        Command::Call { method, params } => (method.as_str(), params.clone()),
    }
}

/// `{"path": ..., "overwrite": ...}`. A relative path is sent as it is: the daemon takes it from
/// its own output directory, which is where the service may write.
fn output_params(path: Option<&Path>, overwrite: bool) -> Option<Value> {
    let mut params = Map::new();
    if let Some(path) = path {
        params.insert("path".into(), json!(path));
    }
    if overwrite {
        params.insert("overwrite".into(), Value::Bool(true));
    }
    (!params.is_empty()).then_some(Value::Object(params))
}

/// A readable rendering of a command's result.
fn render(command: &Command, result: &Value) -> String {
    match command {
        Command::Status => match serde_json::from_value::<StatusReport>(result.clone()) {
            Ok(status) => render_status(&status),
            Err(_) => readable(result, &[]),
        },
        Command::Engine {
            action: EngineAction::List,
        } => match serde_json::from_value::<Vec<EngineInfo>>(result.clone()) {
            Ok(engines) => table(
                &["ENGINE", "DESCRIPTION"],
                &[false, false],
                engines
                    .into_iter()
                    .map(|e| vec![e.name, e.description])
                    .collect(),
            ),
            Err(_) => readable(result, &[]),
        },
        Command::Engine {
            action: EngineAction::Set { name },
        } => format!("engine set to {name}\n"),
        Command::Record {
            action: RecordAction::Start { .. },
        } => match result.get("path").and_then(Value::as_str) {
            Some(path) => format!("recording to {path}\n"),
            None => readable(result, &[]),
        },
        Command::Snapshot { .. } => match result.get("paths").and_then(Value::as_array) {
            Some(paths) => paths
                .iter()
                .map(|p| format!("{}\n", p.as_str().unwrap_or_default()))
                .collect(),
            None => readable(result, &[]),
        },
        Command::Record {
            action: RecordAction::Stop,
        } => match result.get("path").and_then(Value::as_str) {
            Some(path) => format!("stopped recording {path}\n{}", readable(result, &["path"])),
            None => readable(result, &[]),
        },
        Command::Reload => {
            let list = |key: &str| {
                let names: Vec<&str> = result
                    .get(key)
                    .and_then(Value::as_array)
                    .map(|a| a.iter().filter_map(Value::as_str).collect())
                    .unwrap_or_default();
                if names.is_empty() {
                    "nothing".to_owned()
                } else {
                    names.join(", ")
                }
            };
            format!(
                "configuration reloaded\napplied           {}\nneeds a restart   {}\n",
                list("applied"),
                list("restart_required")
            )
        }
        Command::Step { .. } => match result.get("frames").and_then(Value::as_u64) {
            Some(n) => format!("stepped {n} frame set{}\n", if n == 1 { "" } else { "s" }),
            None => readable(result, &[]),
        },
        Command::Lights {
            action: LightsAction::Export { .. },
        } => format!(
            "wrote {} ({}×{} linear RGB radiance, equirectangular)\n",
            result["path"].as_str().unwrap_or("?"),
            result["width"],
            result["height"]
        ),
        Command::Lights {
            action: LightsAction::Get { .. },
        } if result.is_null() => "no lighting estimate yet\n".to_owned(),
        Command::Lights {
            action: LightsAction::Get { .. },
        } => match serde_json::from_value::<LightingEstimate>(result.clone()) {
            Ok(estimate) => render_lights(&estimate),
            Err(_) => readable(result, &[]),
        },
        _ => readable(result, &[]),
    }
}

/// A JSON result as indented `key  value` lines with rounded numbers (floats the daemon widened
/// from f32 print as `27.3`, not `27.299999237060547`), leaving out the top-level `skip` keys.
fn readable(value: &Value, skip: &[&str]) -> String {
    fn scalar(value: &Value) -> String {
        match value {
            Value::Number(n) if n.is_f64() => round(n.as_f64().unwrap_or(f64::NAN)),
            Value::String(s) => s.clone(),
            Value::Null => "-".to_owned(),
            other => other.to_string(),
        }
    }
    fn lines(value: &Value, indent: usize, skip: &[&str], out: &mut String) {
        let entries: Vec<(String, &Value)> = match value {
            Value::Object(map) => map
                .iter()
                .filter(|(k, _)| !skip.contains(&k.as_str()))
                .map(|(k, v)| (k.clone(), v))
                .collect(),
            Value::Array(items) => items
                .iter()
                .enumerate()
                .map(|(i, v)| (format!("[{i}]"), v))
                .collect(),
            scalar_value => {
                out.push_str(&format!("{:indent$}{}\n", "", scalar(scalar_value)));
                return;
            }
        };
        let width = entries
            .iter()
            .map(|(k, _)| k.chars().count())
            .max()
            .unwrap_or(0);
        for (key, value) in entries {
            match value {
                Value::Array(items) if items.iter().all(|v| !v.is_object() && !v.is_array()) => {
                    let items: Vec<String> = items.iter().map(scalar).collect();
                    out.push_str(&format!(
                        "{:indent$}{key:<width$}  [{}]\n",
                        "",
                        items.join(", ")
                    ));
                }
                Value::Object(_) | Value::Array(_) => {
                    out.push_str(&format!("{:indent$}{key}\n", ""));
                    lines(value, indent + 2, &[], out);
                }
                _ => out.push_str(&format!("{:indent$}{key:<width$}  {}\n", "", scalar(value))),
            }
        }
    }
    let mut out = String::new();
    lines(value, 0, skip, &mut out);
    out
}

/// Six significant digits, trailing zeros dropped: enough for any parameter or timing shown.
fn round(x: f64) -> String {
    if !x.is_finite() {
        return x.to_string();
    }
    if x == 0.0 {
        return "0".to_owned();
    }
    let digits = (5 - x.abs().log10().floor() as i32).clamp(0, 12) as usize;
    let text = format!("{x:.digits$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        text
    }
}

/// `lights get --as RENDERER`: the estimate converted, as one JSON document (`null` before the
/// first estimate).
fn for_renderer(renderer: Renderer, result: &Value) -> String {
    let converted = serde_json::from_value::<Option<LightingEstimate>>(result.clone())
        .ok()
        .flatten()
        .map(|estimate| match renderer {
            Renderer::Unity => serde_json::to_value(sh_conventions::unity_lighting(&estimate)),
            Renderer::Threejs => serde_json::to_value(sh_conventions::threejs_lighting(&estimate)),
        });
    match converted {
        Some(Ok(value)) => format!("{value}\n"),
        _ => "null\n".to_owned(),
    }
}

fn render_lights(estimate: &LightingEstimate) -> String {
    let vector = |v: glam::Vec3| format!("[{:.3}, {:.3}, {:.3}]", v.x, v.y, v.z);
    let main = match &estimate.main_light {
        Some(main) => format!(
            "direction {}  colour {}  intensity {:.3} W/m²",
            vector(main.direction_in_world),
            vector(main.color),
            main.intensity
        ),
        None => "none".to_owned(),
    };
    let environment = match estimate.environment_stamp {
        Some(stamp) => format!("probe frame at {} ns (host)", stamp.host_ns),
        None => "no probe".to_owned(),
    };
    let mut out = format!(
        "main light   {main}\nenvironment  {environment}; SH9 DC {}\nall light    SH9 DC {} total, {} without the main light\nlights       {}\n",
        vector(estimate.sh9.coeffs[0]),
        vector(estimate.sh9_total.coeffs[0]),
        vector(estimate.sh9_ambient.coeffs[0]),
        estimate.lights.len()
    );
    for light in &estimate.lights {
        out.push_str(&format!(
            "  {}\n",
            serde_json::to_string(light).unwrap_or_default()
        ));
    }
    out
}

/// An engine's own report (`auto`: what it chose and why, and its candidates); other shapes
/// as JSON.
fn render_engine_status(engine: &Value) -> String {
    let Some(chosen) = engine["chosen"].as_str() else {
        return format!("engine says {engine}\n");
    };
    let number = |v: &Value, digits: usize| {
        v.as_f64()
            .map_or("-".to_owned(), |v| format!("{v:.digits$}"))
    };
    let mut out = format!(
        "auto        chose {chosen}: {}\n            predicted error {}, {} ms of {} ({}), {} switches{}\n",
        engine["reason"].as_str().unwrap_or("-"),
        number(&engine["predicted_error"], 3),
        number(&engine["predicted_ms"], 1),
        number(&engine["budget_ms"], 0),
        engine["motion"].as_str().unwrap_or("-"),
        engine["switches"].as_u64().unwrap_or(0),
        engine["probing"]
            .as_str()
            .map_or(String::new(), |p| format!(", probing {p}")),
    );
    let f = &engine["features"];
    if f.is_object() {
        out.push_str(&format!(
            "            scene: shadow {}, bleeding {}, occlusion {}, gloss {} (indirect share {}){}\n",
            number(&f["shadow"], 2),
            number(&f["bleeding"], 2),
            number(&f["occlusion"], 2),
            number(&f["glossy"], 2),
            number(&engine["indirect_share"], 2),
            if f["environment"].as_bool() == Some(true) {
                ", environment map"
            } else {
                ""
            },
        ));
    }
    for c in engine["candidates"].as_array().into_iter().flatten() {
        let cost = match (c["cost_ms"].as_f64(), c["estimated_cost_ms"].as_f64()) {
            (Some(ms), _) => format!("{ms:.1} ms"),
            (None, Some(ms)) => format!("~{ms:.0} ms (not measured)"),
            (None, None) => "not measured".to_owned(),
        };
        out.push_str(&format!(
            "              {:<24} predicted {}  {}\n",
            c["candidate"].as_str().unwrap_or("-"),
            number(&c["predicted_error"], 3),
            cost
        ));
    }
    out
}

fn render_status(status: &StatusReport) -> String {
    let recording = match &status.recording {
        Some(r) => format!("{} ({} messages)", r.path.display(), r.messages),
        None => "off".to_owned(),
    };
    let skipped = &status.frames_skipped;
    let mut out = format!(
        "engine      {} ({} frame sets not rendered)\nuptime      {}\nframe sets  {} rendered of {} ({} incomplete), {:.1} fps\nlatency     p50 {:.1} ms, p99 {:.1} ms (capture to composite)\nskipped     {} (superseded {}, discarded by the synchroniser {}, queue drops {})\nbus drops   {}\noutputs     {} dropped, {} failed\nrecording   {}\n",
        status.engine,
        status.render_errors,
        format_uptime(status.uptime_s),
        status.frames_rendered,
        status.reference_frames,
        status.sync_missing,
        status.render_fps,
        status.latency_ms.p50,
        status.latency_ms.p99,
        skipped.total,
        skipped.superseded,
        skipped.sync_discarded,
        skipped.queue_dropped,
        status.bus_drops,
        status.outputs_dropped,
        status.outputs_failed,
        recording,
    );
    if let Some(t) = &status.tracking {
        let optional =
            |v: Option<f64>, unit: &str| v.map_or("-".to_owned(), |v| format!("{v:.2} {unit}"));
        out.push_str(&format!(
            "tracking    {} ({}): pose age {}, reprojection RMS {}, {} tags; {} frame sets untracked\n",
            t.state.name(),
            t.source,
            optional(t.pose_age_ms, "ms"),
            optional(t.reprojection_rms_px, "px"),
            t.tags_used,
            t.untracked_frames,
        ));
    }
    if let Some(a) = &status.albedo {
        out.push_str(&format!(
            "albedo      {}: {} of {} surface vertices measured, {} cells skipped\n",
            if a.estimated { "measured" } else { "carried" },
            a.measured_vertices,
            a.vertices,
            a.skipped_cells,
        ));
    }
    if let Some(engine) = &status.engine_status {
        out.push_str(&render_engine_status(engine));
    }
    if let Some(live) = &status.live_view {
        let urls: Vec<&str> = [&live.foxglove, &live.page]
            .into_iter()
            .flatten()
            .map(String::as_str)
            .collect();
        out.push_str(&format!("live view   {}\n", urls.join(", ")));
    }
    if !status.devices.is_empty() {
        out.push('\n');
        out.push_str(&table(
            &[
                "DEVICE",
                "STREAM",
                "BACKEND",
                "STATE",
                "FPS",
                "FRAMES",
                "DROPS",
                "LAST ERROR",
            ],
            &[false, false, false, false, true, true, true, false],
            status
                .devices
                .iter()
                .map(|d| {
                    vec![
                        d.name.clone(),
                        d.stream.to_string(),
                        d.backend.clone(),
                        d.state.name().to_owned(),
                        format!("{:.1}", d.fps),
                        d.frames.to_string(),
                        d.drops.to_string(),
                        d.last_error.clone().unwrap_or_else(|| "-".to_owned()),
                    ]
                })
                .collect(),
        ));
    }
    if !status.stages.is_empty() {
        out.push('\n');
        out.push_str(&table(
            &["STAGE", "FRAMES", "LAST ms", "MEAN ms", "P50 ms", "P99 ms"],
            &[false, true, true, true, true, true],
            status
                .stages
                .iter()
                .map(|s| {
                    vec![
                        s.name.clone(),
                        s.frames.to_string(),
                        format!("{:.2}", s.last_ms),
                        format!("{:.2}", s.mean_ms),
                        format!("{:.2}", s.p50_ms),
                        format!("{:.2}", s.p99_ms),
                    ]
                })
                .collect(),
        ));
    }
    if !status.sync_streams.is_empty() {
        out.push('\n');
        out.push_str(&table(
            &["SYNC STREAM", "MATCHED", "MISSING", "LATE", "DROPPED"],
            &[false, true, true, true, true],
            status
                .sync_streams
                .iter()
                .map(|s| {
                    vec![
                        s.stream.name().to_owned(),
                        s.matched.to_string(),
                        s.missing.to_string(),
                        s.late.to_string(),
                        s.dropped.to_string(),
                    ]
                })
                .collect(),
        ));
    }
    out
}

fn format_uptime(uptime_s: f64) -> String {
    let total = if uptime_s.is_finite() && uptime_s > 0.0 {
        uptime_s as u64
    } else {
        0
    };
    let (h, m, s) = (total / 3600, total / 60 % 60, total % 60);
    if h > 0 {
        format!("{h}h {m:02}m {s:02}s")
    } else if m > 0 {
        format!("{m}m {s:02}s")
    } else {
        format!("{s}s")
    }
}

/// Columns padded to their widest cell; `right` right-aligns numeric columns.
fn table(headers: &[&str], right: &[bool], rows: Vec<Vec<String>>) -> String {
    let mut widths: Vec<usize> = headers.iter().map(|h| h.chars().count()).collect();
    for row in &rows {
        for (width, cell) in widths.iter_mut().zip(row) {
            *width = (*width).max(cell.chars().count());
        }
    }
    let header_row: Vec<String> = headers.iter().map(|h| (*h).to_owned()).collect();
    let mut out = String::new();
    for row in std::iter::once(&header_row).chain(&rows) {
        let cells: Vec<String> = row
            .iter()
            .zip(&widths)
            .zip(right.iter().chain(std::iter::repeat(&false)))
            .map(|((cell, &width), &right)| {
                if right {
                    format!("{cell:>width$}")
                } else {
                    format!("{cell:<width$}")
                }
            })
            .collect();
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    out
}
