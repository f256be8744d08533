//! Typed frame bus: one topic per stream, each with a latest-value slot and bounded drop-oldest
//! queues, plus pools of reusable frames so that steady state allocates nothing.
//!
//! Producers (device threads) call [`Topic::publish`], which never blocks, never takes a lock a
//! consumer can hold for long, and never allocates once warmed up: the message is stored as the
//! topic's latest value (an [`ArcSwap`] whose cells are recycled) and force-pushed into each
//! subscriber's [`ArrayQueue`], evicting that subscriber's oldest message when it is full. A slow
//! consumer therefore loses its own oldest frames (counted per subscriber) and slows nobody else.
//!
//! Consumers that want the newest frame read [`Topic::latest`]; consumers that want every frame
//! (the recorder, the synchroniser) [`Topic::subscribe`] at setup time and drain their
//! [`Subscription`], blocking in [`Subscription::recv_timeout`] without spinning.

use std::fmt;
use std::ops::{Deref, DerefMut};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering, fence};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

use arc_swap::ArcSwap;
use crossbeam_queue::ArrayQueue;

use crate::frame::{Frame, Image};
use crate::stream::{LampState, MarkerSet, ProbeImage, StreamMessage};

/// A frame shared between the producer's pool and every consumer that still reads it.
pub type Shared<T> = Arc<Frame<T>>;

/// Recycled latest-value cells kept per topic. Two circulate in steady state (the stored one and
/// the spare); a third absorbs a reader that briefly holds the old one.
const SPARE_LATEST_CELLS: usize = 3;

/// A typed topic. Cloning gives another handle to the same topic.
pub struct Topic<M> {
    inner: Arc<TopicInner<M>>,
}

struct TopicInner<M> {
    name: &'static str,
    /// The newest message. Cells are `Arc<Option<M>>` so that an emptied cell can be reused
    /// (`Arc::get_mut`) instead of allocating a new `Arc` per publish.
    latest: ArcSwap<Option<M>>,
    spare_cells: ArrayQueue<Arc<Option<M>>>,
    subscribers: ArcSwap<Vec<Arc<Subscriber<M>>>>,
    published: AtomicU64,
    /// Drops of every subscriber this topic ever had, including those since unsubscribed.
    dropped: AtomicU64,
}

struct Subscriber<M> {
    name: Option<&'static str>,
    queue: ArrayQueue<M>,
    dropped: AtomicU64,
    doorbell: Doorbell,
}

/// Wakes receivers blocked in [`Subscription::recv_timeout`] without allocating and without the
/// publisher touching the mutex unless somebody sleeps. The mutex is only held between a
/// receiver's last emptiness check and its `Condvar` wait, never while a consumer works.
struct Doorbell {
    sleepers: AtomicUsize,
    lock: Mutex<()>,
    wake: Condvar,
}

impl Doorbell {
    fn new() -> Self {
        Self {
            sleepers: AtomicUsize::new(0),
            lock: Mutex::new(()),
            wake: Condvar::new(),
        }
    }

    /// Called after the message is in the queue. The fence pairs with the one in [`Self::wait`]
    /// (Dekker): either the sleeper sees the message, or we see the sleeper and notify it.
    fn ring(&self) {
        fence(Ordering::SeqCst);
        if self.sleepers.load(Ordering::SeqCst) > 0 {
            drop(self.lock.lock().unwrap_or_else(PoisonError::into_inner));
            self.wake.notify_all();
        }
    }

    /// Sleeps up to `timeout` unless `ready()` already holds. May return early (spuriously).
    fn wait(&self, timeout: Duration, ready: impl Fn() -> bool) {
        self.sleepers.fetch_add(1, Ordering::SeqCst);
        fence(Ordering::SeqCst);
        let guard = self.lock.lock().unwrap_or_else(PoisonError::into_inner);
        if !ready() {
            // Poisoning cannot corrupt `()`; a timeout or spurious wake is handled by the caller.
            drop(
                self.wake
                    .wait_timeout(guard, timeout)
                    .unwrap_or_else(PoisonError::into_inner),
            );
        }
        self.sleepers.fetch_sub(1, Ordering::SeqCst);
    }
}

impl<M> Clone for Topic<M> {
    fn clone(&self) -> Self {
        Self {
            inner: Arc::clone(&self.inner),
        }
    }
}

