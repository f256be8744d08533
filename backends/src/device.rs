//! The device contract and the runner thread that enforces it.

use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};
use relight_core::bus::Bus;
use relight_core::{StreamKind, StreamMessage};

/// Where a device is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum DeviceState {
    /// Opening (first time or after a loss).
    Connecting = 0,
    Running = 1,
    /// Disconnected; the runner is waiting to reopen it.
    Lost = 2,
    /// Ended: stopped on request, end of a recording, or a configuration error.
    Stopped = 3,
}

impl DeviceState {
    pub fn name(self) -> &'static str {
        match self {
            DeviceState::Connecting => "connecting",
            DeviceState::Running => "running",
            DeviceState::Lost => "lost",
            DeviceState::Stopped => "stopped",
        }
    }

    fn from_u8(v: u8) -> Self {
        match v {
            0 => DeviceState::Connecting,
            1 => DeviceState::Running,
            2 => DeviceState::Lost,
            _ => DeviceState::Stopped,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    /// The configuration can never work (bad path, unsupported mode): not retried.
    #[error("{device}: invalid configuration: {reason}")]
    Config { device: String, reason: String },
    /// The device is not there (yet): retried with backoff.
    #[error("{device}: not found: {reason}")]
    NotFound { device: String, reason: String },
    /// The device went away while running: reported as `Lost`, retried with backoff.
    #[error("{device}: disconnected: {reason}")]
    Disconnected { device: String, reason: String },
    /// The device delivered data that cannot be decoded; the frame is dropped and counted.
    #[error("{device}: bad data: {reason}")]
    BadData { device: String, reason: String },
}

impl DeviceError {
    fn retryable(&self) -> bool {
        !matches!(self, DeviceError::Config { .. })
    }
}

/// Why [`Device::run`] returned without an error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunEnd {
    /// The source has nothing more (end of a recording without looping).
    EndOfStream,
    /// [`DeviceContext::should_stop`] became true.
    StopRequested,
}

/// Live counters of one device, shared between its runner thread and the status report.
#[derive(Debug)]
pub struct DeviceStatus {
    pub name: String,
    pub backend: &'static str,
    pub streams: Vec<StreamKind>,
    state: AtomicU8,
    /// Frames published, per stream (indexed like `StreamKind::ALL`).
    frames: [AtomicU64; 5],
    drops: AtomicU64,
    reconnects: AtomicU64,
    last_error: Mutex<Option<String>>,
    fps: Mutex<[FpsMeter; 5]>,
}

#[derive(Debug)]
struct FpsMeter {
    window_start: Instant,
    frames_in_window: u64,
    fps: f64,
}

impl DeviceStatus {
    fn new(name: String, backend: &'static str, streams: Vec<StreamKind>) -> Self {
        Self {
            name,
            backend,
            streams,
            state: AtomicU8::new(DeviceState::Connecting as u8),
            frames: Default::default(),
            drops: AtomicU64::new(0),
            reconnects: AtomicU64::new(0),
            last_error: Mutex::new(None),
            fps: Mutex::new(std::array::from_fn(|_| FpsMeter {
                window_start: Instant::now(),
                frames_in_window: 0,
                fps: 0.0,
            })),
        }
    }

