//! The OpenNI2 backend through Debian's libopenni2 itself: OpenNI's DummyDevice driver (reached
//! by the URI `Dummy`; a 320 × 240 synthetic source whose frames are a closed-form pattern,
//! DummyDevice.cpp), OpenNI's recorder writing `.oni` files from it, and the OniFile driver
//! playing them back — frame for frame, to the end, looping, and across the failure paths the
//! runner must survive (a recording that appears late, a stream that stops delivering).
//!
//! OpenNI2 has one context per process; the tests take turns (`serial`) so that one test's
//! devices (which OpenNI keeps listed while the context lives) cannot change what another
//! test's "first enumerated device" is. `two_devices_share_one_openni_context` runs two devices
//! at once on purpose. The process records DummyDevice once and every playback test uses that
//! file: a second OpenNI recorder in one process is what Debian's libOpenNI2 can crash on (its
//! error logger probes the first recorder's ended thread; see the backend's `ffi` module).

#![cfg(feature = "openni2")]

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::{Duration, Instant};

use relight_backends::device::Backoff;
use relight_backends::openni2::{
    DepthFormat, OpenNi2Config, OpenNi2Device, list_devices, record_oni,
};
use relight_backends::{Device, DeviceError, DeviceRunner, DeviceState};
use relight_core::bus::{Bus, Subscription};
use relight_core::frame::host_now_ns;
use relight_core::{Frame, Image, PixelFormat, StreamKind};

/// DummyDevice.cpp: OZ_RESOLUTION_X × OZ_RESOLUTION_Y, one frame every 33 ms, timestamps
/// `frameId * 33000` µs.
const WIDTH: i32 = 320;
const HEIGHT: i32 = 240;
const FRAME_US: u64 = 33_000;

fn serial() -> MutexGuard<'static, ()> {
    static SERIAL: Mutex<()> = Mutex::new(());
    SERIAL.lock().unwrap_or_else(PoisonError::into_inner)
}

fn tiny_backoff() -> Backoff {
    Backoff {
        initial: Duration::from_millis(20),
        max: Duration::from_millis(50),
    }
}

fn dummy_config() -> OpenNi2Config {
    OpenNi2Config {
        uri: Some("Dummy".into()),
        ..OpenNi2Config::default()
    }
}

fn playback_config(path: &Path) -> OpenNi2Config {
    OpenNi2Config {
        uri: Some(path.to_str().unwrap().into()),
        ..OpenNi2Config::default()
    }
}

fn spawn(config: OpenNi2Config, streams: &[StreamKind], bus: &Arc<Bus>) -> DeviceRunner {
    let device = OpenNi2Device::new(config, streams).unwrap();
    DeviceRunner::spawn("openni2", Box::new(device), bus.clone(), tiny_backoff()).unwrap()
}

fn wait_until(timeout: Duration, mut done: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if done() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    done()
}

fn receive(sub: &Subscription<Arc<Frame<Image>>>, n: usize) -> Vec<Arc<Frame<Image>>> {
    let mut frames = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(10);
    while frames.len() < n && Instant::now() < deadline {
        if let Some(frame) = sub.recv_timeout(Duration::from_millis(100)) {
            frames.push(frame);
        }
    }
    assert_eq!(frames.len(), n, "frames within 10 s");
    frames
}

/// Where DummyDevice draws its disk in frames 1..=n: it starts at `start`, moves by `step` per
/// frame and bounces off the borders (`Mainloop` of OzDepthStream / OzImageStream).
fn disk_centres(n: u32, start: (i32, i32), step: (i32, i32)) -> Vec<(i32, i32)> {
    let (mut c, mut d) = (start, step);
    (0..n)
        .map(|_| {
            let drawn = c;
            c = (c.0 + d.0, c.1 + d.1);
            if c.0 < d.0.abs() || c.0 > WIDTH - 1 - d.0.abs() {
                d.0 = -d.0;
            }
            if c.1 < d.1.abs() || c.1 > HEIGHT - 1 - d.1.abs() {
                d.1 = -d.1;
            }
            drawn
        })
        .collect()
}

fn in_disk(x: i32, y: i32, c: (i32, i32)) -> bool {
    (c.0 - 10..c.0 + 10).contains(&x)
        && (c.1 - 10..c.1 + 10).contains(&y)
        && (x - c.0).pow(2) + (y - c.1).pow(2) < 70
}