impl<M> fmt::Debug for Topic<M> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Topic")
            .field("name", &self.inner.name)
            .field("published", &self.inner.published.load(Ordering::Relaxed))
            .field("subscribers", &self.inner.subscribers.load().len())
            .finish()
    }
}

/// Counters of one topic, for monitoring (`relightctl status`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicStats {
    pub name: &'static str,
    pub published: u64,
    /// Messages lost to drop-oldest over the topic's life, by any subscriber.
    pub dropped: u64,
    pub subscribers: Vec<SubscriberStats>,
}

/// Counters of one current subscriber.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SubscriberStats {
    pub name: Option<&'static str>,
    pub capacity: usize,
    pub queued: usize,
    pub dropped: u64,
}

impl<M: Clone + Send + Sync + 'static> Topic<M> {
    pub fn new(name: &'static str) -> Self {
        Self {
            inner: Arc::new(TopicInner {
                name,
                latest: ArcSwap::from_pointee(None),
                spare_cells: ArrayQueue::new(SPARE_LATEST_CELLS),
                subscribers: ArcSwap::from_pointee(Vec::new()),
                published: AtomicU64::new(0),
                dropped: AtomicU64::new(0),
            }),
        }
    }

    pub fn name(&self) -> &'static str {
        self.inner.name
    }

    /// Stores `msg` as the latest value, force-pushes it into every subscriber's queue (a full
    /// queue loses its oldest message, counted) and wakes blocked receivers.
    ///
    /// Lock-free on the producer side and allocation-free in steady state. Allocations happen
    /// only on a thread's first publish (arc-swap's per-thread node) and when a `latest()` reader
    /// was holding the previous latest cell at the very moment of the swap.
    pub fn publish(&self, msg: M) {
        let inner = &*self.inner;
        let subscribers = inner.subscribers.load();
        for subscriber in subscribers.iter() {
            if subscriber.queue.force_push(msg.clone()).is_some() {
                subscriber.dropped.fetch_add(1, Ordering::Relaxed);
                inner.dropped.fetch_add(1, Ordering::Relaxed);
            }
            subscriber.doorbell.ring();
        }
        drop(subscribers);

        let cell = match inner.spare_cells.pop() {
            Some(mut cell) => match Arc::get_mut(&mut cell) {
                Some(value) => {
                    *value = Some(msg);
                    cell
                }
                None => Arc::new(Some(msg)),
            },
            None => Arc::new(Some(msg)),
        };
        let mut previous = inner.latest.swap(cell);
        if let Some(value) = Arc::get_mut(&mut previous) {
            // Release the previous frame now, so its pool slot frees as soon as consumers do.
            *value = None;
            // A full spare queue means enough cells circulate; this one is simply freed.
            let _ = inner.spare_cells.push(previous);
        }
        inner.published.fetch_add(1, Ordering::Release);
    }

    /// The newest message published, if any.
    pub fn latest(&self) -> Option<M> {
        Option::clone(&self.inner.latest.load())
    }

    /// A new subscriber whose queue holds at most `capacity` messages (at least 1). It sees
    /// messages published from now on. Allocates: call at setup time.
    pub fn subscribe(&self, capacity: usize) -> Subscription<M> {
        self.subscribe_inner(None, capacity)
    }

    /// Like [`Self::subscribe`], with a name shown in [`TopicStats`] (`"recorder"`, `"sync"`).
    pub fn subscribe_named(&self, name: &'static str, capacity: usize) -> Subscription<M> {
        self.subscribe_inner(Some(name), capacity)
    }

    fn subscribe_inner(&self, name: Option<&'static str>, capacity: usize) -> Subscription<M> {
        let subscriber = Arc::new(Subscriber {
            name,
            queue: ArrayQueue::new(capacity.max(1)),
            dropped: AtomicU64::new(0),
            doorbell: Doorbell::new(),
        });
        self.inner.subscribers.rcu(|current| {
            let mut next = Vec::with_capacity(current.len() + 1);
            next.extend(current.iter().cloned());
            next.push(Arc::clone(&subscriber));
            next
        });
        tracing::debug!(topic = self.inner.name, subscriber = ?name, capacity, "subscribed");
        Subscription {
            topic: Arc::clone(&self.inner),
            subscriber,
        }
    }

    /// Messages published since the topic was created.
    pub fn published(&self) -> u64 {
        self.inner.published.load(Ordering::Acquire)
    }

    /// Messages lost to drop-oldest by all subscribers, past ones included.
    pub fn dropped(&self) -> u64 {
        self.inner.dropped.load(Ordering::Relaxed)
    }

    pub fn subscriber_count(&self) -> usize {
        self.inner.subscribers.load().len()
    }

    /// A snapshot of the counters (allocates; for monitoring, not per frame).
    pub fn stats(&self) -> TopicStats {
        let subscribers = self
            .inner
            .subscribers
            .load()
            .iter()
            .map(|s| SubscriberStats {
                name: s.name,
                capacity: s.queue.capacity(),
                queued: s.queue.len(),
                dropped: s.dropped.load(Ordering::Relaxed),
            })
            .collect();
        TopicStats {
            name: self.inner.name,
            published: self.published(),
            dropped: self.dropped(),
            subscribers,
        }
    }
}

