//! [`MarkerDevice`]: any [`MarkerTracker`] run on the colour stream, as a [`Device`].
//!
//! It subscribes to the bus's colour topic (queue of one: when detection is slower than the
//! camera it works on the newest frame and the older ones are dropped by the bus), detects
//! markers with the colour camera's calibration, smooths each marker's pose with a One-Euro
//! filter keyed by family and id, and publishes a [`MarkerSet`] carrying the colour frame's
//! `seq` and `stamp`, so the synchroniser pairs it with the image it came from.

use std::collections::HashMap;
use std::time::Duration;

use relight_core::bus::FramePool;
use relight_core::camera::CameraModel;
use relight_core::{Image, MarkerSet, StreamKind, StreamMessage};

use super::one_euro::{OneEuroConfig, PoseFilter};
use super::pose::DPose;
use crate::device::{Device, DeviceContext, DeviceError, RunEnd};
use crate::sources::MarkerTracker;

/// How long one wait for a colour frame lasts before the stop flag is checked again.
const COLOR_WAIT: Duration = Duration::from_millis(50);
/// Marker sets in flight: the bus's latest value and `all` queue consumers, plus one being filled.
const POOL_FRAMES: usize = 8;

/// A marker tracker on the colour stream.
#[derive(Debug)]
pub struct MarkerDevice<T: MarkerTracker> {
    backend: &'static str,
    tracker: T,
    camera: CameraModel,
    filter: OneEuroConfig,
    filters: HashMap<(String, u32), PoseFilter>,
    pool: FramePool<MarkerSet>,
    scratch: MarkerSet,
}

impl<T: MarkerTracker> MarkerDevice<T> {
    /// `camera` is the colour camera's calibration (the rig calibration's colour camera); images
    /// of another resolution with the same aspect ratio use it rescaled. `backend` names the
    /// detector in status reports (`apriltag`, `aruco`).
    pub fn new(
        backend: &'static str,
        tracker: T,
        camera: CameraModel,
        filter: OneEuroConfig,
    ) -> Result<Self, DeviceError> {
        let invalid = |reason: String| DeviceError::Config {
            device: backend.into(),
            reason,
        };
        camera
            .validate()
            .map_err(|e| invalid(format!("colour camera calibration: {e}")))?;
        filter.validate().map_err(invalid)?;
        Ok(Self {
            backend,
            tracker,
            camera,
            filter,
            filters: HashMap::new(),
            pool: FramePool::new(POOL_FRAMES),
            scratch: MarkerSet::default(),
        })
    }

    pub fn tracker(&self) -> &T {
        &self.tracker
    }

    /// The calibration for an image of `width × height`: the configured one, rescaled when the
    /// stream runs at another resolution of the same aspect ratio.
    fn camera_for(&self, image: &Image) -> Result<CameraModel, DeviceError> {
        let (width, height) = (image.width(), image.height());
        if (width, height) == (self.camera.width(), self.camera.height()) {
            return Ok(self.camera);
        }
        let aspect = |w: u32, h: u32| f64::from(w) / f64::from(h.max(1));
        if (aspect(width, height) / aspect(self.camera.width(), self.camera.height()) - 1.0).abs()
            > 0.01
        {
            return Err(DeviceError::Config {
                device: self.backend.into(),
                reason: format!(
                    "colour images are {width}×{height} but the camera is calibrated at {}×{}, \
                     another aspect ratio",
                    self.camera.width(),
                    self.camera.height()
                ),
            });
        }
        Ok(self.camera.resized(width, height))
    }

    /// Smooths every detection's pose with its marker's filter; forgets markers unseen for
    /// longer than the filter's reset time.
    fn smooth(&mut self, time_ns: u64, markers: &mut MarkerSet) {
        if !self.filter.enabled {
            return;
        }
        let reset_ns = (self.filter.reset_after_s * 1e9) as u64;
        self.filters.retain(|_, filter| {
            filter
                .last_time_ns()
                .is_some_and(|last| time_ns.saturating_sub(last) <= reset_ns && last <= time_ns)
        });
        for detection in &mut markers.detections {
            let filter = self
                .filters
                .entry((detection.family.clone(), detection.marker_id))
                .or_insert_with(|| PoseFilter::new(self.filter));
            let pose = DPose::from_pose(&detection.camera_from_marker);
            detection.camera_from_marker = filter.filter(time_ns, &pose).to_pose();
        }
    }
}