    pub fn state(&self) -> DeviceState {
        DeviceState::from_u8(self.state.load(Ordering::Acquire))
    }
    /// Frames published on all streams.
    pub fn frames(&self) -> u64 {
        self.frames.iter().map(|f| f.load(Ordering::Relaxed)).sum()
    }
    /// Frames published on `stream`.
    pub fn stream_frames(&self, stream: StreamKind) -> u64 {
        self.frames[stream_index(stream)].load(Ordering::Relaxed)
    }
    /// Frames the device produced but could not deliver (bad data, pool exhausted).
    pub fn drops(&self) -> u64 {
        self.drops.load(Ordering::Relaxed)
    }
    pub fn reconnects(&self) -> u64 {
        self.reconnects.load(Ordering::Relaxed)
    }
    pub fn last_error(&self) -> Option<String> {
        self.last_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
    /// Frames per second of `stream` over the last complete one-second window.
    pub fn fps(&self, stream: StreamKind) -> f64 {
        let meters = self.fps.lock().unwrap_or_else(PoisonError::into_inner);
        let meter = &meters[stream_index(stream)];
        if meter.window_start.elapsed() > Duration::from_secs(2) {
            0.0
        } else {
            meter.fps
        }
    }

    fn set_state(&self, state: DeviceState) {
        self.state.store(state as u8, Ordering::Release);
    }

    fn set_error(&self, error: &DeviceError) {
        *self
            .last_error
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(error.to_string());
    }

    fn count_frame(&self, stream: StreamKind) {
        let i = stream_index(stream);
        self.frames[i].fetch_add(1, Ordering::Relaxed);
        let mut meters = self.fps.lock().unwrap_or_else(PoisonError::into_inner);
        let meter = &mut meters[i];
        meter.frames_in_window += 1;
        let elapsed = meter.window_start.elapsed();
        if elapsed >= Duration::from_secs(1) {
            meter.fps = meter.frames_in_window as f64 / elapsed.as_secs_f64();
            meter.frames_in_window = 0;
            meter.window_start = Instant::now();
        }
    }
}

fn stream_index(stream: StreamKind) -> usize {
    StreamKind::ALL
        .iter()
        .position(|&k| k == stream)
        .unwrap_or(0)
}

/// What a running device sees of the world: where to publish, whether to stop, and (for
/// stepped replay) a channel of step requests.
#[derive(Debug)]
pub struct DeviceContext {
    bus: Arc<Bus>,
    status: Arc<DeviceStatus>,
    stop: Arc<AtomicBool>,
    steps: Receiver<u32>,
    /// Cuts the reconnect backoff short (a hot-plug arrival); see [`DeviceRunner::spawn_with_wake`].
    wake: Receiver<()>,
}

impl DeviceContext {
    /// Publish one frame to the bus and count it.
    pub fn publish(&self, msg: StreamMessage) {
        self.status.count_frame(msg.kind());
        self.bus.publish(msg);
    }

    /// Count a frame that was captured but had to be dropped (bad data, pool exhausted).
    pub fn count_drop(&self) {
        self.status.drops.fetch_add(1, Ordering::Relaxed);
    }

    /// The bus this device publishes to, for devices that consume other streams (a marker
    /// tracker reads the colour stream, the lamp reads its marker's pose).
    pub fn bus(&self) -> &Arc<Bus> {
        &self.bus
    }

    pub fn should_stop(&self) -> bool {
        self.stop.load(Ordering::Acquire)
    }

    /// Sleep up to `duration`, waking early when a stop is requested. Returns false on stop.
    pub fn sleep(&self, duration: Duration) -> bool {
        let deadline = Instant::now() + duration;
        loop {
            if self.should_stop() {
                return false;
            }
            let now = Instant::now();
            if now >= deadline {
                return true;
            }
            std::thread::sleep((deadline - now).min(Duration::from_millis(20)));
        }
    }

    /// Wait for a step request (stepped replay): the number of frames to advance, or `None`
    /// when a stop was requested.
    pub fn wait_step(&self) -> Option<u32> {
        loop {
            if self.should_stop() {
                return None;
            }
            match self.steps.recv_timeout(Duration::from_millis(50)) {
                Ok(n) => return Some(n),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return None,
            }
        }
    }

    /// The reconnect backoff: sleep up to `duration`, ending early on a stop request or a
    /// wake. A wake channel whose sender is gone (the hot-plug watcher stopped or never
    /// started) degrades to the plain sleep.
    fn backoff_sleep(&self, duration: Duration) -> BackoffEnd {
        let deadline = Instant::now() + duration;
        loop {
            if self.should_stop() {
                return BackoffEnd::Stopped;
            }
            let now = Instant::now();
            if now >= deadline {
                return BackoffEnd::Elapsed;
            }
            match self
                .wake
                .recv_timeout((deadline - now).min(Duration::from_millis(20)))
            {
                Ok(()) => return BackoffEnd::Woken,
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => {
                    return if self.sleep(deadline.saturating_duration_since(Instant::now())) {
                        BackoffEnd::Elapsed
                    } else {
                        BackoffEnd::Stopped
                    };
                }
            }
        }
    }

    /// Forget wakes that came before an open attempt: that attempt already sees the device.
    fn drain_wakes(&self) {
        while self.wake.try_recv().is_ok() {}
    }
}

/// How a reconnect backoff ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BackoffEnd {
    Elapsed,
    Woken,
    Stopped,
}