/// A consumer's queue on one topic. Dropping it unsubscribes.
pub struct Subscription<M> {
    topic: Arc<TopicInner<M>>,
    subscriber: Arc<Subscriber<M>>,
}

impl<M> fmt::Debug for Subscription<M> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Subscription")
            .field("topic", &self.topic.name)
            .field("name", &self.subscriber.name)
            .field("queued", &self.subscriber.queue.len())
            .field("dropped", &self.subscriber.dropped.load(Ordering::Relaxed))
            .finish()
    }
}

impl<M> Subscription<M> {
    /// The oldest queued message, without waiting.
    pub fn try_recv(&self) -> Option<M> {
        self.subscriber.queue.pop()
    }

    /// The oldest queued message, waiting up to `timeout` for one to be published. Sleeps on a
    /// condition variable; never spins.
    pub fn recv_timeout(&self, timeout: Duration) -> Option<M> {
        let deadline = Instant::now().checked_add(timeout);
        loop {
            if let Some(msg) = self.subscriber.queue.pop() {
                return Some(msg);
            }
            let remaining = match deadline {
                Some(deadline) => deadline.saturating_duration_since(Instant::now()),
                None => timeout,
            };
            if remaining.is_zero() {
                return None;
            }
            let queue = &self.subscriber.queue;
            self.subscriber
                .doorbell
                .wait(remaining, || !queue.is_empty());
        }
    }

    /// Messages this subscriber lost because its queue was full (drop-oldest).
    pub fn dropped(&self) -> u64 {
        self.subscriber.dropped.load(Ordering::Relaxed)
    }

    pub fn len(&self) -> usize {
        self.subscriber.queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.subscriber.queue.is_empty()
    }

    pub fn capacity(&self) -> usize {
        self.subscriber.queue.capacity()
    }

    pub fn topic_name(&self) -> &'static str {
        self.topic.name
    }
}

impl<M> Drop for Subscription<M> {
    fn drop(&mut self) {
        let me = &self.subscriber;
        self.topic.subscribers.rcu(|current| {
            current
                .iter()
                .filter(|s| !Arc::ptr_eq(s, me))
                .cloned()
                .collect::<Vec<_>>()
        });
        tracing::debug!(topic = self.topic.name, subscriber = ?me.name, "unsubscribed");
    }
}

/// The rig's topics, one per stream, plus `all`, which carries every message of every stream
/// (for the recorder and the synchroniser).
#[derive(Debug, Clone)]
pub struct Bus {
    pub depth: Topic<Shared<Image>>,
    pub color: Topic<Shared<Image>>,
    pub probe: Topic<Shared<ProbeImage>>,
    pub markers: Topic<Shared<MarkerSet>>,
    pub lamp: Topic<Shared<LampState>>,
    pub all: Topic<StreamMessage>,
}

impl Default for Bus {
    fn default() -> Self {
        Self::new()
    }
}

impl Bus {
    pub fn new() -> Self {
        Self {
            depth: Topic::new("depth"),
            color: Topic::new("color"),
            probe: Topic::new("probe"),
            markers: Topic::new("markers"),
            lamp: Topic::new("lamp"),
            all: Topic::new("all"),
        }
    }