/// DummyDevice's depth frame `frame_id` (from 1): zero but for a disk of 1000 + 3 (x − y) mm
/// around a centre that starts at (0, 0) and moves diagonally, and a first row of 2000 mm.
fn dummy_depth_mm(frame_id: u32) -> Vec<u16> {
    let c = disk_centres(frame_id, (0, 0), (1, 1))[frame_id as usize - 1];
    let mut depth = vec![0u16; (WIDTH * HEIGHT) as usize];
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            if in_disk(x, y, c) {
                depth[(y * WIDTH + x) as usize] = (1000 + (x - y) * 3) as u16;
            }
        }
    }
    depth[..WIDTH as usize].fill(2000);
    depth
}

/// DummyDevice's colour frame `frame_id`: black but for a disk coloured by its position around
/// a centre that starts at (160, 120) and moves by (−3, 1), and a blue first pixel.
fn dummy_rgb(frame_id: u32) -> Vec<u8> {
    let c = disk_centres(frame_id, (160, 120), (-3, 1))[frame_id as usize - 1];
    let mut rgb = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    let channel = |v: f64| (255.0 * v) as i32 as u8;
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            if in_disk(x, y, c) {
                let i = ((y * WIDTH + x) * 3) as usize;
                rgb[i] = channel(f64::from(x) / f64::from(WIDTH));
                rgb[i + 1] = channel(f64::from(y) / f64::from(HEIGHT));
                rgb[i + 2] = channel(f64::from(WIDTH - x) / f64::from(WIDTH));
            }
        }
    }
    rgb[2] = 255;
    rgb
}

fn assert_dummy_depth(frame: &Frame<Image>, frame_id: u32) {
    let image = &frame.payload;
    assert_eq!(
        (image.width(), image.height(), image.format()),
        (320, 240, PixelFormat::DepthU16Mm)
    );
    assert!(
        image.as_u16().unwrap() == dummy_depth_mm(frame_id).as_slice(),
        "depth seq {} is not DummyDevice frame {frame_id}",
        frame.seq
    );
}

/// Frames of each stream the shared recording is made of.
const RECORDED_FRAMES: u32 = 10;

/// DummyDevice's depth and colour, recorded once per process with OpenNI's recorder.
#[derive(Debug)]
struct Recording {
    path: PathBuf,
    depth_frames: u32,
    color_frames: u32,
}

fn recording() -> &'static Recording {
    static RECORDING: OnceLock<Recording> = OnceLock::new();
    RECORDING.get_or_init(|| {
        // In Cargo's per-target scratch directory; files of test processes that have ended are
        // cleared out.
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR"));
        for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let pid = name
                .strip_prefix("openni2-dummy-")
                .and_then(|rest| rest.strip_suffix(".oni"));
            if let Some(pid) = pid
                && !Path::new("/proc").join(pid).exists()
            {
                let _ = std::fs::remove_file(entry.path());
            }
        }
        let path = dir.join(format!("openni2-dummy-{}.oni", std::process::id()));
        let summary = record_oni(
            &dummy_config(),
            &[StreamKind::Depth, StreamKind::Color],
            &path,
            RECORDED_FRAMES,
        )
        .unwrap();
        assert_eq!(summary.path, path);
        let depth_frames = summary.frames(StreamKind::Depth).unwrap();
        let color_frames = summary.frames(StreamKind::Color).unwrap();
        // The recorder takes every frame the driver raises while it runs: at least what the
        // reader counted, one more for the stream that got there first.
        for n in [depth_frames, color_frames] {
            assert!(
                n >= RECORDED_FRAMES,
                "{n} frames recorded for {RECORDED_FRAMES} read"
            );
        }
        Recording {
            path,
            depth_frames,
            color_frames,
        }
    })
}

/// A copy of the shared recording at `path`, for tests that move or damage it.
fn copy_recording(path: &Path) {
    let staging = path.with_extension("staging");
    std::fs::copy(&recording().path, &staging).unwrap();
    std::fs::rename(&staging, path).unwrap();
}

/// Which DummyDevice frame a recorded one is (the recorder renumbers from 1).
fn dummy_frame_id(image: &Image) -> u32 {
    let depth = image.as_u16().unwrap();
    (1..=2000)
        .find(|&k| depth == dummy_depth_mm(k).as_slice())
        .expect("a DummyDevice frame")
}

