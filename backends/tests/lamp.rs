//! The serial lamp over a pseudo-terminal: the test holds the master side and plays the lamp's
//! firmware ([`LampReport::to_line`]); the backend opens the slave through `serialport`, exactly
//! as it opens a USB-serial adapter.

#![cfg(feature = "lamp")]

use std::ffi::OsString;
use std::fs::File;
use std::io::Write;
use std::os::unix::ffi::OsStringExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use glam::{Quat, Vec3};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use relight_backends::device::Backoff;
use relight_backends::lamp::{LampConfig, MarkerPositioner, SerialLamp};
use relight_backends::lamp_protocol::LampReport;
use relight_backends::sources::{FrameSource, SourceDevice};
use relight_backends::{DeviceError, DeviceRunner, DeviceState, DeviceStatus};
use relight_core::bus::{Bus, Subscription};
use relight_core::rig::RigCalibration;
use relight_core::{Frame, LampState, MarkerDetection, MarkerSet, Pose, Timestamp};

const LAMP_MARKER: u32 = 7;
const MAX_INTENSITY_W_SR: f32 = 3.0;

/// A pseudo-terminal pair: the master stays here, `slave` is the path the backend opens.
struct Pty {
    master: File,
    slave: PathBuf,
}

fn open_pty() -> Pty {
    use rustix::pty::{OpenptFlags, grantpt, openpt, ptsname, unlockpt};
    let master =
        openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY | OpenptFlags::CLOEXEC).expect("openpt");
    grantpt(&master).expect("grantpt");
    unlockpt(&master).expect("unlockpt");
    let name = ptsname(&master, Vec::new()).expect("ptsname");
    // Raw from the start, so bytes written before the backend configures the port are not
    // cooked (CR → LF, echo) by the line discipline.
    let mut termios = rustix::termios::tcgetattr(&master).expect("tcgetattr");
    termios.make_raw();
    rustix::termios::tcsetattr(&master, rustix::termios::OptionalActions::Now, &termios)
        .expect("tcsetattr");
    Pty {
        master: File::from(master),
        slave: PathBuf::from(OsString::from_vec(name.into_bytes())),
    }
}

fn report(seq: u32) -> LampReport {
    LampReport {
        seq,
        on: !seq.is_multiple_of(5),
        level: f32::from(u8::try_from(seq % 100).unwrap()) / 100.0,
        cct_k: 2000 + 10 * (seq % 500),
        orientation: seq
            .is_multiple_of(2)
            .then(|| Quat::from_rotation_z(0.01 * (seq % 300) as f32)),
    }
}

fn world_from_camera() -> Pose {
    Pose::new(Quat::from_rotation_y(0.4), Vec3::new(0.5, 1.2, 2.0))
}

fn rig() -> RigCalibration {
    RigCalibration {
        lamp_marker_from_light: Pose::from_translation(Vec3::new(0.0, 0.04, -0.02)),
        ..RigCalibration::default()
    }
}

fn lamp_seen_at(seq: u64, camera_from_marker: Pose) -> Arc<Frame<MarkerSet>> {
    let detection = |marker_id, camera_from_marker| MarkerDetection {
        family: "tag36h11".into(),
        marker_id,
        corners_px: [glam::Vec2::ZERO; 4],
        camera_from_marker,
        reprojection_rms_px: 0.2,
    };
    Arc::new(Frame::new(
        seq,
        Timestamp::now(),
        MarkerSet {
            detections: vec![
                detection(0, Pose::IDENTITY),
                detection(LAMP_MARKER, camera_from_marker),
            ],
        },
    ))
}

fn no_lamp_seen(seq: u64) -> Arc<Frame<MarkerSet>> {
    Arc::new(Frame::new(seq, Timestamp::now(), MarkerSet::default()))
}

fn light_in_world(camera_from_marker: Pose) -> Vec3 {
    (world_from_camera() * camera_from_marker * rig().lamp_marker_from_light).translation
}

fn lamp(port: &Path, bus: &Bus) -> SerialLamp {
    let config = LampConfig::new(port, MAX_INTENSITY_W_SR, LAMP_MARKER);
    SerialLamp::on_bus(config, bus, &rig(), world_from_camera()).unwrap()
}

