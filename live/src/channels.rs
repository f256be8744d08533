//! The Foxglove channels, in Foxglove's own schemas (protobuf, from the SDK), and how a frame
//! becomes their messages.
//!
//! | topic | schema | when |
//! |---|---|---|
//! | `/relight/composite` | `foxglove.CompressedImage` (JPEG) or `foxglove.RawImage` (`rgb8`) | every frame published |
//! | `/relight/color` | the same, the camera image the composite is built on | every frame |
//! | `/relight/delta` | `foxglove.CompressedImage`: Δ in false colour (red < 0 < blue) | every frame |
//! | `/relight/depth` | `foxglove.RawImage`, `16UC1` mm or `32FC1` m | every frame with depth |
//! | `/relight/camera_calibration` | `foxglove.CameraCalibration` of the rendered camera | every frame |
//! | `/tf` | `foxglove.FrameTransforms` (see [`crate::frames`]) | every frame |
//! | `/relight/scene` | `foxglove.SceneUpdate`: the virtual object and the lights | twice a second |
//! | `/relight/lighting` | JSON: the lighting estimate (`lights.get`) | twice a second |
//! | `/relight/status` | JSON: the status report (`status`) | twice a second |
//!
//! Nothing is encoded for a channel no client subscribes to.

use std::sync::Arc;
use std::time::{Duration, Instant};

use foxglove::messages::{
    ArrowPrimitive, CameraCalibration, Color, CompressedImage, FrameTransform, FrameTransforms,
    Point3, Quaternion, RawImage, SceneEntity, SceneUpdate, SpherePrimitive, Timestamp,
    TriangleListPrimitive, Vector3,
};
use foxglove::{Channel, Context, RawChannel};
use glam::{Quat, Vec3};
use relight_core::light::Light;
use relight_core::scene::{Scene, SceneCamera};
use relight_core::{Image, PixelFormat, Pose};
use serde_json::Value;

use crate::frames;
use crate::images;
use crate::{ImageEncoding, RigFrames, ViewFrame};

pub const COMPOSITE: &str = "/relight/composite";
pub const COLOR: &str = "/relight/color";
pub const DELTA: &str = "/relight/delta";
pub const DEPTH: &str = "/relight/depth";
pub const CAMERA_CALIBRATION: &str = "/relight/camera_calibration";
pub const TF: &str = "/tf";
pub const SCENE: &str = "/relight/scene";
pub const LIGHTING: &str = "/relight/lighting";
pub const STATUS: &str = "/relight/status";

/// How often the 3D scene is sent again (its meshes are the largest message).
const SCENE_INTERVAL: Duration = Duration::from_millis(500);

/// An image channel in the encoding the configuration chose.
enum ImageChannel {
    Jpeg(Channel<CompressedImage>),
    Raw(Channel<RawImage>),
}

impl ImageChannel {
    fn new(context: &Arc<Context>, topic: &str, encoding: ImageEncoding) -> Self {
        match encoding {
            ImageEncoding::Jpeg => Self::Jpeg(context.channel_builder(topic).build()),
            ImageEncoding::Raw => Self::Raw(context.channel_builder(topic).build()),
        }
    }

    fn has_sinks(&self) -> bool {
        match self {
            Self::Jpeg(c) => c.has_sinks(),
            Self::Raw(c) => c.has_sinks(),
        }
    }

    /// Log an `Rgb8` image; `jpeg` is its encoding when the caller already has one.
    fn log(&self, image: &Image, jpeg: Option<&[u8]>, quality: u8, timestamp: Timestamp) {
        if !self.has_sinks() || image.pixel_count() == 0 {
            return;
        }
        match self {
            Self::Jpeg(channel) => {
                let data = match jpeg {
                    Some(bytes) => bytes.to_vec(),
                    None => match images::jpeg(image, quality) {
                        Ok(bytes) => bytes,
                        Err(error) => {
                            tracing::debug!(%error, topic = channel.topic(), "image not sent");
                            return;
                        }
                    },
                };
                channel.log(&CompressedImage {
                    timestamp: Some(timestamp),
                    frame_id: frames::CAMERA.into(),
                    data: data.into(),
                    format: "jpeg".into(),
                });
            }
            Self::Raw(channel) => {
                let Some(pixels) = image.as_u8() else { return };
                channel.log(&RawImage {
                    timestamp: Some(timestamp),
                    frame_id: frames::CAMERA.into(),
                    width: image.width(),
                    height: image.height(),
                    encoding: image.format().ros_encoding().into(),
                    step: image.stride() as u32,
                    data: pixels.to_vec().into(),
                });
            }
        }
    }
}