#[test]
fn dummy_depth_frames_are_the_driver_pattern_with_its_indices_and_clock() {
    let _serial = serial();
    let bus = Arc::new(Bus::new());
    let depth = bus.depth.subscribe(64);
    let mut runner = spawn(dummy_config(), &[StreamKind::Depth], &bus);
    // Each frame with the host time the test got it.
    let mut frames = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(10);
    while frames.len() < 30 && Instant::now() < deadline {
        if let Some(frame) = depth.recv_timeout(Duration::from_millis(100)) {
            frames.push((frame, host_now_ns()));
        }
    }
    runner.stop();
    assert_eq!(frames.len(), 30, "frames within 10 s");

    let status = runner.status();
    assert_eq!(status.state(), DeviceState::Stopped);
    assert_eq!(status.last_error(), None);
    let mut gaps = 0;
    for pair in frames.windows(2) {
        let (a, b) = (&pair[0].0, &pair[1].0);
        assert!(b.seq > a.seq, "seq increases");
        assert!(b.stamp.host_ns > a.stamp.host_ns);
        gaps += b.seq - a.seq - 1;
    }
    assert_eq!(status.drops(), gaps, "every index gap is counted as drops");
    for (frame, _) in &frames {
        let frame_id = u32::try_from(frame.seq).unwrap();
        assert_dummy_depth(frame, frame_id);
        assert_eq!(frame.stamp.device_ns, frame.seq * FRAME_US * 1000);
    }

    // Measured, not asserted. The driver's pace on the host clock; the read-back latency from
    // OpenNI handing a frame over (host stamp) to a subscriber holding it; and how much the
    // hand-over time wanders against the driver's clock, a straight line through both clocks
    // taken out (DummyDevice sleeps 33 ms per frame, so its real period is a little longer).
    let (first, last) = (&frames[0].0, &frames[frames.len() - 1].0);
    let span_s = (last.stamp.host_ns - first.stamp.host_ns) as f64 / 1e9;
    let fps = (last.seq - first.seq) as f64 / span_s;
    let latency_ms: Vec<f64> = frames
        .iter()
        .map(|(f, got_ns)| got_ns.saturating_sub(f.stamp.host_ns) as f64 / 1e6)
        .collect();
    let mut sorted = latency_ms.clone();
    sorted.sort_by(f64::total_cmp);
    let median_latency = sorted[sorted.len() / 2];
    let max_latency = sorted[sorted.len() - 1];
    let points: Vec<(f64, f64)> = frames
        .iter()
        .map(|(f, _)| {
            (
                (f.stamp.device_ns - first.stamp.device_ns) as f64 / 1e6,
                (f.stamp.host_ns - first.stamp.host_ns) as f64 / 1e6,
            )
        })
        .collect();
    let n = points.len() as f64;
    let (mx, my) = (
        points.iter().map(|p| p.0).sum::<f64>() / n,
        points.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let slope = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum::<f64>()
        / points.iter().map(|p| (p.0 - mx).powi(2)).sum::<f64>();
    let residual_ms = points
        .iter()
        .map(|p| (p.1 - my - slope * (p.0 - mx)).abs())
        .fold(0.0, f64::max);
    eprintln!(
        "DummyDevice depth: {fps:.2} fps over {} frames ({gaps} missed); read-back latency \
         {median_latency:.2} ms median, {max_latency:.2} ms max; host/device clock ratio {slope:.4}, \
         hand-over jitter {residual_ms:.2} ms max",
        frames.len()
    );
}

#[test]
fn dummy_depth_and_colour_together_run_unregistered() {
    let _serial = serial();
    let bus = Arc::new(Bus::new());
    let depth = bus.depth.subscribe(64);
    let color = bus.color.subscribe(64);
    // DummyDevice has no registration: that is logged, and both streams run.
    let mut runner = spawn(
        dummy_config(),
        &[StreamKind::Color, StreamKind::Depth],
        &bus,
    );
    let depth_frames = receive(&depth, 8);
    let color_frames = receive(&color, 8);
    runner.stop();
    assert_eq!(runner.status().last_error(), None);
    assert_eq!(
        runner.status().streams,
        vec![StreamKind::Depth, StreamKind::Color]
    );

    for frame in &depth_frames {
        assert_dummy_depth(frame, u32::try_from(frame.seq).unwrap());
    }
    for frame in &color_frames {
        let image = &frame.payload;
        assert_eq!(
            (image.width(), image.height(), image.format()),
            (320, 240, PixelFormat::Rgb8)
        );
        let frame_id = u32::try_from(frame.seq).unwrap();
        assert!(
            image.as_u8().unwrap() == dummy_rgb(frame_id).as_slice(),
            "colour seq {} is not DummyDevice frame {frame_id}",
            frame.seq
        );
        assert_eq!(frame.stamp.device_ns, frame.seq * FRAME_US * 1000);
    }
}

/// Which DummyDevice colour frame a recorded one is.
fn dummy_rgb_id(image: &Image) -> u32 {
    let rgb = image.as_u8().unwrap();
    (1..=2000)
        .find(|&k| rgb == dummy_rgb(k).as_slice())
        .expect("a DummyDevice colour frame")
}

#[test]
fn recording_plays_back_frame_for_frame_then_ends() {
    let _serial = serial();
    let recording = recording();
    let bus = Arc::new(Bus::new());
    let depth = bus.depth.subscribe(64);
    let color = bus.color.subscribe(64);
    let mut runner = spawn(
        playback_config(&recording.path),
        &[StreamKind::Depth, StreamKind::Color],
        &bus,
    );
    assert!(
        wait_until(Duration::from_secs(10), || runner.is_finished()),
        "playback ends by itself"
    );
    runner.stop();
    let status = runner.status();
    assert_eq!(status.state(), DeviceState::Stopped);
    assert_eq!(status.last_error(), None, "ended with EndOfStream");

    let depth_frames: Vec<_> = std::iter::from_fn(|| depth.try_recv()).collect();
    let color_frames: Vec<_> = std::iter::from_fn(|| color.try_recv()).collect();
    // OniFile does not wait for its reader, and OpenNI keeps one frame per stream: a reader
    // starved of CPU loses frames, which the index gaps count. Every recorded frame is either
    // delivered or counted (normally all are delivered).
    assert_eq!(
        depth_frames.len() + color_frames.len() + status.drops() as usize,
        (recording.depth_frames + recording.color_frames) as usize
    );
    let last_seq = |frames: &[Arc<Frame<Image>>]| frames.last().map(|f| f.seq);
    assert_eq!(
        last_seq(&depth_frames),
        Some(u64::from(recording.depth_frames))
    );
    assert_eq!(
        last_seq(&color_frames),
        Some(u64::from(recording.color_frames))
    );
    // Frame for frame what DummyDevice drew, in order, with the driver's spacing (the recorder
    // renumbers each stream from 1 and rebases its clock to its first frame).
    let first_depth = dummy_frame_id(&depth_frames[0].payload) - (depth_frames[0].seq as u32 - 1);
    for frame in &depth_frames {
        assert_dummy_depth(frame, first_depth + frame.seq as u32 - 1);
        assert_eq!(frame.stamp.device_ns, (frame.seq - 1) * FRAME_US * 1000);
    }
    let first_color = dummy_rgb_id(&color_frames[0].payload) - (color_frames[0].seq as u32 - 1);
    for frame in &color_frames {
        assert_eq!(frame.payload.format(), PixelFormat::Rgb8);
        let expected = dummy_rgb(first_color + frame.seq as u32 - 1);
        assert!(frame.payload.as_u8().unwrap() == expected.as_slice());
        assert_eq!(frame.stamp.device_ns, (frame.seq - 1) * FRAME_US * 1000);
    }
    for frames in [&depth_frames, &color_frames] {
        assert!(frames.windows(2).all(|p| p[1].seq > p[0].seq));
    }
}

#[test]
fn looping_playback_rewinds_with_continuing_sequence_numbers() {
    let _serial = serial();
    let recording = recording();
    let bus = Arc::new(Bus::new());
    let depth = bus.depth.subscribe(64);
    // The test keeps every frame it receives: the pool must outlast them.
    let config = OpenNi2Config {
        loop_playback: true,
        playback_speed: 2.0,
        pool_frames: 4 * recording.depth_frames as usize,
        ..playback_config(&recording.path)
    };
    let mut runner = spawn(config, &[StreamKind::Depth], &bus);
    let frames = receive(&depth, 3 * recording.depth_frames as usize);
    runner.stop();
    assert_eq!(runner.status().last_error(), None);

    let first_id = dummy_frame_id(&frames[0].payload);
    for pair in frames.windows(2) {
        assert!(pair[1].seq > pair[0].seq, "seq never goes back on a rewind");
    }
    let rewinds = frames
        .windows(2)
        .filter(|pair| pair[1].stamp.device_ns < pair[0].stamp.device_ns)
        .count();
    assert!(rewinds >= 2, "{rewinds} rewinds in three recordings' worth");
    for frame in &frames {
        // Within a pass, the device clock says which recorded frame this is.
        let index = frame.stamp.device_ns / (FRAME_US * 1000);
        assert!(index < u64::from(recording.depth_frames));
        assert_dummy_depth(frame, first_id + index as u32);
    }
}

#[test]
fn a_recording_that_appears_late_is_lost_until_then_and_plays() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let late = dir.path().join("late.oni");

    let bus = Arc::new(Bus::new());
    let depth = bus.depth.subscribe(64);
    let mut runner = spawn(playback_config(&late), &[StreamKind::Depth], &bus);
    let status = runner.status().clone();
    assert!(wait_until(Duration::from_secs(5), || {
        status.state() == DeviceState::Lost
    }));
    let error = status.last_error().unwrap();
    assert!(
        error.contains("not found") && error.contains("late.oni"),
        "{error}"
    );

    copy_recording(&late);
    assert!(
        wait_until(Duration::from_secs(10), || runner.is_finished()),
        "plays once it is there, then ends"
    );
    runner.stop();
    let frames: Vec<_> = std::iter::from_fn(|| depth.try_recv()).collect();
    assert_eq!(
        frames.len() + status.drops() as usize,
        recording().depth_frames as usize
    );
    assert_eq!(status.state(), DeviceState::Stopped);
}

