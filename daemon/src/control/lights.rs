//! The published lighting estimate (`lights.get`) and its subscribers (`lights.subscribe`).
//!
//! The pipeline calls [`LightsBoard::publish`] when the light it renders with changes; control
//! connections read the latest estimate or hold a [`LightsSubscription`].
//!
//! Queueing policy: every subscriber has a one-slot mailbox. An update replaces one that was not
//! taken yet (coalesce to newest; counted in [`LightsSubscription::coalesced`]), so a slow
//! subscriber gets fewer updates but never a stale one, and the last update it gets is the
//! current estimate. Publishing only swaps pointers under short locks: it never waits on a
//! subscriber, whatever the subscriber does. A subscription that was dropped is forgotten at the
//! next publish.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError, Weak};
use std::time::{Duration, Instant};

use crate::lock;
use relight_core::scene::EnvironmentMap;
use relight_recon::estimate::LightingEstimate;

/// The latest lighting estimate and the subscribers to be told about the next one.
#[derive(Debug, Default)]
pub struct LightsBoard {
    /// Held while registering a subscriber too, so that none misses an update in between.
    latest: Mutex<Option<Arc<LightingEstimate>>>,
    subscribers: Mutex<Vec<Weak<Slot>>>,
    published: AtomicU64,
    /// The HDR environment the estimate was made from (`lights.export`).
    environment: Mutex<Option<Arc<EnvironmentMap>>>,
}

/// One subscriber's mailbox.
#[derive(Debug, Default)]
struct Slot {
    state: Mutex<SlotState>,
    ready: Condvar,
}

#[derive(Debug, Default)]
struct SlotState {
    pending: Option<Arc<LightingEstimate>>,
    closed: bool,
    /// Updates replaced before they were taken.
    coalesced: u64,
}

impl LightsBoard {
    pub fn new() -> Self {
        Self::default()
    }

    /// The HDR environment map the current estimate comes from (the probe's merged map, else
    /// the scene file's); `None` without either.
    pub fn environment(&self) -> Option<Arc<EnvironmentMap>> {
        lock(&self.environment).clone()
    }

    /// Replaces the environment [`Self::environment`] returns.
    pub fn publish_environment(&self, environment: Option<Arc<EnvironmentMap>>) {
        *lock(&self.environment) = environment;
    }

    /// The current estimate; `None` before the first [`Self::publish`].
    pub fn latest(&self) -> Option<Arc<LightingEstimate>> {
        lock(&self.latest).clone()
    }

    /// Makes `estimate` the current one and hands it to every subscriber (replacing an update a
    /// subscriber has not taken yet). An estimate equal to the current one changes nothing and
    /// returns `false`. Never blocks on subscribers.
    pub fn publish(&self, estimate: impl Into<Arc<LightingEstimate>>) -> bool {
        let estimate = estimate.into();
        let mut latest = lock(&self.latest);
        if latest.as_deref() == Some(&*estimate) {
            return false;
        }
        *latest = Some(Arc::clone(&estimate));
        self.published.fetch_add(1, Ordering::Relaxed);
        let mut subscribers = lock(&self.subscribers);
        subscribers.retain(|weak| match weak.upgrade() {
            Some(slot) => slot.offer(&estimate),
            None => false,
        });
        true
    }

    /// Estimates published so far (equal ones skipped).
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Relaxed)
    }

    /// Subscribers still registered (closed and dropped ones go at the next publish).
    pub fn subscribers(&self) -> usize {
        lock(&self.subscribers)
            .iter()
            .filter(|weak| weak.strong_count() > 0)
            .count()
    }

    /// A new subscription; its first update is the current estimate, if there is one.
    pub fn subscribe(&self) -> LightsSubscription {
        let latest = lock(&self.latest);
        let slot = Arc::new(Slot::default());
        lock(&slot.state).pending = latest.clone();
        lock(&self.subscribers).push(Arc::downgrade(&slot));
        LightsSubscription { slot }
    }
}

impl Slot {
    /// Puts `estimate` in the mailbox; `false` once the subscription is closed.
    fn offer(&self, estimate: &Arc<LightingEstimate>) -> bool {
        let mut state = lock(&self.state);
        if state.closed {
            return false;
        }
        if state.pending.replace(Arc::clone(estimate)).is_some() {
            state.coalesced += 1;
        }
        drop(state);
        self.ready.notify_all();
        true
    }
}

/// Why [`LightsSubscription::recv_timeout`] returned no update.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecvError {
    Timeout,
    /// [`LightsSubscription::close`] was called.
    Closed,
}

/// A subscriber's end: updates of the [`LightsBoard`] it came from. Clones share the mailbox (one
/// thread waits for updates, another may [`Self::close`] it).
#[derive(Debug, Clone)]
pub struct LightsSubscription {
    slot: Arc<Slot>,
}

