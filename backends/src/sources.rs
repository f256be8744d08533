//! Typed sources: what a single-stream hardware backend implements. [`SourceDevice`] turns any of
//! them into a [`Device`], drawing frames from a pool so steady-state capture allocates nothing.

use std::sync::Arc;

use relight_core::bus::{FramePool, Shared};
use relight_core::camera::CameraModel;
use relight_core::{Frame, Image, LampState, MarkerSet, ProbeImage, StreamKind, StreamMessage};

use crate::device::{Device, DeviceContext, DeviceError, RunEnd};

/// What one read gave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Capture {
    /// `frame` was filled and should be published.
    Frame,
    /// Nothing this time (timeout); try again.
    Idle,
    /// The source has no more frames.
    EndOfStream,
}

/// A payload type that travels on one of the rig's streams.
pub trait StreamPayload: Default + Send + Sync + 'static {
    fn into_message(kind: StreamKind, frame: Shared<Self>) -> Option<StreamMessage>;
}

impl StreamPayload for Image {
    fn into_message(kind: StreamKind, frame: Shared<Self>) -> Option<StreamMessage> {
        match kind {
            StreamKind::Depth => Some(StreamMessage::Depth(frame)),
            StreamKind::Color => Some(StreamMessage::Color(frame)),
            _ => None,
        }
    }
}

impl StreamPayload for ProbeImage {
    fn into_message(kind: StreamKind, frame: Shared<Self>) -> Option<StreamMessage> {
        (kind == StreamKind::Probe).then_some(StreamMessage::Probe(frame))
    }
}

impl StreamPayload for MarkerSet {
    fn into_message(kind: StreamKind, frame: Shared<Self>) -> Option<StreamMessage> {
        (kind == StreamKind::Markers).then_some(StreamMessage::Markers(frame))
    }
}

impl StreamPayload for LampState {
    fn into_message(kind: StreamKind, frame: Shared<Self>) -> Option<StreamMessage> {
        (kind == StreamKind::Lamp).then_some(StreamMessage::Lamp(frame))
    }
}

/// A backend that captures one stream. `read` blocks (with a timeout) for the next frame and
/// fills `frame` in place — payload, `seq` (the device's frame index, so gaps show drops) and
/// `stamp` (device clock and host arrival time).
pub trait FrameSource: Send + 'static {
    type Payload: StreamPayload;
    fn backend(&self) -> &'static str;
    fn stream(&self) -> StreamKind;
    fn open(&mut self) -> Result<(), DeviceError>;
    fn read(&mut self, frame: &mut Frame<Self::Payload>) -> Result<Capture, DeviceError>;
    fn close(&mut self) {}
}

/// Depth cameras (OpenNI2, libfreenect): `DepthU16Mm` or `DepthF32M` images.
pub trait DepthSource: FrameSource<Payload = Image> {}

/// Colour cameras: `Rgb8` images.
pub trait ColorSource: FrameSource<Payload = Image> {}

/// The fish-eye light probe, with exposure control for HDR brackets.
pub trait ProbeSource: FrameSource<Payload = ProbeImage> {
    /// Fix the exposure (manual mode).
    fn set_exposure_us(&mut self, exposure_us: u32) -> Result<(), DeviceError>;
    /// Cycle through these exposures, one per frame, tagging each frame with its exposure.
    /// An empty list returns to a fixed exposure.
    fn set_bracketing(&mut self, exposures_us: &[u32]) -> Result<(), DeviceError>;
}

/// The pocket lamp: position from its marker, on/off and intensity from its serial line.
pub trait LampTracker: FrameSource<Payload = LampState> {}

/// Square-marker detection (AprilTag, ArUco): an image in, detections with poses out.
pub trait MarkerTracker: Send + 'static {
    fn family(&self) -> &str;
    /// Detect markers in `image` seen by `camera`, replacing the contents of `out`.
    fn detect(
        &mut self,
        image: &Image,
        camera: &CameraModel,
        out: &mut MarkerSet,
    ) -> Result<(), DeviceError>;
}

/// Runs a [`FrameSource`] under the device contract.
#[derive(Debug)]
pub struct SourceDevice<S: FrameSource> {
    source: S,
    pool: FramePool<S::Payload>,
}

