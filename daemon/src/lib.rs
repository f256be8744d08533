//! relightd internals: configuration, pipeline, control socket, sinks.
pub mod bench;
pub mod config;
pub mod control;
pub mod devices;
pub mod governor_bench;
pub mod pipeline;
pub mod score;
pub mod sinks;
pub mod soak;
pub mod timing;
pub mod worker;

/// A mutex's guard, also after a panic elsewhere poisoned it: the daemon's shared state stays
/// readable (status, control) rather than taking every thread down with one.
pub(crate) fn lock<T>(mutex: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}