impl LightsSubscription {
    /// Waits for the next update; `None` once closed.
    pub fn recv(&self) -> Option<Arc<LightingEstimate>> {
        let mut state = lock(&self.slot.state);
        loop {
            if state.closed {
                return None;
            }
            if let Some(estimate) = state.pending.take() {
                return Some(estimate);
            }
            state = self
                .slot
                .ready
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }

    /// Waits at most `timeout` for the next update.
    pub fn recv_timeout(&self, timeout: Duration) -> Result<Arc<LightingEstimate>, RecvError> {
        let deadline = Instant::now() + timeout;
        let mut state = lock(&self.slot.state);
        loop {
            if state.closed {
                return Err(RecvError::Closed);
            }
            if let Some(estimate) = state.pending.take() {
                return Ok(estimate);
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(RecvError::Timeout);
            }
            state = self
                .slot
                .ready
                .wait_timeout(state, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }

    /// The waiting update, if any, without blocking.
    pub fn try_recv(&self) -> Option<Arc<LightingEstimate>> {
        let mut state = lock(&self.slot.state);
        if state.closed {
            return None;
        }
        state.pending.take()
    }

    /// Ends the subscription: waiting and later receives return at once without an update, and
    /// the board drops it at its next publish.
    pub fn close(&self) {
        let mut state = lock(&self.slot.state);
        state.closed = true;
        state.pending = None;
        drop(state);
        self.slot.ready.notify_all();
    }

    /// Updates that were replaced by a newer one before this subscriber took them.
    pub fn coalesced(&self) -> u64 {
        lock(&self.slot.state).coalesced
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use relight_core::light::Light;
    use relight_core::sh::Sh9Rgb;

    use super::*;

    fn estimate(intensity: f32) -> LightingEstimate {
        LightingEstimate::from_lights(
            vec![Light::Point {
                position_in_world: Vec3::Y,
                intensity: Vec3::splat(intensity),
            }],
            0,
            Sh9Rgb::ZERO,
            None,
            Vec3::ZERO,
        )
    }

    fn intensity(estimate: &LightingEstimate) -> f32 {
        estimate.main_light.map_or(0.0, |m| m.intensity)
    }

    #[test]
    fn nothing_before_the_first_publish() {
        let board = LightsBoard::new();
        assert!(board.latest().is_none());
        let subscription = board.subscribe();
        assert!(subscription.try_recv().is_none());
        assert_eq!(
            subscription.recv_timeout(Duration::from_millis(5)).err(),
            Some(RecvError::Timeout)
        );
        assert!(board.publish(estimate(1.0)));
        assert_eq!(board.latest().as_deref(), Some(&estimate(1.0)));
        assert_eq!(subscription.try_recv().as_deref(), Some(&estimate(1.0)));
    }

    #[test]
    fn a_new_subscriber_gets_the_current_estimate_first() {
        let board = LightsBoard::new();
        board.publish(estimate(1.0));
        let subscription = board.subscribe();
        assert_eq!(
            subscription
                .recv_timeout(Duration::from_secs(1))
                .map(|e| intensity(&e)),
            Ok(1.0)
        );
        assert!(subscription.try_recv().is_none(), "once");
    }

    #[test]
    fn an_unchanged_estimate_is_not_published_again() {
        let board = LightsBoard::new();
        let subscription = board.subscribe();
        assert!(board.publish(estimate(1.0)));
        assert!(subscription.try_recv().is_some());
        assert!(!board.publish(estimate(1.0)));
        assert!(subscription.try_recv().is_none());
        assert_eq!(board.published(), 1);
    }

    #[test]
    fn a_slow_subscriber_gets_the_newest_and_never_blocks_the_publisher() {
        let board = LightsBoard::new();
        let slow = board.subscribe();
        let fast = board.subscribe();
        for i in 1..=1000 {
            board.publish(estimate(i as f32));
            assert_eq!(fast.try_recv().map(|e| intensity(&e)), Some(i as f32));
        }
        assert_eq!(slow.try_recv().map(|e| intensity(&e)), Some(1000.0));
        assert!(slow.try_recv().is_none());
        assert_eq!(slow.coalesced(), 999);
        assert_eq!(fast.coalesced(), 0);
    }

    #[test]
    fn closing_wakes_the_waiter_and_unregisters() {
        let board = Arc::new(LightsBoard::new());
        let subscription = board.subscribe();
        let waiter = {
            let subscription = subscription.clone();
            std::thread::spawn(move || subscription.recv())
        };
        std::thread::sleep(Duration::from_millis(20));
        subscription.close();
        assert!(waiter.join().expect("waiter").is_none());
        assert_eq!(
            subscription.recv_timeout(Duration::from_secs(1)).err(),
            Some(RecvError::Closed)
        );
        board.publish(estimate(2.0));
        assert_eq!(board.subscribers(), 0);

        let dropped = board.subscribe();
        assert_eq!(board.subscribers(), 1);
        drop(dropped);
        board.publish(estimate(3.0));
        assert_eq!(board.subscribers(), 0);
    }

    #[test]
    fn a_waiting_subscriber_wakes_on_publish() {
        let board = Arc::new(LightsBoard::new());
        let subscription = board.subscribe();
        let waiter = std::thread::spawn(move || subscription.recv());
        std::thread::sleep(Duration::from_millis(20));
        board.publish(estimate(4.0));
        let got = waiter.join().expect("waiter").expect("an update");
        assert_eq!(intensity(&got), 4.0);
    }
}
