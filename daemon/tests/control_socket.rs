//! The control socket end to end: a real Unix socket in a temp dir, a fake pipeline behind it.

use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Barrier, Mutex};
use std::time::Duration;

use relight_core::StreamKind;
use relight_daemon::control::{
    AlbedoStatus, Client, ClientError, ControlError, ControlServer, ControlServerHandle,
    ControlTarget, DeviceState, DeviceStatus, EngineInfo, FramesSkipped, LightsBoard,
    LiveViewStatus, OutputRequest, PeerCred, Percentiles, RecordingStatus, ServerError,
    ServerOptions, StageTiming, StatusReport, SyncStreamStatus, TrackingStatus, codes,
    peer_allowed,
};
use relight_daemon::pipeline::tracking::TrackingState;
use serde_json::{Map, Value, json};

const TIMEOUT: Duration = Duration::from_secs(10);

/// A pipeline stand-in that remembers what it was asked.
#[derive(Default)]
struct FakePipeline {
    calls: Mutex<Vec<String>>,
    engine: Mutex<String>,
    params: Mutex<Map<String, Value>>,
    recording: Mutex<Option<PathBuf>>,
    lights: LightsBoard,
}

impl FakePipeline {
    fn log(&self, call: String) {
        self.calls.lock().expect("calls lock").push(call);
    }

    fn calls(&self) -> Vec<String> {
        self.calls.lock().expect("calls lock").clone()
    }
}

fn sample_status(engine: &str, recording: Option<PathBuf>) -> StatusReport {
    StatusReport {
        uptime_s: 3725.5,
        engine: engine.to_owned(),
        devices: vec![DeviceStatus {
            name: "kinect".into(),
            stream: StreamKind::Depth,
            backend: "freenect".into(),
            state: DeviceState::Lost,
            fps: 29.97,
            frames: 1200,
            drops: 3,
            last_error: Some("usb transfer failed".into()),
        }],
        stages: vec![StageTiming {
            name: "recon".into(),
            frames: 1190,
            last_ms: 4.25,
            mean_ms: 4.0,
            p50_ms: 3.9,
            p99_ms: 7.5,
        }],
        frame_sets: 1190,
        reference_frames: 1200,
        frames_rendered: 1190,
        frames_skipped: FramesSkipped {
            total: 10,
            superseded: 10,
            sync_discarded: 0,
            queue_dropped: 0,
        },
        latency_ms: Percentiles {
            p50: 41.0,
            p99: 67.5,
        },
        render_fps: 29.5,
        outputs_dropped: 0,
        outputs_failed: 0,
        sync_missing: 10,
        sync_streams: vec![SyncStreamStatus {
            stream: StreamKind::Depth,
            matched: 1190,
            missing: 0,
            late: 2,
            dropped: 0,
        }],
        bus_drops: 2,
        render_errors: 0,
        recording: recording.map(|path| RecordingStatus { path, messages: 77 }),
        tracking: Some(TrackingStatus {
            source: "markers".into(),
            state: TrackingState::Held,
            pose_age_ms: Some(66.7),
            reprojection_rms_px: Some(0.12),
            tags_used: 9,
            world_from_camera: Some(relight_core::Pose::IDENTITY),
            untracked_frames: 4,
        }),
        albedo: Some(AlbedoStatus {
            estimated: true,
            measured_vertices: 3667,
            vertices: 4494,
            skipped_cells: 827,
        }),
        live_view: Some(LiveViewStatus {
            foxglove: Some("ws://127.0.0.1:8765".into()),
            page: Some("http://127.0.0.1:8080/".into()),
        }),
        engine_status: Some(json!({ "chosen": "dir vpl_count=64", "predicted_error": 0.2 })),
    }
}

impl ControlTarget for FakePipeline {
    fn status(&self) -> StatusReport {
        self.log("status".into());
        sample_status(
            &self.engine.lock().expect("engine lock"),
            self.recording.lock().expect("recording lock").clone(),
        )
    }

    fn engine_list(&self) -> Vec<EngineInfo> {
        self.log("engine_list".into());
        vec![
            EngineInfo {
                name: "passthrough".into(),
                description: "shows the color image".into(),
                params_schema: json!({ "type": "object" }),
            },
            EngineInfo {
                name: "dlpv".into(),
                description: "differential light propagation volumes".into(),
                params_schema: json!({ "type": "object", "properties": { "steps": { "type": "integer" } } }),
            },
        ]
    }

    fn engine_set(&self, name: &str) -> Result<(), ControlError> {
        self.log(format!("engine_set {name}"));
        if !["passthrough", "dlpv"].contains(&name) {
            return Err(ControlError::engine_unknown(name));
        }
        *self.engine.lock().expect("engine lock") = name.to_owned();
        Ok(())
    }

    fn engine_params_get(&self) -> Value {
        self.log("engine_params_get".into());
        Value::Object(self.params.lock().expect("params lock").clone())
    }

    fn engine_params_set(&self, params: Map<String, Value>) -> Result<Value, ControlError> {
        self.log(format!(
            "engine_params_set {}",
            Value::Object(params.clone())
        ));
        let mut current = self.params.lock().expect("params lock");
        current.extend(params);
        Ok(Value::Object(current.clone()))
    }

    fn record_start(&self, request: OutputRequest) -> Result<PathBuf, ControlError> {
        let path = request.path;
        self.log(format!("record_start {path:?}"));
        let mut recording = self.recording.lock().expect("recording lock");
        if recording.is_some() {
            return Err(ControlError::busy("already recording"));
        }
        let path = path.unwrap_or_else(|| PathBuf::from("/rec/auto.mcap"));
        *recording = Some(path.clone());
        Ok(path)
    }

    fn record_stop(&self) -> Result<Value, ControlError> {
        self.log("record_stop".into());
        match self.recording.lock().expect("recording lock").take() {
            Some(path) => Ok(json!({ "path": path, "messages": 77 })),
            None => Err(ControlError::failed("not recording")),
        }
    }

    fn snapshot(&self, request: OutputRequest) -> Result<Vec<PathBuf>, ControlError> {
        let path = request.path;
        self.log(format!("snapshot {path:?}"));
        let dir = path.unwrap_or_else(|| PathBuf::from("/snap"));
        if dir == Path::new("/panic") {
            panic!("fake pipeline bug");
        }
        Ok(vec![dir.join("color.png"), dir.join("composite.png")])
    }

