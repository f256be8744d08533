//! End to end: `relightd` replaying the bundled desk recording with its scene publishes the
//! lighting estimate — the scene file's point light plus the tracked pocket lamp until the
//! light probe's first bracket is merged, then the probe's median-cut lights and SH9 plus the
//! lamp — on the control socket (`lights.get`, `lights.subscribe` → `lights.update`), and bad `lights.*` requests get
//! JSON-RPC errors while the daemon keeps serving.

mod support;

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use relight_daemon::control::{Client, ClientError, codes};
use relight_recon::estimate::LightingEstimate;
use serde_json::{Value, json};
use support::Daemon;

const TIMEOUT: Duration = Duration::from_secs(10);
/// The scene file's own light (tests/scenes/desk_box/scene.toml); other point lights: the lamp.
const SCENE_LIGHT_POSITION: [f32; 3] = [0.0, 1.1, 0.2];

fn start_daemon(dir: &Path) -> Daemon {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
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

[scene]
dir = "{scene}"
depth_stride = 4

[snapshot]
dir = "{snapshots}"
"#,
        snapshots = dir.join("snapshots").display(),
        socket = socket.display(),
        recording = root.join("tests/fixtures/demo.mcap").display(),
        scene = root.join("tests/scenes/desk_box").display(),
    );
    support::start(dir, &config, socket, "warn", &[])
}

/// An EXR the daemon wrote, as the environment map it was.
fn read_exr_map(path: &Path) -> relight_core::scene::EnvironmentMap {
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |resolution, _| {
            (
                resolution.width(),
                vec![glam::Vec3::ZERO; resolution.width() * resolution.height()],
            )
        },
        |(width, pixels): &mut (usize, Vec<glam::Vec3>),
         position,
         (r, g, b, _a): (f32, f32, f32, f32)| {
            pixels[position.y() * *width + position.x()] = glam::Vec3::new(r, g, b);
        },
    )
    .expect("an EXR");
    let size = image.layer_data.size;
    relight_core::scene::EnvironmentMap {
        width: size.width() as u32,
        height: size.height() as u32,
        radiance: image.layer_data.channel_data.pixels.1,
    }
}

/// The lamp's light in `estimate`, if the lamp is on.
fn lamp_light(estimate: &LightingEstimate) -> Option<relight_core::light::Light> {
    estimate.lights.iter().copied().find(|light| {
        matches!(light, relight_core::light::Light::Point { position_in_world, .. }
            if position_in_world.to_array() != SCENE_LIGHT_POSITION)
    })
}