/// Every channel the view publishes on.
pub struct Channels {
    composite: ImageChannel,
    color: ImageChannel,
    delta: Channel<CompressedImage>,
    depth: Channel<RawImage>,
    calibration: Channel<CameraCalibration>,
    tf: Channel<FrameTransforms>,
    scene: Channel<SceneUpdate>,
    lighting: Arc<RawChannel>,
    status: Arc<RawChannel>,
    rig: RigFrames,
    last_scene: Option<Instant>,
}

impl std::fmt::Debug for Channels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Channels").finish_non_exhaustive()
    }
}

fn json_channel(context: &Arc<Context>, topic: &str) -> Arc<RawChannel> {
    context
        .channel_builder(topic)
        .message_encoding("json")
        .build_raw()
        .expect("a JSON channel without a schema is always valid")
}

impl Channels {
    pub fn new(context: &Arc<Context>, image: ImageEncoding, rig: RigFrames) -> Self {
        Self {
            composite: ImageChannel::new(context, COMPOSITE, image),
            color: ImageChannel::new(context, COLOR, image),
            delta: context.channel_builder(DELTA).build(),
            depth: context.channel_builder(DEPTH).build(),
            calibration: context.channel_builder(CAMERA_CALIBRATION).build(),
            tf: context.channel_builder(TF).build(),
            scene: context.channel_builder(SCENE).build(),
            lighting: json_channel(context, LIGHTING),
            status: json_channel(context, STATUS),
            rig,
            last_scene: None,
        }
    }

    /// One frame on every channel someone subscribes to.
    pub fn frame(&mut self, frame: &ViewFrame, composite_jpeg: Option<&[u8]>, quality: u8) {
        let timestamp = timestamp(frame.host_ns);
        self.composite
            .log(&frame.composite, composite_jpeg, quality, timestamp);
        if let Some(color) = &frame.color
            && color.payload.format() == PixelFormat::Rgb8
        {
            self.color.log(&color.payload, None, quality, timestamp);
        }
        if self.delta.has_sinks()
            && let Some((false_colour, _)) = images::delta_false_colour(&frame.delta, None)
            && let Ok(data) = images::jpeg(&false_colour, quality)
        {
            self.delta.log(&CompressedImage {
                timestamp: Some(timestamp),
                frame_id: frames::CAMERA.into(),
                data: data.into(),
                format: "jpeg".into(),
            });
        }
        if self.depth.has_sinks()
            && let Some(depth) = &frame.depth
            && let Some((encoding, data)) = images::depth_raw(&depth.payload)
        {
            self.depth.log(&RawImage {
                timestamp: Some(timestamp),
                frame_id: frames::CAMERA.into(),
                width: depth.payload.width(),
                height: depth.payload.height(),
                encoding: encoding.into(),
                step: depth.payload.width() * if encoding == "16UC1" { 2 } else { 4 },
                data: data.into(),
            });
        }
        if let Some(scene) = &frame.scene {
            if self.calibration.has_sinks() {
                self.calibration
                    .log(&camera_calibration(&scene.camera, timestamp));
            }
            if self.scene.has_sinks()
                && self
                    .last_scene
                    .is_none_or(|t| t.elapsed() >= SCENE_INTERVAL)
            {
                self.last_scene = Some(Instant::now());
                self.scene.log(&scene_update(scene, timestamp));
            }
        }
        if self.tf.has_sinks() {
            self.tf.log(&self.transforms(frame, timestamp));
        }
    }

    /// The status report and the lighting estimate, as JSON.
    pub fn reports(&self, status: &Value, lighting: Option<&Value>) {
        if self.status.has_sinks() {
            self.status.log(status.to_string().as_bytes());
        }
        if let Some(lighting) = lighting
            && self.lighting.has_sinks()
        {
            self.lighting.log(lighting.to_string().as_bytes());
        }
    }

