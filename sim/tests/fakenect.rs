//! The freenect backend through the real libfreenect API, played by fakenect (libfreenect's
//! replay library) from dumps the simulator writes.
//!
//! **How a test runs against fakenect.** This binary is linked to `libfreenect.so.0.5`; fakenect
//! ships a library of that soname in `/usr/lib/<multiarch>/fakenect/`. Each `…_under_fakenect`
//! test below re-executes this binary (`current_exe() --exact <child> --ignored`) with that
//! directory on `LD_LIBRARY_PATH`, `FAKENECT_PATH` set to a fresh dump directory (or unset) and
//! `RELIGHT_FAKENECT_CHILD=1`; the child test does the work and the parent checks that exactly
//! that one test ran and passed. Child tests are `#[ignore]`d so that a normal run skips them,
//! and return at once without the marker so that `--ignored` runs pass too. (The marker rather
//! than `FAKENECT_PATH` decides, because one child must run with `FAKENECT_PATH` unset.)
//! fakenect keeps process-wide state, so each scenario gets its own child process.

#![cfg(feature = "freenect")]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::Vec3;
use relight_backends::device::Backoff;
use relight_backends::freenect::disparity::{self, INVERSE_DEPTH_PER_CODE, RAW_INVALID};
use relight_backends::freenect::dump::{DumpWriter, ticks_at};
use relight_backends::freenect::{DepthMode, FreenectConfig, FreenectDevice, library_is_fakenect};
use relight_backends::{Device, DeviceError, DeviceRunner, DeviceState};
use relight_core::bus::{Bus, Shared, Subscription};
use relight_core::light::Light;
use relight_core::scene::{Material, Scene, SceneCamera};
use relight_core::{Image, PixelFormat, Pose, StreamKind, StreamMessage};
use relight_reference::shapes::{cuboid, quad};
use relight_sim::fakenect::write_fakenect_dump;
use relight_sim::rig::{SimRig, SimSettings};

const CHILD_MARKER: &str = "RELIGHT_FAKENECT_CHILD";

/// Simulated at 160 × 120 (written to the dump ×4 to fakenect's 640 × 480).
const SIM_WIDTH: u32 = 160;
const SIM_HEIGHT: u32 = 120;
const FACTOR: usize = 4;

// ---------------------------------------------------------------------------------------------
// Parent side: spawn the children.

/// Where fakenect's `libfreenect.so.0.5` lives (Debian: `/usr/lib/<multiarch>/fakenect`).
fn fakenect_library_dir() -> PathBuf {
    let candidates = [
        PathBuf::from(format!(
            "/usr/lib/{}-linux-gnu/fakenect",
            std::env::consts::ARCH
        )),
        PathBuf::from("/usr/lib/fakenect"),
        PathBuf::from("/usr/local/lib/fakenect"),
        PathBuf::from("/usr/lib64/fakenect"),
    ];
    candidates
        .iter()
        .find(|dir| dir.join("libfreenect.so.0.5").exists())
        .cloned()
        .unwrap_or_else(|| {
            panic!("fakenect not found in {candidates:?}: install Debian's libfreenect-dev")
        })
}

/// Run the ignored test `child` of this binary under fakenect; returns its output.
fn run_child(child: &str, fakenect_path: Option<&Path>) -> String {
    let logs = tempfile::tempdir().unwrap();
    let (out_path, err_path) = (logs.path().join("stdout"), logs.path().join("stderr"));
    let mut library_path = fakenect_library_dir().into_os_string();
    if let Some(existing) = std::env::var_os("LD_LIBRARY_PATH") {
        library_path.push(":");
        library_path.push(existing);
    }
    let mut command = Command::new(std::env::current_exe().unwrap());
    command
        .args([
            "--exact",
            child,
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_MARKER, "1")
        .env("LD_LIBRARY_PATH", library_path)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out_path).unwrap())
        .stderr(std::fs::File::create(&err_path).unwrap());
    match fakenect_path {
        Some(path) => command.env("FAKENECT_PATH", path),
        None => command.env_remove("FAKENECT_PATH"),
    };
    let mut process = command.spawn().unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(status) = process.try_wait().unwrap() {
            break Some(status);
        }
        if Instant::now() > deadline {
            process.kill().ok();
            process.wait().ok();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let stdout = std::fs::read_to_string(&out_path).unwrap_or_default();
    let stderr = std::fs::read_to_string(&err_path).unwrap_or_default();
    assert!(
        status.is_some_and(|s| s.success()) && stdout.contains("test result: ok. 1 passed"),
        "child `{child}` failed ({status:?}):\n--- stdout\n{stdout}\n--- stderr\n{stderr}"
    );
    print!("{stdout}");
    stdout
}