    /// Publishes to the message's typed topic and to `all`. Allocation-free like
    /// [`Topic::publish`]: only `Arc`s are cloned.
    pub fn publish(&self, msg: StreamMessage) {
        match &msg {
            StreamMessage::Depth(frame) => self.depth.publish(Arc::clone(frame)),
            StreamMessage::Color(frame) => self.color.publish(Arc::clone(frame)),
            StreamMessage::Probe(frame) => self.probe.publish(Arc::clone(frame)),
            StreamMessage::Markers(frame) => self.markers.publish(Arc::clone(frame)),
            StreamMessage::Lamp(frame) => self.lamp.publish(Arc::clone(frame)),
        }
        self.all.publish(msg);
    }

    /// Messages lost to drop-oldest on every topic, by every subscriber.
    pub fn total_dropped(&self) -> u64 {
        self.depth.dropped()
            + self.color.dropped()
            + self.probe.dropped()
            + self.markers.dropped()
            + self.lamp.dropped()
            + self.all.dropped()
    }

    /// Counters of every topic (allocates; for monitoring).
    pub fn stats(&self) -> Vec<TopicStats> {
        vec![
            self.depth.stats(),
            self.color.stats(),
            self.probe.stats(),
            self.markers.stats(),
            self.lamp.stats(),
            self.all.stats(),
        ]
    }
}

/// Reusable frames so that steady state allocates nothing. The producer owns the pool; a slot is
/// free again once no consumer holds its `Arc` any more.
///
/// Size it above the most frames that can be in flight at once: one latest value per topic the
/// frame goes to, plus every subscriber queue's capacity, plus one in each consumer's hands.
pub struct FramePool<T> {
    slots: Vec<Shared<T>>,
    next: usize,
    exhausted: u64,
}

impl<T> fmt::Debug for FramePool<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("FramePool")
            .field("capacity", &self.slots.len())
            .field("in_flight", &self.in_flight())
            .field("exhausted", &self.exhausted)
            .finish()
    }
}

impl<T: Default> FramePool<T> {
    /// Preallocates `capacity` frames with default payloads.
    pub fn new(capacity: usize) -> Self {
        Self::with_init(capacity, T::default)
    }
}

impl<T> FramePool<T> {
    /// Preallocates `capacity` frames whose payloads come from `init`, e.g. images already at
    /// the sensor's size so that even the first fill allocates nothing.
    pub fn with_init(capacity: usize, mut init: impl FnMut() -> T) -> Self {
        Self {
            slots: (0..capacity)
                .map(|_| Arc::new(Frame::new(0, Default::default(), init())))
                .collect(),
            next: 0,
            exhausted: 0,
        }
    }

    /// A free frame to fill in place, or `None` when every frame is still held by a consumer:
    /// the caller then drops the captured frame and counts it (never blocks, never allocates).
    /// The slot's previous contents are left as they were, so buffers are reused.
    pub fn acquire(&mut self) -> Option<PoolSlot<'_, T>> {
        let len = self.slots.len();
        let start = self.next;
        let Some(index) = (0..len)
            .map(|step| (start + step) % len)
            .find(|&i| Arc::get_mut(&mut self.slots[i]).is_some())
        else {
            self.exhausted += 1;
            return None;
        };
        self.next = (index + 1) % len;
        Some(PoolSlot {
            frame: &mut self.slots[index],
        })
    }

    /// Frames currently held outside the pool.
    pub fn in_flight(&self) -> usize {
        self.slots
            .iter()
            .filter(|s| Arc::strong_count(s) > 1)
            .count()
    }

    pub fn capacity(&self) -> usize {
        self.slots.len()
    }

    /// How many times [`Self::acquire`] found no free frame.
    pub fn exhausted(&self) -> u64 {
        self.exhausted
    }
}

/// A pooled frame being filled. Derefs (mutably) to the [`Frame`]; [`PoolSlot::share`] ends the
/// filling and hands out the frame for publishing.
pub struct PoolSlot<'a, T> {
    /// Invariant: uniquely owned (`Arc::get_mut` succeeds) for the slot's whole life. `acquire`
    /// checked it, and the pool stays mutably borrowed, so nobody can clone it meanwhile.
    frame: &'a mut Shared<T>,
}

impl<T> fmt::Debug for PoolSlot<'_, T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("PoolSlot")
            .field("seq", &self.frame.seq)
            .field("stamp", &self.frame.stamp)
            .finish_non_exhaustive()
    }
}