#[test]
fn a_stream_that_stops_delivering_is_lost_and_resumes_when_reopened() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let live = dir.path().join("live.oni");
    copy_recording(&live);

    let bus = Arc::new(Bus::new());
    let depth = bus.depth.subscribe(256);
    let config = OpenNi2Config {
        loop_playback: true,
        stall_timeout_ms: 400,
        ..playback_config(&live)
    };
    let mut runner = spawn(config, &[StreamKind::Depth], &bus);
    let status = runner.status().clone();
    let before = receive(&depth, 3);

    // Pull the medium: OniFile's reader keeps its descriptor, whose file is now empty, so no
    // frame comes any more; then the path is gone for the reopen attempts.
    std::fs::OpenOptions::new()
        .write(true)
        .open(&live)
        .unwrap()
        .set_len(0)
        .unwrap();
    std::fs::remove_file(&live).unwrap();
    assert!(
        wait_until(Duration::from_secs(10), || status.reconnects() >= 1),
        "stall reported as a loss: {:?}",
        status.last_error()
    );
    assert!(wait_until(Duration::from_secs(5), || {
        status.state() == DeviceState::Lost
            && status.last_error().is_some_and(|e| e.contains("not found"))
    }));

    // Put it back: the runner's next attempt opens it and frames flow again.
    copy_recording(&live);
    let last_seq_before = before.last().unwrap().seq;
    let mut resumed = false;
    assert!(wait_until(Duration::from_secs(10), || {
        while let Some(frame) = depth.try_recv() {
            resumed |= frame.seq > last_seq_before && status.state() == DeviceState::Running;
        }
        resumed
    }));
    runner.stop();
    assert_eq!(status.state(), DeviceState::Stopped);
}

