//! End to end: `relightd` on a replay configuration with a temporary socket, driven by
//! `relightctl` and by hostile raw requests; the recording it makes must read back frame-exact.

mod support;

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use relight_core::recording::{OutputMessage, RecordingReader};
use relight_core::{StreamKind, StreamMessage};
use serde_json::{Value, json};
use support::Daemon;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/demo.mcap")
}

fn start_daemon(dir: &Path) -> Daemon {
    start_daemon_with(dir, "")
}

/// The replay daemon of `start_daemon` with `extra` TOML sections appended to its config.
fn start_daemon_with(dir: &Path, extra: &str) -> Daemon {
    let socket = dir.join("control.sock");
    let config = format!(
        r#"
[daemon]
socket = "{socket}"
watchdog = false

[replay]
path = "{recording}"
mode = "realtime"
loop = true

[engine]
name = "passthrough"

[recorder]
dir = "{dir}/recordings"

[snapshot]
dir = "{dir}/snapshots"
{extra}
"#,
        socket = socket.display(),
        recording = fixture().display(),
        dir = dir.display(),
    );
    support::start(dir, &config, socket, "warn", &[])
}

fn ctl(socket: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .arg("--socket")
        .arg(socket)
        .args(args)
        .output()
        .expect("relightctl runs")
}

