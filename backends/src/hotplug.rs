//! USB hot-plug watcher: tells the rest of the daemon when one of the rig's USB devices arrives
//! or leaves, so that a device runner waiting out its reconnect backoff retries at once.
//!
//! [`HotplugWatcher::start`] registers one libusb hot-plug callback (libusb's
//! `libusb_hotplug_register_callback`, through `rusb`) and runs libusb's event loop on its own
//! thread; the callback describes each device ([`UsbDeviceInfo`]), keeps those that match the
//! watched [`UsbFilter`]s and hands them to subscribers over crossbeam channels:
//! [`HotplugWatcher::subscribe`] gives every event, [`HotplugWatcher::wake_on`] gives the wake
//! channel of [`crate::DeviceRunner::spawn_with_wake`]. Matching is done here rather than by
//! libusb's own filter because libusb matches only the *device* class, while a UVC camera
//! announces video (0x0e) on its interfaces behind a device class of 0xef (miscellaneous, IAD).
//!
//! The watcher is an optimisation, never a requirement: when libusb cannot start (no usbfs in a
//! container, no udev) or has no hot-plug support, `start` returns a [`HotplugError`] that says
//! so and the devices reconnect by their polling backoff alone. The same happens if the event
//! loop fails later: the wake senders are dropped and the runners fall back to polling.

use std::fmt;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender, TrySendError};
use rusb::UsbContext;
use serde::Deserialize;

/// Events a subscriber may hold before further ones are dropped (counted).
const EVENT_QUEUE: usize = 64;

/// How often the event loop looks at its stop flag when nothing interrupts it.
const EVENT_LOOP_TICK: Duration = Duration::from_millis(250);

/// USB class code of video devices (UVC), on the interface or the device.
pub const CLASS_VIDEO: u8 = 0x0e;

/// A set of USB devices: every field that is set must match.
///
/// Written in configuration as `"vvvv:pppp"` (hex vendor and product), `"vvvv:*"` (any product
/// of a vendor) or `"class:cc"` (hex class code, matched against the device class and every
/// interface class).
#[derive(Debug, Clone, PartialEq, Eq, Hash, Deserialize)]
#[serde(try_from = "String")]
pub struct UsbFilter {
    /// What the filter stands for, shown in events and logs (`kinect-v1-camera`).
    pub label: String,
    pub vendor_id: Option<u16>,
    pub product_id: Option<u16>,
    pub class: Option<u8>,
}

impl UsbFilter {
    /// One product of one vendor.
    pub fn id(label: impl Into<String>, vendor_id: u16, product_id: u16) -> Self {
        Self {
            label: label.into(),
            vendor_id: Some(vendor_id),
            product_id: Some(product_id),
            class: None,
        }
    }

    /// Every product of a vendor.
    pub fn vendor(label: impl Into<String>, vendor_id: u16) -> Self {
        Self {
            label: label.into(),
            vendor_id: Some(vendor_id),
            product_id: None,
            class: None,
        }
    }

    /// Every device with this class on the device or on one of its interfaces.
    pub fn class(label: impl Into<String>, class: u8) -> Self {
        Self {
            label: label.into(),
            vendor_id: None,
            product_id: None,
            class: Some(class),
        }
    }

    /// The rig's usual devices: Kinect v1 (camera 045e:02ae, motor 045e:02b0, audio 045e:02ad),
    /// PrimeSense sensors (1d27:0600, 1d27:0601), IDS uEye cameras (1409:*) and any UVC camera
    /// (class 0x0e). A lamp's USB-serial adapter is added from its `usb_id`.
    pub fn rig_defaults() -> Vec<UsbFilter> {
        vec![
            Self::id("kinect-v1-camera", 0x045e, 0x02ae),
            Self::id("kinect-v1-motor", 0x045e, 0x02b0),
            Self::id("kinect-v1-audio", 0x045e, 0x02ad),
            Self::id("primesense", 0x1d27, 0x0600),
            Self::id("primesense", 0x1d27, 0x0601),
            Self::vendor("ids-ueye", 0x1409),
            Self::class("uvc-camera", CLASS_VIDEO),
        ]
    }

    /// Whether `device` is one of this filter's devices. Pure: the seam that tests use.
    pub fn matches(&self, device: &UsbDeviceInfo) -> bool {
        self.vendor_id.is_none_or(|v| v == device.vendor_id)
            && self.product_id.is_none_or(|p| p == device.product_id)
            && self
                .class
                .is_none_or(|c| c == device.device_class || device.interface_classes.contains(&c))
    }
}

