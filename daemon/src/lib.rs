//! relightd internals: configuration, pipeline, control socket, sinks.
pub mod bench;
pub mod config;
pub mod control;
pub mod devices;
pub mod pipeline;
pub mod score;
pub mod sinks;
pub mod soak;
pub mod timing;
pub mod worker;