    fn config_reload(&self) -> Result<Value, ControlError> {
        self.log("config_reload".into());
        Ok(json!({ "changed": ["sync.tolerance_ms"] }))
    }

    fn lights(&self) -> Option<&LightsBoard> {
        Some(&self.lights)
    }
}

struct Fixture {
    _dir: tempfile::TempDir,
    socket: PathBuf,
    fake: Arc<FakePipeline>,
    server: Option<ControlServerHandle>,
}

impl Fixture {
    fn new(options: ServerOptions) -> Self {
        let dir = tempfile::tempdir().expect("temp dir");
        let socket = dir.path().join("control.sock");
        let fake = Arc::new(FakePipeline::default());
        *fake.engine.lock().expect("engine lock") = "passthrough".into();
        let server = ControlServer::bind_with(&socket, options, fake.clone())
            .expect("bind")
            .spawn()
            .expect("spawn");
        Self {
            _dir: dir,
            socket,
            fake,
            server: Some(server),
        }
    }

    fn client(&self) -> Client {
        Client::connect(&self.socket, TIMEOUT).expect("connect")
    }
}

fn default_fixture() -> Fixture {
    Fixture::new(ServerOptions::default())
}

/// Sends one raw line and returns the parsed response line.
fn exchange(client: &mut Client, line: &[u8]) -> Value {
    client.send_raw(line).expect("send");
    client.send_raw(b"\n").expect("send newline");
    client.read_response().expect("response")
}

fn error_code(response: &Value) -> i64 {
    response["error"]["code"]
        .as_i64()
        .unwrap_or_else(|| panic!("not an error response: {response}"))
}

fn error_message(response: &Value) -> &str {
    response["error"]["message"].as_str().unwrap_or_default()
}

fn rpc_error(result: Result<Value, ClientError>) -> ControlError {
    match result {
        Err(ClientError::Rpc(error)) => error,
        other => panic!("expected a JSON-RPC error, got {other:?}"),
    }
}

/// The connection still answers after whatever came before.
fn assert_usable(client: &mut Client) {
    assert_eq!(client.call("rpc.ping", None).expect("ping"), json!("pong"));
}

#[test]
fn every_method_happy_path() {
    let fx = default_fixture();
    let mut c = fx.client();

    let status: StatusReport =
        serde_json::from_value(c.call("status", None).expect("status")).expect("status shape");
    assert_eq!(status, sample_status("passthrough", None));

    let engines: Vec<EngineInfo> =
        serde_json::from_value(c.call("engine.list", Some(json!({}))).expect("engine.list"))
            .expect("engine list shape");
    assert_eq!(engines.len(), 2);
    assert_eq!(engines[1].name, "dlpv");

    assert_eq!(
        c.call("engine.set", Some(json!({ "name": "dlpv" })))
            .expect("set by name"),
        Value::Null
    );
    assert_eq!(
        c.call("engine.set", Some(json!(["passthrough"])))
            .expect("set by position"),
        Value::Null
    );

    assert_eq!(c.call("engine.params.get", None).expect("get"), json!({}));
    assert_eq!(
        c.call(
            "engine.params.set",
            Some(json!({ "params": { "steps": 8 } }))
        )
        .expect("wrapped"),
        json!({ "steps": 8 })
    );
    assert_eq!(
        c.call("engine.params.set", Some(json!({ "gain": 1.5 })))
            .expect("bare"),
        json!({ "steps": 8, "gain": 1.5 })
    );
    assert_eq!(
        c.call("engine.params.set", Some(json!([{ "steps": 4 }])))
            .expect("positional"),
        json!({ "steps": 4, "gain": 1.5 })
    );
    assert_eq!(
        c.call("engine.params.get", Some(json!([]))).expect("get"),
        json!({ "steps": 4, "gain": 1.5 })
    );

    assert_eq!(
        c.call("record.start", Some(json!({ "path": "/tmp/a.mcap" })))
            .expect("start"),
        json!({ "path": "/tmp/a.mcap" })
    );
    let status: StatusReport =
        serde_json::from_value(c.call("status", None).expect("status")).expect("status shape");
    assert_eq!(
        status.recording.map(|r| r.path),
        Some(PathBuf::from("/tmp/a.mcap"))
    );
    assert_eq!(
        c.call("record.stop", None).expect("stop"),
        json!({ "path": "/tmp/a.mcap", "messages": 77 })
    );
    assert_eq!(
        c.call("record.start", Some(json!({ "path": null })))
            .expect("start default"),
        json!({ "path": "/rec/auto.mcap" })
    );
    c.call("record.stop", None).expect("stop");

    assert_eq!(
        c.call("snapshot", Some(json!(["/tmp/s"])))
            .expect("snapshot"),
        json!({ "paths": ["/tmp/s/color.png", "/tmp/s/composite.png"] })
    );
    assert_eq!(
        c.call("snapshot", None).expect("snapshot default"),
        json!({ "paths": ["/snap/color.png", "/snap/composite.png"] })
    );
    assert_eq!(
        c.call("config.reload", None).expect("reload"),
        json!({ "changed": ["sync.tolerance_ms"] })
    );
    assert_usable(&mut c);
    let version = c.call("version", None).expect("version");
    assert_eq!(version["name"], "relightd");
    assert_eq!(version["protocol"], "jsonrpc-2.0");
    assert!(version["version"].is_string(), "{version}");

    assert_eq!(
        fx.fake.calls(),
        vec![
            "status",
            "engine_list",
            "engine_set dlpv",
            "engine_set passthrough",
            "engine_params_get",
            r#"engine_params_set {"steps":8}"#,
            r#"engine_params_set {"gain":1.5}"#,
            r#"engine_params_set {"steps":4}"#,
            "engine_params_get",
            r#"record_start Some("/tmp/a.mcap")"#,
            "status",
            "record_stop",
            "record_start None",
            "record_stop",
            r#"snapshot Some("/tmp/s")"#,
            "snapshot None",
            "config_reload",
        ]
    );
}

#[test]
fn pipeline_errors_keep_their_codes() {
    let fx = default_fixture();
    let mut c = fx.client();
    let error = rpc_error(c.call("engine.set", Some(json!({ "name": "nope" }))));
    assert_eq!(error.code, codes::ENGINE_UNKNOWN);
    assert!(error.message.contains("nope"), "{error:?}");

    c.call("record.start", None).expect("start");
    let error = rpc_error(c.call("record.start", None));
    assert_eq!(error.code, codes::BUSY);
    c.call("record.stop", None).expect("stop");
    let error = rpc_error(c.call("record.stop", None));
    assert_eq!(error.code, codes::FAILED);
    assert_usable(&mut c);
}