impl fmt::Display for UsbFilter {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.label)
    }
}

/// Why a filter did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("USB filter `{text}`: expected `vvvv:pppp`, `vvvv:*` or `class:cc` (hex)")]
pub struct UsbFilterParseError {
    pub text: String,
}

impl FromStr for UsbFilter {
    type Err = UsbFilterParseError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let error = || UsbFilterParseError {
            text: text.to_owned(),
        };
        let hex16 = |s: &str| {
            (s.len() == 4)
                .then(|| u16::from_str_radix(s, 16).ok())
                .flatten()
        };
        let (left, right) = text.split_once(':').ok_or_else(error)?;
        if left.eq_ignore_ascii_case("class") {
            let class = (right.len() == 2)
                .then(|| u8::from_str_radix(right, 16).ok())
                .flatten()
                .ok_or_else(error)?;
            return Ok(Self::class(text, class));
        }
        let vendor_id = hex16(left).ok_or_else(error)?;
        if right == "*" {
            return Ok(Self::vendor(text, vendor_id));
        }
        Ok(Self::id(text, vendor_id, hex16(right).ok_or_else(error)?))
    }
}

impl TryFrom<String> for UsbFilter {
    type Error = UsbFilterParseError;
    fn try_from(text: String) -> Result<Self, Self::Error> {
        text.parse()
    }
}

/// What the watcher knows of a USB device (from its cached descriptors; nothing is opened).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct UsbDeviceInfo {
    pub bus_number: u8,
    pub address: u8,
    /// Hub ports from the root to the device: stable across replugs into the same socket.
    pub port_numbers: Vec<u8>,
    pub vendor_id: u16,
    pub product_id: u16,
    pub device_class: u8,
    /// Class codes of every interface (alternate settings included) of every configuration.
    pub interface_classes: Vec<u8>,
}

impl fmt::Display for UsbDeviceInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{:04x}:{:04x} on bus {} address {}",
            self.vendor_id, self.product_id, self.bus_number, self.address
        )
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HotplugKind {
    Arrived,
    Left,
}

/// One watched device arrived or left.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HotplugEvent {
    pub kind: HotplugKind,
    pub device: UsbDeviceInfo,
    /// Label of the first watched filter the device matches.
    pub filter: String,
}

/// Why the watcher is not running; in every case devices reconnect by polling.
#[derive(Debug, thiserror::Error)]
pub enum HotplugError {
    #[error("USB hot-plug: this libusb has no hot-plug support; devices reconnect by polling")]
    Unsupported,
    #[error(
        "USB hot-plug: libusb cannot start ({0}; no /dev/bus/usb or udev here?); devices reconnect by polling"
    )]
    Init(rusb::Error),
    #[error(
        "USB hot-plug: libusb refused the hot-plug callback ({0}); devices reconnect by polling"
    )]
    Register(rusb::Error),
    #[error("USB hot-plug: cannot start the event thread ({0}); devices reconnect by polling")]
    Thread(std::io::Error),
}

enum Sink {
    /// Every watched event.
    Events(Sender<HotplugEvent>),
    /// A wake per arrival matching `filters`; a capacity-1 channel, so wakes coalesce.
    Wake {
        filters: Vec<UsbFilter>,
        tx: Sender<()>,
    },
}

/// Matches events against the watched filters and hands them to the subscribers. Called from
/// libusb's event thread; never blocks it (full queues drop, counted).
#[derive(Default)]
struct Dispatcher {
    filters: Vec<UsbFilter>,
    /// `None` once the event loop ended: subscribers' channels are then disconnected.
    sinks: Mutex<Option<Vec<Sink>>>,
    dropped: AtomicU64,
}

impl fmt::Debug for Dispatcher {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let sinks = self
            .sinks
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
            .map(Vec::len);
        f.debug_struct("Dispatcher")
            .field("filters", &self.filters)
            .field("sinks", &sinks)
            .field("dropped", &self.dropped.load(Ordering::Relaxed))
            .finish()
    }
}

impl Dispatcher {
    fn new(filters: Vec<UsbFilter>) -> Self {
        Self {
            filters,
            sinks: Mutex::new(Some(Vec::new())),
            dropped: AtomicU64::new(0),
        }
    }

    /// Adds a sink; when the loop has ended the sink is dropped at once (its receiver sees
    /// a disconnected channel).
    fn add(&self, sink: Sink) {
        if let Some(sinks) = self
            .sinks
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .as_mut()
        {
            sinks.push(sink);
        }
    }