impl<T: MarkerTracker> Device for MarkerDevice<T> {
    fn backend(&self) -> &'static str {
        self.backend
    }

    fn streams(&self) -> Vec<StreamKind> {
        vec![StreamKind::Markers]
    }

    fn open(&mut self) -> Result<(), DeviceError> {
        self.filters.clear();
        Ok(())
    }

    fn run(&mut self, ctx: &DeviceContext) -> Result<RunEnd, DeviceError> {
        let colour = ctx.bus().color.subscribe_named("markers", 1);
        while !ctx.should_stop() {
            let Some(frame) = colour.recv_timeout(COLOR_WAIT) else {
                continue;
            };
            let camera = self.camera_for(&frame.payload)?;
            let mut markers = std::mem::take(&mut self.scratch);
            match self.tracker.detect(&frame.payload, &camera, &mut markers) {
                Ok(()) => {}
                Err(DeviceError::BadData { device, reason }) => {
                    tracing::trace!(%device, %reason, seq = frame.seq, "colour frame not usable for markers");
                    ctx.count_drop();
                    self.scratch = markers;
                    continue;
                }
                Err(error) => {
                    self.scratch = markers;
                    return Err(error);
                }
            }
            self.smooth(frame.stamp.device_ns, &mut markers);
            match self.pool.acquire() {
                Some(mut slot) => {
                    slot.seq = frame.seq;
                    slot.stamp = frame.stamp;
                    // Swap, so the pooled set's buffers come back as the next scratch.
                    std::mem::swap(&mut slot.payload, &mut markers);
                    self.scratch = markers;
                    ctx.publish(StreamMessage::Markers(slot.share()));
                }
                None => {
                    self.scratch = markers;
                    ctx.count_drop();
                }
            }
        }
        Ok(RunEnd::StopRequested)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::time::Instant;

    use glam::{Quat, Vec2, Vec3};
    use relight_core::bus::Bus;
    use relight_core::camera::Pinhole;
    use relight_core::{Frame, MarkerDetection, PixelFormat, Pose, Timestamp};

    use super::*;
    use crate::device::{Backoff, DeviceRunner};

    /// Reads a marker's x position (cm) from the first pixel of the image; an image whose first
    /// pixel is 255 is "unreadable"; records the camera size it was given.
    #[derive(Debug)]
    struct PixelTracker {
        sizes: Arc<std::sync::Mutex<Vec<(u32, u32)>>>,
    }

    impl MarkerTracker for PixelTracker {
        fn family(&self) -> &str {
            "pixel"
        }
        fn detect(
            &mut self,
            image: &Image,
            camera: &CameraModel,
            out: &mut MarkerSet,
        ) -> Result<(), DeviceError> {
            self.sizes
                .lock()
                .unwrap()
                .push((camera.width(), camera.height()));
            let value = image.as_u8().and_then(|p| p.first().copied()).unwrap_or(0);
            if value == 255 {
                return Err(DeviceError::BadData {
                    device: "pixel".into(),
                    reason: "saturated".into(),
                });
            }
            out.detections.clear();
            out.detections.push(MarkerDetection {
                family: "pixel".into(),
                marker_id: 1,
                corners_px: [Vec2::ZERO; 4],
                camera_from_marker: Pose::new(
                    Quat::IDENTITY,
                    Vec3::new(f32::from(value) / 100.0, 0.0, -1.0),
                ),
                reprojection_rms_px: 0.0,
            });
            Ok(())
        }
    }

    fn camera() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 31.5,
            cy: 23.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })
    }

    fn colour(seq: u64, value: u8, width: u32, height: u32) -> StreamMessage {
        let mut image = Image::new(width, height, PixelFormat::Rgb8);
        image.as_u8_mut().unwrap().fill(value);
        let time_ns = seq * 33_333_333;
        StreamMessage::Color(Arc::new(Frame::new(
            seq,
            Timestamp::new(time_ns, 1_000 + time_ns),
            image,
        )))
    }

    fn wait_for(mut done: impl FnMut() -> bool) {
        let deadline = Instant::now() + Duration::from_secs(20);
        while !done() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    #[test]
    fn marker_sets_carry_the_colour_frame_seq_and_stamp_and_are_filtered() {
        let bus = Arc::new(Bus::new());
        let markers = bus.markers.subscribe(64);
        let sizes = Arc::new(std::sync::Mutex::new(Vec::new()));
        let device = MarkerDevice::new(
            "pixel",
            PixelTracker {
                sizes: sizes.clone(),
            },
            camera(),
            OneEuroConfig {
                beta: 0.0,
                ..OneEuroConfig::default()
            },
        )
        .unwrap();
        let mut runner =
            DeviceRunner::spawn("markers", Box::new(device), bus.clone(), Backoff::default())
                .unwrap();
        // Publish only once the device listens, one frame at a time (its queue holds one).
        wait_for(|| bus.color.subscriber_count() == 1);
        let values = [10u8, 10, 255, 50, 50, 50];
        let mut received = Vec::new();
        for (seq, value) in values.iter().enumerate() {
            let size = if seq == 4 { (128, 96) } else { (64, 48) };
            bus.publish(colour(seq as u64, *value, size.0, size.1));
            if *value != 255 {
                let frame = markers
                    .recv_timeout(Duration::from_secs(20))
                    .expect("markers");
                received.push(frame);
            } else {
                wait_for(|| runner.status().drops() == 1);
            }
        }
        runner.stop();
        assert_eq!(runner.status().drops(), 1);
        let seqs: Vec<u64> = received.iter().map(|f| f.seq).collect();
        assert_eq!(seqs, vec![0, 1, 3, 4, 5]);
        for frame in &received {
            assert_eq!(frame.stamp.device_ns, frame.seq * 33_333_333);
            assert_eq!(frame.stamp.host_ns, 1_000 + frame.seq * 33_333_333);
        }
        // A step from 0.10 to 0.50 m is smoothed by the 1 Hz low-pass: each frame moves the
        // filtered pose by α of the remaining distance (the dropped frame makes one gap of 2 T).
        let x: Vec<f32> = received
            .iter()
            .map(|f| f.payload.detections[0].camera_from_marker.translation.x)
            .collect();
        assert_eq!(x[0], 0.1);
        assert_eq!(x[1], 0.1);
        let alpha = |dt_s: f64| crate::markers::one_euro::smoothing_factor(1.0, dt_s) as f32;
        let expected = 0.1 + (0.5 - 0.1) * alpha(2.0 / 30.0);
        assert!((x[2] - expected).abs() < 1e-4, "{} vs {expected}", x[2]);
        assert!(x[3] > x[2] && x[4] > x[3] && x[4] < 0.5);
        // The double-resolution frame got the camera rescaled.
        assert!(sizes.lock().unwrap().contains(&(128, 96)));
    }

    #[test]
    fn invalid_calibration_or_aspect_is_a_config_error() {
        let sizes = Arc::new(std::sync::Mutex::new(Vec::new()));
        let CameraModel::Pinhole(pinhole) = camera() else {
            unreachable!()
        };
        let broken = CameraModel::Pinhole(Pinhole {
            fx: -1.0,
            ..pinhole
        });
        let tracker = PixelTracker {
            sizes: sizes.clone(),
        };
        assert!(matches!(
            MarkerDevice::new("pixel", tracker, broken, OneEuroConfig::default()),
            Err(DeviceError::Config { .. })
        ));
        let device = MarkerDevice::new(
            "pixel",
            PixelTracker { sizes },
            camera(),
            OneEuroConfig::default(),
        )
        .unwrap();
        let square = Image::new(64, 64, PixelFormat::Rgb8);
        assert!(matches!(
            device.camera_for(&square),
            Err(DeviceError::Config { .. })
        ));
    }
}
