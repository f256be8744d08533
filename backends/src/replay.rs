//! Replay of MCAP recordings as a device: real time (optionally sped up), as fast as possible,
//! or stepped on request; looping on request.
//!
//! Replayed frames are re-stamped on the host clock as if they had just arrived (the recorded
//! spacing is kept, scaled by the speed), so the synchroniser and everything after it behave
//! exactly as with live hardware. Device timestamps are kept as recorded. On each loop the
//! sequence numbers continue instead of restarting, so consumers do not mistake a loop for a
//! burst of drops.
//!
//! A fast replay with [`Backpressure`] is lossless: it runs ahead of its consumer by a bounded
//! number of reference frames, and waits for it beyond that, instead of letting drop-oldest
//! queues discard what the consumer could not take yet.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

use relight_core::frame::host_now_ns;
use relight_core::recording::{RecordingReader, TopicMap};
use relight_core::{StreamKind, StreamMessage, Timestamp};

use crate::device::{Device, DeviceContext, DeviceError, RunEnd};

/// How fast a recording plays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ReplayMode {
    /// Keep the recorded spacing, divided by `speed` (2.0 plays twice as fast).
    Realtime { speed: f64 },
    /// As fast as possible; with [`Replay::with_backpressure`], as fast as the consumer takes it.
    Fast,
    /// Only when [`Stepper::step`](crate::device::Stepper::step) asks, that many messages at a time (or, with
    /// [`Replay::stepping_by`], that many messages of one stream: frame sets).
    Stepped,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ReplayConfig {
    pub path: PathBuf,
    pub mode: ReplayMode,
    pub looping: bool,
}

/// Flow control between a fast replay and its one consumer, counted in messages of one stream
/// (the synchroniser's reference): the replay publishes one only while fewer than `window` are
/// outstanding, and the consumer says how many it has finished with.
#[derive(Debug)]
pub struct Backpressure {
    stream: StreamKind,
    window: u64,
    /// Published so far, and finished with by the consumer.
    counts: Mutex<(u64, u64)>,
    done: Condvar,
}

impl Backpressure {
    pub fn new(stream: StreamKind, window: u64) -> Arc<Self> {
        Arc::new(Self {
            stream,
            window: window.max(1),
            counts: Mutex::new((0, 0)),
            done: Condvar::new(),
        })
    }

    /// The producer's side: wait for room for one more message, returning false once `stop()`
    /// holds (checked every 50 ms).
    fn acquire(&self, stop: impl Fn() -> bool) -> bool {
        let mut counts = self.counts.lock().unwrap_or_else(PoisonError::into_inner);
        while counts.0 - counts.1.min(counts.0) >= self.window {
            if stop() {
                return false;
            }
            counts = self
                .done
                .wait_timeout(counts, Duration::from_millis(50))
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        counts.0 += 1;
        true
    }

    /// The consumer's side: it has finished with `finished` messages in all (rendered them, or
    /// thrown them away). Never decreases the count.
    pub fn finished(&self, finished: u64) {
        let mut counts = self.counts.lock().unwrap_or_else(PoisonError::into_inner);
        if finished > counts.1 {
            counts.1 = finished;
            drop(counts);
            self.done.notify_all();
        }
    }

    /// Messages published and not yet finished with.
    pub fn outstanding(&self) -> u64 {
        let counts = self.counts.lock().unwrap_or_else(PoisonError::into_inner);
        counts.0.saturating_sub(counts.1)
    }
}

/// The replay device. Publishes every stream found in the recording.
#[derive(Debug)]
pub struct Replay {
    config: ReplayConfig,
    reader: Option<RecordingReader>,
    topics: TopicMap,
    streams: Vec<StreamKind>,
    backpressure: Option<Arc<Backpressure>>,
    /// In stepped mode, the stream whose messages the steps count.
    step_stream: Option<StreamKind>,
}

impl Replay {
    /// Check the configuration and read the recording's channel list. The recording itself
    /// is (re)read on every open.
    pub fn new(config: ReplayConfig) -> Result<Self, DeviceError> {
        Self::with_topics(config, TopicMap::default())
    }

