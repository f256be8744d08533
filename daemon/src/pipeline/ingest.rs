//! The ingest stage: every message off the bus, through the timestamp synchroniser, into frame
//! sets, by the pipeline's latency policy.
//!
//! Live sources (devices, the simulator, a realtime replay) yield only the newest decided set;
//! older ones are counted as superseded, so a slow engine shows the camera late by its own
//! render time, not by a growing queue. Fast and stepped replays are lossless: every set is
//! yielded, decided on the data's clock, and a fast replay is told how many reference frames
//! are done with ([`Backpressure`]).

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use relight_backends::Backpressure;
use relight_core::StreamMessage;
use relight_core::bus::Subscription;
use relight_core::frame::host_now_ns;
use relight_core::sync::{FrameSet, SyncConfig as CoreSyncConfig, Synchronizer};

use super::status::Counters;
use crate::control::types::SyncStreamStatus;
use crate::timing::StageTimer;

/// A decided frame set, and when its reference frame reached the render thread.
#[derive(Debug)]
pub struct ReadySet {
    pub set: FrameSet,
    pub arrived: Option<Instant>,
}

pub struct Ingest {
    /// Every message of every stream, subscribed before the sources started.
    subscription: Subscription<StreamMessage>,
    synchronizer: Synchronizer,
    lossless: bool,
    backpressure: Option<Arc<Backpressure>>,
    /// Wall-clock arrival of recent reference frames, to time how long sets wait to render.
    arrivals: VecDeque<(u64, Instant)>,
    /// The newest host stamp seen: the synchroniser's clock in lossless replays, whose stamps
    /// are the recording's and run ahead of (or behind) the wall clock.
    data_clock_ns: u64,
    references_received: u64,
    /// The newest decided set not yielded yet (live sources).
    newest: Option<FrameSet>,
    /// From decision to render: the `queue` stage.
    queue: StageTimer,
    /// Frame sets and time at the last copy of the sync counters into the status.
    stats_at: u64,
    stats_time: Instant,
}

impl std::fmt::Debug for Ingest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ingest")
            .field("lossless", &self.lossless)
            .field("references_received", &self.references_received)
            .finish_non_exhaustive()
    }
}

impl Ingest {
    pub fn new(
        subscription: Subscription<StreamMessage>,
        synchronizer: Synchronizer,
        lossless: bool,
        backpressure: Option<Arc<Backpressure>>,
        queue: StageTimer,
    ) -> Self {
        Self {
            subscription,
            synchronizer,
            lossless,
            backpressure,
            arrivals: VecDeque::new(),
            data_clock_ns: 0,
            references_received: 0,
            newest: None,
            queue,
            stats_at: 0,
            stats_time: Instant::now(),
        }
    }

    pub fn is_lossless(&self) -> bool {
        self.lossless
    }

    /// New synchroniser settings (`config.reload`); sets waiting in the old one are dropped.
    pub fn reconfigure(&mut self, sync: CoreSyncConfig) {
        match Synchronizer::new(sync) {
            Ok(s) => self.synchronizer = s,
            Err(error) => tracing::warn!(%error, "sync settings not applied"),
        }
    }

    /// The next message off the bus: waits up to `wait` for the first of a turn, then takes
    /// what is queued without waiting (`wait` zero).
    pub fn recv(&self, wait: Duration) -> Option<StreamMessage> {
        if wait.is_zero() {
            self.subscription.try_recv()
        } else {
            self.subscription.recv_timeout(wait)
        }
    }

    /// True when nothing is queued on the bus.
    pub fn is_drained(&self) -> bool {
        self.subscription.is_empty()
    }

    /// A message into the synchroniser.
    pub fn push(&mut self, msg: StreamMessage) {
        let host_ns = msg.stamp().host_ns;
        self.data_clock_ns = self.data_clock_ns.max(host_ns);
        if msg.kind() == self.synchronizer.config().reference {
            self.references_received += 1;
            if self.arrivals.len() == 64 {
                self.arrivals.pop_front();
            }
            self.arrivals.push_back((host_ns, Instant::now()));
        }
        self.synchronizer.push(msg);
    }

    /// The next set to render, if one is decided. Lossless, every set in order: a lossless
    /// replay runs on the data clock and can decide as it reads (which also frees its
    /// back-pressure sooner). Live, the newest decided set, once a backlog has been read whole:
    /// on the wall clock its old reference frames are already past max_wait, and would be
    /// decided before their partners, queued right behind them, were read.
    pub fn next_set(&mut self, counters: &Counters) -> Option<ReadySet> {
        self.release_backpressure();
        let set = if self.lossless {
            self.synchronizer.pop_ready(self.data_clock_ns)
        } else {
            let now_ns = host_now_ns().max(self.data_clock_ns);
            while let Some(set) = self.synchronizer.pop_ready(now_ns) {
                self.keep_newest(set, counters);
            }
            self.newest.take()
        };
        set.map(|set| self.ready(set))
    }

    /// Once the sources have ended: what the synchroniser still holds, decided as it stands.
    pub fn flush(&mut self, counters: &Counters) -> Vec<ReadySet> {
        let sets = self.synchronizer.flush();
        if self.lossless {
            return sets.into_iter().map(|set| self.ready(set)).collect();
        }
        for set in sets {
            self.keep_newest(set, counters);
        }
        self.newest
            .take()
            .map(|set| self.ready(set))
            .into_iter()
            .collect()
    }

    fn keep_newest(&mut self, set: FrameSet, counters: &Counters) {
        if self.newest.replace(set).is_some() {
            counters.skipped_superseded.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn ready(&self, set: FrameSet) -> ReadySet {
        let arrived = self
            .arrivals
            .iter()
            .find(|(host_ns, _)| *host_ns == set.stamp.host_ns)
            .map(|(_, t)| *t);
        self.queue
            .record(arrived.map_or(0.0, |t| t.elapsed().as_secs_f64() * 1e3));
        ReadySet { set, arrived }
    }

    /// Tell a fast replay how many reference frames are done with: read, and no longer
    /// waiting in the synchroniser (rendered or discarded), plus what the queue dropped.
    fn release_backpressure(&self) {
        if let Some(gate) = &self.backpressure {
            gate.finished(
                (self.references_received + self.subscription.dropped())
                    .saturating_sub(self.synchronizer.pending() as u64),
            );
        }
    }

    /// Copy the synchroniser's counters for status reports, a few times a second; `now` copies
    /// them whatever the time (the last copy, when the sources end).
    pub fn publish_stats(&mut self, counters: &Counters, now: bool) {
        counters
            .skipped_queue
            .store(self.subscription.dropped(), Ordering::Relaxed);
        let sets = counters.frame_sets.load(Ordering::Relaxed);
        if !now {
            if sets == self.stats_at {
                return;
            }
            if sets < self.stats_at + 10 && self.stats_time.elapsed() < Duration::from_millis(250) {
                return;
            }
        }
        self.stats_at = sets;
        self.stats_time = Instant::now();
        let config = self.synchronizer.config();
        let stats = self.synchronizer.stats();
        if let Some(reference) = stats.stream(config.reference) {
            counters
                .skipped_sync
                .store(reference.late + reference.dropped, Ordering::Relaxed);
        }
        counters.set_sync_streams(
            stats
                .streams
                .iter()
                .filter(|s| config.expected.contains(&s.kind))
                .map(|s| SyncStreamStatus {
                    stream: s.kind,
                    matched: s.matched,
                    missing: s.missing,
                    late: s.late,
                    dropped: s.dropped + s.unused,
                })
                .collect(),
        );
    }
}
