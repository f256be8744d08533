//! The control socket: JSON-RPC 2.0 over a Unix stream socket, one request per line.
//!
//! - [`types`]: the [`ControlTarget`] trait the pipeline implements and the reports it returns;
//! - [`rpc`]: request parsing and dispatch (transport-free, so it is tested without sockets);
//! - [`server`]: the socket, peer-credential checks, one thread per connection (and one more
//!   per connection subscribed to the lighting estimate);
//! - [`lights`]: the published lighting estimate and its subscribers (`lights.*` methods);
//! - [`client`]: the blocking client used by `relightctl` and the end-to-end tests.

pub mod client;
pub mod lights;
pub mod rpc;
pub mod server;
pub mod types;

pub use client::{Client, ClientError, Notification};
pub use lights::{LightsBoard, LightsSubscription};
pub use server::{
    ControlServer, ControlServerHandle, PeerCred, ServerError, ServerOptions, peer_allowed,
};
pub use types::{
    AlbedoStatus, ControlError, ControlTarget, DeviceState, DeviceStatus, EngineInfo,
    FramesSkipped, LiveViewStatus, OutputRequest, Percentiles, RecordingStatus, StageTiming,
    StatusReport, SyncStreamStatus, TrackingStatus, codes,
};
