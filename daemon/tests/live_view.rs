//! The live view end to end: `relightd replay --live-view --live-page` relights the bundled
//! recording; a Foxglove protocol client (`foxglove.sdk.v1`, the WebSocket protocol's current
//! name for what was `foxglove.websocket.v1`, over tokio-tungstenite)
//! subscribes and decodes a composite and the transforms, and headless Chromium renders the
//! page to a screenshot whose composite must not be blank.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use prost::Message as _;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

struct Replay(Child);

impl Drop for Replay {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// The daemon's status once its live view listens and has rendered a frame.
fn wait_for_live_view(socket: &Path, replay: &mut Replay) -> Value {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        if let Some(status) = replay.0.try_wait().unwrap() {
            panic!("relightd replay exited with {status}");
        }
        let out = Command::new(env!("CARGO_BIN_EXE_relightctl"))
            .args(["--json", "--socket"])
            .arg(socket)
            .arg("status")
            .output()
            .unwrap();
        if out.status.success() {
            let status: Value = serde_json::from_slice(&out.stdout).unwrap();
            if status["frames_rendered"].as_u64().unwrap_or(0) > 0 {
                return status;
            }
        }
        assert!(Instant::now() < deadline, "no frame rendered in time");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// One message of a Foxglove binary `MessageData` frame: opcode 1, subscription id, log time,
/// payload.
fn message_data(bytes: &[u8]) -> Option<(u32, &[u8])> {
    (bytes.len() >= 13 && bytes[0] == 1).then(|| {
        (
            u32::from_le_bytes(bytes[1..5].try_into().unwrap()),
            &bytes[13..],
        )
    })
}

/// Subscribe to the composite and `/tf` as Foxglove does, and return the first of each.
async fn foxglove_client(
    url: &str,
) -> (
    foxglove::messages::CompressedImage,
    foxglove::messages::FrameTransforms,
) {
    let mut request = url.into_client_request().unwrap();
    request
        .headers_mut()
        .insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut socket, response) = tokio_tungstenite::connect_async(request).await.unwrap();
    assert_eq!(
        response.headers()["Sec-WebSocket-Protocol"],
        "foxglove.sdk.v1"
    );
    let mut channels: Vec<Value> = Vec::new();
    let mut composite = None;
    let mut transforms = None;
    let (composite_sub, tf_sub) = (1, 2);
    let mut subscribed = false;
    while composite.is_none() || transforms.is_none() {
        match socket
            .next()
            .await
            .expect("the server keeps the connection")
            .unwrap()
        {
            Message::Text(text) => {
                let op: Value = serde_json::from_str(&text).unwrap();
                if op["op"] == "advertise" {
                    channels.extend(op["channels"].as_array().unwrap().iter().cloned());
                }
            }
            Message::Binary(bytes) => {
                let Some((subscription, payload)) = message_data(&bytes) else {
                    continue;
                };
                if subscription == composite_sub && composite.is_none() {
                    composite = Some(foxglove::messages::CompressedImage::decode(payload).unwrap());
                } else if subscription == tf_sub && transforms.is_none() {
                    transforms =
                        Some(foxglove::messages::FrameTransforms::decode(payload).unwrap());
                }
            }
            _ => {}
        }
        let id = |topic: &str| {
            channels
                .iter()
                .find(|c| c["topic"] == topic)
                .map(|c| c["id"].clone())
        };
        if !subscribed
            && let (Some(composite_id), Some(tf_id)) = (id("/relight/composite"), id("/tf"))
        {
            for (topic, schema) in [
                ("/relight/composite", "foxglove.CompressedImage"),
                ("/tf", "foxglove.FrameTransforms"),
            ] {
                let channel = channels.iter().find(|c| c["topic"] == topic).unwrap();
                assert_eq!(channel["schemaName"], schema);
                assert_eq!(channel["encoding"], "protobuf");
            }
            let subscribe = json!({"op": "subscribe", "subscriptions": [
                {"id": composite_sub, "channelId": composite_id},
                {"id": tf_sub, "channelId": tf_id},
            ]});
            socket
                .send(Message::Text(subscribe.to_string().into()))
                .await
                .unwrap();
            subscribed = true;
        }
    }
    for topic in [
        "/relight/delta",
        "/relight/depth",
        "/relight/camera_calibration",
        "/relight/scene",
        "/relight/status",
        "/relight/lighting",
    ] {
        assert!(
            channels.iter().any(|c| c["topic"] == topic),
            "{topic} is advertised"
        );
    }
    (composite.unwrap(), transforms.unwrap())
}

/// Chromium when installed (`scripts/test` installs it and sets `RELIGHT_REQUIRE_CHROMIUM`).
fn chromium() -> Option<PathBuf> {
    let found = ["chromium", "chromium-browser", "google-chrome"]
        .iter()
        .find_map(|name| {
            let out = Command::new("sh")
                .args(["-c", &format!("command -v {name}")])
                .output()
                .ok()?;
            out.status
                .success()
                .then(|| PathBuf::from(String::from_utf8_lossy(&out.stdout).trim()))
        });
    if found.is_none() {
        assert!(
            std::env::var_os("RELIGHT_REQUIRE_CHROMIUM").is_none(),
            "RELIGHT_REQUIRE_CHROMIUM is set and no chromium is installed"
        );
        eprintln!("no chromium: the page's screenshot check is skipped");
    }
    found
}

#[test]
fn the_live_view_serves_foxglove_and_a_page_with_the_relit_composite() {
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("control.sock");
    let mut replay = Replay(
        Command::new(env!("CARGO_BIN_EXE_relightd"))
            .arg("replay")
            .arg(repo("tests/fixtures/demo.mcap"))
            .args(["--loop", "--engine", "differential", "--scene"])
            .arg(repo("tests/scenes/desk_box"))
            .args(["--live-view", "127.0.0.1:0", "--live-page", "127.0.0.1:0"])
            .arg("--socket")
            .arg(&socket)
            .env("RELIGHT_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let status = wait_for_live_view(&socket, &mut replay);
    let foxglove_url = status["live_view"]["foxglove"].as_str().unwrap().to_owned();
    let page_url = status["live_view"]["page"].as_str().unwrap().to_owned();

    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let (composite, transforms) = runtime.block_on(async {
        tokio::time::timeout(Duration::from_secs(60), foxglove_client(&foxglove_url))
            .await
            .expect("a composite and a transform within a minute")
    });
    assert_eq!(composite.format, "jpeg");
    assert_eq!(composite.frame_id, "color");
    let mut decoder = jpeg_decoder::Decoder::new(&composite.data[..]);
    let pixels = decoder.decode().unwrap();
    let info = decoder.info().unwrap();
    assert_eq!(
        (info.width, info.height),
        (320, 240),
        "the recording's size"
    );
    let mean = pixels.iter().map(|&v| f64::from(v)).sum::<f64>() / pixels.len() as f64;
    assert!(mean > 20.0, "the composite is not black (mean {mean})");

    let find = |parent: &str, child: &str| {
        transforms
            .transforms
            .iter()
            .find(|t| t.parent_frame_id == parent && t.child_frame_id == child)
            .unwrap_or_else(|| panic!("{parent} → {child} in {transforms:?}"))
    };
    find("map", "world");
    let camera = find("world", "color");
    let q = camera.rotation.as_ref().unwrap();
    let norm = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    assert!((norm - 1.0).abs() < 1e-3, "a unit rotation");
    // The board lies in front of the camera: in the optical frame, +z.
    let marker = transforms
        .transforms
        .iter()
        .find(|t| t.parent_frame_id == "color" && t.child_frame_id.starts_with("marker_"))
        .expect("the markers of the frame set, under the camera");
    assert!(marker.translation.as_ref().unwrap().z > 0.1, "{marker:?}");
    find("world", "virtual_object");

    let Some(chromium) = chromium() else { return };
    let screenshot = dir.path().join("page.png");
    let out = Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--window-size=1200,700",
            "--virtual-time-budget=5000",
        ])
        .arg(format!(
            "--user-data-dir={}",
            dir.path().join("chromium").display()
        ))
        .arg(format!("--screenshot={}", screenshot.display()))
        .arg(&page_url)
        .output()
        .unwrap();
    assert!(
        screenshot.exists(),
        "chromium wrote no screenshot: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(&screenshot).unwrap(),
    ));
    let mut reader = decoder.read_info().unwrap();
    let mut buffer = vec![0; reader.output_buffer_size().unwrap()];
    let frame = reader.next_frame(&mut buffer).unwrap();
    let channels = frame.color_type.samples();
    // The page puts the composite at (16, 16), 640 wide: 480 high at the recording's 4:3.
    let mut colours = std::collections::HashSet::new();
    let mut background = 0;
    let mut samples = 0;
    for y in (40..460).step_by(4) {
        for x in (40..620).step_by(4) {
            let i = (y * frame.width as usize + x) * channels;
            let rgb = [buffer[i], buffer[i + 1], buffer[i + 2]];
            background += usize::from(rgb == [0x11, 0x11, 0x11]);
            colours.insert(rgb.map(|v| v / 8));
            samples += 1;
        }
    }
    assert!(
        background * 10 < samples,
        "the page's composite area is mostly page background ({background} of {samples})"
    );
    assert!(
        colours.len() > 50,
        "the composite in the screenshot is flat ({} colours)",
        colours.len()
    );
}
