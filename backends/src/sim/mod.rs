//! The simulated rig: sensor streams with their real defects, rendered from a scene whose truth
//! is known, so every estimator downstream can be scored.
//!
//! - [`kinect`]: Kinect v1 depth from true depth (disparity noise and quantisation, projector
//!   shadows, dropouts on dark, specular and grazing surfaces, range limits).
//! - [`probe`]: the fish-eye light probe's view of the environment at one exposure.
//! - [`response`]: the colour camera's and the probe's known response curve (linear radiance →
//!   8-bit code), so photometric calibration can be checked against it.
//! - [`trajectory`]: camera paths (static, slow orbit, hand shake).
//! - [`markers`]: AprilTag `tag36h11` codes and a printed marker board.
//! - [`device`]: the rig as a live `[sim]` source of the daemon.
//! - [`rig`]: all of the above around a [`Scene`](relight_core::scene::Scene): sensor
//!   messages and ground truth per frame, written to MCAP by [`rig::write_recording`].

pub mod device;
pub mod kinect;
pub mod markers;
pub mod probe;
pub mod response;
pub mod rig;
pub mod trajectory;