fn wait_until(what: &str, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(15);
    while !done() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn write_lines(master: &mut File, seqs: impl IntoIterator<Item = u32>) {
    for seq in seqs {
        master.write_all(report(seq).to_line().as_bytes()).unwrap();
    }
}

fn lamp_frames(subscription: &Subscription<Arc<Frame<LampState>>>) -> Vec<Arc<Frame<LampState>>> {
    std::iter::from_fn(|| subscription.try_recv()).collect()
}

/// A firmware session: the byte chunks the lamp writes (each one `write`), and what the backend
/// must make of them.
struct Session {
    chunks: Vec<Vec<u8>>,
    good: Vec<u32>,
    bad_lines: u64,
}

/// Reports from just below the u32 wrap, with every kind of damage a serial line sees between
/// them. The first and last report are good, so every gap lies between two received reports.
fn damaged_session(rng: &mut Pcg64, count: u32) -> Session {
    let first = u32::MAX - 40;
    let mut session = Session {
        chunks: Vec::new(),
        good: Vec::new(),
        bad_lines: 0,
    };
    let noise = |rng: &mut Pcg64, len| -> Vec<u8> {
        // A baud-rate mismatch reads as bytes with the high bit set.
        (0..len).map(|_| rng.random_range(0x80..=0xffu8)).collect()
    };
    for i in 0..count {
        let seq = first.wrapping_add(i);
        let line = report(seq).to_line().into_bytes();
        let edge = i == 0 || i == count - 1;
        match rng.random_range(0..10) {
            // Lost by the firmware's UART: never sent.
            0 if !edge => {}
            // A flipped bit: wrong checksum.
            1 if !edge => {
                let mut corrupted = line.clone();
                let at = rng.random_range(2..corrupted.len() - 5);
                corrupted[at] ^= 0x02;
                session.chunks.push(corrupted);
                session.bad_lines += 1;
            }
            // Cut off mid-line; the next `$` starts over.
            2 if !edge => {
                let cut = rng.random_range(3..line.len() - 5);
                session.chunks.push(line[..cut].to_vec());
                session.bad_lines += 1;
            }
            _ => {
                // A good line, often split across writes (and so across reads).
                let mut rest = line.as_slice();
                while !rest.is_empty() {
                    let take = rng.random_range(1..=rest.len());
                    session.chunks.push(rest[..take].to_vec());
                    rest = &rest[take..];
                }
                session.good.push(seq);
            }
        }
        if i == count - 1 {
            break;
        }
        // Damage between lines.
        match rng.random_range(0..8) {
            0 => session.chunks.push(b"lamp v1.2 booting\r\n".to_vec()),
            1 => {
                // Noise outside any line is ignored, unless it follows a cut line, which it
                // then ends: the cut line is counted either way, once.
                let len = rng.random_range(1..40);
                session.chunks.push(noise(rng, len));
            }
            2 => {
                let mut chunk = b"$".to_vec();
                let len = rng.random_range(1..40);
                chunk.extend(noise(rng, len));
                chunk.extend(b"\r\n");
                session.chunks.push(chunk);
                session.bad_lines += 1;
            }
            3 => {
                let mut chunk = b"$RLAMP,".to_vec();
                chunk.extend(std::iter::repeat_n(b'7', 300));
                chunk.extend(b"\r\n");
                session.chunks.push(chunk);
                session.bad_lines += 1;
            }
            _ => {}
        }
    }
    session
}

/// Plays `chunks` into the pty, pausing now and then so that they arrive in separate reads.
fn play(mut master: File, chunks: Vec<Vec<u8>>) -> JoinHandle<File> {
    std::thread::spawn(move || {
        for (i, chunk) in chunks.iter().enumerate() {
            master.write_all(chunk).unwrap();
            if i % 3 == 0 {
                std::thread::sleep(Duration::from_micros(300));
            }
        }
        master
    })
}

fn unwrap_from(first: u32, seq: u32) -> u64 {
    u64::from(first) + u64::from(seq.wrapping_sub(first))
}

#[test]
fn every_good_report_arrives_and_bad_lines_and_gaps_are_counted() {
    let pty = open_pty();
    let bus = Arc::new(Bus::new());
    let frames = bus.lamp.subscribe(1024);
    let camera_from_marker = Pose::new(Quat::from_rotation_x(0.3), Vec3::new(0.1, 0.0, -1.5));
    bus.markers.publish(lamp_seen_at(1, camera_from_marker));
    let lamp = lamp(&pty.slave, &bus);
    let counters = lamp.counters();
    let mut runner = DeviceRunner::spawn(
        "lamp",
        // Enough pooled frames for every frame the subscription holds.
        Box::new(SourceDevice::new(lamp, 1024)),
        bus.clone(),
        Backoff::default(),
    )
    .unwrap();
    let status = runner.status().clone();
    wait_until("the port to open", || {
        status.state() == DeviceState::Running
    });

    let mut rng = Pcg64::seed_from_u64(11);
    let session = damaged_session(&mut rng, 400);
    let first = session.good[0];
    let last = *session.good.last().unwrap();
    let span = unwrap_from(first, last) - u64::from(first) + 1;
    let lost = span - session.good.len() as u64;
    assert!(lost > 40 && session.bad_lines > 40, "a weak session");
    let writer = play(pty.master, session.chunks);

    wait_until("every good report and every drop", || {
        status.frames() == session.good.len() as u64 && status.drops() == lost
    });
    let _master = writer.join().unwrap();
    runner.stop();

    let got = lamp_frames(&frames);
    let seqs: Vec<u64> = got.iter().map(|f| f.seq).collect();
    let expected: Vec<u64> = session
        .good
        .iter()
        .map(|&s| unwrap_from(first, s))
        .collect();
    assert_eq!(
        seqs, expected,
        "every good report, in order, unwrapped across the u32 wrap"
    );
    assert!(expected.last().unwrap() > &u64::from(u32::MAX));
    assert_eq!(counters.reports(), session.good.len() as u64);
    assert_eq!(counters.bad_lines(), session.bad_lines);
    assert_eq!(counters.lost_reports(), lost);
    assert_eq!(status.drops(), lost, "each lost report is one drop");
    assert_eq!(counters.restarts(), 0);

    let position = light_in_world(camera_from_marker);
    let mut previous_ns = 0;
    for (frame, &seq) in got.iter().zip(&session.good) {
        let want = report(seq).state(position, MAX_INTENSITY_W_SR);
        assert_eq!(frame.payload.on, want.on);
        assert!((frame.payload.position_in_world - position).length() < 1e-5);
        assert!((frame.payload.intensity - want.intensity).length() < 1e-5);
        assert_eq!(frame.stamp.device_ns, frame.stamp.host_ns);
        assert!(frame.stamp.host_ns >= previous_ns);
        previous_ns = frame.stamp.host_ns;
    }
    assert_eq!(status.state(), DeviceState::Stopped);
}

#[test]
fn the_lamp_waits_for_its_marker_then_keeps_its_last_position() {
    let mut pty = open_pty();
    let bus = Arc::new(Bus::new());
    let frames = bus.lamp.subscribe(64);
    let lamp = lamp(&pty.slave, &bus);
    let counters = lamp.counters();
    let mut runner = DeviceRunner::spawn(
        "lamp",
        Box::new(SourceDevice::new(lamp, 64)),
        bus.clone(),
        Backoff::default(),
    )
    .unwrap();
    let status = runner.status().clone();
    wait_until("the port to open", || {
        status.state() == DeviceState::Running
    });

    // Never seen: nothing is published (no made-up position), nothing counted lost.
    bus.markers.publish(no_lamp_seen(1));
    write_lines(&mut pty.master, 100..105);
    wait_until("five reports", || counters.unpositioned_reports() == 5);
    assert!(frames.is_empty());

    let at_a = Pose::from_translation(Vec3::new(0.2, -0.1, -1.0));
    bus.markers.publish(lamp_seen_at(2, at_a));
    write_lines(&mut pty.master, 105..108);
    wait_until("three frames", || frames.len() == 3);

    // Out of sight: the last known position is kept.
    bus.markers.publish(no_lamp_seen(3));
    write_lines(&mut pty.master, 108..110);
    wait_until("two more frames", || frames.len() == 5);

    let at_b = Pose::from_translation(Vec3::new(-0.3, 0.2, -0.8));
    bus.markers.publish(lamp_seen_at(4, at_b));
    write_lines(&mut pty.master, 110..111);
    wait_until("the last frame", || frames.len() == 6);
    runner.stop();

    let got = lamp_frames(&frames);
    assert_eq!(
        got.iter().map(|f| f.seq).collect::<Vec<_>>(),
        (105..111).collect::<Vec<u64>>()
    );
    let positions: Vec<Vec3> = got.iter().map(|f| f.payload.position_in_world).collect();
    let (a, b) = (light_in_world(at_a), light_in_world(at_b));
    for (p, want) in positions.iter().zip([a, a, a, a, a, b]) {
        assert!((*p - want).length() < 1e-5, "{p} vs {want}");
    }
    assert_eq!(status.drops(), 0);
    assert_eq!(counters.unpositioned_reports(), 5);
}

#[test]
fn fallback_position_is_used_until_the_first_sighting() {
    let mut pty = open_pty();
    let bus = Arc::new(Bus::new());
    let frames = bus.lamp.subscribe(64);
    let fallback = [0.0, 2.0, 0.5];
    let config = LampConfig {
        fallback_position: Some(fallback),
        ..LampConfig::new(&pty.slave, MAX_INTENSITY_W_SR, LAMP_MARKER)
    };
    let positioner = MarkerPositioner::new(&config, &rig(), world_from_camera());
    let lamp = SerialLamp::new(config, bus.markers.clone(), positioner).unwrap();
    let mut runner = DeviceRunner::spawn(
        "lamp",
        Box::new(SourceDevice::new(lamp, 64)),
        bus.clone(),
        Backoff::default(),
    )
    .unwrap();
    let status = runner.status().clone();
    wait_until("the port to open", || {
        status.state() == DeviceState::Running
    });
    write_lines(&mut pty.master, 0..2);
    wait_until("two frames", || frames.len() == 2);
    let seen = Pose::from_translation(Vec3::new(0.0, 0.0, -1.0));
    bus.markers.publish(lamp_seen_at(1, seen));
    write_lines(&mut pty.master, 2..3);
    wait_until("a third frame", || frames.len() == 3);
    runner.stop();
    let got = lamp_frames(&frames);
    assert_eq!(got[0].payload.position_in_world, Vec3::from(fallback));
    assert_eq!(got[1].payload.position_in_world, Vec3::from(fallback));
    assert!((got[2].payload.position_in_world - light_in_world(seen)).length() < 1e-5);
}

#[test]
fn open_errors_follow_the_device_contract() {
    let bus = Bus::new();
    let dir = tempfile::tempdir().unwrap();
    let open = |path: &Path| lamp(path, &bus).open();

    let missing = open(&dir.path().join("ttyUSB9"));
    assert!(
        matches!(missing, Err(DeviceError::NotFound { .. })),
        "{missing:?}"
    );
    let dangling = dir.path().join("by-id-link");
    std::os::unix::fs::symlink(dir.path().join("gone"), &dangling).unwrap();
    let dangling = open(&dangling);
    assert!(
        matches!(dangling, Err(DeviceError::NotFound { .. })),
        "{dangling:?}"
    );

    let file = dir.path().join("capture.log");
    std::fs::write(&file, b"$RLAMP,1,1,0.5000,3000*00\r\n").unwrap();
    let regular = open(&file);
    assert!(
        matches!(&regular, Err(DeviceError::Config { reason, .. }) if reason.contains("regular file")),
        "{regular:?}"
    );
    let directory = open(dir.path());
    assert!(
        matches!(directory, Err(DeviceError::Config { .. })),
        "{directory:?}"
    );
    // A character device that is not a terminal.
    let null = open(Path::new("/dev/null"));
    assert!(
        matches!(&null, Err(DeviceError::Config { reason, .. }) if reason.contains("not a terminal")),
        "{null:?}"
    );

    let unknown_key = serde_json::json!({
        "port": "/dev/ttyACM0", "max_intensity_w_sr": 2.0, "marker_id": 3, "speed": 9600
    });
    assert!(serde_json::from_value::<LampConfig>(unknown_key).is_err());
    let minimal: LampConfig = serde_json::from_value(serde_json::json!({
        "port": "/dev/serial/by-id/usb-relight_lamp-if00", "max_intensity_w_sr": 2.0, "marker_id": 3
    }))
    .unwrap();
    assert_eq!(
        (minimal.baud, minimal.timeout_ms, minimal.fallback_position),
        (115_200, 100, None)
    );
    let bad = LampConfig { baud: 0, ..minimal };
    let error = SerialLamp::new(bad, bus.markers.clone(), |_: &Frame<MarkerSet>| None).unwrap_err();
    assert!(matches!(error, DeviceError::Config { .. }), "{error}");
}

/// Records every state the runner passes through (consecutive repeats collapsed).
struct StateRecorder {
    done: Arc<AtomicBool>,
    thread: JoinHandle<Vec<DeviceState>>,
}

impl StateRecorder {
    fn start(status: Arc<DeviceStatus>) -> Self {
        let done = Arc::new(AtomicBool::new(false));
        let thread = {
            let done = done.clone();
            std::thread::spawn(move || {
                let mut states = vec![status.state()];
                loop {
                    let finished = done.load(Ordering::Acquire);
                    let state = status.state();
                    if states.last() != Some(&state) {
                        states.push(state);
                    }
                    if finished {
                        return states;
                    }
                    std::thread::sleep(Duration::from_micros(100));
                }
            })
        };
        Self { done, thread }
    }

    fn finish(self) -> Vec<DeviceState> {
        self.done.store(true, Ordering::Release);
        self.thread.join().unwrap()
    }
}

/// Points `link` at `target` atomically, as udev does with `/dev/serial/by-id` links.
fn repoint(link: &Path, target: &Path) {
    let fresh = link.with_extension("new");
    std::os::unix::fs::symlink(target, &fresh).unwrap();
    std::fs::rename(&fresh, link).unwrap();
}

#[test]
fn unplug_is_reported_lost_and_a_replug_on_the_stable_link_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("usb-relight_lamp-if00");
    let mut first = open_pty();
    repoint(&link, &first.slave);

    let bus = Arc::new(Bus::new());
    let frames = bus.lamp.subscribe(64);
    bus.markers
        .publish(lamp_seen_at(1, Pose::from_translation(-Vec3::Z)));
    let backoff = Backoff {
        initial: Duration::from_millis(10),
        max: Duration::from_millis(40),
    };
    let mut runner = DeviceRunner::spawn(
        "lamp",
        Box::new(SourceDevice::new(lamp(&link, &bus), 64)),
        bus.clone(),
        backoff,
    )
    .unwrap();
    let status = runner.status().clone();
    let recorder = StateRecorder::start(status.clone());
    wait_until("the port to open", || {
        status.state() == DeviceState::Running
    });
    write_lines(&mut first.master, 0..5);
    wait_until("five frames", || status.frames() == 5);

    // Unplug: udev removes the link, the pty's master goes away and the backend's slave hangs
    // up. (Removing the link rather than leaving it dangling also keeps a pty that another test
    // opens meanwhile, which may get the old number, out of this lamp's reach.)
    std::fs::remove_file(&link).unwrap();
    drop(first);
    wait_until("the loss", || status.state() == DeviceState::Lost);
    assert!(status.last_error().unwrap().contains("disconnected"));
    // Reopening fails as NotFound and is retried.
    wait_until("a refused reopen", || {
        status.last_error().is_some_and(|e| e.contains("not found"))
    });
    assert_eq!(status.state(), DeviceState::Lost);

    // Replug: a new device node, and the stable link follows it.
    let mut second = open_pty();
    repoint(&link, &second.slave);
    wait_until("the reopen", || status.state() == DeviceState::Running);
    write_lines(&mut second.master, 5..10);
    wait_until("five more frames", || status.frames() == 10);
    runner.stop();

    let states: Vec<DeviceState> = recorder
        .finish()
        .into_iter()
        .filter(|&s| s != DeviceState::Connecting)
        .fold(Vec::new(), |mut states, s| {
            if states.last() != Some(&s) {
                states.push(s);
            }
            states
        });
    assert_eq!(
        states,
        [
            DeviceState::Running,
            DeviceState::Lost,
            DeviceState::Running,
            DeviceState::Stopped
        ]
    );
    assert_eq!(status.reconnects(), 1);
    assert_eq!(status.drops(), 0);
    let seqs: Vec<u64> = lamp_frames(&frames).iter().map(|f| f.seq).collect();
    assert_eq!(seqs, (0..10).collect::<Vec<u64>>());
    drop(second);
}