#[test]
fn replay_with_a_lamp_publishes_its_light_to_subscribers() {
    let dir = tempfile::tempdir().expect("temp dir");
    let daemon = start_daemon(dir.path());

    // A subscriber gets the current estimate (or the first one) and then every change; the lamp
    // reports every third frame, moving, so an update with the lamp on comes within seconds.
    let mut subscriber = Client::connect(&daemon.socket, TIMEOUT).expect("connect");
    assert_eq!(
        subscriber
            .call("lights.subscribe", None)
            .expect("subscribe"),
        Value::Null
    );
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut from_scene_file = None;
    let (update, lamp) = loop {
        assert!(
            Instant::now() < deadline,
            "no update from the probe with the lamp on"
        );
        let notification = match subscriber.next_notification() {
            Ok(notification) => notification,
            Err(ClientError::Timeout(_)) => continue,
            Err(err) => panic!("subscription ended: {err}"),
        };
        assert_eq!(notification.method, "lights.update");
        let estimate: LightingEstimate =
            serde_json::from_value(notification.params.clone()).expect("an estimate");
        match (estimate.environment_stamp, lamp_light(&estimate)) {
            (None, _) => from_scene_file = Some(estimate),
            (Some(_), Some(lamp)) => break (estimate, lamp),
            (Some(_), None) => {}
        }
    };
    // Before the probe's first bracket: the scene file's light.
    if let Some(first) = from_scene_file {
        assert!(
            first.lights.iter().any(|light| matches!(light,
                relight_core::light::Light::Point { position_in_world, .. }
                    if position_in_world.to_array() == SCENE_LIGHT_POSITION)),
            "the scene file's light: {first:?}"
        );
    }
    // From the probe: median-cut directional lights (16 by default) and the lamp.
    let directional = update
        .lights
        .iter()
        .filter(|l| matches!(l, relight_core::light::Light::Directional { .. }))
        .count();
    assert!(directional >= 8, "{directional} probe lights: {update:?}");
    assert!(update.sh9.is_finite() && update.sh9.coeffs[0].max_element() > 0.0);
    let main = update.main_light.expect("the scene is lit");
    assert!(
        main.direction_in_world.is_finite()
            && (main.direction_in_world.length() - 1.0).abs() < 1e-4
            && main.intensity > 0.0
            && main.color.max_element() == 1.0,
        "{main:?}"
    );
    // The lights it renders with are above the virtual box: the main light travels downwards.
    assert!(main.direction_in_world.y < 0.0, "{main:?} from {lamp:?}");

    // `lights.get` on another connection serves an estimate of the same shape.
    let mut other = Client::connect(&daemon.socket, TIMEOUT).expect("connect");
    let current = other.call("lights.get", None).expect("lights.get");
    let current: LightingEstimate = serde_json::from_value(current).expect("an estimate");
    assert!(current.main_light.is_some(), "{current:?}");

    // `lights.export` writes the probe's HDR map it came from, into the snapshot directory; its
    // SH projection is the estimate's `sh9` (a later bracket may have replaced it in between:
    // the simulated probe of a still scene repeats itself to within its noise).
    let exported = other
        .call("lights.export", Some(json!({ "path": "env.exr" })))
        .expect("lights.export");
    let path = dir.path().join("snapshots/env.exr");
    assert_eq!(exported["path"], json!(path), "{exported}");
    let map = read_exr_map(&path);
    assert_eq!((map.width, map.height), (128, 64), "{exported}");
    assert!(
        map.radiance
            .iter()
            .all(|r| r.is_finite() && r.min_element() >= 0.0)
    );
    let projected = relight_recon::irradiance::project_sh9(&map).expect("projects");
    let (dc, expected) = (projected.coeffs[0], current.sh9.coeffs[0]);
    assert!(
        ((dc - expected).abs() / expected).max_element() < 0.05,
        "exported map's DC {dc} vs the estimate's {expected}"
    );
    match other.call("lights.export", Some(json!({ "path": "env.exr" }))) {
        Err(ClientError::Rpc(error)) => assert_eq!(error.code, codes::IO, "{error:?}"),
        other => panic!("an existing file is refused, got {other:?}"),
    }

    // Bad input: JSON-RPC errors, and both connections keep working.
    for (params, code) in [
        (json!({ "rate_hz": 5 }), codes::INVALID_PARAMS),
        (json!([true]), codes::INVALID_PARAMS),
    ] {
        match other.call("lights.subscribe", Some(params.clone())) {
            Err(ClientError::Rpc(error)) => assert_eq!(error.code, code, "{params}: {error:?}"),
            other => panic!("{params}: expected an error, got {other:?}"),
        }
    }
    let line = br#"{"jsonrpc":"2.0","id":9,"method":"lights.subscribe","params":5}"#;
    other.send_raw(line).expect("send");
    other.send_raw(b"\n").expect("send");
    let response = other.read_response().expect("response");
    assert_eq!(
        response["error"]["code"],
        codes::INVALID_REQUEST,
        "{response}"
    );
    assert_eq!(other.call("rpc.ping", None).expect("ping"), json!("pong"));
    assert_eq!(
        subscriber.call("rpc.ping", None).expect("ping"),
        json!("pong")
    );
    let status = other.call("status", None).expect("status");
    assert_eq!(status["render_errors"], 0, "{status}");

    // relightctl shows it too.
    let out = Command::new(env!("CARGO_BIN_EXE_relightctl"))
        .arg("--socket")
        .arg(&daemon.socket)
        .args(["--json", "lights", "get"])
        .output()
        .expect("relightctl runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let printed: LightingEstimate =
        serde_json::from_slice(&out.stdout).expect("relightctl --json prints the estimate");
    assert!(printed.main_light.is_some());
}
