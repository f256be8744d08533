//! The uEye backend against a fake `libueye_api.so` (tests/fixtures/ueye/fake_ueye.c) that the
//! tests compile with the system C compiler: the real FFI path, from `dlopen` to
//! `is_ExitCamera`, with a simulated camera whose images are a known function of the exposure.
#![cfg(feature = "ueye")]
// The tests steer the fake camera through its exported `fake_ueye_*` functions.
#![allow(unsafe_code)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

use relight_backends::device::Backoff;
use relight_backends::sources::{Capture, FrameSource, ProbeSource};
use relight_backends::ueye::{UeyeColor, UeyeConfig, UeyeLayout, UeyeProbe};
use relight_backends::{DeviceError, DeviceRunner, DeviceState};
use relight_core::bus::Bus;
use relight_core::{Frame, Image, PixelFormat, ProbeImage};

/// A freshly built fake library: each test gets its own file, hence its own camera state.
struct FakeCamera {
    _dir: tempfile::TempDir,
    path: PathBuf,
    library: libloading::Library,
}

impl FakeCamera {
    fn build() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("libueye_api.so");
        let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/ueye/fake_ueye.c");
        let compiler = std::env::var("CC").unwrap_or_else(|_| "cc".into());
        let status = Command::new(compiler)
            .args([
                "-shared", "-fPIC", "-O2", "-Wall", "-Wextra", "-Werror", "-o",
            ])
            .arg(&path)
            .arg(&source)
            .arg("-lpthread")
            .status()
            .expect("run the C compiler");
        assert!(status.success(), "compiling {}", source.display());
        // SAFETY: the fake library has no initialisers.
        let library = unsafe { libloading::Library::new(&path) }.unwrap();
        Self {
            _dir: dir,
            path,
            library,
        }
    }

    fn config(&self) -> UeyeConfig {
        UeyeConfig {
            library: Some(self.path.to_str().unwrap().to_owned()),
            ..UeyeConfig::default()
        }
    }

    fn call(&self, name: &str, arg: i32) {
        // SAFETY: every fake_ueye_* control takes one int and returns nothing.
        unsafe {
            let f: libloading::Symbol<unsafe extern "C" fn(i32)> = self.library.get(name).unwrap();
            f(arg);
        }
    }

    fn query(&self, name: &str) -> i32 {
        // SAFETY: the fake_ueye_* queries take nothing and return an int.
        unsafe {
            let f: libloading::Symbol<unsafe extern "C" fn() -> i32> =
                self.library.get(name).unwrap();
            f()
        }
    }

    fn set_present(&self, present: bool) {
        self.call("fake_ueye_set_present", i32::from(present));
    }
}

/// What the fake camera records for pixel (x, y) at `exposure_us` and master gain `gain`:
/// radiance (1 + (x + 2y) mod 8) × (4, 2, 1) per ms, times the gain factor, rounded, clipped.
fn expected_pixel(x: u32, y: u32, exposure_us: u32, gain_percent: u64) -> [u8; 3] {
    let radiance = 1 + u64::from((x + 2 * y) % 8);
    let gain_x100 = 100 + 3 * gain_percent;
    [4u64, 2, 1].map(|w| {
        ((radiance * w * u64::from(exposure_us) * gain_x100 + 50_000) / 100_000).min(255) as u8
    })
}

fn expected_image(width: u32, height: u32, exposure_us: u32, gain_percent: u64) -> Vec<u8> {
    (0..height)
        .flat_map(|y| (0..width).flat_map(move |x| expected_pixel(x, y, exposure_us, gain_percent)))
        .collect()
}

fn read_frames(probe: &mut UeyeProbe, count: usize) -> Vec<Frame<ProbeImage>> {
    let mut frames = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    while frames.len() < count {
        assert!(Instant::now() < deadline, "only {} frames", frames.len());
        let mut frame = Frame::<ProbeImage>::default();
        match probe.read(&mut frame).unwrap() {
            Capture::Frame => frames.push(frame),
            Capture::Idle => {}
            Capture::EndOfStream => panic!("a camera does not end"),
        }
    }
    frames
}