    /// [`Replay::new`] reading the streams from other topics than relight's own (a bag another
    /// tool recorded).
    pub fn with_topics(config: ReplayConfig, topics: TopicMap) -> Result<Self, DeviceError> {
        if let ReplayMode::Realtime { speed } = config.mode
            && !(speed.is_finite() && speed > 0.0)
        {
            return Err(DeviceError::Config {
                device: "replay".into(),
                reason: format!("speed must be a positive number, got {speed}"),
            });
        }
        let mut replay = Self {
            config,
            reader: None,
            topics,
            streams: Vec::new(),
            backpressure: None,
            step_stream: None,
        };
        replay.open()?;
        replay.streams = replay.scan_streams();
        Ok(replay)
    }

    fn scan_streams(&self) -> Vec<StreamKind> {
        let mut kinds: Vec<StreamKind> = self
            .reader
            .iter()
            .flat_map(|r| r.messages())
            .filter_map(Result::ok)
            .map(|m| m.kind())
            .collect();
        kinds.sort();
        kinds.dedup();
        kinds
    }

    pub fn reader(&self) -> Option<&RecordingReader> {
        self.reader.as_ref()
    }

    /// In stepped mode, count steps in messages of `stream` (the synchroniser's reference): a
    /// step publishes one of them and every other message up to the next one, so `step(n)`
    /// completes `n` frame sets. Messages before the first are published at the start.
    pub fn stepping_by(mut self, stream: StreamKind) -> Self {
        self.step_stream = Some(stream);
        self
    }

    /// In fast mode, publish no further ahead of the consumer than `backpressure` allows.
    pub fn with_backpressure(mut self, backpressure: Arc<Backpressure>) -> Self {
        self.backpressure = Some(backpressure);
        self
    }
}

/// Shifts one pass over the recording onto the host clock and onto continuing sequence numbers.
#[derive(Debug, Default)]
struct Restamp {
    /// Host time the recording's first message maps to.
    host_origin_ns: u64,
    /// The recording's first host stamp.
    recorded_origin_ns: Option<u64>,
    /// Per stream: offset added to sequence numbers, and the last sequence number published.
    seq: BTreeMap<StreamKind, (u64, u64)>,
    /// Last published host stamp, to start the next loop one frame period later.
    last_host_ns: u64,
}

impl Restamp {
    fn start_pass(&mut self, now_ns: u64) {
        self.host_origin_ns = now_ns.max(self.last_host_ns + 1);
        self.recorded_origin_ns = None;
        for (offset, last) in self.seq.values_mut() {
            *offset = *last + 1;
        }
    }

    /// Where this message belongs on the host clock, relative to the pass start, in recorded ns.
    fn recorded_offset_ns(&mut self, stamp: Timestamp) -> u64 {
        let origin = *self.recorded_origin_ns.get_or_insert(stamp.host_ns);
        stamp.host_ns.saturating_sub(origin)
    }

    fn apply(&mut self, msg: &mut StreamMessage, offset_ns: u64) {
        let host_ns = self.host_origin_ns + offset_ns;
        self.last_host_ns = self.last_host_ns.max(host_ns);
        let entry = self.seq.entry(msg.kind()).or_insert((0, 0));
        let seq_offset = entry.0;
        // The reader hands out unique Arcs, so this does not copy the payload.
        let (seq, stamp) = msg.header_mut();
        *seq += seq_offset;
        stamp.host_ns = host_ns;
        entry.1 = entry.1.max(*seq);
    }
}

impl Device for Replay {
    fn backend(&self) -> &'static str {
        "replay"
    }

