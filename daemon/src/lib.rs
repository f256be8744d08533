//! relightd internals: configuration, pipeline, control socket, sinks.
pub mod bench;
pub mod config;
pub mod control;
pub mod depth_stage;
pub mod devices;
pub mod live_frame;
pub mod pipeline;
pub mod score;
pub mod sinks;
pub mod soak;
pub mod timing;
pub mod tracking;
pub mod worker;