#[test]
fn two_devices_share_one_openni_context() {
    let _serial = serial();
    let live_bus = Arc::new(Bus::new());
    let live = live_bus.depth.subscribe(64);
    let replay_bus = Arc::new(Bus::new());
    let replayed = replay_bus.depth.subscribe(64);
    let mut live_runner = spawn(dummy_config(), &[StreamKind::Depth], &live_bus);
    let mut replay_runner = spawn(
        OpenNi2Config {
            loop_playback: true,
            ..playback_config(&recording().path)
        },
        &[StreamKind::Depth],
        &replay_bus,
    );
    receive(&live, 3);
    receive(&replayed, 3);
    // Closing one device must not shut OpenNI down under the other.
    live_runner.stop();
    while replayed.try_recv().is_some() {}
    let after = receive(&replayed, 4);
    assert!(after.windows(2).all(|p| p[1].seq > p[0].seq));
    replay_runner.stop();
    assert_eq!(replay_runner.status().last_error(), None);
    assert_eq!(live_runner.status().last_error(), None);

    // With the last user gone OpenNI was shut down; it initialises again for the next.
    let mut device = OpenNi2Device::new(dummy_config(), &[StreamKind::Depth]).unwrap();
    device.open().unwrap();
    assert_eq!(device.info().unwrap().uri, "Dummy");
    assert_eq!(device.info().unwrap().vendor, "Table Tennis");
    device.close();
}

