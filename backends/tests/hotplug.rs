//! The USB hot-plug watcher against the real libusb of this machine, and its filters.
//!
//! No USB device can be plugged in from a test, so the callback path itself is covered by the
//! dispatcher's unit tests; here: that the watcher starts (or says why it cannot), stops
//! promptly, disconnects its subscribers, and that a device runner whose wake source stops
//! still reconnects by polling.

#![cfg(feature = "hotplug")]

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError};
use relight_backends::device::Backoff;
use relight_backends::hotplug::{
    CLASS_VIDEO, HotplugError, HotplugWatcher, UsbDeviceInfo, UsbFilter,
};
use relight_backends::{Device, DeviceContext, DeviceError, DeviceRunner, DeviceState, RunEnd};
use relight_core::bus::Bus;
use relight_core::{Frame, LampState, StreamKind, StreamMessage, Timestamp};

fn device(vendor_id: u16, product_id: u16, device_class: u8, interfaces: &[u8]) -> UsbDeviceInfo {
    UsbDeviceInfo {
        vendor_id,
        product_id,
        device_class,
        interface_classes: interfaces.to_vec(),
        ..UsbDeviceInfo::default()
    }
}

#[test]
fn filters_parse_from_configuration_text() {
    let lamp: UsbFilter = "10c4:EA60".parse().unwrap();
    assert_eq!(
        (lamp.vendor_id, lamp.product_id, lamp.class),
        (Some(0x10c4), Some(0xea60), None)
    );
    let ueye: UsbFilter = "1409:*".parse().unwrap();
    assert_eq!((ueye.vendor_id, ueye.product_id), (Some(0x1409), None));
    let uvc: UsbFilter = "class:0e".parse().unwrap();
    assert_eq!((uvc.vendor_id, uvc.class), (None, Some(CLASS_VIDEO)));
    for bad in [
        "",
        "10c4",
        "10c4:",
        "10c4:ea6",
        "1x09:*",
        "class:e",
        "class:0e0",
        "*:0600",
    ] {
        let error = bad.parse::<UsbFilter>().unwrap_err();
        assert!(error.to_string().contains("vvvv:pppp"), "{bad}: {error}");
    }
    let from_config: Vec<UsbFilter> =
        serde_json::from_value(serde_json::json!(["045e:02ae", "class:0e"])).unwrap();
    assert_eq!(from_config[0], UsbFilter::id("045e:02ae", 0x045e, 0x02ae));
    assert!(serde_json::from_value::<Vec<UsbFilter>>(serde_json::json!(["kinect"])).is_err());
}

#[test]
fn the_rig_defaults_match_the_rig_devices_and_nothing_else() {
    let defaults = UsbFilter::rig_defaults();
    let label = |d: &UsbDeviceInfo| {
        defaults
            .iter()
            .find(|f| f.matches(d))
            .map(|f| f.label.as_str())
    };
    assert_eq!(
        label(&device(0x045e, 0x02ae, 0, &[0xff])),
        Some("kinect-v1-camera")
    );
    assert_eq!(
        label(&device(0x045e, 0x02b0, 0, &[0xff])),
        Some("kinect-v1-motor")
    );
    assert_eq!(
        label(&device(0x045e, 0x02ad, 0, &[0x01])),
        Some("kinect-v1-audio")
    );
    assert_eq!(
        label(&device(0x1d27, 0x0600, 0, &[0xff])),
        Some("primesense")
    );
    assert_eq!(
        label(&device(0x1d27, 0x0601, 0, &[0xff])),
        Some("primesense")
    );
    assert_eq!(label(&device(0x1409, 0x3240, 0, &[0xff])), Some("ids-ueye"));
    // UVC: video on an interface behind the IAD device class, or (rarely) on the device.
    assert_eq!(
        label(&device(0x046d, 0x0825, 0xef, &[0x0e, 0x01])),
        Some("uvc-camera")
    );
    assert_eq!(
        label(&device(0x0c45, 0x6366, 0x0e, &[])),
        Some("uvc-camera")
    );
    // Another Microsoft product, a keyboard, a USB-serial adapter not configured.
    assert_eq!(label(&device(0x045e, 0x07a5, 0, &[0x03])), None);
    assert_eq!(label(&device(0x046d, 0xc31c, 0, &[0x03])), None);
    assert_eq!(label(&device(0x10c4, 0xea60, 0, &[0xff])), None);
}