/// A source of frames. Implementations open their hardware (or file) in `open`, and capture in
/// `run` until they lose the device (`Err`), run out of data or are asked to stop.
pub trait Device: Send + 'static {
    /// The backend's name (`replay`, `openni2`, …) for status reports.
    fn backend(&self) -> &'static str;
    /// The streams this device publishes.
    fn streams(&self) -> Vec<StreamKind>;
    /// Open (or reopen after a loss). Typed error when it cannot.
    fn open(&mut self) -> Result<(), DeviceError>;
    /// Capture and publish until an end; `Err` means the device was lost.
    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError>;
    /// Release the device; called after `run` returns and before a reopen.
    fn close(&mut self) {}
}

/// Reconnect backoff: doubles from `initial` up to `max`, reset after a successful run.
#[derive(Debug, Clone, Copy)]
pub struct Backoff {
    pub initial: Duration,
    pub max: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Self {
            initial: Duration::from_millis(100),
            max: Duration::from_secs(5),
        }
    }
}

/// Advances a stepped device from another thread.
#[derive(Debug, Clone)]
pub struct Stepper(Sender<u32>);

impl Stepper {
    /// Advance by `frames` messages; false when the device thread has ended.
    pub fn step(&self, frames: u32) -> bool {
        self.0.send(frames).is_ok()
    }
}

/// A device running on its own thread.
#[derive(Debug)]
pub struct DeviceRunner {
    status: Arc<DeviceStatus>,
    stop: Arc<AtomicBool>,
    steps: Sender<u32>,
    thread: Option<JoinHandle<()>>,
}

impl DeviceRunner {
    /// Start `device` on a thread named after it, publishing to `bus`.
    pub fn spawn(
        name: impl Into<String>,
        device: Box<dyn Device>,
        bus: Arc<Bus>,
        backoff: Backoff,
    ) -> std::io::Result<Self> {
        Self::spawn_with_wake(name, device, bus, backoff, crossbeam_channel::never())
    }

    /// Like [`Self::spawn`], with a channel that cuts the reconnect backoff short: a message on
    /// `wake` (a matching USB device arrived, from `hotplug::HotplugWatcher::wake_on`) ends the
    /// current backoff sleep, retries the open at once and restarts the backoff from
    /// `backoff.initial`, because the device node (a tty, a video node) may appear a little
    /// after the USB device itself. Without messages, or once every sender is dropped, the
    /// runner polls with the plain backoff.
    pub fn spawn_with_wake(
        name: impl Into<String>,
        device: Box<dyn Device>,
        bus: Arc<Bus>,
        backoff: Backoff,
        wake: Receiver<()>,
    ) -> std::io::Result<Self> {
        let name = name.into();
        let status = Arc::new(DeviceStatus::new(
            name.clone(),
            device.backend(),
            device.streams(),
        ));
        let stop = Arc::new(AtomicBool::new(false));
        let (steps_tx, steps_rx) = crossbeam_channel::unbounded();
        let ctx = DeviceContext {
            bus,
            status: status.clone(),
            stop: stop.clone(),
            steps: steps_rx,
            wake,
        };
        let thread = std::thread::Builder::new()
            .name(format!("dev-{name}"))
            .spawn(move || run_device(device, &ctx, backoff))?;
        Ok(Self {
            status,
            stop,
            steps: steps_tx,
            thread: Some(thread),
        })
    }

    pub fn status(&self) -> &Arc<DeviceStatus> {
        &self.status
    }

    /// A handle that advances this device when it is a stepped replay.
    pub fn stepper(&self) -> Stepper {
        Stepper(self.steps.clone())
    }

    pub fn is_finished(&self) -> bool {
        self.thread.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Ask the device to stop and wait for its thread.
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!(device = %self.status.name, "device thread panicked");
        }
    }
}