impl<T> PoolSlot<'_, T> {
    /// The filled frame, shared: the pool gets the slot back when every clone is dropped.
    pub fn share(self) -> Shared<T> {
        Arc::clone(self.frame)
    }
}

impl<T> Deref for PoolSlot<'_, T> {
    type Target = Frame<T>;

    fn deref(&self) -> &Frame<T> {
        self.frame
    }
}

impl<T> DerefMut for PoolSlot<'_, T> {
    fn deref_mut(&mut self) -> &mut Frame<T> {
        Arc::get_mut(self.frame).expect("an acquired pool slot is uniquely owned until shared")
    }
}

#[cfg(test)]
mod tests {
    use std::thread;

    use super::*;
    use crate::frame::{PixelFormat, Timestamp};

    fn drain<M>(subscription: &Subscription<M>) -> Vec<M> {
        std::iter::from_fn(|| subscription.try_recv()).collect()
    }

    #[test]
    fn full_queue_drops_oldest_and_counts() {
        let topic = Topic::<u64>::new("numbers");
        let subscription = topic.subscribe(3);
        for n in 1..=5 {
            topic.publish(n);
        }
        assert_eq!(subscription.len(), 3);
        assert_eq!(drain(&subscription), vec![3, 4, 5]);
        assert_eq!(subscription.dropped(), 2);
        assert!(subscription.is_empty());
        assert_eq!(topic.published(), 5);
        assert_eq!(topic.dropped(), 2);
    }

    #[test]
    fn subscribers_of_different_speeds_are_independent() {
        let topic = Topic::<u64>::new("numbers");
        let slow = topic.subscribe_named("slow", 2);
        let fast = topic.subscribe_named("fast", 8);
        let mut fast_got = Vec::new();
        for n in 1..=5 {
            topic.publish(n);
            fast_got.extend(drain(&fast));
        }
        assert_eq!(fast_got, vec![1, 2, 3, 4, 5]);
        assert_eq!(fast.dropped(), 0);
        assert_eq!(drain(&slow), vec![4, 5]);
        assert_eq!(slow.dropped(), 3);

        let stats = topic.stats();
        assert_eq!(stats.published, 5);
        assert_eq!(stats.dropped, 3);
        let by_name = |name| stats.subscribers.iter().find(|s| s.name == Some(name));
        assert_eq!(
            by_name("slow").map(|s| (s.capacity, s.dropped)),
            Some((2, 3))
        );
        assert_eq!(
            by_name("fast").map(|s| (s.capacity, s.dropped)),
            Some((8, 0))
        );
    }

    #[test]
    fn latest_is_the_newest_message() {
        let topic = Topic::<u64>::new("numbers");
        assert_eq!(topic.latest(), None);
        for n in 1..=4 {
            topic.publish(n);
            assert_eq!(topic.latest(), Some(n));
        }
        // Reading does not consume.
        assert_eq!(topic.latest(), Some(4));
    }

    #[test]
    fn dropping_a_subscription_unsubscribes() {
        let topic = Topic::<u64>::new("numbers");
        let kept = topic.subscribe(4);
        let gone = topic.subscribe(4);
        assert_eq!(topic.subscriber_count(), 2);
        topic.publish(1);
        drop(gone);
        assert_eq!(topic.subscriber_count(), 1);
        assert_eq!(topic.stats().subscribers.len(), 1);
        topic.publish(2);
        assert_eq!(drain(&kept), vec![1, 2]);
    }

    #[test]
    fn capacity_zero_still_keeps_the_newest() {
        let topic = Topic::<u64>::new("numbers");
        let subscription = topic.subscribe(0);
        topic.publish(1);
        topic.publish(2);
        assert_eq!(drain(&subscription), vec![2]);
        assert_eq!(subscription.dropped(), 1);
    }

    #[test]
    fn recv_timeout_wakes_on_publish_from_another_thread() {
        let topic = Topic::<u64>::new("numbers");
        let subscription = topic.subscribe(4);
        let publisher = {
            let topic = topic.clone();
            thread::spawn(move || {
                thread::sleep(Duration::from_millis(20));
                topic.publish(7);
            })
        };
        // Generous timeout: the assertion is about the value, not the time it took.
        assert_eq!(subscription.recv_timeout(Duration::from_secs(30)), Some(7));
        publisher.join().expect("publisher thread");
    }