#[test]
fn malformed_json_is_a_parse_error() {
    let fx = default_fixture();
    let mut c = fx.client();
    for line in [
        &b"{\"jsonrpc\": \"2.0\", \"method\": \"status\""[..],
        b"{not json}",
        b"[1, 2",
    ] {
        let response = exchange(&mut c, line);
        assert_eq!(error_code(&response), codes::PARSE_ERROR, "{response}");
        assert_eq!(response["id"], Value::Null);
        assert_eq!(response["jsonrpc"], "2.0");
        assert_usable(&mut c);
    }
}

#[test]
fn non_object_request_is_invalid() {
    let fx = default_fixture();
    let mut c = fx.client();
    for line in ["42", "\"status\"", "null", "true"] {
        let response = exchange(&mut c, line.as_bytes());
        assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
        assert_eq!(response["id"], Value::Null);
    }
    assert_usable(&mut c);
}

#[test]
fn wrong_envelope_is_invalid_request() {
    let fx = default_fixture();
    let mut c = fx.client();
    let response = exchange(&mut c, br#"{"jsonrpc":"1.0","method":"status","id":7}"#);
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    assert_eq!(response["id"], 7);
    assert!(error_message(&response).contains("jsonrpc"), "{response}");

    let response = exchange(&mut c, br#"{"method":"status","id":"a"}"#);
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    assert_eq!(response["id"], "a");

    let response = exchange(&mut c, br#"{"jsonrpc":"2.0","method":1,"params":"bar"}"#);
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    assert_eq!(response["id"], Value::Null);

    let response = exchange(
        &mut c,
        br#"{"jsonrpc":"2.0","method":"status","id":{"x":1}}"#,
    );
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    assert_eq!(response["id"], Value::Null);

    let response = exchange(
        &mut c,
        br#"{"jsonrpc":"2.0","method":"status","params":3,"id":2}"#,
    );
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    assert_eq!(response["id"], 2);
    assert!(fx.fake.calls().is_empty(), "{:?}", fx.fake.calls());
    assert_usable(&mut c);
}

/// JSON-RPC ids come back digit for digit: an id is the client's to match responses by, and a
/// 2^64 that came back as 1.8446744073709552e19 matched nothing.
#[test]
fn ids_are_echoed_exactly_as_sent() {
    let fake = FakePipeline::default();
    for id in [
        "18446744073709551616",
        "-9223372036854775809",
        "1.0",
        "1e3",
        "0.1000000000000000055511151231257827",
        "-0",
        "\"x\\u00e9\"",
    ] {
        let line = format!(r#"{{"jsonrpc":"2.0","method":"rpc.ping","id":{id}}}"#);
        let response = relight_daemon::control::rpc::handle_line(line.as_bytes(), &fake)
            .expect("a request with an id is answered");
        let echoed = serde_json::from_str::<Value>(&response).expect("JSON")["id"].to_string();
        let sent = serde_json::from_str::<Value>(id).expect("JSON").to_string();
        assert_eq!(echoed, sent, "{response}");
        if !id.starts_with('"') {
            assert!(response.contains(&format!(r#""id":{id}"#)), "{response}");
        }
    }
}

#[test]
fn unknown_method_is_named() {
    let fx = default_fixture();
    let mut c = fx.client();
    let error = rpc_error(c.call("engine.sett", None));
    assert_eq!(error.code, codes::METHOD_NOT_FOUND);
    assert!(error.message.contains("engine.sett"), "{error:?}");
    assert_usable(&mut c);
}

#[test]
fn wrong_params_name_the_field() {
    let fx = default_fixture();
    let mut c = fx.client();
    let cases = [
        ("engine.set", json!({ "name": 3 }), "name"),
        ("engine.set", json!({}), "name"),
        ("engine.set", json!({ "nme": "dlpv" }), "nme"),
        ("engine.set", json!(["dlpv", "extra"]), "at most 1"),
        ("record.start", json!({ "path": 5 }), "path"),
        ("snapshot", json!({ "path": [] }), "path"),
        ("engine.params.set", json!({ "params": "x" }), "params"),
        ("engine.params.set", json!([1]), "params"),
        ("status", json!({ "verbose": true }), "verbose"),
    ];
    for (method, params, field) in cases {
        let error = rpc_error(c.call(method, Some(params.clone())));
        assert_eq!(
            error.code,
            codes::INVALID_PARAMS,
            "{method} {params}: {error:?}"
        );
        assert!(
            error.message.contains(field),
            "{method} {params}: {error:?}"
        );
    }
    let error = rpc_error(c.call("engine.params.set", None));
    assert_eq!(error.code, codes::INVALID_PARAMS);
    assert!(fx.fake.calls().is_empty(), "{:?}", fx.fake.calls());
    assert_usable(&mut c);
}

#[test]
fn oversized_line_is_skipped_and_the_next_request_answered() {
    let fx = Fixture::new(ServerOptions {
        max_request_bytes: 1024,
        ..ServerOptions::default()
    });
    let mut c = fx.client();
    let huge = format!(
        r#"{{"jsonrpc":"2.0","method":"status","id":1,"pad":"{}"}}"#,
        "x".repeat(200_000)
    );
    let mut bytes = huge.clone().into_bytes();
    bytes.extend_from_slice(b"\n{\"jsonrpc\":\"2.0\",\"method\":\"rpc.ping\",\"id\":2}\n");
    // The writer runs on its own thread: the server must drain the long line while we write it.
    let mut writer = UnixStream::connect(&fx.socket).expect("connect");
    let mut reader = std::io::BufReader::new(writer.try_clone().expect("clone"));
    let send = std::thread::spawn(move || std::io::Write::write_all(&mut writer, &bytes));
    let mut first = String::new();
    std::io::BufRead::read_line(&mut reader, &mut first).expect("first response");
    let mut second = String::new();
    std::io::BufRead::read_line(&mut reader, &mut second).expect("second response");
    send.join().expect("writer thread").expect("write");

    let first: Value = serde_json::from_str(&first).expect("json");
    assert_eq!(error_code(&first), codes::INVALID_REQUEST, "{first}");
    assert_eq!(
        error_message(&first),
        format!("request too large ({} bytes > 1024)", huge.len())
    );
    assert_eq!(first["id"], Value::Null);
    let second: Value = serde_json::from_str(&second).expect("json");
    assert_eq!(second["result"], "pong", "{second}");
    assert_eq!(second["id"], 2);

    // and through the client, on a connection that already answered
    assert_usable(&mut c);
    c.send_raw(&vec![b' '; 5000]).expect("send");
    let response = exchange(&mut c, b"");
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    assert_usable(&mut c);
    assert!(fx.fake.calls().is_empty(), "{:?}", fx.fake.calls());
}

#[test]
fn invalid_utf8_is_a_parse_error() {
    let fx = default_fixture();
    let mut c = fx.client();
    let response = exchange(
        &mut c,
        b"{\"jsonrpc\":\"2.0\",\"method\":\"st\xffatus\",\"id\":1}",
    );
    assert_eq!(error_code(&response), codes::PARSE_ERROR, "{response}");
    assert!(error_message(&response).contains("UTF-8"), "{response}");
    assert_eq!(response["id"], Value::Null);
    assert_usable(&mut c);
}

#[test]
fn batches_answer_each_request_and_skip_notifications() {
    let fx = default_fixture();
    let mut c = fx.client();
    let batch = json!([
        { "jsonrpc": "2.0", "method": "rpc.ping", "id": 1 },
        { "jsonrpc": "2.0", "method": "engine.set", "params": { "name": "dlpv" } },
        42,
        { "jsonrpc": "2.0", "method": "nope", "id": "x" },
        { "jsonrpc": "2.0", "method": "engine.list", "id": 3 }
    ]);
    let response = exchange(&mut c, batch.to_string().as_bytes());
    let responses = response.as_array().expect("batch response is an array");
    assert_eq!(responses.len(), 4, "{response}");
    let by_id = |id: Value| {
        responses
            .iter()
            .find(|r| r["id"] == id)
            .unwrap_or_else(|| panic!("no response with id {id}: {response}"))
    };
    assert_eq!(by_id(json!(1))["result"], "pong");
    assert_eq!(error_code(by_id(json!("x"))), codes::METHOD_NOT_FOUND);
    assert_eq!(by_id(json!(3))["result"].as_array().map(Vec::len), Some(2));
    assert!(
        responses
            .iter()
            .any(|r| r["id"] == Value::Null && error_code(r) == codes::INVALID_REQUEST),
        "{response}"
    );
    assert!(fx.fake.calls().contains(&"engine_set dlpv".to_owned()));

    let response = exchange(&mut c, b"[]");
    assert!(
        response.is_object(),
        "empty batch gets one error object: {response}"
    );
    assert_eq!(error_code(&response), codes::INVALID_REQUEST);
    assert_eq!(response["id"], Value::Null);

    // A batch of notifications only gets no response: the next line answers the ping.
    c.send_raw(br#"[{"jsonrpc":"2.0","method":"engine.set","params":["passthrough"]}]"#)
        .expect("send");
    c.send_raw(b"\n").expect("send");
    assert_usable(&mut c);
    assert_eq!(
        fx.fake.calls().last().map(String::as_str),
        Some("engine_set passthrough")
    );
}

#[test]
fn notification_gets_no_reply() {
    let fx = default_fixture();
    let mut c = fx.client();
    c.notify("engine.set", Some(json!({ "name": "dlpv" })))
        .expect("notify");
    // Even failing notifications stay silent.
    c.notify("no.such.method", None).expect("notify");
    c.notify("engine.set", Some(json!({ "name": 1 })))
        .expect("notify");
    let response = exchange(&mut c, br#"{"jsonrpc":"2.0","method":"rpc.ping","id":99}"#);
    assert_eq!(response["id"], 99, "{response}");
    assert_eq!(response["result"], "pong");
    assert_eq!(fx.fake.calls(), vec!["engine_set dlpv"]);
    // A blank line is not a request either.
    let response = exchange(
        &mut c,
        b"  \n{\"jsonrpc\":\"2.0\",\"method\":\"rpc.ping\",\"id\":100}",
    );
    assert_eq!(response["id"], 100, "{response}");
}

#[test]
fn handler_panic_is_an_internal_error() {
    let fx = default_fixture();
    let mut c = fx.client();
    let error = rpc_error(c.call("snapshot", Some(json!({ "path": "/panic" }))));
    assert_eq!(error.code, codes::INTERNAL_ERROR);
    assert_usable(&mut c);
}

#[test]
fn twenty_concurrent_clients() {
    let fx = Fixture::new(ServerOptions {
        max_connections: 32,
        ..ServerOptions::default()
    });
    let start = Arc::new(Barrier::new(20));
    let threads: Vec<_> = (0..20)
        .map(|i| {
            let socket = fx.socket.clone();
            let start = Arc::clone(&start);
            std::thread::spawn(move || -> Result<(), ClientError> {
                let mut c = Client::connect(&socket, TIMEOUT)?;
                start.wait();
                for _ in 0..5 {
                    c.call("status", None)?;
                    let name = if i % 2 == 0 { "dlpv" } else { "passthrough" };
                    c.call("engine.set", Some(json!({ "name": name })))?;
                }
                Ok(())
            })
        })
        .collect();
    for thread in threads {
        thread.join().expect("client thread").expect("client calls");
    }
    assert_eq!(fx.fake.calls().len(), 200);
}

#[test]
fn connections_beyond_the_cap_are_refused() {
    let fx = default_fixture();
    let held = Arc::new(Barrier::new(20));
    let threads: Vec<_> = (0..20)
        .map(|_| {
            let socket = fx.socket.clone();
            let held = Arc::clone(&held);
            std::thread::spawn(move || {
                let mut c = Client::connect(&socket, TIMEOUT).expect("connect");
                held.wait(); // all 20 are connected
                let result = c.call("rpc.ping", None);
                held.wait(); // nobody leaves (and frees a slot) before all have an answer
                result
            })
        })
        .collect();
    let results: Vec<_> = threads
        .into_iter()
        .map(|t| t.join().expect("client thread"))
        .collect();
    let served = results.iter().filter(|r| r.is_ok()).count();
    assert_eq!(served, 16, "{results:?}");
    for result in results.into_iter().filter(Result::is_err) {
        let error = rpc_error(result);
        assert_eq!(error.code, codes::TOO_MANY_CONNECTIONS, "{error:?}");
    }
}

#[test]
fn socket_file_mode_and_group() {
    let gid = std::fs::metadata("/proc/self")
        .map(|m| m.gid())
        .expect("own gid");
    let fx = Fixture::new(ServerOptions {
        allowed_gid: Some(gid),
        ..ServerOptions::default()
    });
    let meta = std::fs::metadata(&fx.socket).expect("socket exists");
    assert_eq!(meta.permissions().mode() & 0o7777, 0o660);
    assert_eq!(meta.gid(), gid);

    let dir = tempfile::tempdir().expect("temp dir");
    let socket = dir.path().join("private.sock");
    let server = ControlServer::bind(
        &socket,
        0o600,
        None,
        4096,
        Arc::new(FakePipeline::default()),
    )
    .expect("bind");
    let mode = std::fs::metadata(&socket)
        .expect("socket")
        .permissions()
        .mode();
    assert_eq!(mode & 0o7777, 0o600);
    drop(server);
    assert!(
        !socket.exists(),
        "an unspawned server removes its socket when dropped"
    );
}

#[test]
fn stale_socket_is_replaced_but_live_one_and_files_are_not() {
    let dir = tempfile::tempdir().expect("temp dir");
    let socket = dir.path().join("control.sock");
    drop(UnixListener::bind(&socket).expect("stale listener"));
    assert!(socket.exists(), "a dropped listener leaves its file behind");
    let server = ControlServer::bind(
        &socket,
        0o660,
        None,
        4096,
        Arc::new(FakePipeline::default()),
    )
    .expect("stale socket replaced")
    .spawn()
    .expect("spawn");

    let second = ControlServer::bind(
        &socket,
        0o660,
        None,
        4096,
        Arc::new(FakePipeline::default()),
    );
    assert!(
        matches!(second, Err(ServerError::InUse { .. })),
        "{second:?}"
    );
    let mut c = Client::connect(&socket, TIMEOUT).expect("first server still serves");
    assert_usable(&mut c);
    drop(c);
    server.shutdown();

    let file = dir.path().join("not-a-socket");
    std::fs::write(&file, "precious").expect("write file");
    let result = ControlServer::bind(&file, 0o660, None, 4096, Arc::new(FakePipeline::default()));
    assert!(
        matches!(result, Err(ServerError::NotASocket { .. })),
        "{result:?}"
    );
    assert_eq!(
        std::fs::read_to_string(&file).expect("file kept"),
        "precious"
    );
}

#[test]
fn shutdown_closes_connections_and_removes_the_socket() {
    let mut fx = default_fixture();
    let mut c = fx.client();
    assert_usable(&mut c);
    let server = fx.server.take().expect("server running");
    assert_eq!(server.active_connections(), 1);
    server.shutdown();
    assert!(!fx.socket.exists(), "socket file removed");
    assert!(matches!(c.read_response(), Err(ClientError::Closed)));
    assert!(matches!(
        Client::connect(&fx.socket, TIMEOUT),
        Err(ClientError::Connect { .. })
    ));
}

#[test]
fn peer_credentials_decide_access() {
    let peer = |uid, gid| PeerCred {
        pid: Some(4242),
        uid,
        gid,
    };
    let daemon_uid = 990;
    let video = 44;
    assert!(peer_allowed(&peer(0, 0), daemon_uid, None, &[]), "root");
    assert!(
        peer_allowed(&peer(990, 990), daemon_uid, None, &[]),
        "the daemon's user"
    );
    assert!(
        !peer_allowed(&peer(1000, 1000), daemon_uid, None, &[]),
        "a stranger"
    );
    assert!(
        !peer_allowed(&peer(1000, 1000), daemon_uid, None, &[video]),
        "group membership without a configured group"
    );
    assert!(
        peer_allowed(&peer(1000, video), daemon_uid, Some(video), &[]),
        "primary group"
    );
    assert!(
        peer_allowed(&peer(1000, 1000), daemon_uid, Some(video), &[27, video]),
        "supplementary group"
    );
    assert!(
        !peer_allowed(&peer(1000, 1000), daemon_uid, Some(video), &[27, 46]),
        "other groups"
    );
}

fn relightctl(socket: &Path, args: &[&str]) -> (i32, String, String) {
    let output = Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .arg("--socket")
        .arg(socket)
        .args(args)
        .output()
        .expect("run relightctl");
    (
        output.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn relightctl_exit_codes_and_output() {
    let fx = default_fixture();

    let (code, out, err) = relightctl(&fx.socket, &["status"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("passthrough"), "{out}");
    assert!(out.contains("1h 02m 05s"), "{out}");
    let device_row = out
        .lines()
        .find(|l| l.starts_with("kinect"))
        .unwrap_or_default();
    for cell in [
        "depth",
        "freenect",
        "lost",
        "30.0",
        "1200",
        "3",
        "usb transfer failed",
    ] {
        assert!(device_row.contains(cell), "{cell} missing in {out}");
    }
    let stage_row = out
        .lines()
        .find(|l| l.starts_with("recon"))
        .unwrap_or_default();
    assert!(
        stage_row.contains("4.25") && stage_row.contains("7.50"),
        "{out}"
    );
    assert!(
        out.contains("live view   ws://127.0.0.1:8765, http://127.0.0.1:8080/"),
        "{out}"
    );

    let (code, out, err) = relightctl(&fx.socket, &["--json", "engine", "list"]);
    assert_eq!(code, 0, "{err}");
    let list: Vec<EngineInfo> = serde_json::from_str(&out).expect("--json prints the result");
    assert_eq!(list.len(), 2);

    let (code, _, err) = relightctl(&fx.socket, &["engine", "set", "warp"]);
    assert_eq!(code, 1);
    assert!(err.contains("unknown engine: warp"), "{err}");

    let (code, out, err) = relightctl(
        &fx.socket,
        &[
            "--json",
            "engine",
            "params",
            "set",
            "steps=8",
            "mode=fast",
            "on=true",
        ],
    );
    assert_eq!(code, 0, "{err}");
    let params: Value = serde_json::from_str(&out).expect("json");
    assert_eq!(params, json!({ "steps": 8, "mode": "fast", "on": true }));

    let (code, out, err) = relightctl(&fx.socket, &["record", "start", "/tmp/x.mcap"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "recording to /tmp/x.mcap");

    let (code, out, err) = relightctl(&fx.socket, &["call", "snapshot", r#"{"path":"/s"}"#]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("/s/composite.png"), "{out}");

    // Readable by default, floats rounded (an f32 0.3 arrives as 0.30000001192092896).
    let (code, out, err) = relightctl(
        &fx.socket,
        &[
            "call",
            "engine.params.set",
            r#"{"params":{"gain":0.30000001192092896}}"#,
        ],
    );
    assert_eq!(code, 0, "{err}");
    assert!(!out.contains('{'), "not JSON: {out}");
    assert!(out.contains("gain") && out.contains("0.3\n"), "{out}");

    let missing = fx.socket.with_file_name("absent.sock");
    let (code, _, err) = relightctl(&missing, &["status"]);
    assert_eq!(code, 3, "unreachable, apart from clap's 2 for usage: {err}");
    assert!(err.contains("absent.sock"), "{err}");
    assert!(err.contains("systemctl status relightd"), "{err}");
    let usage = Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .arg("no-such-command")
        .output()
        .unwrap();
    assert_eq!(usage.status.code(), Some(2));

    // --socket after the command, and RELIGHT_SOCKET instead of it.
    let after = Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .args(["status", "--socket"])
        .arg(&fx.socket)
        .output()
        .unwrap();
    assert!(
        after.status.success(),
        "{}",
        String::from_utf8_lossy(&after.stderr)
    );
    let from_env = Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .args(["engine", "list", "--json"])
        .env("RELIGHT_SOCKET", &fx.socket)
        .output()
        .unwrap();
    assert!(
        from_env.status.success(),
        "{}",
        String::from_utf8_lossy(&from_env.stderr)
    );
    serde_json::from_slice::<Vec<EngineInfo>>(&from_env.stdout).expect("--json after the command");
}

/// An estimate whose main light is a point light of `intensity` 1 m above the origin, with
/// `extra` more lights (to make its JSON line long).
fn lamp_estimate(intensity: f32, extra: usize) -> relight_recon::estimate::LightingEstimate {
    use relight_core::light::Light;
    let lamp = Light::Point {
        position_in_world: glam::Vec3::Y,
        intensity: glam::Vec3::splat(intensity),
    };
    let dim = Light::Directional {
        direction_in_world: glam::Vec3::NEG_Y,
        irradiance: glam::Vec3::splat(1e-3),
    };
    let mut lights = vec![lamp];
    lights.extend(std::iter::repeat_n(dim, extra));
    relight_recon::estimate::LightingEstimate::from_lights(
        lights,
        0,
        relight_core::sh::Sh9Rgb::ZERO,
        None,
        glam::Vec3::ZERO,
    )
}

fn update_intensity(message: &Value) -> f64 {
    assert_eq!(message["jsonrpc"], "2.0", "{message}");
    assert_eq!(message["method"], "lights.update", "{message}");
    assert!(message.get("id").is_none(), "{message}");
    message["params"]["main_light"]["intensity"]
        .as_f64()
        .unwrap_or_else(|| panic!("no main light in {message}"))
}

#[test]
fn lights_get_is_null_until_the_first_estimate() {
    let fx = default_fixture();
    let mut c = fx.client();
    assert_eq!(c.call("lights.get", None).expect("get"), Value::Null);
    fx.fake.lights.publish(lamp_estimate(2.0, 0));
    let estimate = c.call("lights.get", Some(json!([]))).expect("get");
    assert_eq!(estimate["main_light"]["intensity"], 2.0, "{estimate}");
    assert_eq!(
        estimate["main_light"]["direction_in_world"],
        json!([0.0, -1.0, 0.0])
    );
    assert_eq!(estimate["lights"][0]["type"], "point");
    assert_eq!(estimate["environment_stamp"], Value::Null);
    assert_eq!(estimate["sh9"].as_array().map(Vec::len), Some(9));
}

#[test]
fn subscriber_gets_the_current_estimate_after_the_ack_then_each_change() {
    let fx = default_fixture();
    fx.fake.lights.publish(lamp_estimate(1.0, 0));
    let mut c = fx.client();

    // Raw lines, to see the order: the response first, then the current estimate.
    let ack = exchange(
        &mut c,
        br#"{"jsonrpc":"2.0","id":7,"method":"lights.subscribe"}"#,
    );
    assert_eq!(ack, json!({ "jsonrpc": "2.0", "result": null, "id": 7 }));
    assert_eq!(update_intensity(&c.read_response().expect("update")), 1.0);

    fx.fake.lights.publish(lamp_estimate(2.0, 0));
    assert_eq!(update_intensity(&c.read_response().expect("update")), 2.0);
    // An unchanged estimate is not sent again: the next line is the ping's answer.
    assert!(!fx.fake.lights.publish(lamp_estimate(2.0, 0)));
    assert_usable(&mut c);
    // Subscribing twice changes nothing.
    assert_eq!(
        c.call("lights.subscribe", None).expect("again"),
        Value::Null
    );
    fx.fake.lights.publish(lamp_estimate(3.0, 0));
    let notification = c.next_notification().expect("update");
    assert_eq!(notification.method, "lights.update");
    assert_eq!(notification.params["main_light"]["intensity"], 3.0);

    // After the unsubscribe response, nothing more comes.
    assert_eq!(
        c.call("lights.unsubscribe", None).expect("unsubscribe"),
        Value::Null
    );
    assert_eq!(fx.fake.lights.subscribers(), 0);
    fx.fake.lights.publish(lamp_estimate(4.0, 0));
    assert_usable(&mut c);
    assert_eq!(fx.fake.lights.subscribers(), 0);
}

#[test]
fn notifications_arriving_during_a_call_are_kept_for_later() {
    let fx = default_fixture();
    let mut c = fx.client();
    c.call("lights.subscribe", None).expect("subscribe");
    fx.fake.lights.publish(lamp_estimate(5.0, 0));
    // The update is on the wire before the ping's response; the call skips and keeps it.
    std::thread::sleep(Duration::from_millis(50));
    assert_usable(&mut c);
    let notification = c.next_notification().expect("kept update");
    assert_eq!(notification.params["main_light"]["intensity"], 5.0);
}

#[test]
fn lights_methods_reject_params_and_the_connection_goes_on() {
    let fx = default_fixture();
    let mut c = fx.client();
    for (method, params) in [
        ("lights.subscribe", json!({ "rate": 10 })),
        ("lights.subscribe", json!([1])),
        ("lights.get", json!({ "verbose": true })),
        ("lights.unsubscribe", json!(["now"])),
        ("lights.export", json!({})),
        ("lights.export", json!({ "path": 7 })),
        (
            "lights.export",
            json!({ "path": "env.exr", "format": "hdr" }),
        ),
    ] {
        let error = rpc_error(c.call(method, Some(params.clone())));
        assert_eq!(
            error.code,
            codes::INVALID_PARAMS,
            "{method} {params}: {error:?}"
        );
    }
    let response = exchange(
        &mut c,
        br#"{"jsonrpc":"2.0","id":1,"method":"lights.subscribe","params":"x"}"#,
    );
    assert_eq!(error_code(&response), codes::INVALID_REQUEST, "{response}");
    // None of them subscribed.
    fx.fake.lights.publish(lamp_estimate(1.0, 0));
    assert_usable(&mut c);
    assert_eq!(fx.fake.lights.subscribers(), 0);
    let error = rpc_error(c.call("lights.sub", None));
    assert_eq!(error.code, codes::METHOD_NOT_FOUND);
    let methods = error.data.expect("method list")["methods"].clone();
    // A target that does not export says so rather than writing anything.
    let error = rpc_error(c.call("lights.export", Some(json!({ "path": "env.exr" }))));
    assert_eq!(error.code, codes::FAILED, "{error:?}");
    for method in [
        "lights.get",
        "lights.export",
        "lights.subscribe",
        "lights.unsubscribe",
    ] {
        assert!(
            methods
                .as_array()
                .is_some_and(|m| m.contains(&json!(method))),
            "{methods}"
        );
    }
}

#[test]
fn subscribed_connections_are_not_closed_for_idling() {
    let fx = Fixture::new(ServerOptions {
        idle_timeout: Duration::from_millis(100),
        ..ServerOptions::default()
    });
    let mut idle = fx.client();
    assert_usable(&mut idle);
    let mut listening = fx.client();
    listening.call("lights.subscribe", None).expect("subscribe");
    std::thread::sleep(Duration::from_millis(400));
    assert!(matches!(idle.read_response(), Err(ClientError::Closed)));
    fx.fake.lights.publish(lamp_estimate(6.0, 0));
    let update = listening.next_notification().expect("still listening");
    assert_eq!(update.params["main_light"]["intensity"], 6.0);
}

/// A subscriber that never reads fills its socket buffer; the publisher and the other clients go
/// on regardless, and it is disconnected after the write timeout.
#[test]
fn a_subscriber_that_never_reads_blocks_nobody_and_is_dropped() {
    let fx = Fixture::new(ServerOptions {
        write_timeout: Duration::from_millis(300),
        ..ServerOptions::default()
    });
    let mut stuck = fx.client();
    stuck.call("lights.subscribe", None).expect("subscribe");
    let mut reader = fx.client();
    reader.call("lights.subscribe", None).expect("subscribe");

    // Each update is some 10 KB of JSON: a few dozen fill the stuck client's socket buffer.
    for i in 1..=400 {
        fx.fake.lights.publish(lamp_estimate(i as f32, 100));
        assert_usable(&mut reader);
    }
    let mut other = fx.client();
    assert_usable(&mut other);
    // The reader took some updates along the way; coalescing may skip some, but the last one it
    // gets is the newest.
    let mut last = 0.0;
    while let Ok(update) = reader.next_notification() {
        last = update.params["main_light"]["intensity"]
            .as_f64()
            .unwrap_or(0.0);
        if last == 400.0 {
            break;
        }
    }
    assert_eq!(last, 400.0);

    // The stuck subscriber is disconnected once a write has waited for the timeout.
    let deadline = std::time::Instant::now() + TIMEOUT;
    while fx.fake.lights.subscribers() > 1 {
        assert!(
            std::time::Instant::now() < deadline,
            "stuck subscriber still registered"
        );
        fx.fake.lights.publish(lamp_estimate(
            1000.0 + fx.fake.lights.published() as f32,
            100,
        ));
        std::thread::sleep(Duration::from_millis(50));
    }
    let mut ended = false;
    while !ended {
        match stuck.next_notification() {
            Ok(_) => {}
            Err(ClientError::Closed | ClientError::Io(_)) => ended = true,
            Err(err) => panic!("expected the connection to end, got {err}"),
        }
    }
    assert_usable(&mut other);
}

#[test]
fn relightctl_lights_get_and_watch() {
    let fx = default_fixture();
    let (code, out, err) = relightctl(&fx.socket, &["lights", "get"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "no lighting estimate yet");
    let (code, out, err) = relightctl(&fx.socket, &["--json", "lights", "get"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "null");

    fx.fake.lights.publish(lamp_estimate(2.0, 0));
    let (code, out, err) = relightctl(&fx.socket, &["lights", "get"]);
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains("main light") && out.contains("2.000 W/m²"),
        "{out}"
    );
    assert!(out.contains(r#""type":"point""#), "{out}");

    // For Unity: the lamp 1 m above, 2 W/m², is the main light, travelling down (x mirrored,
    // nothing to mirror), `color · intensity` = E / π; with it taken out, the ambient probe is
    // empty. For three.js: the intensity is the irradiance, the probe 27 floats.
    let (code, out, err) = relightctl(&fx.socket, &["lights", "get", "--as", "unity"]);
    assert_eq!(code, 0, "{err}");
    let unity: Value = serde_json::from_str(&out).expect("JSON");
    let intensity = unity["main_light"]["intensity"].as_f64().unwrap();
    assert!(
        (intensity - 2.0 / std::f64::consts::PI).abs() < 1e-6,
        "{unity}"
    );
    assert_eq!(unity["main_light"]["direction"][1].as_f64(), Some(-1.0));
    let ambient = unity["ambient_probe"].as_array().unwrap();
    assert_eq!(ambient.len(), 3);
    assert!(
        ambient
            .iter()
            .flat_map(|row| row.as_array().unwrap())
            .all(|c| c.as_f64().unwrap().abs() < 1e-6),
        "{unity}"
    );
    let total_dc = unity["total_probe"][0][0].as_f64().unwrap();
    assert!(total_dc > 0.1, "{unity}");
    let (code, out, err) = relightctl(&fx.socket, &["lights", "get", "--as", "threejs"]);
    assert_eq!(code, 0, "{err}");
    let three: Value = serde_json::from_str(&out).expect("JSON");
    assert_eq!(three["main_light"]["intensity"].as_f64(), Some(2.0));
    assert_eq!(three["total_probe"].as_array().map(Vec::len), Some(27));

    let mut watch = Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .arg("--socket")
        .arg(&fx.socket)
        .args(["--timeout-ms", "200", "lights", "watch"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("relightctl lights watch");
    let stdout = watch.stdout.take().expect("stdout");
    let mut lines = std::io::BufRead::lines(std::io::BufReader::new(stdout));
    let mut next_intensity = || -> f64 {
        let line = lines.next().expect("a line").expect("utf-8");
        let estimate: Value = serde_json::from_str(&line).expect("one JSON estimate per line");
        estimate["main_light"]["intensity"]
            .as_f64()
            .expect("intensity")
    };
    assert_eq!(next_intensity(), 2.0);
    // Quiet for longer than the client timeout: it keeps watching.
    std::thread::sleep(Duration::from_millis(500));
    fx.fake.lights.publish(lamp_estimate(3.0, 0));
    assert_eq!(next_intensity(), 3.0);
    let _ = watch.kill();
    let _ = watch.wait();
}

/// Sixteen peers that each keep a request line open by trickling a byte at a time fill every
/// slot; the request deadline cuts each one off, so the owner's `status` gets through.
#[test]
fn trickling_clients_do_not_lock_out_the_owner() {
    let deadline = Duration::from_millis(400);
    let fx = Fixture::new(ServerOptions {
        request_deadline: deadline,
        ..ServerOptions::default()
    });
    let connected = Arc::new(Barrier::new(17));
    let tricklers: Vec<_> = (0..16)
        .map(|_| {
            let socket = fx.socket.clone();
            let connected = Arc::clone(&connected);
            std::thread::spawn(move || {
                let mut stream = UnixStream::connect(&socket).expect("connect");
                std::io::Write::write_all(&mut stream, b"{").expect("first byte");
                connected.wait();
                // One byte every 50 ms until the server answers (and hangs up).
                let read_answer = |stream: &mut UnixStream| {
                    let mut buf = [0u8; 512];
                    match std::io::Read::read(stream, &mut buf) {
                        Ok(n) if n > 0 => Some(String::from_utf8_lossy(&buf[..n]).into_owned()),
                        _ => None,
                    }
                };
                stream.set_nonblocking(true).expect("non-blocking");
                let started = std::time::Instant::now();
                while started.elapsed() < TIMEOUT {
                    std::thread::sleep(Duration::from_millis(50));
                    if let Some(answer) = read_answer(&mut stream) {
                        return answer;
                    }
                    if std::io::Write::write_all(&mut stream, b" ").is_err() {
                        stream.set_nonblocking(false).expect("blocking");
                        let _ = stream.set_read_timeout(Some(Duration::from_secs(1)));
                        return read_answer(&mut stream).unwrap_or_default();
                    }
                }
                String::new()
            })
        })
        .collect();
    connected.wait();
    // While all sixteen trickle, a seventeenth connection is refused.
    let refused = Client::connect(&fx.socket, TIMEOUT).and_then(|mut c| c.call("status", None));
    assert_eq!(rpc_error(refused).code, codes::TOO_MANY_CONNECTIONS);
    let started = std::time::Instant::now();
    let status = loop {
        match Client::connect(&fx.socket, TIMEOUT).and_then(|mut c| c.call("status", None)) {
            Ok(status) => break status,
            Err(_) if started.elapsed() < TIMEOUT => std::thread::sleep(Duration::from_millis(20)),
            Err(error) => panic!("the owner is still locked out: {error:?}"),
        }
    };
    assert_eq!(status["engine"], "passthrough");
    assert!(started.elapsed() < TIMEOUT);
    for trickler in tricklers {
        let told = trickler.join().expect("trickler");
        assert!(told.contains("not finished within"), "{told}");
    }
}

/// Subscribers have their own cap and do not take request slots.
#[test]
fn subscribers_are_capped_apart_from_request_connections() {
    let fx = Fixture::new(ServerOptions {
        max_connections: 4,
        max_subscribers: 3,
        ..ServerOptions::default()
    });
    let mut subscribers: Vec<Client> = (0..3)
        .map(|_| {
            let mut c = fx.client();
            c.call("lights.subscribe", None).expect("subscribe");
            c
        })
        .collect();
    let mut fourth = fx.client();
    let error = rpc_error(fourth.call("lights.subscribe", None));
    assert_eq!(error.code, codes::BUSY);
    assert!(error.message.contains("at most 3"), "{error:?}");
    // Three subscribers and one request connection open: three more request connections fit.
    let mut others: Vec<Client> = (0..3).map(|_| fx.client()).collect();
    for c in &mut others {
        assert_usable(c);
    }
    // A subscriber that leaves frees its subscription for another.
    subscribers.pop();
    let started = std::time::Instant::now();
    while fourth.call("lights.subscribe", None).is_err() {
        assert!(started.elapsed() < TIMEOUT, "subscription slot not freed");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn an_oversized_batch_reply_is_an_error_naming_the_limit() {
    let fx = Fixture::new(ServerOptions {
        max_reply_bytes: 4096,
        ..ServerOptions::default()
    });
    let mut c = fx.client();
    let batch: Vec<Value> = (0..200)
        .map(|id| json!({ "jsonrpc": "2.0", "method": "engine.list", "id": id }))
        .collect();
    let reply = exchange(&mut c, serde_json::to_string(&batch).unwrap().as_bytes());
    assert_eq!(reply["error"]["code"], codes::INVALID_REQUEST);
    assert_eq!(reply["error"]["data"]["max_reply_bytes"], 4096);
    let answered = reply["error"]["data"]["answered"]
        .as_u64()
        .expect("answered");
    assert!((1..200).contains(&answered), "{reply}");
    assert!(
        reply["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("4096-byte limit")),
        "{reply}"
    );
    // A batch under the limit is answered in full, and the connection stays usable.
    let small: Vec<Value> = (0..3)
        .map(|id| json!({ "jsonrpc": "2.0", "method": "rpc.ping", "id": id }))
        .collect();
    let reply = exchange(&mut c, serde_json::to_string(&small).unwrap().as_bytes());
    assert_eq!(reply.as_array().map(Vec::len), Some(3));
    assert_usable(&mut c);
}