impl<S: FrameSource> SourceDevice<S> {
    /// `pool_frames` bounds how many frames consumers may hold at once before capture drops.
    pub fn new(source: S, pool_frames: usize) -> Self {
        Self {
            source,
            pool: FramePool::new(pool_frames),
        }
    }
}

impl<S: FrameSource> Device for SourceDevice<S> {
    fn backend(&self) -> &'static str {
        self.source.backend()
    }

    fn streams(&self) -> Vec<StreamKind> {
        vec![self.source.stream()]
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        self.source.open()
    }

    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        let kind = self.source.stream();
        let mut scratch = Frame::<S::Payload>::default();
        while !ctx.should_stop() {
            // With every pooled frame still held downstream, capture into a scratch frame and
            // drop it: the device must keep being drained, and nothing may allocate or block.
            let mut slot = self.pool.acquire();
            let frame = match slot.as_deref_mut() {
                Some(frame) => frame,
                None => &mut scratch,
            };
            match self.source.read(frame) {
                Ok(Capture::Frame) => match slot {
                    Some(slot) => match S::Payload::into_message(kind, slot.share()) {
                        Some(msg) => ctx.publish(msg),
                        None => ctx.count_drop(),
                    },
                    None => ctx.count_drop(),
                },
                Ok(Capture::Idle) => {}
                Ok(Capture::EndOfStream) => return Ok(RunEnd::EndOfStream),
                Err(DeviceError::BadData { device, reason }) => {
                    tracing::trace!(%device, %reason, "dropped a bad frame");
                    ctx.count_drop();
                }
                Err(error) => return Err(error),
            }
        }
        Ok(RunEnd::StopRequested)
    }

    fn close(&mut self) {
        self.source.close();
    }
}

/// A convenience for tests and simple sources: wrap a frame as the message of its stream.
pub fn message<P: StreamPayload>(kind: StreamKind, frame: Frame<P>) -> Option<StreamMessage> {
    P::into_message(kind, Arc::new(frame))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::{Backoff, DeviceRunner, DeviceState};
    use relight_core::bus::Bus;
    use relight_core::{PixelFormat, Timestamp};
    use std::time::{Duration, Instant};

    /// Every third read is garbage; ends after `frames` reads.
    struct Garbled {
        reads: u64,
        frames: u64,
    }

    impl FrameSource for Garbled {
        type Payload = Image;
        fn backend(&self) -> &'static str {
            "garbled"
        }
        fn stream(&self) -> StreamKind {
            StreamKind::Depth
        }
        fn open(&mut self) -> Result<(), DeviceError> {
            Ok(())
        }
        fn read(&mut self, frame: &mut Frame<Image>) -> Result<Capture, DeviceError> {
            self.reads += 1;
            if self.reads > self.frames {
                return Ok(Capture::EndOfStream);
            }
            if self.reads.is_multiple_of(3) {
                return Err(DeviceError::BadData {
                    device: "garbled".into(),
                    reason: "short USB transfer".into(),
                });
            }
            frame.payload.reshape(8, 6, PixelFormat::DepthU16Mm);
            if let Some(d) = frame.payload.as_u16_mut() {
                d.fill(self.reads as u16);
            }
            frame.seq = self.reads;
            frame.stamp = Timestamp::now();
            Ok(Capture::Frame)
        }
    }
    impl DepthSource for Garbled {}

    #[test]
    fn bad_frames_are_counted_and_good_ones_published() {
        let bus = Arc::new(Bus::new());
        let sub = bus.depth.subscribe(32);
        let device = SourceDevice::new(
            Garbled {
                reads: 0,
                frames: 9,
            },
            16,
        );
        let mut runner =
            DeviceRunner::spawn("depth", Box::new(device), bus, Backoff::default()).unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        while !runner.is_finished() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(2));
        }
        runner.stop();
        assert_eq!(runner.status().state(), DeviceState::Stopped);
        assert_eq!(runner.status().drops(), 3);
        let mut seqs = Vec::new();
        while let Some(frame) = sub.try_recv() {
            assert!(
                frame
                    .payload
                    .as_u16()
                    .unwrap()
                    .iter()
                    .all(|&d| u64::from(d) == frame.seq)
            );
            seqs.push(frame.seq);
        }
        assert_eq!(seqs, vec![1, 2, 4, 5, 7, 8]);
    }
}