/// The daemon's wiring: a watcher if libusb lets us have one, else none (and polling).
fn watcher_or_reason(filters: Vec<UsbFilter>) -> Result<HotplugWatcher, HotplugError> {
    let started = HotplugWatcher::start(filters);
    match &started {
        Ok(_) => eprintln!("libusb hot-plug watcher started on this machine"),
        Err(error) => eprintln!("no hot-plug watcher on this machine: {error}"),
    }
    started
}

#[test]
fn the_watcher_runs_here_or_says_that_devices_poll_and_stops_promptly() {
    match watcher_or_reason(UsbFilter::rig_defaults()) {
        Ok(mut watcher) => {
            assert!(watcher.is_running());
            let events = watcher.subscribe();
            let wake = watcher.wake_on(UsbFilter::rig_defaults());
            watcher.stop();
            assert!(!watcher.is_running());
            // Stopping disconnects every subscriber (whatever arrived before).
            assert_disconnects(&events);
            assert_disconnects(&wake);
            assert_eq!(watcher.dropped_events(), 0);
        }
        Err(error) => assert!(
            error.to_string().contains("reconnect by polling"),
            "{error}"
        ),
    }
}

fn assert_disconnects<T: std::fmt::Debug>(rx: &Receiver<T>) {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        match rx.recv_deadline(deadline) {
            Ok(_) => {}
            Err(RecvTimeoutError::Disconnected) => return,
            Err(RecvTimeoutError::Timeout) => panic!("channel still connected after stop"),
        }
    }
}

/// Refuses to open until `plugged`; then publishes one frame and runs until stopped.
struct Pluggable {
    plugged: Arc<AtomicBool>,
}

impl Device for Pluggable {
    fn backend(&self) -> &'static str {
        "pluggable"
    }
    fn streams(&self) -> Vec<StreamKind> {
        vec![StreamKind::Lamp]
    }
    fn open(&mut self) -> Result<(), DeviceError> {
        if self.plugged.load(Ordering::SeqCst) {
            Ok(())
        } else {
            Err(DeviceError::NotFound {
                device: "pluggable".into(),
                reason: "not plugged in".into(),
            })
        }
    }
    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        ctx.publish(StreamMessage::Lamp(Arc::new(Frame::new(
            1,
            Timestamp::now(),
            LampState::default(),
        ))));
        while ctx.sleep(Duration::from_millis(5)) {}
        Ok(RunEnd::StopRequested)
    }
}

#[test]
fn a_runner_whose_watcher_stopped_or_never_started_reconnects_by_polling() {
    let lamp = UsbFilter::id("lamp", 0x10c4, 0xea60);
    let mut watched = UsbFilter::rig_defaults();
    watched.push(lamp.clone());
    let mut watcher = watcher_or_reason(watched).ok();
    let wake = watcher
        .as_ref()
        .map_or_else(crossbeam_channel::never, |w| w.wake_on(vec![lamp]));
    let plugged = Arc::new(AtomicBool::new(false));
    let backoff = Backoff {
        initial: Duration::from_millis(5),
        max: Duration::from_millis(20),
    };
    let mut runner = DeviceRunner::spawn_with_wake(
        "lamp",
        Box::new(Pluggable {
            plugged: plugged.clone(),
        }),
        Arc::new(Bus::new()),
        backoff,
        wake,
    )
    .unwrap();
    let status = runner.status().clone();
    let deadline = Instant::now() + Duration::from_secs(10);
    while status.state() != DeviceState::Lost {
        assert!(Instant::now() < deadline, "never refused");
        std::thread::sleep(Duration::from_millis(1));
    }
    // The watcher goes away while the device is missing: the wake channel disconnects.
    if let Some(watcher) = watcher.as_mut() {
        watcher.stop();
    }
    plugged.store(true, Ordering::SeqCst);
    while status.frames() == 0 {
        assert!(Instant::now() < deadline, "never reconnected by polling");
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!(status.state(), DeviceState::Running);
    runner.stop();
}
