//! relightd internals: configuration, pipeline, control socket, sinks.
