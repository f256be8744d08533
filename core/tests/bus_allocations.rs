//! The bus's promise: in steady state a producer filling pooled frames and publishing them
//! through the [`Bus`] to blocking subscribers allocates nothing, on either side.
//!
//! A counting global allocator counts only on threads that opted in (a thread-local flag) and
//! only while the measurement window is open, so the test harness's own threads cannot make the
//! count flaky.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread;
use std::time::Duration;

use relight_core::bus::{Bus, FramePool, Subscription};
use relight_core::{Image, PixelFormat, StreamMessage, Timestamp};

struct CountingAllocator;

static MEASURING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    // `const` and without a destructor: reading it never allocates or registers anything.
    static TRACKED: Cell<bool> = const { Cell::new(false) };
}

fn count_allocation() {
    if MEASURING.load(Ordering::Relaxed) && TRACKED.with(Cell::get) {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
    }
}

// SAFETY: every method forwards to `System` with the caller's arguments unchanged, so the
// `GlobalAlloc` contract holds exactly as it does for `System`; counting touches only atomics
// and a const thread-local, neither of which allocates.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count_allocation();
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count_allocation();
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count_allocation();
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;
const QUEUE_CAPACITY: usize = 4;
/// More than can be in flight: one latest value per topic, both queues, one frame in each
/// consumer's hands.
const POOL_CAPACITY: usize = 4 * QUEUE_CAPACITY;
const WARM_UP_FRAMES: u64 = 200;
const MEASURED_FRAMES: u64 = 1000;

/// Drains `subscription` until `stop`, touching each frame like a real consumer would.
fn consume<M: Send + Sync + 'static>(
    subscription: Subscription<M>,
    stop: Arc<AtomicBool>,
    read: fn(&M) -> u64,
) -> thread::JoinHandle<u64> {
    thread::spawn(move || {
        TRACKED.with(|t| t.set(true));
        let mut received = 0_u64;
        let mut checksum = 0_u64;
        loop {
            // Read the flag first: once it is set, everything was published, and the drain
            // below sees it all.
            let stopping = stop.load(Ordering::Acquire);
            let msg = if stopping {
                subscription.try_recv()
            } else {
                subscription.recv_timeout(Duration::from_millis(5))
            };
            match msg {
                Some(msg) => {
                    checksum = checksum.wrapping_add(read(&msg));
                    received += 1;
                }
                None if stopping => break,
                None => {}
            }
        }
        TRACKED.with(|t| t.set(false));
        std::hint::black_box(checksum);
        drop(subscription);
        received
    })
}

#[test]
fn steady_state_publishing_allocates_nothing() {
    let bus = Bus::new();
    let stop = Arc::new(AtomicBool::new(false));
    let depth_consumer = consume(
        bus.depth.subscribe_named("depth consumer", QUEUE_CAPACITY),
        Arc::clone(&stop),
        |frame| u64::from(frame.payload.as_u16().map_or(0, |d| d[0])),
    );
    let all_consumer = consume(
        bus.all.subscribe_named("recorder", QUEUE_CAPACITY),
        Arc::clone(&stop),
        StreamMessage::seq,
    );

    let mut pool = FramePool::with_init(POOL_CAPACITY, || {
        Image::new(WIDTH, HEIGHT, PixelFormat::DepthU16Mm)
    });
    let mut published = 0_u64;
    let mut publish = |seq: u64| {
        let Some(mut slot) = pool.acquire() else {
            return;
        };
        slot.seq = seq;
        slot.stamp = Timestamp::new(seq * 33_333_333, seq * 33_333_333);
        slot.payload.reshape(WIDTH, HEIGHT, PixelFormat::DepthU16Mm);
        if let Some(depth_mm) = slot.payload.as_u16_mut() {
            depth_mm
                .iter_mut()
                .step_by(97)
                .for_each(|d| *d = (seq % 4000) as u16);
        }
        bus.publish(StreamMessage::Depth(slot.share()));
        published += 1;
    };

    TRACKED.with(|t| t.set(true));
    for seq in 0..WARM_UP_FRAMES {
        publish(seq);
    }
    MEASURING.store(true, Ordering::SeqCst);
    for seq in WARM_UP_FRAMES..WARM_UP_FRAMES + MEASURED_FRAMES {
        publish(seq);
        if seq % 8 == 0 {
            // Let the consumers run, so that blocking and waking are part of what is measured.
            thread::yield_now();
        }
    }
    MEASURING.store(false, Ordering::SeqCst);
    TRACKED.with(|t| t.set(false));
    let allocations = ALLOCATIONS.load(Ordering::SeqCst);

    stop.store(true, Ordering::Release);
    let depth_received = depth_consumer.join().expect("depth consumer");
    let all_received = all_consumer.join().expect("all consumer");

    assert_eq!(
        pool.exhausted(),
        0,
        "the pool is larger than what can be in flight"
    );
    assert_eq!(published, WARM_UP_FRAMES + MEASURED_FRAMES);
    assert!(depth_received > 0 && all_received > 0);
    assert_eq!(
        depth_received + bus.depth.dropped(),
        published,
        "every frame is either received or counted as dropped"
    );
    assert_eq!(all_received + bus.all.dropped(), published);
    assert_eq!(
        allocations, 0,
        "allocations during {MEASURED_FRAMES} steady-state frames"
    );
}