    /// Every frame this frame knows, as `parent_from_child` transforms.
    pub fn transforms(&self, frame: &ViewFrame, timestamp: Timestamp) -> FrameTransforms {
        let mut out = vec![transform(
            frames::MAP,
            frames::WORLD,
            frames::map_from_world(),
            timestamp,
        )];
        let mut world = |child: &str, pose: Pose| {
            out.push(transform(frames::WORLD, child, pose, timestamp));
        };
        if let Some(world_from_camera) = frame.world_from_camera {
            world(
                frames::CAMERA,
                frames::world_from_optical(world_from_camera),
            );
        }
        if let Some(pose) = self.rig.world_from_board {
            world(frames::BOARD, pose);
        }
        if let Some(pose) = self.rig.world_from_probe {
            world(frames::PROBE, frames::world_from_optical(pose));
        }
        if let Some(lamp) = &frame.lamp {
            world(frames::LAMP, at(lamp.position_in_world));
        }
        if let Some(scene) = &frame.scene {
            for (index, position) in scene
                .lights
                .iter()
                .enumerate()
                .filter_map(|(i, light)| light_position(light).map(|p| (i, p)))
            {
                world(&frames::light(index), at(position));
            }
            if let Some(centre) = virtual_centre(scene) {
                world(frames::VIRTUAL_OBJECT, at(centre));
            }
        }
        if frame.world_from_camera.is_some()
            && let Some(markers) = &frame.markers
        {
            for detection in &markers.payload.detections {
                out.push(transform(
                    frames::CAMERA,
                    &frames::marker(detection.marker_id),
                    frames::optical_from(detection.camera_from_marker),
                    timestamp,
                ));
            }
        }
        FrameTransforms { transforms: out }
    }
}

fn timestamp(host_ns: u64) -> Timestamp {
    let sec = u32::try_from(host_ns / 1_000_000_000).unwrap_or(u32::MAX);
    Timestamp::new(sec, (host_ns % 1_000_000_000) as u32)
}

fn at(position: Vec3) -> Pose {
    Pose {
        rotation: Quat::IDENTITY,
        translation: position,
    }
}

fn vector(v: Vec3) -> Vector3 {
    Vector3 {
        x: f64::from(v.x),
        y: f64::from(v.y),
        z: f64::from(v.z),
    }
}

fn quaternion(q: Quat) -> Quaternion {
    Quaternion {
        x: f64::from(q.x),
        y: f64::from(q.y),
        z: f64::from(q.z),
        w: f64::from(q.w),
    }
}

fn pose(p: Pose) -> foxglove::messages::Pose {
    foxglove::messages::Pose {
        position: Some(vector(p.translation)),
        orientation: Some(quaternion(p.rotation)),
    }
}

fn transform(parent: &str, child: &str, parent_from_child: Pose, ts: Timestamp) -> FrameTransform {
    FrameTransform {
        timestamp: Some(ts),
        parent_frame_id: parent.into(),
        child_frame_id: child.into(),
        translation: Some(vector(parent_from_child.translation)),
        rotation: Some(quaternion(parent_from_child.rotation)),
    }
}

fn light_position(light: &Light) -> Option<Vec3> {
    match light {
        Light::Point {
            position_in_world, ..
        }
        | Light::Spot {
            position_in_world, ..
        } => Some(*position_in_world),
        _ => None,
    }
}

/// The centre of the virtual meshes' bounding box.
fn virtual_centre(scene: &Scene) -> Option<Vec3> {
    let mut points = scene
        .meshes
        .iter()
        .filter(|m| m.is_virtual)
        .flat_map(|m| m.positions_in_world.iter().copied())
        .peekable();
    points.peek()?;
    let (lo, hi) = points.fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
        (lo.min(p), hi.max(p))
    });
    Some((lo + hi) / 2.0)
}