    #[test]
    fn recv_timeout_returns_none_when_nothing_comes() {
        let topic = Topic::<u64>::new("numbers");
        let subscription = topic.subscribe(4);
        assert_eq!(subscription.recv_timeout(Duration::from_millis(10)), None);
        assert_eq!(subscription.recv_timeout(Duration::ZERO), None);
    }

    #[test]
    fn many_messages_across_threads_arrive_in_order() {
        let topic = Topic::<u64>::new("numbers");
        let subscription = topic.subscribe(10_000);
        let publisher = {
            let topic = topic.clone();
            thread::spawn(move || (0..10_000).for_each(|n| topic.publish(n)))
        };
        let mut got = Vec::new();
        while got.len() < 10_000 {
            match subscription.recv_timeout(Duration::from_secs(30)) {
                Some(n) => got.push(n),
                None => break,
            }
        }
        publisher.join().expect("publisher thread");
        assert_eq!(got, (0..10_000).collect::<Vec<_>>());
    }

    fn lamp(seq: u64) -> StreamMessage {
        StreamMessage::Lamp(Arc::new(Frame::new(
            seq,
            Timestamp::new(seq, seq),
            LampState::default(),
        )))
    }

    #[test]
    fn bus_publishes_to_the_typed_topic_and_to_all() {
        let bus = Bus::new();
        let lamps = bus.lamp.subscribe(4);
        let everything = bus.all.subscribe(4);
        let depths = bus.depth.subscribe(4);
        bus.publish(lamp(1));
        let depth = Arc::new(Frame::new(
            2,
            Timestamp::new(2, 2),
            Image::new(2, 2, PixelFormat::DepthU16Mm),
        ));
        bus.publish(StreamMessage::Depth(Arc::clone(&depth)));

        assert_eq!(
            drain(&lamps).iter().map(|f| f.seq).collect::<Vec<_>>(),
            vec![1]
        );
        assert_eq!(
            drain(&depths).iter().map(|f| f.seq).collect::<Vec<_>>(),
            vec![2]
        );
        let kinds_and_seqs: Vec<_> = drain(&everything)
            .iter()
            .map(|m| (m.kind(), m.seq()))
            .collect();
        assert_eq!(
            kinds_and_seqs,
            vec![(crate::StreamKind::Lamp, 1), (crate::StreamKind::Depth, 2)]
        );
        assert!(bus.depth.latest().is_some_and(|f| Arc::ptr_eq(&f, &depth)));
        assert_eq!(bus.color.latest(), None);

        for seq in 3..10 {
            bus.publish(lamp(seq));
        }
        // 7 more lamps into two queues of 4 that held 0 and 0 ⇒ 3 drops each.
        assert_eq!(bus.total_dropped(), 6);
    }

    #[test]
    fn pool_reuses_frames_once_consumers_let_go() {
        let mut pool = FramePool::with_init(2, || Image::new(4, 3, PixelFormat::DepthU16Mm));
        let first = {
            let mut slot = pool.acquire().expect("free slot");
            slot.seq = 1;
            slot.payload.as_u16_mut().expect("u16 depth")[0] = 1500;
            slot.share()
        };
        let second = pool.acquire().expect("free slot").share();
        assert_eq!(pool.in_flight(), 2);
        assert!(pool.acquire().is_none());
        assert_eq!(pool.exhausted(), 1);

        let first_ptr = Arc::as_ptr(&first);
        assert_eq!(first.payload.as_u16().map(|d| d[0]), Some(1500));
        drop(first);
        assert_eq!(pool.in_flight(), 1);
        {
            let reused = pool.acquire().expect("slot freed by the consumer");
            assert_eq!(&*reused as *const Frame<Image>, first_ptr);
            // The buffer comes back as it was left: filling it in place reuses its memory.
            assert_eq!(reused.seq, 1);
        }
        drop(second);
        assert_eq!(pool.in_flight(), 0);
    }

    #[test]
    fn frames_held_only_as_latest_value_stay_in_flight() {
        let mut pool = FramePool::<LampState>::new(2);
        let topic = Topic::new("lamp");
        topic.publish(pool.acquire().expect("free slot").share());
        assert_eq!(pool.in_flight(), 1);
        topic.publish(pool.acquire().expect("free slot").share());
        // Publishing the second released the first from the latest-value slot.
        assert_eq!(pool.in_flight(), 1);
    }
}