#[test]
fn open_errors_are_typed_and_carry_openni_messages() {
    let _serial = serial();
    let open = |config: OpenNi2Config| {
        OpenNi2Device::new(config, &[StreamKind::Depth])
            .unwrap()
            .open()
            .unwrap_err()
    };

    match open(OpenNi2Config {
        uri: Some("no-such-device".into()),
        ..OpenNi2Config::default()
    }) {
        DeviceError::NotFound { reason, .. } => {
            assert!(
                reason.contains("Couldn't open device 'no-such-device'"),
                "{reason}"
            );
        }
        other => panic!("{other}"),
    }

    // The mode DummyDevice does not list, and the depth format it does not have.
    match open(OpenNi2Config {
        width: Some(640),
        height: Some(480),
        ..dummy_config()
    }) {
        DeviceError::Config { reason, .. } => {
            assert!(reason.contains("640x480@30 DEPTH_1_MM"), "{reason}");
            assert!(
                reason.contains("supports 320x240@30 DEPTH_1_MM"),
                "{reason}"
            );
        }
        other => panic!("{other}"),
    }
    match open(OpenNi2Config {
        depth_format: Some(DepthFormat::Depth100Um),
        ..dummy_config()
    }) {
        DeviceError::Config { reason, .. } => assert!(reason.contains("DEPTH_100_UM"), "{reason}"),
        other => panic!("{other}"),
    }

    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("garbage.oni");
    std::fs::write(&garbage, b"not an OpenNI recording").unwrap();
    match open(playback_config(&garbage)) {
        DeviceError::Config { reason, .. } => {
            assert!(
                reason.contains("not a readable OpenNI recording"),
                "{reason}"
            );
        }
        other => panic!("{other}"),
    }
    match open(playback_config(&dir.path().join("absent.oni"))) {
        DeviceError::NotFound { reason, .. } => assert!(reason.contains("absent.oni"), "{reason}"),
        other => panic!("{other}"),
    }

    // Nothing enumerated (DummyDevice is reached only by name): no default device; with real
    // hardware attached, the default is the first one listed.
    let listed = list_devices().unwrap();
    let mut default = OpenNi2Device::new(OpenNi2Config::default(), &[StreamKind::Depth]).unwrap();
    match (listed.first(), default.open()) {
        (None, Err(DeviceError::NotFound { reason, .. })) => {
            assert!(reason.contains("no device connected"), "{reason}");
        }
        (Some(first), Ok(())) => assert_eq!(default.info().unwrap().uri, first.uri),
        (first, result) => panic!("listed {first:?}, opened {result:?}"),
    }
}

#[test]
fn configuration_is_checked_before_any_device_is_touched() {
    let config: Result<OpenNi2Config, _> =
        serde_json::from_value(serde_json::json!({ "uri": "Dummy", "exposure": 3 }));
    assert!(config.unwrap_err().to_string().contains("exposure"));
    let config: OpenNi2Config = serde_json::from_value(serde_json::json!({
        "uri": "/data/take1.oni", "loop": true, "playback_speed": 0.5,
        "depth_format": "depth_100_um", "width": 640, "height": 480, "fps": 30,
        "registration": false, "stall_timeout_ms": 2000, "pool_frames": 8
    }))
    .unwrap();
    assert!(config.loop_playback);
    assert_eq!(config.depth_format, Some(DepthFormat::Depth100Um));

    let config_error = |result: Result<OpenNi2Device, DeviceError>| {
        matches!(result, Err(DeviceError::Config { .. }))
    };
    assert!(config_error(OpenNi2Device::new(
        dummy_config(),
        &[StreamKind::Probe]
    )));
    assert!(config_error(OpenNi2Device::new(
        OpenNi2Config {
            playback_speed: -1.0,
            ..dummy_config()
        },
        &[StreamKind::Depth]
    )));
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(
        record_oni(
            &dummy_config(),
            &[StreamKind::Depth],
            &dir.path().join("none.oni"),
            0
        ),
        Err(DeviceError::Config { .. })
    ));
}