#[test]
fn bracketed_frames_are_tagged_with_the_exposure_they_were_taken_at() {
    let fake = FakeCamera::build();
    fake.call("fake_ueye_set_latency", 2);
    fake.call("fake_ueye_set_drop_every", 7);
    let mut probe = UeyeProbe::new(UeyeConfig {
        width: Some(32),
        height: Some(24),
        fps: Some(100.0),
        exposure_latency_frames: 2,
        bracket_us: vec![250, 1_004, 4_000],
        gain_percent: Some(20),
        ..fake.config()
    })
    .unwrap();
    probe.open().unwrap();
    let setup = probe.setup().unwrap();
    assert_eq!(
        (setup.width, setup.height, setup.layout),
        (32, 24, UeyeLayout::Rgb8)
    );
    assert!(
        setup.pitch >= 32 * 3 && setup.pitch.is_multiple_of(64),
        "pitch {}",
        setup.pitch
    );
    assert_eq!(
        fake.query("fake_ueye_auto_shutter"),
        0,
        "auto shutter left on"
    );
    let expected_gain_db = 20.0 * (1.6f32).log10();
    assert!(
        (setup.gain_db - expected_gain_db).abs() < 1e-4,
        "{}",
        setup.gain_db
    );

    let frames = read_frames(&mut probe, 30);
    // Exposures as the camera applied them (10 µs steps), cycled in order.
    let tags: Vec<u32> = frames.iter().map(|f| f.payload.exposure_us).collect();
    for (i, tag) in tags.iter().enumerate() {
        assert_eq!(*tag, [250, 1_000, 4_000][i % 3], "frame {i}: {tags:?}");
    }
    for frame in &frames {
        let image = &frame.payload.image;
        assert_eq!(
            (image.width(), image.height(), image.format()),
            (32, 24, PixelFormat::Rgb8)
        );
        assert_eq!(
            image.as_u8().unwrap(),
            &expected_image(32, 24, frame.payload.exposure_us, 20)[..],
            "frame {} tagged {} µs",
            frame.seq,
            frame.payload.exposure_us
        );
        assert_eq!(frame.payload.gain_db, setup.gain_db);
    }
    // Brightness ∝ tagged exposure (no pixel is saturated at these exposures).
    let mean_per_us: Vec<f64> = frames
        .iter()
        .map(|f| {
            let px = f.payload.image.as_u8().unwrap();
            px.iter().map(|&v| f64::from(v)).sum::<f64>()
                / px.len() as f64
                / f64::from(f.payload.exposure_us)
        })
        .collect();
    let long = mean_per_us
        .iter()
        .zip(&tags)
        .filter(|(_, t)| **t == 4_000)
        .map(|(m, _)| *m);
    let mid = mean_per_us
        .iter()
        .zip(&tags)
        .filter(|(_, t)| **t == 1_000)
        .map(|(m, _)| *m);
    for (l, m) in long.zip(mid) {
        assert!((l / m - 1.0).abs() < 0.01, "brightness per µs {l} vs {m}");
    }
    // Sequence numbers count camera frames: settling frames and lost transfers leave gaps, and
    // the device clock advances 10 ms per camera frame.
    for pair in frames.windows(2) {
        let gap = pair[1].seq - pair[0].seq;
        assert!(
            (3..=4).contains(&gap),
            "a kept frame every latency + 1 frames (+ losses): {gap}"
        );
        let dt = pair[1].stamp.device_ns - pair[0].stamp.device_ns;
        assert_eq!(dt, gap * 10_000_000);
    }
    probe.close();
    assert_eq!(
        fake.query("fake_ueye_allocated_memories"),
        0,
        "ring freed on close"
    );
}

/// Guards the test above: with the latency underestimated, images and tags disagree.
#[test]
fn an_underestimated_latency_shows_in_the_images() {
    let fake = FakeCamera::build();
    fake.call("fake_ueye_set_latency", 2);
    let mut probe = UeyeProbe::new(UeyeConfig {
        exposure_latency_frames: 0,
        bracket_us: vec![500, 1_000, 2_000],
        ..fake.config()
    })
    .unwrap();
    probe.open().unwrap();
    let frames = read_frames(&mut probe, 20);
    let (w, h) = (64, 48);
    let mismatched = frames
        .iter()
        .filter(|f| {
            f.payload.image.as_u8().unwrap() != &expected_image(w, h, f.payload.exposure_us, 0)[..]
        })
        .count();
    assert!(mismatched >= 10, "{mismatched} of 20 frames mis-tagged");
}