#[test]
fn fakenect_plays_the_simulated_dump_in_order_in_millimetres_and_in_colour() {
    let dir = tempfile::tempdir().unwrap();
    run_child("replay_child", Some(&dir.path().join("dump")));
}

#[test]
fn damaged_dump_drops_bad_frames_and_a_missing_one_is_a_pulled_cable_under_fakenect() {
    let dir = tempfile::tempdir().unwrap();
    run_child("damaged_dump_child", Some(&dir.path().join("dump")));
}

#[test]
fn vanished_dump_keeps_the_device_lost_until_stopped_under_fakenect() {
    let dir = tempfile::tempdir().unwrap();
    run_child("vanished_dump_child", Some(&dir.path().join("dump")));
}

#[test]
fn missing_fakenect_path_is_a_configuration_error_not_an_exit_under_fakenect() {
    run_child("no_fakenect_path_child", None);
}

#[test]
fn absent_or_malformed_dumps_are_typed_errors_under_fakenect() {
    let dir = tempfile::tempdir().unwrap();
    run_child("bad_dump_child", Some(&dir.path().join("dump")));
}

// ---------------------------------------------------------------------------------------------
// Child side.

fn in_child() -> bool {
    std::env::var_os(CHILD_MARKER).is_some()
}

fn dump_dir() -> PathBuf {
    PathBuf::from(std::env::var_os("FAKENECT_PATH").expect("the parent sets FAKENECT_PATH"))
}

/// A floor with a box on it under a point light: depth edges, a projector shadow and holes.
fn scene() -> Scene {
    let material = |albedo: f32| Material {
        name: format!("grey {albedo}"),
        albedo: Vec3::splat(albedo),
        specular: Vec3::ZERO,
        shininess: 0.0,
        emission: Vec3::ZERO,
    };
    Scene {
        name: "box on floor".into(),
        meshes: vec![
            quad("floor", Vec3::ZERO, Vec3::X * 3.0, -Vec3::Z * 3.0, 0, false),
            cuboid(
                "box",
                Vec3::new(-0.25, 0.0, -0.2),
                Vec3::new(0.15, 0.35, 0.2),
                1,
                false,
            ),
        ],
        materials: vec![material(0.5), material(0.8)],
        camera: SceneCamera {
            world_from_camera: Pose::look_at(Vec3::new(0.3, 1.1, 1.6), Vec3::ZERO, Vec3::Y),
            yfov_rad: 0.8,
            width: SIM_WIDTH,
            height: SIM_HEIGHT,
        },
        lights: vec![Light::Point {
            position_in_world: Vec3::new(0.5, 2.0, 1.0),
            intensity: Vec3::splat(4.0),
        }],
        environment: None,
        environment_lights: Vec::new(),
        shadow_proxy: None,
        surface_revision: None,
    }
}

fn rig(frames: u32) -> SimRig {
    let settings = SimSettings {
        width: SIM_WIDTH,
        height: SIM_HEIGHT,
        frames,
        color_spp: 1,
        truth_every: 0,
        ..SimSettings::default()
    };
    SimRig::new(&scene(), settings).unwrap()
}

fn config(pool_frames: usize) -> FreenectConfig {
    FreenectConfig {
        pool_frames,
        ..FreenectConfig::default()
    }
}

fn fast_backoff() -> Backoff {
    Backoff {
        initial: Duration::from_millis(20),
        max: Duration::from_millis(80),
    }
}

fn drain(sub: &Subscription<Shared<Image>>) -> Vec<Shared<Image>> {
    std::iter::from_fn(|| sub.try_recv()).collect()
}