    fn streams(&self) -> Vec<StreamKind> {
        self.streams.clone()
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        let path = &self.config.path;
        let reader = RecordingReader::open(path).map_err(|error| DeviceError::Config {
            device: "replay".into(),
            reason: format!("cannot read recording {}: {error}", path.display()),
        })?;
        self.reader = Some(reader.with_topics(self.topics.clone()));
        Ok(())
    }

    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        let Some(reader) = self.reader.as_ref() else {
            return Err(DeviceError::NotFound {
                device: "replay".into(),
                reason: "recording not open".into(),
            });
        };
        let mut restamp = Restamp::default();
        let mut steps_left = 0u32;
        loop {
            restamp.start_pass(host_now_ns());
            let pass_start = Instant::now();
            let mut published = 0u64;
            for item in reader.messages() {
                let mut msg = match item {
                    Ok(msg) => msg,
                    Err(error) => {
                        tracing::error!(path = %self.config.path.display(), %error, "skipping unreadable part of the recording");
                        ctx.count_drop();
                        continue;
                    }
                };
                let offset_ns = restamp.recorded_offset_ns(msg.stamp());
                match self.config.mode {
                    ReplayMode::Realtime { speed } => {
                        let due = Duration::from_nanos((offset_ns as f64 / speed) as u64);
                        let wait = due.saturating_sub(pass_start.elapsed());
                        if !wait.is_zero() && !ctx.sleep(wait) {
                            return Ok(RunEnd::StopRequested);
                        }
                        restamp.apply(&mut msg, (offset_ns as f64 / speed) as u64);
                    }
                    ReplayMode::Fast => {
                        if let Some(gate) = &self.backpressure
                            && msg.kind() == gate.stream
                            && !gate.acquire(|| ctx.should_stop())
                        {
                            return Ok(RunEnd::StopRequested);
                        }
                        restamp.apply(&mut msg, offset_ns);
                    }
                    ReplayMode::Stepped => {
                        if self.step_stream.is_none_or(|kind| kind == msg.kind()) {
                            while steps_left == 0 {
                                match ctx.wait_step() {
                                    Some(n) => steps_left = n,
                                    None => return Ok(RunEnd::StopRequested),
                                }
                            }
                            steps_left -= 1;
                        }
                        restamp.apply(&mut msg, offset_ns);
                    }
                }
                if ctx.should_stop() {
                    return Ok(RunEnd::StopRequested);
                }
                ctx.publish(msg);
                published += 1;
            }
            if !self.config.looping {
                return Ok(RunEnd::EndOfStream);
            }
            if published == 0 {
                return Err(DeviceError::Config {
                    device: "replay".into(),
                    reason: format!(
                        "{} holds no readable frame to loop over",
                        self.config.path.display()
                    ),
                });
            }
            tracing::debug!(path = %self.config.path.display(), "replay looping");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::{Backoff, DeviceRunner, DeviceState};
    use relight_core::bus::Bus;
    use relight_core::recording::{RecordingMeta, RecordingWriter};
    use relight_core::{Frame, Image, PixelFormat};

    /// `frames` depth and colour frames at 30 Hz, each image filled with its frame number so
    /// payloads differ: the messages and the recording that holds them.
    fn write_recording(dir: &std::path::Path, frames: u32) -> (PathBuf, Vec<StreamMessage>) {
        let path = dir.join("rec.mcap");
        let meta = RecordingMeta {
            calibration: None,
            source: "replay test".into(),
        };
        let mut writer = RecordingWriter::create(&path, &meta).unwrap();
        let mut messages = Vec::new();
        for i in 0..u64::from(frames) {
            let stamp = Timestamp::new(i * 33_333_333, 1_000_000_000 + i * 33_333_333);
            let mut depth = Image::new(4, 3, PixelFormat::DepthU16Mm);
            depth.as_u16_mut().unwrap().fill(1000 + i as u16);
            let mut color = Image::new(4, 3, PixelFormat::Rgb8);
            color.as_u8_mut().unwrap().fill(i as u8);
            for msg in [
                StreamMessage::Depth(Arc::new(Frame::new(i, stamp, depth))),
                StreamMessage::Color(Arc::new(Frame::new(i, stamp, color))),
            ] {
                writer.write(&msg).unwrap();
                messages.push(msg);
            }
        }
        writer.finish().unwrap();
        (path, messages)
    }

    fn run_to_end(
        config: ReplayConfig,
        sub_capacity: usize,
    ) -> (Vec<StreamMessage>, Arc<crate::DeviceStatus>) {
        let bus = Arc::new(Bus::new());
        let sub = bus.all.subscribe(sub_capacity);
        let replay = Replay::new(config).unwrap();
        let mut runner =
            DeviceRunner::spawn("replay", Box::new(replay), bus, Backoff::default()).unwrap();
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut got = Vec::new();
        while !(runner.is_finished() && sub.is_empty()) && Instant::now() < deadline {
            if let Some(msg) = sub.recv_timeout(Duration::from_millis(10)) {
                got.push(msg);
            }
        }
        runner.stop();
        (got, runner.status().clone())
    }

    #[test]
    fn fast_replay_publishes_every_frame_in_order_with_payloads_intact() {
        let dir = tempfile::tempdir().unwrap();
        let (path, source) = write_recording(dir.path(), 9);
        let config = ReplayConfig {
            path,
            mode: ReplayMode::Fast,
            looping: false,
        };
        let (got, status) = run_to_end(config, 1024);
        assert_eq!(status.state(), DeviceState::Stopped);
        assert_eq!(got.len(), source.len());
        for (g, s) in got.iter().zip(&source) {
            assert_eq!(
                (g.kind(), g.seq(), g.stamp().device_ns),
                (s.kind(), s.seq(), s.stamp().device_ns)
            );
        }
        // Host stamps keep the recorded spacing.
        let spacing = |m: &[StreamMessage]| m[5].stamp().host_ns - m[0].stamp().host_ns;
        assert_eq!(spacing(&got), spacing(&source));
    }

    #[test]
    fn looping_continues_sequence_numbers_and_time() {
        let dir = tempfile::tempdir().unwrap();
        let (path, source) = write_recording(dir.path(), 3);
        let bus = Arc::new(Bus::new());
        let sub = bus.depth.subscribe(64);
        // Stepped, so a slow test thread cannot lose frames to drop-oldest: three passes.
        let config = ReplayConfig {
            path,
            mode: ReplayMode::Stepped,
            looping: true,
        };
        let mut runner = DeviceRunner::spawn(
            "replay",
            Box::new(Replay::new(config).unwrap()),
            bus,
            Backoff::default(),
        )
        .unwrap();
        runner.stepper().step(3 * source.len() as u32);
        let mut frames = Vec::new();
        while frames.len() < 9 {
            if let Some(f) = sub.recv_timeout(Duration::from_secs(5)) {
                frames.push(f);
            } else {
                panic!("replay stalled");
            }
        }
        runner.stop();
        let depth_in_source = source
            .iter()
            .filter(|m| m.kind() == StreamKind::Depth)
            .count();
        assert_eq!(depth_in_source, 3);
        let seqs: Vec<u64> = frames.iter().map(|f| f.seq).collect();
        assert_eq!(seqs, (0..9).collect::<Vec<_>>());
        assert!(
            frames
                .windows(2)
                .all(|w| w[1].stamp.host_ns > w[0].stamp.host_ns)
        );
        assert_eq!(sub.dropped(), 0);
    }

    #[test]
    fn backpressure_holds_a_fast_replay_to_its_consumer() {
        let dir = tempfile::tempdir().unwrap();
        let (path, source) = write_recording(dir.path(), 6);
        let bus = Arc::new(Bus::new());
        // A queue far too small to hold the recording: only the gate keeps it lossless.
        let sub = bus.depth.subscribe(2);
        let gate = Backpressure::new(StreamKind::Depth, 2);
        let config = ReplayConfig {
            path,
            mode: ReplayMode::Fast,
            looping: false,
        };
        let replay = Replay::new(config).unwrap().with_backpressure(gate.clone());
        let mut runner =
            DeviceRunner::spawn("replay", Box::new(replay), bus, Backoff::default()).unwrap();
        let mut got = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(20);
        while got.len() < 6 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(30));
            assert!(gate.outstanding() <= 2, "ran ahead of the consumer");
            while let Some(frame) = sub.try_recv() {
                got.push(frame.seq);
            }
            gate.finished(got.len() as u64);
        }
        runner.stop();
        let depth = source.iter().filter(|m| m.kind() == StreamKind::Depth);
        assert_eq!(got, depth.map(StreamMessage::seq).collect::<Vec<_>>());
        assert_eq!(sub.dropped(), 0);
    }

    #[test]
    fn stepped_replay_advances_only_on_request() {
        let dir = tempfile::tempdir().unwrap();
        let (path, _) = write_recording(dir.path(), 6);
        let bus = Arc::new(Bus::new());
        let sub = bus.all.subscribe(256);
        let config = ReplayConfig {
            path,
            mode: ReplayMode::Stepped,
            looping: false,
        };
        let mut runner = DeviceRunner::spawn(
            "replay",
            Box::new(Replay::new(config).unwrap()),
            bus,
            Backoff::default(),
        )
        .unwrap();
        assert!(
            sub.recv_timeout(Duration::from_millis(200)).is_none(),
            "nothing before a step"
        );
        runner.stepper().step(4);
        let got: Vec<_> = (0..4)
            .filter_map(|_| sub.recv_timeout(Duration::from_secs(5)))
            .collect();
        assert_eq!(got.len(), 4);
        assert!(
            sub.recv_timeout(Duration::from_millis(200)).is_none(),
            "exactly four"
        );
        runner.stop();
    }

    /// Stepping by depth frames: each step publishes a depth frame and the colour frame that
    /// follows it, nothing of the next pair.
    #[test]
    fn stepping_by_a_stream_publishes_whole_frame_sets() {
        let dir = tempfile::tempdir().unwrap();
        let (path, _) = write_recording(dir.path(), 5);
        let bus = Arc::new(Bus::new());
        let depth = bus.depth.subscribe(16);
        let colour = bus.color.subscribe(16);
        let config = ReplayConfig {
            path,
            mode: ReplayMode::Stepped,
            looping: false,
        };
        let replay = Replay::new(config).unwrap().stepping_by(StreamKind::Depth);
        let mut runner =
            DeviceRunner::spawn("replay", Box::new(replay), bus, Backoff::default()).unwrap();
        runner.stepper().step(2);
        for seq in 0..2 {
            let d = depth.recv_timeout(Duration::from_secs(5)).expect("depth");
            let c = colour.recv_timeout(Duration::from_secs(5)).expect("colour");
            assert_eq!((d.seq, c.seq), (seq, seq));
        }
        assert!(
            depth.recv_timeout(Duration::from_millis(200)).is_none()
                && colour.recv_timeout(Duration::from_millis(50)).is_none(),
            "two frame sets, nothing of the third"
        );
        runner.stop();
    }

    #[test]
    fn missing_or_garbage_recording_is_a_config_error() {
        let dir = tempfile::tempdir().unwrap();
        let missing = ReplayConfig {
            path: dir.path().join("nope.mcap"),
            mode: ReplayMode::Fast,
            looping: false,
        };
        let err = Replay::new(missing).unwrap_err();
        assert!(
            matches!(err, DeviceError::Config { .. }) && err.to_string().contains("nope.mcap"),
            "{err}"
        );
        let garbage = dir.path().join("garbage.mcap");
        std::fs::write(&garbage, b"this is not an mcap file").unwrap();
        let err = Replay::new(ReplayConfig {
            path: garbage,
            mode: ReplayMode::Fast,
            looping: false,
        })
        .unwrap_err();
        assert!(err.to_string().contains("garbage.mcap"), "{err}");
        let bad_speed = ReplayConfig {
            path: dir.path().join("x"),
            mode: ReplayMode::Realtime { speed: 0.0 },
            looping: false,
        };
        assert!(
            Replay::new(bad_speed)
                .unwrap_err()
                .to_string()
                .contains("speed")
        );
    }
}
