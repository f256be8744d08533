//! Timestamp synchroniser: groups the streams' messages into [`FrameSet`]s, one per frame of a
//! reference stream (depth by default).
//!
//! Matching is on `stamp.host_ns`. Each reference frame takes, from every other expected stream,
//! the message nearest in time within `tolerance_ns` (ties go to the earlier message); a message
//! can serve several sets, so a 10 Hz lamp still pairs with 30 Hz depth. A set is *decided* (and
//! emitted, oldest first) when no nearer message can still come for any expected stream; or when
//! the host clock passes `ref + max_wait`, in which case unmatched streams are listed in
//! [`FrameSet::missing`]. Streams arrive in host-time order, so a stream is settled once it has
//! delivered a message at or beyond `ref + tolerance`, or, sooner, at or beyond `ref + d` where
//! `d` is the distance of the best candidate already buffered (anything later is farther).
//!
//! Memory is bounded whatever the input: at most [`MAX_BUFFERED_PER_STREAM`] messages per stream
//! and as many pending reference frames. Messages that cannot be used (out of order, unexpected
//! stream, overflow) are counted in [`SyncStats`] and dropped; nothing here panics on input.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use crate::bus::Shared;
use crate::frame::{Image, Timestamp};
use crate::stream::{LampState, MarkerSet, ProbeImage, StreamKind, StreamMessage};

/// Messages buffered per stream, and reference frames pending, at most. At 30 Hz this is two
/// seconds, far beyond any sensible `max_wait_ns`.
pub const MAX_BUFFERED_PER_STREAM: usize = 64;

/// A stream whose host timestamp jumps back by more than this (or by four `max_wait_ns`, when
/// larger) is taken to mean the host clock was reset: the synchroniser starts over instead of
/// dropping that stream until the clock catches up.
const CLOCK_RESET_BACKWARDS_NS: u64 = 1_000_000_000;

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct SyncConfig {
    /// The stream that defines the sets: one set per reference frame, stamped with its time.
    pub reference: StreamKind,
    /// The streams a set should contain, the reference among them.
    pub expected: Vec<StreamKind>,
    /// Largest |stream − reference| host-time difference that still pairs two messages.
    pub tolerance_ns: u64,
    /// How long after the reference time a set may wait for slow streams before it is emitted
    /// with those streams missing.
    pub max_wait_ns: u64,
}