#[test]
fn exposure_changes_at_run_time_reach_the_camera() {
    let fake = FakeCamera::build();
    fake.call("fake_ueye_set_latency", 1);
    let mut probe = UeyeProbe::new(UeyeConfig {
        exposure_us: Some(800),
        exposure_latency_frames: 1,
        ..fake.config()
    })
    .unwrap();
    let control = probe.exposure_control();
    probe.open().unwrap();
    let first = read_frames(&mut probe, 3);
    assert!(first.iter().all(|f| f.payload.exposure_us == 800));
    control.set_bracketing(&[300, 600]);
    let bracketed = read_frames(&mut probe, 6);
    // The frame in flight keeps its tag; the bracket then starts from its first exposure.
    let tags: Vec<u32> = bracketed.iter().map(|f| f.payload.exposure_us).collect();
    assert_eq!(tags, [800, 300, 600, 300, 600, 300]);
    probe.set_exposure_us(1_500).unwrap();
    let fixed = read_frames(&mut probe, 4);
    assert_eq!(fixed.last().unwrap().payload.exposure_us, 1_500);
    for f in bracketed.iter().chain(&fixed) {
        assert_eq!(
            f.payload.image.as_u8().unwrap(),
            &expected_image(64, 48, f.payload.exposure_us, 0)[..]
        );
    }
    assert!(matches!(
        probe.set_bracketing(&[100, 0]),
        Err(DeviceError::Config { .. })
    ));
}

#[test]
fn an_unplugged_camera_is_reported_lost_and_resumes_when_plugged_back() {
    let fake = FakeCamera::build();
    // Enough pooled frames that the unread subscription below never starves capture.
    let probe = UeyeProbe::new(UeyeConfig {
        exposure_latency_frames: 0,
        pool_frames: 1024,
        ..fake.config()
    })
    .unwrap();
    let bus = Arc::new(Bus::new());
    let frames = bus.probe.subscribe(1024);
    let backoff = Backoff {
        initial: Duration::from_millis(5),
        max: Duration::from_millis(20),
    };
    let mut runner =
        DeviceRunner::spawn("probe", Box::new(probe.into_device()), bus, backoff).unwrap();
    let status = runner.status().clone();
    let wait_until = |what: &str, done: &dyn Fn() -> bool| {
        let deadline = Instant::now() + Duration::from_secs(20);
        while !done() {
            assert!(Instant::now() < deadline, "timed out waiting for {what}");
            std::thread::sleep(Duration::from_millis(2));
        }
    };
    wait_until("frames", &|| status.frames() >= 10);
    assert_eq!(status.state(), DeviceState::Running);

    // Pull the cable mid-stream and keep it out.
    fake.call("fake_ueye_unplug_after", 3);
    wait_until("the loss", &|| status.state() == DeviceState::Lost);
    let frames_when_lost = status.frames();
    assert_eq!(
        status.reconnects(),
        1,
        "lost while running, not while opening"
    );
    std::thread::sleep(Duration::from_millis(100));
    // Retrying with backoff: between attempts it is Lost, during one Connecting.
    assert!(
        matches!(status.state(), DeviceState::Lost | DeviceState::Connecting),
        "stays lost while unplugged: {:?}",
        status.state()
    );
    assert!(
        status.last_error().unwrap().contains("no camera connected"),
        "{:?}",
        status.last_error()
    );
    assert_eq!(fake.query("fake_ueye_inits"), 1, "no camera, no open");

    fake.set_present(true);
    wait_until("frames after re-plugging", &|| {
        status.frames() >= frames_when_lost + 10
    });
    assert_eq!(status.state(), DeviceState::Running);
    assert!(status.reconnects() >= 1);
    assert_eq!(fake.query("fake_ueye_inits"), 2);
    runner.stop();
    assert_eq!(
        fake.query("fake_ueye_allocated_memories"),
        0,
        "ring freed on stop"
    );

    let seqs: Vec<u64> = std::iter::from_fn(|| frames.try_recv())
        .map(|f| f.seq)
        .collect();
    assert_eq!(seqs.len() as u64, status.frames());
    assert!(
        seqs.windows(2).all(|w| w[1] > w[0]),
        "sequence numbers keep increasing: {seqs:?}"
    );
}