fn wait_until(what: &str, timeout: Duration, done: impl Fn() -> bool) {
    let deadline = Instant::now() + timeout;
    while !done() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Pixel (x, y) of a 640 × 480 frame comes from (x / 4, y / 4) of the simulated one.
fn source_index(i: usize) -> usize {
    let (x, y) = (i % 640, i / 640);
    (y / FACTOR) * SIM_WIDTH as usize + x / FACTOR
}

/// The most a depth of `mm` can move through an 11-bit code and back: the code is the nearest
/// to raw* = (B − 1/z)/C, off by δ ≤ ½, so z' = z/(1 − C z δ) and |z' − z| ≤ C z² ½/(1 − C z ½);
/// the result is rounded to whole mm (+½).
fn quantisation_bound_mm(mm: u16) -> f64 {
    let z = f64::from(mm) / 1000.0;
    let c = INVERSE_DEPTH_PER_CODE;
    1000.0 * c * z * z * 0.5 / (1.0 - c * z * 0.5) + 0.5
}

#[test]
#[ignore = "runs only as a child under fakenect"]
fn replay_child() {
    if !in_child() {
        return;
    }
    assert!(
        library_is_fakenect(),
        "LD_LIBRARY_PATH did not bring in fakenect"
    );
    const FRAMES: u32 = 24;
    let rig = rig(FRAMES);
    let mut writer = DumpWriter::create(&dump_dir()).unwrap();
    let mut truth = Vec::new();
    for frame in rig.frames() {
        for msg in &frame.messages {
            writer.write_message(msg).unwrap();
        }
        let (StreamMessage::Depth(depth), StreamMessage::Color(color)) =
            (&frame.messages[0], &frame.messages[1])
        else {
            panic!("the rig sends depth, then colour");
        };
        truth.push((depth.clone(), color.clone()));
    }
    let summary = writer.finish().unwrap();
    assert_eq!(
        (summary.depth_frames, summary.color_frames),
        (FRAMES, FRAMES)
    );

    let bus = Arc::new(Bus::new());
    let (depth_sub, color_sub) = (bus.depth.subscribe(64), bus.color.subscribe(64));
    let device = FreenectDevice::new(config(FRAMES as usize + 4)).unwrap();
    let mut runner =
        DeviceRunner::spawn("kinect", Box::new(device), bus, Backoff::default()).unwrap();
    wait_until("the end of the dump", Duration::from_secs(60), || {
        runner.is_finished()
    });
    runner.stop();
    let status = runner.status();
    assert_eq!(status.state(), DeviceState::Stopped);
    assert_eq!(status.last_error(), None);
    assert_eq!((status.drops(), status.reconnects()), (0, 0));
    let (depth, color) = (drain(&depth_sub), drain(&color_sub));
    assert_eq!(
        (depth.len(), color.len()),
        (FRAMES as usize, FRAMES as usize)
    );

    let (mut max_error, mut max_ratio, mut sum_sq, mut valid) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    for (i, (got, (sim, _))) in depth.iter().zip(&truth).enumerate() {
        assert_eq!(got.seq, i as u64, "depth frames in order, none lost");
        assert_eq!(
            (
                got.payload.width(),
                got.payload.height(),
                got.payload.format()
            ),
            (640, 480, PixelFormat::DepthU16Mm)
        );
        // The dump carries the simulator's device clock as 60 MHz ticks.
        let ticks = u64::from(ticks_at(sim.stamp.device_ns));
        assert_eq!(got.stamp.device_ns, ticks * 50 / 3);
        assert!(got.stamp.device_ns.abs_diff(sim.stamp.device_ns) <= 17);
        let sim_mm = sim.payload.as_u16().unwrap();
        for (j, &mm) in got.payload.as_u16().unwrap().iter().enumerate() {
            let expected = sim_mm[source_index(j)];
            if disparity::mm_to_raw(expected) == RAW_INVALID {
                assert_eq!(mm, 0, "frame {i} pixel {j}: no measurement stays none");
                continue;
            }
            assert_ne!(mm, 0, "frame {i} pixel {j}: a measurement stays one");
            let error = (f64::from(mm) - f64::from(expected)).abs();
            let bound = quantisation_bound_mm(expected);
            assert!(
                error <= bound,
                "frame {i} pixel {j}: {mm} mm vs simulated {expected} mm (bound {bound:.2})"
            );
            max_error = max_error.max(error);
            max_ratio = max_ratio.max(error / bound);
            sum_sq += error * error;
            valid += 1;
        }
    }
    assert!(
        valid > 640 * 480 * FRAMES as usize / 2,
        "{valid} valid depth pixels"
    );
    for (i, (got, (_, sim))) in color.iter().zip(&truth).enumerate() {
        assert_eq!(got.seq, i as u64, "colour frames in order, none lost");
        assert_eq!(
            (
                got.payload.width(),
                got.payload.height(),
                got.payload.format()
            ),
            (640, 480, PixelFormat::Rgb8)
        );
        let sim_rgb = sim.payload.as_u8().unwrap();
        let got_rgb = got.payload.as_u8().unwrap();
        for j in 0..640 * 480 {
            let s = source_index(j) * 3;
            assert_eq!(
                &got_rgb[j * 3..j * 3 + 3],
                &sim_rgb[s..s + 3],
                "frame {i} pixel {j}"
            );
        }
    }
    for frames in [&depth, &color] {
        assert!(
            frames
                .windows(2)
                .all(|w| w[1].stamp.host_ns > w[0].stamp.host_ns)
        );
        assert!(frames.windows(2).all(|w| {
            (33_333_300..=33_333_400).contains(&(w[1].stamp.device_ns - w[0].stamp.device_ns))
        }));
    }
    let fps = |frames: &[Shared<Image>]| {
        let span = frames.last().unwrap().stamp.host_ns - frames[0].stamp.host_ns;
        (frames.len() - 1) as f64 * 1e9 / span as f64
    };
    println!(
        "fakenect replay: {FRAMES} depth + {FRAMES} colour frames at 640×480, recorded at 30 fps; \
         played at {:.1} fps depth, {:.1} fps colour",
        fps(&depth),
        fps(&color)
    );
    println!(
        "depth through 11-bit codes: max error {max_error:.1} mm, rms {:.2} mm over {valid} \
         valid pixels; worst error / bound {max_ratio:.2}",
        (sum_sq / valid as f64).sqrt()
    );
}

#[test]
#[ignore = "runs only as a child under fakenect"]
fn damaged_dump_child() {
    if !in_child() {
        return;
    }
    assert!(library_is_fakenect());
    const FRAMES: u32 = 10;
    let dir = dump_dir();
    let summary = write_fakenect_dump(&dir, &rig(FRAMES)).unwrap();
    // Lines: d0 r0 d1 r1 … — cut colour frame 2 short, and take depth frame 6 away.
    let (truncated, withheld) = (&summary.entries[5], &summary.entries[12]);
    assert!(truncated.starts_with("r-") && withheld.starts_with("d-"));
    let bytes = std::fs::read(dir.join(truncated)).unwrap();
    std::fs::write(dir.join(truncated), &bytes[..1000]).unwrap();
    let aside = dir.join("withheld");
    std::fs::rename(dir.join(withheld), &aside).unwrap();

    let bus = Arc::new(Bus::new());
    let (depth_sub, color_sub) = (bus.depth.subscribe(64), bus.color.subscribe(64));
    let device = FreenectDevice::new(config(FRAMES as usize + 4)).unwrap();
    let mut runner = DeviceRunner::spawn("kinect", Box::new(device), bus, fast_backoff()).unwrap();
    let status = runner.status().clone();
    wait_until("the missing frame", Duration::from_secs(30), || {
        status.state() == DeviceState::Lost
    });
    // It stays lost — reopening fails while the file is away — and nothing ends the process.
    std::thread::sleep(Duration::from_millis(300));
    assert!(!runner.is_finished());
    assert_ne!(status.state(), DeviceState::Running);
    assert_eq!(status.reconnects(), 1);
    assert!(status.last_error().unwrap().contains(withheld.as_str()));
    assert_eq!(status.stream_frames(StreamKind::Depth), 6);
    assert_eq!(status.stream_frames(StreamKind::Color), 5);
    assert_eq!(status.drops(), 1, "the truncated colour frame");

    // The cable is back: playback resumes at the frame it lost.
    std::fs::rename(&aside, dir.join(withheld)).unwrap();
    wait_until("the end of the dump", Duration::from_secs(30), || {
        runner.is_finished()
    });
    runner.stop();
    assert_eq!(status.state(), DeviceState::Stopped);
    assert_eq!((status.reconnects(), status.drops()), (1, 1));
    let depth_seqs: Vec<u64> = drain(&depth_sub).iter().map(|f| f.seq).collect();
    let color_seqs: Vec<u64> = drain(&color_sub).iter().map(|f| f.seq).collect();
    assert_eq!(depth_seqs, (0..u64::from(FRAMES)).collect::<Vec<_>>());
    let mut expected_color: Vec<u64> = (0..u64::from(FRAMES)).collect();
    expected_color.retain(|&s| s != 2);
    assert_eq!(color_seqs, expected_color, "the dropped frame leaves a gap");
    println!("damaged dump: Lost once, resumed, depth {depth_seqs:?}, colour {color_seqs:?}");
}

#[test]
#[ignore = "runs only as a child under fakenect"]
fn vanished_dump_child() {
    if !in_child() {
        return;
    }
    assert!(library_is_fakenect());
    let dir = dump_dir();
    let summary = write_fakenect_dump(&dir, &rig(6)).unwrap();
    std::fs::remove_file(dir.join(&summary.entries[6])).unwrap();

    let bus = Arc::new(Bus::new());
    let color_sub = bus.color.subscribe(8);
    let device = FreenectDevice::new(FreenectConfig {
        color: false,
        pool_frames: 8,
        ..FreenectConfig::default()
    })
    .unwrap();
    let mut runner = DeviceRunner::spawn("kinect", Box::new(device), bus, fast_backoff()).unwrap();
    let status = runner.status().clone();
    assert_eq!(status.streams, vec![StreamKind::Depth]);
    wait_until("the missing frame", Duration::from_secs(30), || {
        status.state() == DeviceState::Lost
    });
    assert_eq!(status.stream_frames(StreamKind::Depth), 3);
    // Now the whole recording goes: every reopen fails, the device stays lost.
    std::fs::remove_dir_all(&dir).unwrap();
    std::thread::sleep(Duration::from_millis(400));
    assert!(!runner.is_finished());
    assert_ne!(status.state(), DeviceState::Running);
    assert!(
        status.last_error().unwrap().contains("missing"),
        "{:?}",
        status.last_error()
    );
    runner.stop();
    assert_eq!(status.state(), DeviceState::Stopped);
    assert_eq!(status.stream_frames(StreamKind::Depth), 3);
    assert!(color_sub.try_recv().is_none(), "colour was not asked for");
}

#[test]
#[ignore = "runs only as a child under fakenect"]
fn no_fakenect_path_child() {
    if !in_child() {
        return;
    }
    assert!(library_is_fakenect());
    assert!(std::env::var_os("FAKENECT_PATH").is_none());
    let mut device = FreenectDevice::new(FreenectConfig::default()).unwrap();
    match device.open() {
        Err(DeviceError::Config { reason, .. }) => assert!(reason.contains("FAKENECT_PATH")),
        other => panic!("expected Config, got {other:?}"),
    }
    let bus = Arc::new(Bus::new());
    let mut runner = DeviceRunner::spawn("kinect", Box::new(device), bus, fast_backoff()).unwrap();
    wait_until("the runner to give up", Duration::from_secs(10), || {
        runner.is_finished()
    });
    runner.stop();
    assert_eq!(runner.status().state(), DeviceState::Stopped);
    assert_eq!(runner.status().reconnects(), 0);
    assert!(
        runner
            .status()
            .last_error()
            .unwrap()
            .contains("FAKENECT_PATH")
    );
}

#[test]
#[ignore = "runs only as a child under fakenect"]
fn bad_dump_child() {
    if !in_child() {
        return;
    }
    assert!(library_is_fakenect());
    let dir = dump_dir();
    let open = || {
        FreenectDevice::new(FreenectConfig::default())
            .unwrap()
            .open()
    };
    let not_found = |result: Result<(), DeviceError>, what: &str| match result {
        Err(DeviceError::NotFound { reason, .. }) => assert!(reason.contains(what), "{reason}"),
        other => panic!("expected NotFound ({what}), got {other:?}"),
    };
    not_found(open(), "does not exist");
    std::fs::create_dir_all(&dir).unwrap();
    not_found(open(), "INDEX.txt");
    std::fs::write(dir.join("INDEX.txt"), "not a dump\n").unwrap();
    match open() {
        Err(DeviceError::Config { reason, .. }) => assert!(reason.contains("line 1"), "{reason}"),
        other => panic!("expected Config, got {other:?}"),
    }
    let frame = "d-1.000000-60000000.pgm";
    std::fs::write(dir.join("INDEX.txt"), format!("{frame}\n")).unwrap();
    not_found(open(), frame);
    // Header only: fakenect would copy 600 kB from past the end of the file.
    std::fs::write(dir.join(frame), b"P5 640 480 65535\n").unwrap();
    let bus = Arc::new(Bus::new());
    let mut runner = DeviceRunner::spawn(
        "kinect",
        Box::new(FreenectDevice::new(FreenectConfig::default()).unwrap()),
        bus,
        fast_backoff(),
    )
    .unwrap();
    wait_until("the end of the dump", Duration::from_secs(10), || {
        runner.is_finished()
    });
    runner.stop();
    let status = runner.status();
    assert_eq!(status.state(), DeviceState::Stopped);
    assert_eq!((status.frames(), status.drops()), (0, 1));
    // fakenect plays 11-bit codes; mm would need the dump's registration data.
    let mut registered = FreenectDevice::new(FreenectConfig {
        depth_mode: DepthMode::Registered,
        ..FreenectConfig::default()
    })
    .unwrap();
    match registered.open() {
        Err(DeviceError::Config { reason, .. }) => {
            assert!(reason.contains("device.json"), "{reason}")
        }
        other => panic!("expected Config, got {other:?}"),
    }
}