fn ctl_json(socket: &Path, args: &[&str]) -> Value {
    let mut full = vec!["--json"];
    full.extend_from_slice(args);
    let out = ctl(socket, &full);
    assert!(
        out.status.success(),
        "relightctl {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("relightctl --json prints JSON")
}

/// Send raw bytes on a fresh connection and read one response line.
fn raw(socket: &Path, bytes: &[u8]) -> Value {
    let line = raw_line(socket, bytes);
    serde_json::from_str(&line).unwrap_or_else(|e| panic!("bad response {line:?}: {e}"))
}

/// [`raw`]'s response line as text.
fn raw_line(socket: &Path, bytes: &[u8]) -> String {
    let mut stream = UnixStream::connect(socket).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    stream.write_all(bytes).unwrap();
    let mut line = String::new();
    BufReader::new(stream).read_line(&mut line).unwrap();
    line
}

fn wait_for(socket: &Path, what: &str, mut ok: impl FnMut(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let status = ctl_json(socket, &["status"]);
        if ok(&status) {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {status}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn daemon_serves_control_requests_survives_hostile_ones_and_records_frame_exact() {
    let dir = tempfile::tempdir().unwrap();
    let daemon = start_daemon(dir.path());
    let socket = daemon.socket.clone();

    // Status: the replay device runs and frame sets flow through the pipeline.
    let status = wait_for(&socket, "frame sets and sync counters", |s| {
        s["frame_sets"].as_u64() > Some(5)
            && s["sync_streams"].as_array().is_some_and(|a| !a.is_empty())
    });
    assert_eq!(status["engine"], "passthrough");
    let devices = status["devices"].as_array().unwrap();
    assert!(
        devices
            .iter()
            .any(|d| d["backend"] == "replay" && d["state"] == "running"),
        "{status}"
    );
    let stages: Vec<&str> = status["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert!(
        stages.contains(&"queue") && stages.contains(&"render"),
        "{stages:?}"
    );
    let sync = status["sync_streams"].as_array().unwrap();
    assert_eq!(sync.len(), 5, "{status}");
    assert!(
        sync.iter().all(|s| s["matched"].as_u64() > Some(0)),
        "{status}"
    );
    let readable = ctl(&socket, &["status"]);
    assert!(readable.status.success());
    assert!(String::from_utf8_lossy(&readable.stdout).contains("replay"));

    // Engines: list, switch at a frame boundary, refuse unknown names and bad parameters.
    let engines = ctl_json(&socket, &["engine", "list"]);
    let names: Vec<&str> = engines
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "passthrough",
            "depth_preview",
            "differential",
            "dlpv",
            "dvct",
            "dir",
            "ibl",
            "auto",
            "pt"
        ]
    );
    let unknown = ctl(&socket, &["engine", "set", "dlvp"]);
    assert_eq!(unknown.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&unknown.stderr).contains("passthrough"),
        "lists known engines"
    );
    ctl_json(&socket, &["engine", "set", "depth_preview"]);
    wait_for(&socket, "engine switch", |s| s["engine"] == "depth_preview");
    let params = ctl_json(&socket, &["engine", "params", "set", "opacity=0.25"]);
    assert_eq!(params["opacity"], 0.25);
    let bad = ctl(&socket, &["engine", "params", "set", "opacity=5"]);
    assert_eq!(bad.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("outside"));

    // Record about a second of the replay.
    let recording = dir.path().join("e2e.mcap");
    ctl_json(&socket, &["record", "start", recording.to_str().unwrap()]);
    let again = ctl(&socket, &["record", "start", recording.to_str().unwrap()]);
    assert_eq!(again.status.code(), Some(1), "a second start is refused");
    std::thread::sleep(Duration::from_millis(1200));
    let summary = ctl_json(&socket, &["record", "stop"]);
    assert!(summary["messages"].as_u64().unwrap() > 10, "{summary}");

    // Snapshot.
    let snap_dir = dir.path().join("snap");
    let snap = ctl_json(&socket, &["snapshot", snap_dir.to_str().unwrap()]);
    let paths = snap["paths"].as_array().unwrap_or_else(|| panic!("{snap}"));
    assert!(!paths.is_empty());
    for path in paths {
        let bytes = std::fs::read(path.as_str().unwrap()).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
    }

    let code = |v: &Value| v["error"]["code"].as_i64();

    // Unsafe writes: nothing is overwritten or created through a link unless asked for, and
    // relative paths land in the recordings directory.
    let rpc = |request: Value| {
        let mut line = request.to_string().into_bytes();
        line.push(b'\n');
        raw(&socket, &line)
    };
    let record = |params: Value| {
        let started =
            rpc(json!({"jsonrpc": "2.0", "id": 1, "method": "record.start", "params": params}));
        if started.get("result").is_some() {
            rpc(json!({"jsonrpc": "2.0", "id": 2, "method": "record.stop"}));
        }
        started
    };
    let taken = dir.path().join("taken.mcap");
    std::fs::write(&taken, b"keep").unwrap();
    let refused = record(json!({"path": taken}));
    assert_eq!(code(&refused), Some(-32003), "{refused}");
    assert_eq!(refused["error"]["data"]["path"], json!(taken), "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("exists"),
        "{refused}"
    );
    assert_eq!(std::fs::read(&taken).unwrap(), b"keep");
    let replaced = record(json!({"path": taken, "overwrite": true}));
    assert!(replaced.get("result").is_some(), "{replaced}");
    assert_ne!(std::fs::read(&taken).unwrap(), b"keep");
    let dangling = dir.path().join("dangling.mcap");
    let target = dir.path().join("target.mcap");
    std::os::unix::fs::symlink(&target, &dangling).unwrap();
    assert_eq!(code(&record(json!({"path": dangling}))), Some(-32003));
    assert!(!target.exists(), "a dangling link's target is not created");
    let relative = record(json!({"path": "relative.mcap"}));
    assert_eq!(
        relative["result"]["path"],
        json!(dir.path().join("recordings/relative.mcap")),
        "{relative}"
    );
    assert_eq!(code(&record(json!({"path": "../up.mcap"}))), Some(-32003));
    assert!(!dir.path().join("up.mcap").exists());
    assert_eq!(code(&record(json!({"path": "a\nb.mcap"}))), Some(-32602));
    let exact = raw_line(
        &socket,
        b"{\"jsonrpc\":\"2.0\",\"id\":18446744073709551616,\"method\":\"rpc.ping\"}\n",
    );
    assert!(exact.contains("\"id\":18446744073709551616"), "{exact}");

    // Hostile requests: each gets the proper JSON-RPC error and the daemon keeps serving.
    assert_eq!(code(&raw(&socket, b"{not json\n")), Some(-32700));
    assert_eq!(code(&raw(&socket, b"42\n")), Some(-32600));
    assert_eq!(
        code(&raw(
            &socket,
            b"{\"jsonrpc\":\"1.0\",\"id\":1,\"method\":\"status\"}\n"
        )),
        Some(-32600)
    );
    let unknown = raw(
        &socket,
        b"{\"jsonrpc\":\"2.0\",\"id\":2,\"method\":\"reboot\"}\n",
    );
    assert_eq!(code(&unknown), Some(-32601));
    assert_eq!(unknown["id"], 2);
    let wrong_type = raw(
        &socket,
        b"{\"jsonrpc\":\"2.0\",\"id\":3,\"method\":\"engine.set\",\"params\":{\"name\":7}}\n",
    );
    assert_eq!(code(&wrong_type), Some(-32602));
    assert_eq!(code(&raw(&socket, b"\xff\xfe\n")), Some(-32700));
    let mut huge = vec![b'['; 200_000];
    huge.push(b'\n');
    assert_eq!(code(&raw(&socket, &huge)), Some(-32600));
    let batch = raw(
        &socket,
        json!([{"jsonrpc": "2.0", "id": 1, "method": "rpc.ping"}, {"jsonrpc": "2.0", "id": 2, "method": "nope"}])
            .to_string()
            .as_bytes()
            .iter()
            .chain(b"\n")
            .copied()
            .collect::<Vec<u8>>()
            .as_slice(),
    );
    let batch = batch.as_array().expect("batch answered with an array");
    assert_eq!(batch.len(), 2);
    // A client that disconnects mid-request does not hurt.
    {
        let mut stream = UnixStream::connect(&socket).unwrap();
        stream
            .write_all(b"{\"jsonrpc\":\"2.0\",\"id\":1,\"meth")
            .unwrap();
    }
    let alive = wait_for(&socket, "progress after hostile requests", |s| {
        s["frame_sets"].as_u64() > status["frame_sets"].as_u64()
    });
    assert_eq!(alive["engine"], "depth_preview");

    // SIGTERM: a clean exit that removes the socket.
    let mut daemon = daemon;
    send_sigterm(daemon.child.id());
    let deadline = Instant::now() + Duration::from_secs(15);
    let exit = loop {
        if let Some(exit) = daemon.child.try_wait().unwrap() {
            break exit;
        }
        assert!(
            Instant::now() < deadline,
            "relightd did not stop on SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(exit.success(), "{exit:?}");
    assert!(!socket.exists(), "socket removed on exit");

    assert_recording_is_frame_exact(&recording);
}

fn send_sigterm(pid: u32) {
    let status = Command::new("kill")
        .arg("-TERM")
        .arg(pid.to_string())
        .status()
        .unwrap();
    assert!(status.success());
}

/// Every recorded message equals the fixture's message of the same stream and device time
/// (the replay re-stamps the host clock and continues sequence numbers across loops), and no
/// stream has a gap in its sequence numbers.
fn assert_recording_is_frame_exact(recording: &Path) {
    let source = RecordingReader::open(&fixture()).unwrap();
    let mut by_device_time: HashMap<(StreamKind, u64), StreamMessage> = HashMap::new();
    let mut per_stream: HashMap<StreamKind, u64> = HashMap::new();
    for msg in source.messages() {
        let msg = msg.unwrap();
        *per_stream.entry(msg.kind()).or_default() += 1;
        by_device_time.insert((msg.kind(), msg.stamp().device_ns), msg);
    }
    let recorded = RecordingReader::open(recording).unwrap();
    assert!(recorded.warnings().is_empty(), "{:?}", recorded.warnings());
    assert_eq!(
        recorded.meta().calibration,
        source.meta().calibration,
        "calibration carried over"
    );
    let mut last_seq: HashMap<StreamKind, u64> = HashMap::new();
    let mut count = 0;
    for msg in recorded.messages() {
        let msg = msg.unwrap();
        count += 1;
        let original = by_device_time
            .get(&(msg.kind(), msg.stamp().device_ns))
            .unwrap_or_else(|| {
                panic!(
                    "{} frame at device time {} not in the fixture",
                    msg.kind(),
                    msg.stamp().device_ns
                )
            });
        let n = per_stream[&msg.kind()];
        assert_eq!(msg.seq() % n, original.seq() % n);
        assert!(
            msg.payload_eq(original),
            "{} seq {} differs",
            msg.kind(),
            msg.seq()
        );
        if let Some(prev) = last_seq.insert(msg.kind(), msg.seq()) {
            assert_eq!(msg.seq(), prev + 1, "{} lost frames", msg.kind());
        }
    }
    assert!(count > 10);
}

/// Live engine switching on the bundled recording with a scene: passthrough → differential →
/// dlpv → dvct → dir (small settings so lavapipe keeps up), each built off the render thread and swapped
/// between frames, every frame set rendered without an error.
#[test]
fn gpu_engines_switch_live_while_replaying() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/desk_box");
    let daemon = start_daemon_with(
        dir.path(),
        &format!("[scene]\ndir = \"{}\"\ndepth_stride = 4\n", scene.display()),
    );
    let socket = daemon.socket.clone();
    for (engine, params) in [
        ("differential", vec!["rsm_size=128"]),
        ("dlpv", vec!["rsm_size=64", "volume_size=8", "steps=4"]),
        ("dvct", vec!["rsm_size=64", "volume_size=16"]),
        (
            "dir",
            vec!["rsm_size=64", "vpl_count=32", "ism_points=2048"],
        ),
        ("ibl", vec!["rsm_size=64", "map_size=16", "env_lights=4"]),
        ("pt", vec!["spp=1", "bounces=2"]),
        ("auto", vec!["budget_ms=20"]),
    ] {
        let out = ctl(&socket, &["engine", "set", engine]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let mut args = vec!["engine", "params", "set"];
        args.extend(params.iter().copied());
        let out = ctl(&socket, &args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let start = ctl_json(&socket, &["status"])["frame_sets"]
            .as_u64()
            .unwrap();
        let status = wait_for(&socket, &format!("{engine} rendering"), |s| {
            s["engine"] == engine && s["frame_sets"].as_u64().unwrap() >= start + 3
        });
        assert_eq!(status["render_errors"], 0, "{status}");
        let stages: Vec<String> = status["stages"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["name"].as_str().unwrap_or_default().to_owned())
            .collect();
        assert!(stages.iter().any(|s| s == "scene"), "{stages:?}");
        // The depth stage's parts, on the GPU or on the CPU.
        assert!(
            stages
                .iter()
                .any(|s| s == "depth.recon upload" || s == "depth.cpu filter"),
            "{stages:?}"
        );
        if engine == "auto" {
            // What it chose and why, in status and as relightctl prints it.
            let report = &status["engine_status"];
            assert!(report["chosen"].is_string(), "{status}");
            assert!(report["features"].is_object(), "{status}");
            let out = ctl(&socket, &["status"]);
            let text = String::from_utf8_lossy(&out.stdout);
            assert!(text.contains("auto        chose"), "{text}");
        } else {
            assert!(status["engine_status"].is_null(), "{status}");
        }
    }
}

/// `relightd record` killed with SIGKILL mid-write leaves a file without summary or footer (the
/// reference Python reader rejects it); `recording check` says it is damaged, `recording repair`
/// copies every message relight can read into a complete file, and the reference Python `mcap`
/// reader (tests/helpers/mcap_check.py) reads that copy with the same message count.
#[test]
fn a_recording_cut_by_sigkill_is_repaired_into_one_the_reference_reader_reads() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("relightd.toml");
    std::fs::write(
        &config,
        format!(
            "[daemon]\nsocket = \"{}/control.sock\"\nwatchdog = false\n\n[replay]\npath = \"{}\"\nmode = \"fast\"\nloop = true\n",
            dir.path().display(),
            fixture().display()
        ),
    )
    .unwrap();
    let relightd = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_relightd"))
            .arg("--config")
            .arg(&config)
            .args(args)
            .env("RELIGHT_LOG", "warn")
            .output()
            .expect("relightd runs")
    };
    let cut = dir.path().join("cut.mcap");
    let mut recorder = Daemon {
        child: Command::new(env!("CARGO_BIN_EXE_relightd"))
            .arg("--config")
            .arg(&config)
            .args(["record", "--out"])
            .arg(&cut)
            .env("RELIGHT_LOG", "warn")
            .stdout(std::process::Stdio::null())
            .spawn()
            .expect("relightd record starts"),
        socket: dir.path().join("control.sock"),
    };
    // Several chunks on disk, with the writer still going.
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::fs::metadata(&cut).map_or(0, |m| m.len()) < 4 << 20 {
        assert!(
            recorder.child.try_wait().unwrap().is_none(),
            "relightd record exited early"
        );
        assert!(Instant::now() < deadline, "the recording never grew");
        std::thread::sleep(Duration::from_millis(20));
    }
    recorder.child.kill().unwrap();
    recorder.child.wait().unwrap();

    let inspect = |file: &Path| {
        let out = relightd(&["recording", "check", "--json", file.to_str().unwrap()]);
        let report: Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
        let total: u64 = report["messages"]
            .as_object()
            .unwrap()
            .values()
            .map(|n| n.as_u64().unwrap())
            .sum::<u64>()
            + report["truth_messages"].as_u64().unwrap();
        (out.status.code(), report, total)
    };
    let (code, report, cut_messages) = inspect(&cut);
    assert_eq!(code, Some(1), "a cut file is damaged: {report}");
    assert_eq!(report["has_summary"], false, "{report}");
    assert!(cut_messages > 10, "{report}");

    let repaired = dir.path().join("repaired.mcap");
    let out = relightd(&[
        "recording",
        "repair",
        cut.to_str().unwrap(),
        repaired.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (code, report, repaired_messages) = inspect(&repaired);
    assert_eq!(code, Some(0), "the copy is whole: {report}");
    assert_eq!(repaired_messages, cut_messages);

    if std::env::var("RELIGHT_SKIP_PYTHON_INTEROP").is_ok_and(|v| v == "1") {
        eprintln!("RELIGHT_SKIP_PYTHON_INTEROP=1: skipping the reference reader");
        return;
    }
    let helper = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/helpers/mcap_check.py");
    let out = Command::new("python3")
        .arg(&helper)
        .arg(&repaired)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "the reference reader rejects the repaired file: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let seen: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(seen["message_count"], seen["statistics_message_count"]);
    // The stream messages; frame_info, camera_info and /tf travel beside them.
    let streams: u64 = seen["channels"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| {
            StreamKind::ALL
                .iter()
                .any(|&kind| c["topic"] == relight_core::recording::topic(kind))
        })
        .map(|c| c["message_count"].as_u64().unwrap())
        .sum();
    assert_eq!(streams, repaired_messages, "{seen}");
}

/// `[recorder] color_encoding = "jpeg"` and `outputs = true`: the colour goes in compressed,
/// and every rendered frame's composite and Δ, and the lighting estimate, go in beside it.
#[test]
fn a_recording_takes_compressed_colour_and_what_was_rendered() {
    let dir = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let config = dir.path().join("relightd.toml");
    std::fs::write(
        &config,
        format!(
            "[daemon]\nsocket = \"{dir}/control.sock\"\nwatchdog = false\n\n\
             [replay]\npath = \"{fixture}\"\nmode = \"fast\"\n\n\
             [engine]\nname = \"differential\"\n\n\
             [scene]\ndir = \"{scene}\"\ndepth_stride = 4\n\n\
             [recorder]\ncolor_encoding = \"jpeg\"\njpeg_quality = 80\noutputs = true\n",
            dir = dir.path().display(),
            fixture = fixture().display(),
            scene = root.join("tests/scenes/desk_box").display(),
        ),
    )
    .unwrap();
    let out_path = dir.path().join("out.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_relightd"))
        .arg("--config")
        .arg(&config)
        .args(["record", "--seconds", "6", "--out"])
        .arg(&out_path)
        .env("RELIGHT_LOG", "warn")
        .output()
        .expect("relightd record runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let reader = RecordingReader::open(&out_path).unwrap();
    assert_eq!(reader.format_version(), Some("2"));
    assert!(
        reader
            .topics()
            .contains(&"/color/image_raw/compressed".to_owned()),
        "{:?}",
        reader.topics()
    );
    let messages: Vec<StreamMessage> = reader.messages().collect::<Result<_, _>>().unwrap();
    let colours: Vec<_> = messages
        .iter()
        .filter_map(|m| match m {
            StreamMessage::Color(f) => Some(f),
            _ => None,
        })
        .collect();
    assert!(!colours.is_empty());
    for colour in &colours {
        assert_eq!(
            (colour.payload.width(), colour.payload.height()),
            (320, 240)
        );
        assert_eq!(colour.payload.format(), relight_core::PixelFormat::Rgb8);
    }

    let outputs: Vec<OutputMessage> = reader.outputs().collect::<Result<_, _>>().unwrap();
    let composites: Vec<_> = outputs
        .iter()
        .filter_map(|o| match o {
            OutputMessage::Composite(f) => Some(f),
            _ => None,
        })
        .collect();
    let deltas = outputs
        .iter()
        .filter(|o| matches!(o, OutputMessage::Delta(_)))
        .count();
    assert!(!composites.is_empty(), "no composite recorded");
    assert_eq!(deltas, composites.len(), "a Δ beside each composite");
    for composite in &composites {
        assert_eq!(
            (composite.payload.width(), composite.payload.height()),
            (320, 240)
        );
    }
    // A composite carries its frame set's stamp, the reference (depth) frame's; sets from
    // before the recording started may still be rendered after it.
    let depth_stamps: Vec<u64> = messages
        .iter()
        .filter(|m| m.kind() == StreamKind::Depth)
        .map(|m| m.stamp().host_ns)
        .collect();
    let first_depth = depth_stamps.iter().min().copied().unwrap();
    for composite in composites.iter().filter(|c| c.stamp.host_ns >= first_depth) {
        assert!(
            depth_stamps.contains(&composite.stamp.host_ns),
            "composite at {} is no recorded depth frame's",
            composite.stamp.host_ns
        );
    }
    let estimate = outputs
        .iter()
        .find_map(|o| match o {
            OutputMessage::Lighting(f) => Some(f),
            _ => None,
        })
        .expect("the probe's lighting estimate recorded");
    let json: Value = serde_json::from_str(&estimate.payload).unwrap();
    assert!(json["sh9_total"].is_array(), "{json}");
}

/// `relightd replay --tracking scene` registers the camera by the scene file's pose (a tripod)
/// although the recording's calibration knows the marker board, which it would use otherwise.
#[test]
fn replay_takes_the_tracking_source_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let replay = |tracking: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_relightd"))
            .args(["--config", "/dev/null", "replay"])
            .arg(fixture())
            .args(["--mode", "fast", "--engine", "passthrough", "--socket"])
            .arg(dir.path().join("control.sock"))
            .args(tracking)
            .env("RUST_LOG", "info")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(
            out.status.success() && stdout.contains("rendered 60 of 60 frame sets"),
            "{stdout}\n{stderr}"
        );
        stderr
    };
    assert!(replay(&[]).contains(r#"camera tracking source="markers""#));
    assert!(replay(&["--tracking", "scene"]).contains(r#"camera tracking source="scene""#));
}

/// `relightd replay --live-config` takes the live settings (`[tracking]`, `[scene]`, `[sync]`)
/// from a configuration file, the command line's `--tracking` still wins, and a bad file is
/// refused with its line before anything runs.
#[test]
fn replay_takes_live_settings_from_a_configuration_file() {
    let dir = tempfile::tempdir().unwrap();
    let live = dir.path().join("live.toml");
    let replay = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_relightd"))
            .args(["--config", "/dev/null", "replay"])
            .arg(fixture())
            .args(["--mode", "fast", "--engine", "passthrough", "--socket"])
            .arg(dir.path().join("control.sock"))
            .arg("--live-config")
            .arg(&live)
            .args(extra)
            .env("RUST_LOG", "info")
            .output()
            .unwrap()
    };
    let tracked_by = |extra: &[&str]| {
        let out = replay(extra);
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{stderr}");
        stderr
    };
    std::fs::write(&live, "[tracking]\nsource = \"scene\"\n").unwrap();
    assert!(tracked_by(&[]).contains(r#"camera tracking source="scene""#));
    assert!(tracked_by(&["--tracking", "markers"]).contains(r#"camera tracking source="markers""#));
    std::fs::write(&live, "[scene]\ndepth_stride = 99\n").unwrap();
    let refused = replay(&[]);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success()
            && stderr.contains("live.toml:2")
            && stderr.contains("depth_stride"),
        "{stderr}"
    );
}

/// `relightd replay --param name=value` sets the engine's parameters as a configuration's
/// `[engine.params]` would, checked against its schema before anything runs.
#[test]
fn replay_refuses_an_engine_parameter_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_relightd"))
        .args(["--config", "/dev/null", "replay"])
        .arg(fixture())
        .args(["--mode", "fast", "--engine", "dvct", "--socket"])
        .arg(dir.path().join("control.sock"))
        .args(["--param", "trace_stride=9"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("trace_stride") && stderr.contains("[1, 4]"),
        "{stderr}"
    );
}