impl Default for SyncConfig {
    fn default() -> Self {
        Self {
            reference: StreamKind::Depth,
            expected: StreamKind::ALL.to_vec(),
            tolerance_ns: 20_000_000,
            max_wait_ns: 100_000_000,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SyncError {
    #[error("reference stream {reference} is not among the expected streams")]
    ReferenceNotExpected { reference: StreamKind },
    #[error("stream {0} is listed twice in the expected streams")]
    DuplicateStream(StreamKind),
    #[error("tolerance_ns must be greater than 0")]
    ZeroTolerance,
    #[error("max_wait_ns ({max_wait_ns}) must be at least tolerance_ns ({tolerance_ns})")]
    MaxWaitBelowTolerance { max_wait_ns: u64, tolerance_ns: u64 },
}

/// One reference frame and the messages of the other streams nearest to it.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSet {
    /// The reference frame's timestamp.
    pub stamp: Timestamp,
    pub depth: Option<Shared<Image>>,
    pub color: Option<Shared<Image>>,
    pub probe: Option<Shared<ProbeImage>>,
    pub markers: Option<Shared<MarkerSet>>,
    pub lamp: Option<Shared<LampState>>,
    /// Expected streams with no message within tolerance, in `SyncConfig::expected` order.
    pub missing: Vec<StreamKind>,
    /// `stream host_ns − reference host_ns` of every matched non-reference stream.
    pub skew_ns: Vec<(StreamKind, i64)>,
}

impl FrameSet {
    fn new(stamp: Timestamp) -> Self {
        Self {
            stamp,
            depth: None,
            color: None,
            probe: None,
            markers: None,
            lamp: None,
            missing: Vec::new(),
            skew_ns: Vec::new(),
        }
    }

    /// Whether every expected stream was matched.
    pub fn is_complete(&self) -> bool {
        self.missing.is_empty()
    }

    /// Whether the set holds a message of `kind`.
    pub fn has(&self, kind: StreamKind) -> bool {
        match kind {
            StreamKind::Depth => self.depth.is_some(),
            StreamKind::Color => self.color.is_some(),
            StreamKind::Probe => self.probe.is_some(),
            StreamKind::Markers => self.markers.is_some(),
            StreamKind::Lamp => self.lamp.is_some(),
        }
    }

    fn insert(&mut self, msg: StreamMessage) {
        match msg {
            StreamMessage::Depth(f) => self.depth = Some(f),
            StreamMessage::Color(f) => self.color = Some(f),
            StreamMessage::Probe(f) => self.probe = Some(f),
            StreamMessage::Markers(f) => self.markers = Some(f),
            StreamMessage::Lamp(f) => self.lamp = Some(f),
        }
    }
}

/// Counters of one stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamSyncStats {
    pub kind: StreamKind,
    /// Sets this stream's message was part of (a message serving three sets counts three).
    pub matched: u64,
    /// Sets emitted without this stream.
    pub missing: u64,
    /// Messages that arrived after a set they could have joined was emitted.
    pub late: u64,
    /// Messages thrown away unused: out of order, not expected, or over the buffer bound.
    pub dropped: u64,
    /// Messages discarded because no set could use them (e.g. 60 Hz color against 30 Hz depth).
    pub unused: u64,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SyncStats {
    pub sets_emitted: u64,
    /// Sets emitted with no stream missing.
    pub complete_sets: u64,
    /// Times the host clock jumped back and the synchroniser started over.
    pub clock_resets: u64,
    /// Per stream, in [`StreamKind::ALL`] order.
    pub streams: Vec<StreamSyncStats>,
}

impl SyncStats {
    pub fn stream(&self, kind: StreamKind) -> Option<&StreamSyncStats> {
        self.streams.iter().find(|s| s.kind == kind)
    }
}

#[derive(Debug)]
struct Buffered {
    msg: StreamMessage,
    host_ns: u64,
    used: bool,
}

/// Groups stream messages into [`FrameSet`]s; see the module documentation for the rules.
#[derive(Debug)]
pub struct Synchronizer {
    config: SyncConfig,
    reset_backwards_ns: u64,
    /// Reference frames not yet emitted, oldest first.
    pending: VecDeque<StreamMessage>,
    /// Per stream (index [`slot`]), non-reference messages in host-time order.
    buffers: [VecDeque<Buffered>; 5],
    /// Per stream, the newest host time accepted.
    newest_ns: [Option<u64>; 5],
    last_emitted_ns: Option<u64>,
    /// Per stream, a message stamped before this would have served the last emitted set better
    /// than what it got (or at all): it is late.
    late_before_ns: [u64; 5],
    sets_emitted: u64,
    complete_sets: u64,
    clock_resets: u64,
    streams: [StreamSyncStats; 5],
}

fn slot(kind: StreamKind) -> usize {
    match kind {
        StreamKind::Depth => 0,
        StreamKind::Color => 1,
        StreamKind::Probe => 2,
        StreamKind::Markers => 3,
        StreamKind::Lamp => 4,
    }
}

fn skew_ns(host_ns: u64, reference_ns: u64) -> i64 {
    if host_ns >= reference_ns {
        i64::try_from(host_ns - reference_ns).unwrap_or(i64::MAX)
    } else {
        i64::try_from(reference_ns - host_ns).map_or(i64::MIN, |d| -d)
    }
}

impl Synchronizer {
    pub fn new(config: SyncConfig) -> Result<Self, SyncError> {
        if !config.expected.contains(&config.reference) {
            return Err(SyncError::ReferenceNotExpected {
                reference: config.reference,
            });
        }
        for (i, kind) in config.expected.iter().enumerate() {
            if config.expected[..i].contains(kind) {
                return Err(SyncError::DuplicateStream(*kind));
            }
        }
        if config.tolerance_ns == 0 {
            return Err(SyncError::ZeroTolerance);
        }
        if config.max_wait_ns < config.tolerance_ns {
            return Err(SyncError::MaxWaitBelowTolerance {
                max_wait_ns: config.max_wait_ns,
                tolerance_ns: config.tolerance_ns,
            });
        }
        Ok(Self {
            reset_backwards_ns: CLOCK_RESET_BACKWARDS_NS.max(config.max_wait_ns.saturating_mul(4)),
            config,
            pending: VecDeque::with_capacity(MAX_BUFFERED_PER_STREAM),
            buffers: std::array::from_fn(|_| VecDeque::with_capacity(MAX_BUFFERED_PER_STREAM)),
            newest_ns: [None; 5],
            last_emitted_ns: None,
            late_before_ns: [0; 5],
            sets_emitted: 0,
            complete_sets: 0,
            clock_resets: 0,
            streams: StreamKind::ALL.map(|kind| StreamSyncStats {
                kind,
                matched: 0,
                missing: 0,
                late: 0,
                dropped: 0,
                unused: 0,
            }),
        })
    }

    pub fn config(&self) -> &SyncConfig {
        &self.config
    }

    /// Takes one message of any stream. Never blocks, never panics; bounded memory.
    pub fn push(&mut self, msg: StreamMessage) {
        let kind = msg.kind();
        let k = slot(kind);
        let host_ns = msg.stamp().host_ns;
        if !self.config.expected.contains(&kind) {
            self.streams[k].dropped += 1;
            return;
        }
        if let Some(newest_ns) = self.newest_ns[k]
            && host_ns < newest_ns
        {
            if newest_ns - host_ns > self.reset_backwards_ns {
                tracing::warn!(
                    stream = %kind,
                    back_ns = newest_ns - host_ns,
                    "host clock jumped back; synchroniser starts over"
                );
                self.reset();
            } else {
                tracing::trace!(stream = %kind, host_ns, newest_ns, "out-of-order message dropped");
                self.streams[k].dropped += 1;
                return;
            }
        }
        self.newest_ns[k] = Some(host_ns);

        if kind == self.config.reference {
            if self.last_emitted_ns.is_some_and(|e| host_ns <= e) {
                self.streams[k].late += 1;
                return;
            }
            if self.pending.len() >= MAX_BUFFERED_PER_STREAM {
                self.pending.pop_front();
                self.streams[k].dropped += 1;
            }
            self.pending.push_back(msg);
        } else {
            if host_ns < self.late_before_ns[k] {
                self.streams[k].late += 1;
            }
            let buffer = &mut self.buffers[k];
            if buffer.len() >= MAX_BUFFERED_PER_STREAM {
                buffer.pop_front();
                self.streams[k].dropped += 1;
            }
            buffer.push_back(Buffered {
                msg,
                host_ns,
                used: false,
            });
        }
        self.prune(kind);
    }

    /// The oldest pending set, if it is decided: no expected stream can still deliver a nearer
    /// message, or `now_host_ns` is past `ref + max_wait`. Sets come out in reference order; call
    /// repeatedly until `None`.
    pub fn pop_ready(&mut self, now_host_ns: u64) -> Option<FrameSet> {
        let reference_ns = self.pending.front()?.stamp().host_ns;
        let timed_out = now_host_ns > reference_ns.saturating_add(self.config.max_wait_ns);
        if !(timed_out || self.settled(reference_ns)) {
            return None;
        }
        let reference = self.pending.pop_front()?;
        Some(self.emit(reference))
    }

    /// Whether every expected stream has delivered a message at or beyond the reference time
    /// plus the distance of its best candidate (plus the tolerance when it has none).
    fn settled(&self, reference_ns: u64) -> bool {
        self.config.expected.iter().all(|&kind| {
            if kind == self.config.reference {
                return true;
            }
            let k = slot(kind);
            let reach_ns = self
                .nearest(k, reference_ns)
                .map_or(self.config.tolerance_ns, |(_, distance_ns)| distance_ns);
            self.newest_ns[k].is_some_and(|t| t >= reference_ns.saturating_add(reach_ns))
        })
    }

    /// Index and distance of the buffered message of stream slot `k` nearest to `reference_ns`
    /// within tolerance; the earlier one on a tie.
    fn nearest(&self, k: usize, reference_ns: u64) -> Option<(usize, u64)> {
        self.buffers[k]
            .iter()
            .map(|b| b.host_ns.abs_diff(reference_ns))
            .enumerate()
            .filter(|&(_, distance_ns)| distance_ns <= self.config.tolerance_ns)
            .min_by_key(|&(_, distance_ns)| distance_ns)
    }

    /// End of stream: emits every pending set with what has arrived.
    pub fn flush(&mut self) -> Vec<FrameSet> {
        let mut sets = Vec::with_capacity(self.pending.len());
        while let Some(reference) = self.pending.pop_front() {
            sets.push(self.emit(reference));
        }
        sets
    }

    /// Reference frames waiting for their set to be decided.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Reference frames waiting plus other messages buffered.
    pub fn buffered(&self) -> usize {
        self.pending.len() + self.buffers.iter().map(VecDeque::len).sum::<usize>()
    }

    pub fn stats(&self) -> SyncStats {
        SyncStats {
            sets_emitted: self.sets_emitted,
            complete_sets: self.complete_sets,
            clock_resets: self.clock_resets,
            streams: self.streams.to_vec(),
        }
    }

    fn emit(&mut self, reference: StreamMessage) -> FrameSet {
        let reference_stamp = reference.stamp();
        let reference_ns = reference_stamp.host_ns;
        let tolerance_ns = self.config.tolerance_ns;
        let mut set = FrameSet::new(reference_stamp);
        set.missing.reserve(self.config.expected.len());
        set.skew_ns.reserve(self.config.expected.len());
        self.streams[slot(reference.kind())].matched += 1;
        set.insert(reference);

        for &kind in &self.config.expected {
            if kind == self.config.reference {
                continue;
            }
            let k = slot(kind);
            let nearest = self
                .nearest(k, reference_ns)
                .and_then(|(index, distance_ns)| {
                    Some((self.buffers[k].get_mut(index)?, distance_ns))
                });
            match nearest {
                Some((buffered, distance_ns)) => {
                    buffered.used = true;
                    set.skew_ns
                        .push((kind, skew_ns(buffered.host_ns, reference_ns)));
                    set.insert(buffered.msg.clone());
                    self.streams[k].matched += 1;
                    self.late_before_ns[k] = reference_ns.saturating_add(distance_ns);
                }
                None => {
                    set.missing.push(kind);
                    self.streams[k].missing += 1;
                    self.late_before_ns[k] =
                        reference_ns.saturating_add(tolerance_ns).saturating_add(1);
                }
            }
        }

        self.last_emitted_ns = Some(reference_ns);
        self.sets_emitted += 1;
        if set.is_complete() {
            self.complete_sets += 1;
        }
        for kind in StreamKind::ALL {
            self.prune(kind);
        }
        set
    }

    /// Discards the oldest messages of `kind` that no pending or future set can pick: those
    /// beyond tolerance before the oldest reference that can still come, and those with a newer
    /// message between them and it (always farther from every such reference).
    fn prune(&mut self, kind: StreamKind) {
        if kind == self.config.reference {
            return;
        }
        let oldest_reference_ns = match self.pending.front() {
            Some(reference) => reference.stamp().host_ns,
            None => match self.newest_ns[slot(self.config.reference)] {
                Some(newest_ns) => newest_ns,
                None => return,
            },
        };
        let tolerance_ns = self.config.tolerance_ns;
        let k = slot(kind);
        let buffer = &mut self.buffers[k];
        while let Some(front) = buffer.front() {
            let out_of_reach = front.host_ns.saturating_add(tolerance_ns) < oldest_reference_ns;
            let dominated = buffer
                .get(1)
                .is_some_and(|next| next.host_ns <= oldest_reference_ns);
            if !(out_of_reach || dominated) {
                break;
            }
            if let Some(removed) = buffer.pop_front()
                && !removed.used
            {
                self.streams[k].unused += 1;
            }
        }
    }

    /// Forgets everything pending after a host-clock jump; what is thrown away is counted.
    fn reset(&mut self) {
        self.clock_resets += 1;
        let reference = slot(self.config.reference);
        self.streams[reference].dropped += self.pending.len() as u64;
        self.pending.clear();
        for (k, buffer) in self.buffers.iter_mut().enumerate() {
            self.streams[k].unused += buffer.iter().filter(|b| !b.used).count() as u64;
            buffer.clear();
        }
        self.newest_ns = [None; 5];
        self.last_emitted_ns = None;
        self.late_before_ns = [0; 5];
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::frame::{Frame, PixelFormat};

    const PERIOD_NS: u64 = 33_333_333;
    const MS: u64 = 1_000_000;

    /// Deterministic jitter in [-5 ms, +5 ms] (SplitMix64).
    fn jitter_ns(seed: u64) -> i64 {
        let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D1_049B_B133_111B);
        z ^= z >> 31;
        (z % (10 * MS + 1)) as i64 - 5 * MS as i64
    }

    fn message(kind: StreamKind, seq: u64, host_ns: u64) -> StreamMessage {
        let stamp = Timestamp::new(seq, host_ns);
        match kind {
            StreamKind::Depth => StreamMessage::Depth(Arc::new(Frame::new(
                seq,
                stamp,
                Image::new(1, 1, PixelFormat::DepthU16Mm),
            ))),
            StreamKind::Color => StreamMessage::Color(Arc::new(Frame::new(
                seq,
                stamp,
                Image::new(1, 1, PixelFormat::Rgb8),
            ))),
            StreamKind::Probe => {
                StreamMessage::Probe(Arc::new(Frame::new(seq, stamp, ProbeImage::default())))
            }
            StreamKind::Markers => {
                StreamMessage::Markers(Arc::new(Frame::new(seq, stamp, MarkerSet::default())))
            }
            StreamKind::Lamp => {
                StreamMessage::Lamp(Arc::new(Frame::new(seq, stamp, LampState::default())))
            }
        }
    }

    fn seq_of(set: &FrameSet, kind: StreamKind) -> Option<u64> {
        match kind {
            StreamKind::Depth => set.depth.as_ref().map(|f| f.seq),
            StreamKind::Color => set.color.as_ref().map(|f| f.seq),
            StreamKind::Probe => set.probe.as_ref().map(|f| f.seq),
            StreamKind::Markers => set.markers.as_ref().map(|f| f.seq),
            StreamKind::Lamp => set.lamp.as_ref().map(|f| f.seq),
        }
    }

    /// A rig on a 30 Hz clock: stream `kind` captures on ticks that are multiples of
    /// `every_nth_tick`, its stamp jittered ±5 ms, and is delivered `latency_ns` later.
    /// Returns (delivery time, message) sorted by delivery, seq = tick index.
    fn rig(streams: &[(StreamKind, u64, u64)], ticks: u64) -> Vec<(u64, StreamMessage)> {
        let start_ns = 1_000_000_000;
        let mut deliveries = Vec::new();
        for (stream_index, &(kind, every_nth_tick, latency_ns)) in streams.iter().enumerate() {
            for tick in (0..ticks).filter(|t| t % every_nth_tick == 0) {
                let nominal_ns = start_ns + tick * PERIOD_NS;
                let seed = tick * 16 + stream_index as u64;
                let host_ns = nominal_ns.saturating_add_signed(jitter_ns(seed));
                deliveries.push((host_ns + latency_ns, message(kind, tick, host_ns)));
            }
        }
        deliveries.sort_by_key(|(delivered_ns, _)| *delivered_ns);
        deliveries
    }

    /// Feeds the deliveries in order, polling after each, then flushes. Returns the sets and,
    /// per set, the clock at which it came out (`None` for flushed ones).
    fn run(
        sync: &mut Synchronizer,
        deliveries: Vec<(u64, StreamMessage)>,
    ) -> Vec<(FrameSet, Option<u64>)> {
        let mut out = Vec::new();
        for (now_ns, msg) in deliveries {
            sync.push(msg);
            while let Some(set) = sync.pop_ready(now_ns) {
                out.push((set, Some(now_ns)));
            }
        }
        out.extend(sync.flush().into_iter().map(|set| (set, None)));
        out
    }

    #[test]
    fn jittered_streams_pair_by_nearest_time() {
        let streams = [
            (StreamKind::Depth, 1, 2 * MS),
            (StreamKind::Color, 1, 8 * MS),
            (StreamKind::Probe, 1, 25 * MS),
            (StreamKind::Markers, 1, 15 * MS),
            (StreamKind::Lamp, 1, MS),
        ];
        let mut sync = Synchronizer::new(SyncConfig::default()).expect("valid config");
        let sets = run(&mut sync, rig(&streams, 90));

        assert_eq!(sets.len(), 90);
        for (tick, (set, _)) in sets.iter().enumerate() {
            assert!(set.is_complete(), "set {tick} misses {:?}", set.missing);
            for kind in StreamKind::ALL {
                assert_eq!(seq_of(set, kind), Some(tick as u64), "{kind} of set {tick}");
            }
            assert_eq!(set.skew_ns.len(), 4);
            assert!(
                set.skew_ns
                    .iter()
                    .all(|(_, skew)| skew.unsigned_abs() <= 10 * MS)
            );
        }
        let stats = sync.stats();
        assert_eq!((stats.sets_emitted, stats.complete_sets), (90, 90));
        for s in &stats.streams {
            assert_eq!(
                (s.matched, s.missing, s.late, s.dropped),
                (90, 0, 0, 0),
                "{s:?}"
            );
        }
        assert!(sync.buffered() <= 5);
    }

    #[test]
    fn a_set_waits_until_no_nearer_message_can_come() {
        let mut sync = Synchronizer::new(SyncConfig::default()).expect("valid config");
        sync.push(message(StreamKind::Depth, 0, 100 * MS));
        sync.push(message(StreamKind::Depth, 1, 133 * MS));
        for kind in [StreamKind::Color, StreamKind::Probe, StreamKind::Markers] {
            sync.push(message(kind, 0, 100 * MS));
            sync.push(message(kind, 1, 130 * MS));
        }
        // Lamp 1 ms before the reference: one up to 1 ms after it would tie, so keep waiting.
        sync.push(message(StreamKind::Lamp, 0, 99 * MS));
        assert!(sync.pop_ready(110 * MS).is_none());
        sync.push(message(StreamKind::Lamp, 1, 130 * MS));
        let first = sync.pop_ready(131 * MS).expect("first set decided");
        assert_eq!(first.stamp.host_ns, 100 * MS);
        assert_eq!(seq_of(&first, StreamKind::Lamp), Some(0));
        assert_eq!(
            first.skew_ns.last(),
            Some(&(StreamKind::Lamp, -(MS as i64)))
        );
        // Everyone is 3 ms before the second reference: a nearer message may still come.
        assert!(sync.pop_ready(131 * MS).is_none());
        for kind in [
            StreamKind::Color,
            StreamKind::Probe,
            StreamKind::Markers,
            StreamKind::Lamp,
        ] {
            sync.push(message(kind, 2, 136 * MS));
        }
        let second = sync.pop_ready(137 * MS).expect("second set decided");
        assert!(second.is_complete());
        assert_eq!(seq_of(&second, StreamKind::Color), Some(1));
    }

    #[test]
    fn a_stream_that_never_comes_is_missing_after_max_wait() {
        let streams = [
            (StreamKind::Depth, 1, 2 * MS),
            (StreamKind::Color, 1, 8 * MS),
            (StreamKind::Probe, 1, 25 * MS),
            (StreamKind::Markers, 1, 15 * MS),
        ];
        let config = SyncConfig::default();
        let max_wait_ns = config.max_wait_ns;
        let mut sync = Synchronizer::new(config).expect("valid config");
        let sets = run(&mut sync, rig(&streams, 60));

        assert_eq!(sets.len(), 60);
        for (tick, (set, emitted_at)) in sets.iter().enumerate() {
            assert_eq!(set.missing, vec![StreamKind::Lamp], "set {tick}");
            assert!(set.lamp.is_none());
            assert_eq!(seq_of(set, StreamKind::Probe), Some(tick as u64));
            if let Some(now_ns) = emitted_at {
                assert!(
                    *now_ns > set.stamp.host_ns + max_wait_ns,
                    "set {tick} came out early"
                );
            }
        }
        // All but the last few (flushed at the end) came out through the timeout.
        assert!(sets.iter().filter(|(_, at)| at.is_some()).count() >= 55);
        let stats = sync.stats();
        assert_eq!(stats.stream(StreamKind::Lamp).map(|s| s.missing), Some(60));
        assert_eq!(stats.complete_sets, 0);
    }

    #[test]
    fn a_message_after_its_set_was_emitted_is_late() {
        let mut sync = Synchronizer::new(SyncConfig {
            expected: vec![StreamKind::Depth, StreamKind::Color],
            ..SyncConfig::default()
        })
        .expect("valid config");
        sync.push(message(StreamKind::Depth, 0, 1_000 * MS));
        let set = sync.pop_ready(1_101 * MS).expect("timed out");
        assert_eq!(set.missing, vec![StreamKind::Color]);

        // Color stamped 3 ms after that depth frame shows up now: too late for it.
        sync.push(message(StreamKind::Color, 0, 1_003 * MS));
        // A depth frame at or before the emitted one cannot be emitted in order either.
        sync.push(message(StreamKind::Depth, 1, 1_000 * MS));
        let stats = sync.stats();
        assert_eq!(stats.stream(StreamKind::Color).map(|s| s.late), Some(1));
        assert_eq!(stats.stream(StreamKind::Depth).map(|s| s.late), Some(1));

        // A color frame for the next depth frame is on time.
        sync.push(message(StreamKind::Color, 1, 1_035 * MS));
        sync.push(message(StreamKind::Depth, 2, 1_033 * MS));
        let next = sync.flush();
        assert_eq!(next.len(), 1);
        assert_eq!(seq_of(&next[0], StreamKind::Color), Some(1));
        assert_eq!(
            sync.stats().stream(StreamKind::Color).map(|s| s.late),
            Some(1)
        );
    }

    #[test]
    fn slow_lamp_pairs_with_the_depth_frames_within_tolerance() {
        // Lamp at 10 Hz: on every third depth tick. With 20 ms tolerance it pairs with that tick
        // only; the other sets list it missing, decided by the next lamp (not by the timeout).
        let streams = [
            (StreamKind::Depth, 1, 2 * MS),
            (StreamKind::Lamp, 3, 4 * MS),
        ];
        let config = SyncConfig {
            expected: vec![StreamKind::Depth, StreamKind::Lamp],
            ..SyncConfig::default()
        };
        let max_wait_ns = config.max_wait_ns;
        let mut sync = Synchronizer::new(config).expect("valid config");
        let sets = run(&mut sync, rig(&streams, 60));
        assert_eq!(sets.len(), 60);
        for (tick, (set, emitted_at)) in sets.iter().enumerate() {
            let tick = tick as u64;
            if tick.is_multiple_of(3) {
                assert_eq!(seq_of(set, StreamKind::Lamp), Some(tick), "set {tick}");
            } else {
                assert_eq!(set.missing, vec![StreamKind::Lamp], "set {tick}");
                if let Some(now_ns) = emitted_at {
                    assert!(
                        *now_ns <= set.stamp.host_ns + max_wait_ns,
                        "set {tick} timed out"
                    );
                }
            }
        }
    }

    #[test]
    fn slow_lamp_serves_several_sets_with_a_wide_tolerance() {
        let streams = [
            (StreamKind::Depth, 1, 2 * MS),
            (StreamKind::Lamp, 3, 4 * MS),
        ];
        let mut sync = Synchronizer::new(SyncConfig {
            expected: vec![StreamKind::Depth, StreamKind::Lamp],
            tolerance_ns: 60 * MS,
            max_wait_ns: 150 * MS,
            ..SyncConfig::default()
        })
        .expect("valid config");
        // 58 ticks: the last lamp is on tick 57, so every set has one within 60 ms.
        let sets = run(&mut sync, rig(&streams, 58));
        assert_eq!(sets.len(), 58);
        for (tick, (set, _)) in sets.iter().enumerate() {
            // The nearest 10 Hz lamp tick: 0,1→0; 2,3,4→3; 5,6,7→6 …
            let nearest_lamp_tick = (tick as u64 + 1) / 3 * 3;
            assert!(set.is_complete(), "set {tick}");
            assert_eq!(
                seq_of(set, StreamKind::Lamp),
                Some(nearest_lamp_tick),
                "set {tick}"
            );
        }
        let lamp = sync
            .stats()
            .stream(StreamKind::Lamp)
            .copied()
            .expect("lamp stats");
        assert_eq!((lamp.matched, lamp.unused), (58, 0));
    }

    #[test]
    fn memory_stays_bounded_when_the_reference_stops() {
        let mut sync = Synchronizer::new(SyncConfig::default()).expect("valid config");
        sync.push(message(StreamKind::Depth, 0, 10 * MS));
        for seq in 0..10_000 {
            sync.push(message(StreamKind::Color, seq, 10 * MS + seq * PERIOD_NS));
        }
        assert!(sync.buffered() <= 1 + MAX_BUFFERED_PER_STREAM);
        let color = sync
            .stats()
            .stream(StreamKind::Color)
            .copied()
            .expect("color stats");
        assert_eq!(color.dropped, 10_000 - MAX_BUFFERED_PER_STREAM as u64);
        // Nobody polled while the buffer overflowed, so the matching color frame is gone too.
        let set = sync.pop_ready(u64::MAX).expect("timed out");
        assert!(set.missing.contains(&StreamKind::Color));
    }

    #[test]
    fn memory_stays_bounded_when_a_stream_stops() {
        let mut sync = Synchronizer::new(SyncConfig::default()).expect("valid config");
        for seq in 0..10_000 {
            sync.push(message(StreamKind::Depth, seq, 10 * MS + seq * PERIOD_NS));
        }
        assert!(sync.buffered() <= MAX_BUFFERED_PER_STREAM);
        let depth = sync
            .stats()
            .stream(StreamKind::Depth)
            .copied()
            .expect("depth stats");
        assert_eq!(depth.dropped, 10_000 - MAX_BUFFERED_PER_STREAM as u64);
        assert_eq!(sync.flush().len(), MAX_BUFFERED_PER_STREAM);
    }

    #[test]
    fn timestamps_going_backwards_are_dropped_or_restart_the_clock() {
        let mut sync = Synchronizer::new(SyncConfig {
            expected: vec![StreamKind::Depth, StreamKind::Color],
            ..SyncConfig::default()
        })
        .expect("valid config");
        sync.push(message(StreamKind::Depth, 0, 5_000 * MS));
        sync.push(message(StreamKind::Color, 0, 5_000 * MS));
        // A little back: out of order, dropped.
        sync.push(message(StreamKind::Color, 1, 4_990 * MS));
        assert_eq!(
            sync.stats().stream(StreamKind::Color).map(|s| s.dropped),
            Some(1)
        );
        // Far back: the host clock was reset. Start over rather than wait for it to catch up.
        sync.push(message(StreamKind::Depth, 1, 10 * MS));
        sync.push(message(StreamKind::Color, 2, 11 * MS));
        sync.push(message(StreamKind::Color, 3, 60 * MS));
        let stats = sync.stats();
        assert_eq!(stats.clock_resets, 1);
        let set = sync.pop_ready(20 * MS).expect("decided after the reset");
        assert_eq!(
            (set.stamp.host_ns, seq_of(&set, StreamKind::Color)),
            (10 * MS, Some(2))
        );
        assert_eq!(stats.stream(StreamKind::Depth).map(|s| s.dropped), Some(1));
    }

    #[test]
    fn unexpected_streams_are_counted_and_ignored() {
        let mut sync = Synchronizer::new(SyncConfig {
            expected: vec![StreamKind::Depth],
            ..SyncConfig::default()
        })
        .expect("valid config");
        sync.push(message(StreamKind::Lamp, 0, 10 * MS));
        sync.push(message(StreamKind::Depth, 0, 10 * MS));
        let set = sync.pop_ready(10 * MS).expect("depth alone is complete");
        assert!(set.is_complete() && set.lamp.is_none());
        assert_eq!(
            sync.stats().stream(StreamKind::Lamp).map(|s| s.dropped),
            Some(1)
        );
    }

    #[test]
    fn invalid_configs_are_rejected() {
        let bad = |config: SyncConfig| Synchronizer::new(config).err();
        assert_eq!(
            bad(SyncConfig {
                expected: vec![StreamKind::Color],
                ..SyncConfig::default()
            }),
            Some(SyncError::ReferenceNotExpected {
                reference: StreamKind::Depth
            })
        );
        assert_eq!(
            bad(SyncConfig {
                expected: vec![StreamKind::Depth, StreamKind::Lamp, StreamKind::Lamp],
                ..SyncConfig::default()
            }),
            Some(SyncError::DuplicateStream(StreamKind::Lamp))
        );
        assert_eq!(
            bad(SyncConfig {
                tolerance_ns: 0,
                ..SyncConfig::default()
            }),
            Some(SyncError::ZeroTolerance)
        );
        assert!(matches!(
            bad(SyncConfig {
                max_wait_ns: 1,
                ..SyncConfig::default()
            }),
            Some(SyncError::MaxWaitBelowTolerance { .. })
        ));
    }
}