    fn subscribe(&self) -> Receiver<HotplugEvent> {
        let (tx, rx) = crossbeam_channel::bounded(EVENT_QUEUE);
        self.add(Sink::Events(tx));
        rx
    }

    fn wake_on(&self, filters: Vec<UsbFilter>) -> Receiver<()> {
        let (tx, rx) = crossbeam_channel::bounded(1);
        self.add(Sink::Wake { filters, tx });
        rx
    }

    /// Delivers one event; returns whether a watched filter matched.
    fn dispatch(&self, kind: HotplugKind, device: UsbDeviceInfo) -> bool {
        let Some(filter) = self.filters.iter().find(|f| f.matches(&device)) else {
            return false;
        };
        tracing::info!(%device, filter = %filter, ?kind, "USB device hot-plug");
        let event = HotplugEvent {
            kind,
            device,
            filter: filter.label.clone(),
        };
        let mut guard = self.sinks.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(sinks) = guard.as_mut() else {
            return true;
        };
        sinks.retain(|sink| match sink {
            Sink::Events(tx) => match tx.try_send(event.clone()) {
                Ok(()) => true,
                Err(TrySendError::Full(_)) => {
                    self.dropped.fetch_add(1, Ordering::Relaxed);
                    true
                }
                Err(TrySendError::Disconnected(_)) => false,
            },
            Sink::Wake { filters, tx } => {
                if kind != HotplugKind::Arrived || !filters.iter().any(|f| f.matches(&event.device))
                {
                    // Kept until a send finds its receiver gone.
                    return true;
                }
                // Full means a wake is already pending: this arrival is covered by it.
                !matches!(tx.try_send(()), Err(TrySendError::Disconnected(())))
            }
        });
        true
    }

    /// The event loop ended: disconnect every subscriber.
    fn close(&self) {
        *self.sinks.lock().unwrap_or_else(PoisonError::into_inner) = None;
    }
}

/// The libusb callback: describes the device and dispatches it.
struct Callback {
    dispatcher: Arc<Dispatcher>,
}

impl<T: UsbContext> rusb::Hotplug<T> for Callback {
    fn device_arrived(&mut self, device: rusb::Device<T>) {
        if let Some(info) = describe(&device) {
            self.dispatcher.dispatch(HotplugKind::Arrived, info);
        }
    }

    fn device_left(&mut self, device: rusb::Device<T>) {
        if let Some(info) = describe(&device) {
            self.dispatcher.dispatch(HotplugKind::Left, info);
        }
    }
}

/// Reads a device's cached descriptors (allowed inside a hot-plug callback: libusb's
/// documentation permits any call that takes a `libusb_device`).
fn describe<T: UsbContext>(device: &rusb::Device<T>) -> Option<UsbDeviceInfo> {
    let descriptor = match device.device_descriptor() {
        Ok(descriptor) => descriptor,
        Err(error) => {
            tracing::debug!(%error, bus = device.bus_number(), address = device.address(),
                "hot-plug: no device descriptor; event skipped");
            return None;
        }
    };
    let mut interface_classes = Vec::new();
    for index in 0..descriptor.num_configurations() {
        let Ok(config) = device.config_descriptor(index) else {
            continue;
        };
        for interface in config.interfaces() {
            for setting in interface.descriptors() {
                if !interface_classes.contains(&setting.class_code()) {
                    interface_classes.push(setting.class_code());
                }
            }
        }
    }
    Some(UsbDeviceInfo {
        bus_number: device.bus_number(),
        address: device.address(),
        port_numbers: device.port_numbers().unwrap_or_default(),
        vendor_id: descriptor.vendor_id(),
        product_id: descriptor.product_id(),
        device_class: descriptor.class_code(),
        interface_classes,
    })
}

/// The one libusb call rusb offers only through a function that panics when libusb cannot
/// start (`rusb::has_hotplug` initialises a global context first).
mod ffi {
    #![allow(unsafe_code)]

    /// Whether the linked libusb supports hot-plug (`LIBUSB_CAP_HAS_HOTPLUG`).
    pub fn has_hotplug() -> bool {
        // SAFETY: libusb_has_capability only reads a compile-time property of the library and
        // the backend; it takes no pointers and, per libusb's documentation, may be called
        // before libusb_init.
        unsafe { rusb::ffi::libusb_has_capability(rusb::constants::LIBUSB_CAP_HAS_HOTPLUG) != 0 }
    }
}