#[test]
fn an_absent_camera_is_not_found_and_an_absent_library_is_a_configuration_error() {
    let fake = FakeCamera::build();
    fake.set_present(false);
    let mut probe = UeyeProbe::new(fake.config()).unwrap();
    match probe.open() {
        Err(DeviceError::NotFound { reason, .. }) => {
            assert!(reason.contains("is_InitCamera"), "{reason}")
        }
        other => panic!("expected NotFound, got {other:?}"),
    }

    // A library that loads but is not the uEye API.
    let mut probe = UeyeProbe::new(UeyeConfig {
        library: Some("libc.so.6".into()),
        ..UeyeConfig::default()
    })
    .unwrap();
    match probe.open() {
        Err(DeviceError::Config { reason, .. }) => {
            assert!(
                reason.contains("libc.so.6") && reason.contains("is_InitCamera"),
                "{reason}"
            );
        }
        other => panic!("expected a configuration error, got {other:?}"),
    }
}

#[test]
fn impossible_settings_are_configuration_errors() {
    let fake = FakeCamera::build();
    let mut too_wide = UeyeProbe::new(UeyeConfig {
        width: Some(4096),
        height: Some(48),
        ..fake.config()
    })
    .unwrap();
    match too_wide.open() {
        Err(DeviceError::Config { reason, .. }) => {
            assert!(reason.contains("AOI 4096×48"), "{reason}")
        }
        other => panic!("expected a configuration error, got {other:?}"),
    }
    // At 100 fps the frame period, 10 ms, bounds the exposure.
    let mut too_long = UeyeProbe::new(UeyeConfig {
        fps: Some(100.0),
        bracket_us: vec![1_000, 50_000],
        ..fake.config()
    })
    .unwrap();
    match too_long.open() {
        Err(DeviceError::Config { reason, .. }) => assert!(reason.contains("50000 µs"), "{reason}"),
        other => panic!("expected a configuration error, got {other:?}"),
    }
    assert_eq!(fake.query("fake_ueye_allocated_memories"), 0);
}

#[test]
fn colour_camera_takes_bgr_or_mono_when_rgb_is_refused_and_keeps_auto_exposure() {
    let fake = FakeCamera::build();
    fake.call("fake_ueye_refuse_modes", 1);
    let mut colour = UeyeColor::new(fake.config()).unwrap();
    colour.open().unwrap();
    assert_eq!(colour.setup().unwrap().layout, UeyeLayout::Bgr8);
    assert_eq!(fake.query("fake_ueye_auto_shutter"), 1);
    let mut frame = Frame::<Image>::default();
    let deadline = Instant::now() + Duration::from_secs(10);
    while colour.read(&mut frame).unwrap() != Capture::Frame {
        assert!(Instant::now() < deadline);
    }
    // The fake's auto shutter holds 5 ms; BGR memory must come out as RGB.
    assert_eq!(
        frame.payload.as_u8().unwrap(),
        &expected_image(64, 48, 5_000, 0)[..]
    );
    colour.close();

    fake.call("fake_ueye_refuse_modes", 3);
    let mut mono = UeyeColor::new(UeyeConfig {
        exposure_us: Some(2_000),
        ..fake.config()
    })
    .unwrap();
    mono.open().unwrap();
    assert_eq!(mono.setup().unwrap().layout, UeyeLayout::Mono8);
    assert_eq!(
        fake.query("fake_ueye_auto_shutter"),
        0,
        "a fixed exposure turns auto off"
    );
    // The exposure write lands after a frame or so: wait for the 2 ms image.
    let green_at_2ms: Vec<u8> = expected_image(64, 48, 2_000, 0)
        .chunks_exact(3)
        .flat_map(|p| [p[1]; 3])
        .collect();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        assert!(Instant::now() < deadline, "never saw the 2 ms exposure");
        if mono.read(&mut frame).unwrap() == Capture::Frame
            && frame.payload.as_u8().unwrap() == &green_at_2ms[..]
        {
            break;
        }
    }
}
