//! relightd internals: configuration, pipeline, control socket, sinks.
pub mod bench;
pub mod config;
pub mod control;
pub mod depth_stage;
pub mod devices;
pub mod pipeline;
pub mod sinks;
pub mod timing;