/// Watches the rig's USB devices on its own thread. Stops on [`Self::stop`] or drop.
#[derive(Debug)]
pub struct HotplugWatcher {
    context: rusb::Context,
    dispatcher: Arc<Dispatcher>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl HotplugWatcher {
    /// Start watching the devices matching `filters` (e.g. [`UsbFilter::rig_defaults`] plus the
    /// lamp's adapter). Devices already plugged in are not reported; only changes are.
    pub fn start(filters: Vec<UsbFilter>) -> Result<Self, HotplugError> {
        Self::start_with(filters, ffi::has_hotplug(), rusb::Context::new)
    }

    /// `start`, with libusb's capability and context as inputs (the seam the tests use).
    fn start_with(
        filters: Vec<UsbFilter>,
        has_hotplug: bool,
        context: impl FnOnce() -> rusb::Result<rusb::Context>,
    ) -> Result<Self, HotplugError> {
        if !has_hotplug {
            return Err(HotplugError::Unsupported);
        }
        let context = context().map_err(HotplugError::Init)?;
        let dispatcher = Arc::new(Dispatcher::new(filters));
        let registration = rusb::HotplugBuilder::new()
            .enumerate(false)
            .register::<rusb::Context, _>(
                &context,
                Box::new(Callback {
                    dispatcher: dispatcher.clone(),
                }),
            )
            .map_err(HotplugError::Register)?;
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let context = context.clone();
            let dispatcher = dispatcher.clone();
            let stop = stop.clone();
            std::thread::Builder::new()
                .name("usb-hotplug".into())
                .spawn(move || {
                    event_loop(&context, &stop);
                    drop(registration);
                    dispatcher.close();
                })
                .map_err(HotplugError::Thread)?
        };
        tracing::info!(
            filters = dispatcher.filters.len(),
            "USB hot-plug watcher running"
        );
        Ok(Self {
            context,
            dispatcher,
            stop,
            thread: Some(thread),
        })
    }

    /// Every event of a watched device from now on. The channel holds 64 events; a subscriber
    /// that falls behind loses the newest ones ([`Self::dropped_events`]). It disconnects when
    /// the watcher stops.
    pub fn subscribe(&self) -> Receiver<HotplugEvent> {
        self.dispatcher.subscribe()
    }

    /// A wake channel for [`crate::DeviceRunner::spawn_with_wake`]: one message per arrival of
    /// a device matching `filters` (pending wakes coalesce). Only watched devices are seen, so
    /// list these filters in [`Self::start`] too. It disconnects when the watcher stops, and the
    /// runner then polls.
    pub fn wake_on(&self, filters: Vec<UsbFilter>) -> Receiver<()> {
        self.dispatcher.wake_on(filters)
    }

    /// Events lost because a subscriber's channel was full.
    pub fn dropped_events(&self) -> u64 {
        self.dispatcher.dropped.load(Ordering::Relaxed)
    }

    /// Whether the event loop still runs.
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Stop the event loop and wait for its thread; subscribers' channels disconnect.
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Release);
        self.context.interrupt_handle_events();
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!("USB hot-plug thread panicked");
            self.dispatcher.close();
        }
    }
}

impl Drop for HotplugWatcher {
    fn drop(&mut self) {
        self.stop();
    }
}

