//! Bus throughput and publish→receive latency: 5 producers (one per stream, filling pooled
//! frames) publish through [`Bus`], 3 consumers each drain their own subscription to `all`.
//!
//! Criterion measures throughput (messages published per second, each delivered to all three
//! consumers). Before that, the bench prints latency percentiles over 100 000 messages, once with
//! producers flooding the bus (latency then includes queueing behind up to a full queue) and once
//! paced like real sensors (latency is then the hand-off and wake-up cost alone). The capture
//! instant travels in the payload: `stamp.host_ns` is nanoseconds since a shared `Instant`.
//!
//! `cargo bench -p relight-core --bench bus`; under `cargo test` it runs a small smoke version.

use std::hint::black_box;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Barrier};
use std::thread;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group};
use relight_core::bus::{Bus, FramePool, Shared};
use relight_core::{
    Image, LampState, MarkerSet, PixelFormat, ProbeImage, StreamKind, StreamMessage, Timestamp,
};

const CONSUMERS: usize = 3;
const QUEUE_CAPACITY: usize = 1024;
/// Per producer: every frame of its stream that can be in flight (three full queues, the two
/// latest values, one in each consumer's hands) plus slack.
const POOL_CAPACITY: usize = CONSUMERS * QUEUE_CAPACITY + 16;

#[derive(Debug, Default)]
struct Round {
    elapsed: Duration,
    published: u64,
    /// Summed over consumers.
    received: u64,
    dropped: u64,
    latencies_ns: Vec<u64>,
}

fn nanos_since(origin: Instant) -> u64 {
    u64::try_from(origin.elapsed().as_nanos()).unwrap_or(u64::MAX)
}

/// Fills a pooled frame, stamps it with the time since `origin` and publishes it. Waits (yields)
/// when every pooled frame is still held by consumers: back-pressure, for the bench only.
fn publish_pooled<T>(
    bus: &Bus,
    pool: &mut FramePool<T>,
    seq: u64,
    origin: Instant,
    wrap: fn(Shared<T>) -> StreamMessage,
) {
    loop {
        if let Some(mut slot) = pool.acquire() {
            slot.seq = seq;
            let host_ns = nanos_since(origin);
            slot.stamp = Timestamp::new(host_ns, host_ns);
            bus.publish(wrap(slot.share()));
            return;
        }
        thread::yield_now();
    }
}

fn producer(
    kind: StreamKind,
    bus: Bus,
    messages: u64,
    pace: Option<Duration>,
    origin: Instant,
    start: Arc<Barrier>,
) -> thread::JoinHandle<()> {
    thread::spawn(move || {
        let image = |format| move || Image::new(16, 12, format);
        let mut depth = FramePool::with_init(
            if kind == StreamKind::Depth {
                POOL_CAPACITY
            } else {
                0
            },
            image(PixelFormat::DepthU16Mm),
        );
        let mut color = FramePool::with_init(
            if kind == StreamKind::Color {
                POOL_CAPACITY
            } else {
                0
            },
            image(PixelFormat::Rgb8),
        );
        let pool_size = |k| if k == kind { POOL_CAPACITY } else { 0 };
        let mut probe = FramePool::<ProbeImage>::new(pool_size(StreamKind::Probe));
        let mut markers = FramePool::<MarkerSet>::new(pool_size(StreamKind::Markers));
        let mut lamp = FramePool::<LampState>::new(pool_size(StreamKind::Lamp));
        start.wait();
        for seq in 0..messages {
            match kind {
                StreamKind::Depth => {
                    publish_pooled(&bus, &mut depth, seq, origin, StreamMessage::Depth)
                }
                StreamKind::Color => {
                    publish_pooled(&bus, &mut color, seq, origin, StreamMessage::Color)
                }
                StreamKind::Probe => {
                    publish_pooled(&bus, &mut probe, seq, origin, StreamMessage::Probe)
                }
                StreamKind::Markers => {
                    publish_pooled(&bus, &mut markers, seq, origin, StreamMessage::Markers)
                }
                StreamKind::Lamp => {
                    publish_pooled(&bus, &mut lamp, seq, origin, StreamMessage::Lamp)
                }
            }
            if let Some(pace) = pace {
                thread::sleep(pace);
            }
        }
    })
}

