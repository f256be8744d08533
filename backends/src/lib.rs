//! relight-backends: the device contract and its implementations.
//!
//! Every device runs on its own thread under a [`DeviceRunner`], which owns the failure
//! contract of DESIGN.md: a typed error on open, `Lost` + reconnect with backoff on disconnect,
//! never a panic on bad data. Backends only implement [`Device`]. The replay backend plays MCAP
//! recordings through the same contract, so the daemon cannot tell it from hardware.

pub mod device;
pub mod exposure_schedule;
#[cfg(feature = "freenect")]
pub mod freenect;
#[cfg(feature = "hotplug")]
pub mod hotplug;
#[cfg(feature = "lamp")]
pub mod lamp;
pub mod lamp_protocol;
pub mod markers;
#[cfg(feature = "openni2")]
pub mod openni2;
pub mod pixel_convert;
pub mod replay;
pub mod sources;
#[cfg(feature = "ueye")]
pub mod ueye;
#[cfg(feature = "v4l2")]
pub mod v4l2;

pub use device::{
    Device, DeviceContext, DeviceError, DeviceRunner, DeviceState, DeviceStatus, RunEnd, Stepper,
};
pub use replay::{Backpressure, Replay, ReplayConfig, ReplayMode};
