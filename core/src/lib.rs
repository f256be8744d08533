//! relight-core: the types every relight crate shares.
//!
//! No I/O beyond recordings, no GPU. Units: linear radiance in f32, depth in metres after the
//! backend, right-handed metres with the camera looking down −Z (glTF convention).

pub mod bus;
pub mod camera;
pub mod frame;
pub mod input_file;
pub mod light;
pub mod pose;
pub mod recording;
pub mod rig;
pub mod ros_frames;
pub mod scene;
pub mod sh;
pub mod srgb;
pub mod stream;
pub mod sync;

pub use frame::{Frame, Image, ImageError, PixelFormat, PixelRect, Pixels, Timestamp};
pub use pose::Pose;
pub use stream::{LampState, MarkerDetection, MarkerSet, ProbeImage, StreamKind, StreamMessage};