fn event_loop(context: &rusb::Context, stop: &AtomicBool) {
    while !stop.load(Ordering::Acquire) {
        match context.handle_events(Some(EVENT_LOOP_TICK)) {
            Ok(()) | Err(rusb::Error::Interrupted) => {}
            Err(error) => {
                tracing::error!(%error, "USB hot-plug event loop failed; devices reconnect by polling");
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device(
        vendor_id: u16,
        product_id: u16,
        device_class: u8,
        interfaces: &[u8],
    ) -> UsbDeviceInfo {
        UsbDeviceInfo {
            bus_number: 1,
            address: 9,
            port_numbers: vec![2, 1],
            vendor_id,
            product_id,
            device_class,
            interface_classes: interfaces.to_vec(),
        }
    }

    fn kinect_camera() -> UsbDeviceInfo {
        device(0x045e, 0x02ae, 0x00, &[0xff])
    }

    /// A webcam: device class 0xef (IAD), video on its interfaces, audio beside it.
    fn webcam() -> UsbDeviceInfo {
        device(0x046d, 0x0825, 0xef, &[0x0e, 0x01])
    }

    fn keyboard() -> UsbDeviceInfo {
        device(0x046d, 0xc31c, 0x00, &[0x03])
    }

    #[test]
    fn events_reach_subscribers_with_the_matching_filter() {
        let dispatcher = Dispatcher::new(UsbFilter::rig_defaults());
        let events = dispatcher.subscribe();
        assert!(dispatcher.dispatch(HotplugKind::Arrived, kinect_camera()));
        assert!(dispatcher.dispatch(HotplugKind::Arrived, webcam()));
        assert!(!dispatcher.dispatch(HotplugKind::Arrived, keyboard()));
        assert!(dispatcher.dispatch(HotplugKind::Left, kinect_camera()));
        let got: Vec<(HotplugKind, String)> =
            events.try_iter().map(|e| (e.kind, e.filter)).collect();
        assert_eq!(
            got,
            [
                (HotplugKind::Arrived, "kinect-v1-camera".to_owned()),
                (HotplugKind::Arrived, "uvc-camera".to_owned()),
                (HotplugKind::Left, "kinect-v1-camera".to_owned()),
            ]
        );
    }

    #[test]
    fn wakes_come_only_for_their_own_arrivals_and_coalesce() {
        let lamp = UsbFilter::id("lamp", 0x10c4, 0xea60);
        let mut watched = UsbFilter::rig_defaults();
        watched.push(lamp.clone());
        let dispatcher = Dispatcher::new(watched);
        let lamp_wake = dispatcher.wake_on(vec![lamp]);
        let kinect_wake = dispatcher.wake_on(vec![UsbFilter::vendor("kinect", 0x045e)]);

        dispatcher.dispatch(HotplugKind::Arrived, kinect_camera());
        assert!(
            lamp_wake.try_recv().is_err(),
            "another device woke the lamp"
        );
        assert_eq!(kinect_wake.try_recv(), Ok(()));

        dispatcher.dispatch(HotplugKind::Left, device(0x10c4, 0xea60, 0, &[0xff]));
        assert!(lamp_wake.try_recv().is_err(), "a departure woke the lamp");
        dispatcher.dispatch(HotplugKind::Arrived, device(0x10c4, 0xea60, 0, &[0xff]));
        dispatcher.dispatch(HotplugKind::Arrived, device(0x10c4, 0xea60, 0, &[0xff]));
        assert_eq!(lamp_wake.try_recv(), Ok(()));
        assert!(
            lamp_wake.try_recv().is_err(),
            "two pending arrivals are one wake"
        );
    }

    #[test]
    fn gone_subscribers_are_forgotten_and_full_ones_count_drops() {
        let dispatcher = Dispatcher::new(UsbFilter::rig_defaults());
        let kept = dispatcher.subscribe();
        drop(dispatcher.subscribe());
        drop(dispatcher.wake_on(vec![UsbFilter::class("uvc", CLASS_VIDEO)]));
        drop(dispatcher.wake_on(vec![UsbFilter::vendor("kinect", 0x045e)]));
        for _ in 0..EVENT_QUEUE + 3 {
            dispatcher.dispatch(HotplugKind::Arrived, webcam());
        }
        let sinks = dispatcher.sinks.lock().unwrap().as_ref().map(Vec::len);
        // The Kinect's wake has not been tried yet, so it is still there.
        assert_eq!(sinks, Some(2));
        assert_eq!(kept.len(), EVENT_QUEUE);
        assert_eq!(dispatcher.dropped.load(Ordering::Relaxed), 3);
    }

    #[test]
    fn a_closed_dispatcher_disconnects_old_and_new_subscribers() {
        let dispatcher = Dispatcher::new(UsbFilter::rig_defaults());
        let old = dispatcher.wake_on(UsbFilter::rig_defaults());
        dispatcher.close();
        let new = dispatcher.subscribe();
        assert!(dispatcher.dispatch(HotplugKind::Arrived, kinect_camera()));
        assert_eq!(
            old.try_recv(),
            Err(crossbeam_channel::TryRecvError::Disconnected)
        );
        assert_eq!(
            new.try_recv(),
            Err(crossbeam_channel::TryRecvError::Disconnected)
        );
    }

    #[test]
    fn without_libusb_the_watcher_says_why_and_that_devices_poll() {
        let unsupported = HotplugWatcher::start_with(vec![], false, || {
            panic!("libusb must not be initialised without hot-plug support")
        })
        .unwrap_err();
        assert!(matches!(unsupported, HotplugError::Unsupported));
        let no_usbfs =
            HotplugWatcher::start_with(vec![], true, || Err(rusb::Error::Other)).unwrap_err();
        assert!(matches!(no_usbfs, HotplugError::Init(rusb::Error::Other)));
        for error in [unsupported, no_usbfs] {
            assert!(
                error.to_string().contains("reconnect by polling"),
                "{error}"
            );
        }
    }
}