/// The pinhole the engines render with: square pixels, the principal point at the image's
/// centre, `fy` from the vertical field of view; no distortion (the composite is rendered).
pub fn camera_calibration(camera: &SceneCamera, timestamp: Timestamp) -> CameraCalibration {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let f = h / 2.0 / (f64::from(camera.yfov_rad) / 2.0).tan();
    // Pixel centres at integers, as OpenCV and ROS count them.
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    CameraCalibration {
        timestamp: Some(timestamp),
        frame_id: frames::CAMERA.into(),
        width: camera.width,
        height: camera.height,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: vec![f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
        r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: vec![f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    }
}

fn colour(rgb: Vec3, a: f64) -> Color {
    let c = rgb.clamp(Vec3::ZERO, Vec3::ONE);
    Color {
        r: f64::from(c.x),
        g: f64::from(c.y),
        b: f64::from(c.z),
        a,
    }
}

/// The light's colour at full brightness, for drawing it.
fn light_colour(light: &Light) -> Vec3 {
    let power = match light {
        Light::Point { intensity, .. } | Light::Spot { intensity, .. } => *intensity,
        Light::Directional { irradiance, .. } => *irradiance,
        _ => Vec3::ONE,
    };
    power / power.max_element().max(1e-6)
}

/// The virtual object's triangles in its materials' albedo, a sphere at each point or spot
/// light and an arrow along each directional light, aimed at the object.
pub fn scene_update(scene: &Scene, timestamp: Timestamp) -> SceneUpdate {
    let centre = virtual_centre(scene).unwrap_or(Vec3::ZERO);
    let triangles = scene
        .meshes
        .iter()
        .filter(|m| m.is_virtual)
        .map(|mesh| {
            let albedo = scene
                .materials
                .get(mesh.material)
                .map_or(Vec3::splat(0.8), |m| m.albedo);
            TriangleListPrimitive {
                pose: Some(pose(Pose::IDENTITY)),
                points: mesh
                    .positions_in_world
                    .iter()
                    .map(|p| Point3 {
                        x: f64::from(p.x),
                        y: f64::from(p.y),
                        z: f64::from(p.z),
                    })
                    .collect(),
                color: Some(colour(albedo, 1.0)),
                colors: Vec::new(),
                indices: mesh.triangles.iter().flatten().copied().collect(),
            }
        })
        .collect();
    let mut spheres = Vec::new();
    let mut arrows = Vec::new();
    for light in scene.lights.iter().chain(&scene.environment_lights) {
        let colour = colour(light_colour(light), 1.0);
        if let Some(position) = light_position(light) {
            spheres.push(SpherePrimitive {
                pose: Some(pose(at(position))),
                size: Some(vector(Vec3::splat(0.05))),
                color: Some(colour),
            });
        } else if let Light::Directional {
            direction_in_world, ..
        } = light
        {
            // An arrow 0.5 m long ending at the object, travelling with the light (its +x).
            let direction = direction_in_world.normalize_or_zero();
            let start = centre - direction * 0.5;
            arrows.push(ArrowPrimitive {
                pose: Some(pose(Pose {
                    rotation: Quat::from_rotation_arc(Vec3::X, direction),
                    translation: start,
                })),
                shaft_length: 0.4,
                shaft_diameter: 0.01,
                head_length: 0.1,
                head_diameter: 0.03,
                color: Some(colour),
            });
        }
    }
    let entity = |id: &str| SceneEntity {
        timestamp: Some(timestamp),
        frame_id: frames::WORLD.into(),
        id: id.into(),
        frame_locked: true,
        ..Default::default()
    };
    SceneUpdate {
        deletions: Vec::new(),
        entities: vec![
            SceneEntity {
                triangles,
                ..entity("virtual_object")
            },
            SceneEntity {
                spheres,
                arrows,
                ..entity("lights")
            },
        ],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOPICS: [&str; 9] = [
        COMPOSITE,
        COLOR,
        DELTA,
        DEPTH,
        CAMERA_CALIBRATION,
        TF,
        SCENE,
        LIGHTING,
        STATUS,
    ];

    /// Every string in the layout that names a topic.
    fn topics_in(value: &Value, out: &mut Vec<String>) {
        match value {
            Value::Object(map) => {
                for (key, v) in map {
                    if key.starts_with('/') {
                        out.push(key.clone());
                    }
                    match (key.as_str(), v) {
                        ("imageTopic" | "calibrationTopic" | "topicPath", Value::String(s)) => {
                            // A message path: the topic, then `.field`s.
                            out.push(s.split('.').next().unwrap_or(s).to_owned());
                        }
                        _ => topics_in(v, out),
                    }
                }
            }
            Value::Array(items) => items.iter().for_each(|v| topics_in(v, out)),
            _ => {}
        }
    }

    #[test]
    fn the_shipped_foxglove_layout_names_only_published_topics() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/foxglove-layout.json");
        let layout: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let mut topics = Vec::new();
        topics_in(&layout, &mut topics);
        assert!(topics.len() >= 5, "{topics:?}");
        for topic in topics {
            assert!(TOPICS.contains(&topic.as_str()), "{topic} is not published");
        }
    }

    #[test]
    fn the_calibration_projects_the_image_centre_and_the_field_of_view_edge() {
        let camera = SceneCamera {
            world_from_camera: Pose::IDENTITY,
            yfov_rad: 60f32.to_radians(),
            width: 160,
            height: 120,
        };
        let calibration = camera_calibration(&camera, Timestamp::new(0, 0));
        let k = &calibration.k;
        // A ray at half the vertical field of view lands on the top edge (pixel −0.5).
        let v = k[4] * -(30f64.to_radians().tan()) + k[5];
        assert!((v + 0.5).abs() < 1e-3, "{v}");
        assert_eq!((k[2], k[5]), (79.5, 59.5));
    }
}