impl Drop for DeviceRunner {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The failure contract: open with retries, run, on loss report `Lost` and reopen with backoff.
fn run_device(mut device: Box<dyn Device>, ctx: &DeviceContext, backoff: Backoff) {
    let status = &ctx.status;
    let mut delay = backoff.initial;
    while !ctx.should_stop() {
        status.set_state(DeviceState::Connecting);
        ctx.drain_wakes();
        if let Err(error) = device.open() {
            status.set_error(&error);
            if !error.retryable() {
                tracing::error!(device = %status.name, %error, "cannot open device; giving up");
                break;
            }
            tracing::warn!(device = %status.name, %error, retry_in_ms = delay.as_millis(), "cannot open device");
            status.set_state(DeviceState::Lost);
            match ctx.backoff_sleep(delay) {
                BackoffEnd::Stopped => break,
                BackoffEnd::Woken => delay = backoff.initial,
                BackoffEnd::Elapsed => delay = (delay * 2).min(backoff.max),
            }
            continue;
        }
        status.set_state(DeviceState::Running);
        tracing::info!(device = %status.name, backend = device.backend(), "device running");
        let result = device.run(ctx);
        device.close();
        match result {
            Ok(end) => {
                tracing::info!(device = %status.name, ?end, "device ended");
                break;
            }
            Err(error) => {
                status.set_error(&error);
                if !error.retryable() {
                    tracing::error!(device = %status.name, %error, "device failed; giving up");
                    break;
                }
                tracing::warn!(device = %status.name, %error, "device lost; reconnecting");
                status.set_state(DeviceState::Lost);
                status.reconnects.fetch_add(1, Ordering::Relaxed);
                delay = backoff.initial;
                if ctx.backoff_sleep(delay) == BackoffEnd::Stopped {
                    break;
                }
            }
        }
    }
    status.set_state(DeviceState::Stopped);
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::{Frame, LampState, Timestamp};

    /// Publishes `per_run` lamp frames, then reports a pulled cable; fails to reopen `refusals`
    /// times first.
    struct Flaky {
        per_run: u64,
        refusals: u32,
        seq: u64,
        runs: u32,
    }

    impl Device for Flaky {
        fn backend(&self) -> &'static str {
            "flaky"
        }
        fn streams(&self) -> Vec<StreamKind> {
            vec![StreamKind::Lamp]
        }
        fn open(&mut self) -> Result<(), DeviceError> {
            if self.runs > 0 && self.refusals > 0 {
                self.refusals -= 1;
                return Err(DeviceError::NotFound {
                    device: "flaky".into(),
                    reason: "USB cable out".into(),
                });
            }
            Ok(())
        }
        fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
            self.runs += 1;
            if self.runs > 3 {
                return Ok(RunEnd::EndOfStream);
            }
            for _ in 0..self.per_run {
                self.seq += 1;
                ctx.publish(StreamMessage::Lamp(Arc::new(Frame::new(
                    self.seq,
                    Timestamp::now(),
                    LampState::default(),
                ))));
            }
            Err(DeviceError::Disconnected {
                device: "flaky".into(),
                reason: "cable pulled".into(),
            })
        }
    }

    #[test]
    fn pulled_cable_is_reported_lost_and_the_device_resumes() {
        let bus = Arc::new(Bus::new());
        let sub = bus.lamp.subscribe(64);
        let backoff = Backoff {
            initial: Duration::from_millis(1),
            max: Duration::from_millis(4),
        };
        let device = Flaky {
            per_run: 5,
            refusals: 2,
            seq: 0,
            runs: 0,
        };
        let mut runner = DeviceRunner::spawn("lamp", Box::new(device), bus, backoff).unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while !runner.is_finished() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(2));
        }
        runner.stop();
        let status = runner.status();
        assert_eq!(status.state(), DeviceState::Stopped);
        assert_eq!(status.frames(), 15, "three runs of five frames");
        assert_eq!(status.reconnects(), 3);
        assert!(status.last_error().unwrap().contains("cable pulled"));
        let seqs: Vec<u64> = std::iter::from_fn(|| sub.try_recv())
            .map(|f| f.seq)
            .collect();
        assert_eq!(seqs, (1..=15).collect::<Vec<_>>());
    }

    /// Refuses to open until `plugged`; once open, publishes one frame and runs until stopped.
    struct Pluggable {
        plugged: Arc<AtomicBool>,
        opens: Arc<AtomicU64>,
    }

    impl Device for Pluggable {
        fn backend(&self) -> &'static str {
            "pluggable"
        }
        fn streams(&self) -> Vec<StreamKind> {
            vec![StreamKind::Lamp]
        }
        fn open(&mut self) -> Result<(), DeviceError> {
            self.opens.fetch_add(1, Ordering::SeqCst);
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

    fn wait_until(what: &str, mut done: impl FnMut() -> bool) {
        let deadline = Instant::now() + Duration::from_secs(10);
        while !done() {
            assert!(Instant::now() < deadline, "timed out waiting for {what}");
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    #[test]
    fn a_hotplug_wake_cuts_a_long_backoff_short() {
        // With a one-minute backoff, the device can only be opened within the test's 10 s
        // deadline through the wake channel.
        let backoff = Backoff {
            initial: Duration::from_secs(60),
            max: Duration::from_secs(60),
        };
        let plugged = Arc::new(AtomicBool::new(false));
        let opens = Arc::new(AtomicU64::new(0));
        let device = Pluggable {
            plugged: plugged.clone(),
            opens: opens.clone(),
        };
        let (wake_tx, wake_rx) = crossbeam_channel::bounded(1);
        let bus = Arc::new(Bus::new());
        let mut runner =
            DeviceRunner::spawn_with_wake("lamp", Box::new(device), bus, backoff, wake_rx).unwrap();
        let status = runner.status().clone();
        wait_until("the first refused open", || {
            status.state() == DeviceState::Lost && opens.load(Ordering::SeqCst) == 1
        });
        // The USB device arrives before its device node: the woken open still fails...
        wake_tx.send(()).unwrap();
        wait_until("the woken open to fail", || {
            status.state() == DeviceState::Lost && opens.load(Ordering::SeqCst) == 2
        });
        // ...and the next arrival finds it.
        plugged.store(true, Ordering::SeqCst);
        wake_tx.send(()).unwrap();
        wait_until("the device to run", || status.frames() == 1);
        assert_eq!(status.state(), DeviceState::Running);
        assert_eq!(opens.load(Ordering::SeqCst), 3);
        runner.stop();
        assert_eq!(status.state(), DeviceState::Stopped);
    }

    #[test]
    fn without_a_wake_sender_the_runner_polls_with_its_backoff() {
        // What a daemon gets when the hot-plug watcher cannot start or stops: every sender gone.
        let backoff = Backoff {
            initial: Duration::from_millis(50),
            max: Duration::from_millis(50),
        };
        let plugged = Arc::new(AtomicBool::new(false));
        let opens = Arc::new(AtomicU64::new(0));
        let device = Pluggable {
            plugged: plugged.clone(),
            opens: opens.clone(),
        };
        let (wake_tx, wake_rx) = crossbeam_channel::bounded::<()>(1);
        drop(wake_tx);
        let bus = Arc::new(Bus::new());
        let started = Instant::now();
        let mut runner =
            DeviceRunner::spawn_with_wake("lamp", Box::new(device), bus, backoff, wake_rx).unwrap();
        let status = runner.status().clone();
        wait_until("three refused opens", || opens.load(Ordering::SeqCst) >= 3);
        // Two full backoffs lie between the first and the third attempt: a disconnected wake
        // channel must not turn the backoff into a busy loop.
        assert!(started.elapsed() >= 2 * backoff.initial);
        plugged.store(true, Ordering::SeqCst);
        wait_until("the device to run", || status.frames() == 1);
        assert_eq!(status.state(), DeviceState::Running);
        runner.stop();
    }

    struct BadConfig;
    impl Device for BadConfig {
        fn backend(&self) -> &'static str {
            "bad"
        }
        fn streams(&self) -> Vec<StreamKind> {
            vec![]
        }
        fn open(&mut self) -> Result<(), DeviceError> {
            Err(DeviceError::Config {
                device: "bad".into(),
                reason: "no such file".into(),
            })
        }
        fn run(&mut self, _: &DeviceContext) -> Result<RunEnd, DeviceError> {
            Ok(RunEnd::EndOfStream)
        }
    }

    #[test]
    fn configuration_errors_are_not_retried() {
        let bus = Arc::new(Bus::new());
        let mut runner =
            DeviceRunner::spawn("bad", Box::new(BadConfig), bus, Backoff::default()).unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        while !runner.is_finished() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(2));
        }
        assert!(runner.is_finished());
        runner.stop();
        assert_eq!(runner.status().state(), DeviceState::Stopped);
        assert!(
            runner
                .status()
                .last_error()
                .unwrap()
                .contains("no such file")
        );
    }
}
