//! relight-sim: the simulated rig. Sensor streams with their real defects, rendered from a scene
//! whose truth is known, so every estimator downstream can be scored.
//!
//! - [`kinect`]: Kinect v1 depth from true depth (disparity noise and quantisation, projector
//!   shadows, dropouts on dark, specular and grazing surfaces, range limits).
//! - [`probe`]: the fish-eye light probe's view of the environment at one exposure.
//! - [`response`]: the colour camera's and the probe's known response curve (linear radiance →
//!   8-bit code), so photometric calibration can be checked against it.
//! - [`trajectory`]: camera paths (static, slow orbit, hand shake).
//! - [`markers`]: a printed board of AprilTag `tag36h11` tags (the codes are the detectors',
//!   [`relight_backends::markers::tag36h11`]).
//! - [`device`]: the rig as a live `[sim]` source of the daemon.
//! - [`rig`]: all of the above around a [`Scene`](relight_core::scene::Scene): sensor
//!   messages and ground truth per frame, written to MCAP by [`rig::write_recording`].
//! - `fakenect` (feature `freenect`): the rig as a fakenect dump, for libfreenect's replay.
//!
//! It is test and demo tooling: a rig's build of the daemon needs it only for `[sim]` and
//! `relightd simulate`; the device backends never depend on it. It needs the reference path
//! tracer, which renders its colour frames and truth.

pub mod device;
#[cfg(feature = "freenect")]
pub mod fakenect;
pub mod kinect;
pub mod markers;
pub mod probe;
pub mod response;
pub mod rig;
pub mod trajectory;