/// One run: 5 producers × `per_producer` messages to 3 consumers of `all`.
fn run_round(per_producer: u64, pace: Option<Duration>, record_latency: bool) -> Round {
    let bus = Bus::new();
    let origin = Instant::now();
    let total = per_producer * StreamKind::ALL.len() as u64;
    let producers_left = Arc::new(AtomicUsize::new(StreamKind::ALL.len()));
    let start = Arc::new(Barrier::new(StreamKind::ALL.len() + 1));

    let consumers: Vec<_> = (0..CONSUMERS)
        .map(|_| {
            let subscription = bus.all.subscribe_named("bench consumer", QUEUE_CAPACITY);
            let producers_left = Arc::clone(&producers_left);
            thread::spawn(move || {
                let capacity = if record_latency { total as usize } else { 0 };
                let mut latencies_ns = Vec::with_capacity(capacity);
                let mut received = 0_u64;
                loop {
                    let finished = producers_left.load(Ordering::Acquire) == 0;
                    let msg = if finished {
                        subscription.try_recv()
                    } else {
                        subscription.recv_timeout(Duration::from_millis(20))
                    };
                    match msg {
                        Some(msg) => {
                            let now_ns = nanos_since(origin);
                            if record_latency {
                                latencies_ns.push(now_ns.saturating_sub(msg.stamp().host_ns));
                            }
                            black_box(msg);
                            received += 1;
                        }
                        None if finished => break,
                        None => {}
                    }
                }
                (received, subscription.dropped(), latencies_ns)
            })
        })
        .collect();

    let producers: Vec<_> = StreamKind::ALL
        .into_iter()
        .map(|kind| {
            let (bus, start) = (bus.clone(), Arc::clone(&start));
            let producers_left = Arc::clone(&producers_left);
            let handle = producer(kind, bus, per_producer, pace, origin, start);
            thread::spawn(move || {
                let result = handle.join();
                producers_left.fetch_sub(1, Ordering::Release);
                result
            })
        })
        .collect();

    start.wait();
    let started = Instant::now();
    for producer in producers {
        let joined = producer.join().map(|inner| inner.is_ok());
        assert!(matches!(joined, Ok(true)), "producer thread panicked");
    }
    let mut round = Round::default();
    for consumer in consumers {
        let (received, dropped, latencies_ns) = consumer.join().expect("consumer thread panicked");
        round.received += received;
        round.dropped += dropped;
        round.latencies_ns.extend(latencies_ns);
    }
    round.elapsed = started.elapsed();
    round.published = bus.all.published();
    assert_eq!(round.published, total);
    assert_eq!(round.received + round.dropped, total * CONSUMERS as u64);
    round
}

fn percentile_us(sorted_ns: &[u64], p: f64) -> f64 {
    let Some(last) = sorted_ns.len().checked_sub(1) else {
        return f64::NAN;
    };
    let index = ((last as f64) * p).round() as usize;
    sorted_ns
        .get(index.min(last))
        .map_or(f64::NAN, |&ns| ns as f64 / 1e3)
}

fn report(label: &str, mut round: Round) {
    round.latencies_ns.sort_unstable();
    let seconds = round.elapsed.as_secs_f64();
    println!(
        "bus {label}: {} msgs published in {:.3} s = {:.0} msg/s published, {:.0} msg/s delivered; \
         drops {} of {}; latency µs p50 {:.1}, p90 {:.1}, p99 {:.1}, p99.9 {:.1}, max {:.1}",
        round.published,
        seconds,
        round.published as f64 / seconds,
        round.received as f64 / seconds,
        round.dropped,
        round.published * CONSUMERS as u64,
        percentile_us(&round.latencies_ns, 0.50),
        percentile_us(&round.latencies_ns, 0.90),
        percentile_us(&round.latencies_ns, 0.99),
        percentile_us(&round.latencies_ns, 0.999),
        percentile_us(&round.latencies_ns, 1.0),
    );
}

/// 100 000 messages flooded, then 100 000 paced (each producer sleeps 100 µs between frames).
fn latency_report(per_producer: u64) {
    report(
        "flood (5 producers → 3 consumers of `all`)",
        run_round(per_producer, None, true),
    );
    report(
        "paced (5 producers sleeping 100 µs → 3 consumers of `all`)",
        run_round(per_producer, Some(Duration::from_micros(100)), true),
    );
}

const THROUGHPUT_PER_PRODUCER: u64 = 4_000;

fn throughput(c: &mut Criterion) {
    let mut group = c.benchmark_group("bus");
    group.throughput(Throughput::Elements(
        THROUGHPUT_PER_PRODUCER * StreamKind::ALL.len() as u64,
    ));
    group.bench_function("5_producers_3_consumers_of_all", |b| {
        b.iter_custom(|iters| {
            (0..iters)
                .map(|_| run_round(THROUGHPUT_PER_PRODUCER, None, false).elapsed)
                .sum()
        })
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5));
    targets = throughput
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` does not: keep that a smoke test.
    let benchmarking = std::env::args().any(|arg| arg == "--bench");
    latency_report(if benchmarking { 20_000 } else { 200 });
    benches();
    Criterion::default().configure_from_args().final_summary();
}
