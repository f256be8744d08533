//! A small deterministic synthetic rig: a desk (checkered floor) with a red ball, seen by a
//! depth + colour camera on a slow orbit, lit by a pocket lamp circling above it, with a
//! fish-eye probe bracketing three exposures and a marker on the floor.
//!
//! It is ray-cast analytically (no path tracing) and exists so the pipeline, recorder and replay
//! have repeatable input without hardware; the ground-truth simulator replaces it for accuracy
//! work. Every value is a pure function of the settings and the frame index.

use std::f32::consts::{FRAC_PI_2, PI, TAU};
use std::sync::Arc;

use glam::{DVec2, DVec3, Quat, Vec2, Vec3};
use relight_core::camera::{CameraModel, KannalaBrandt, Pinhole};
use relight_core::rig::RigCalibration;
use relight_core::srgb::linear_to_srgb;
use relight_core::{
    Frame, Image, LampState, MarkerDetection, MarkerSet, PixelFormat, Pose, ProbeImage,
    StreamMessage, Timestamp,
};

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntheticSettings {
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub frames: u32,
    /// Probe images are taken every `probe_every` camera frames, cycling `probe_exposures_us`.
    pub probe_every: u32,
    pub probe_size: u32,
    pub probe_exposures_us: Vec<u32>,
    /// Lamp messages every `lamp_every` camera frames (the serial line is slower).
    pub lamp_every: u32,
    /// Host-clock time of the first frame.
    pub start_ns: u64,
}

impl Default for SyntheticSettings {
    fn default() -> Self {
        Self {
            width: 160,
            height: 120,
            fps: 30,
            frames: 60,
            probe_every: 3,
            probe_size: 96,
            probe_exposures_us: vec![1_000, 4_000, 16_000],
            lamp_every: 3,
            start_ns: 1_700_000_000_000_000_000,
        }
    }
}

const FLOOR_Y: f32 = 0.0;
const BALL_CENTER: Vec3 = Vec3::new(0.0, 0.15, 0.0);
const BALL_RADIUS: f32 = 0.15;
const MARKER_CENTER: Vec3 = Vec3::new(0.35, 0.0, 0.25);
const MARKER_HALF_EDGE: f32 = 0.05;

/// The synthetic rig.
#[derive(Debug, Clone)]
pub struct SyntheticRig {
    settings: SyntheticSettings,
    camera: Pinhole,
    probe: KannalaBrandt,
}

impl SyntheticRig {
    pub fn new(settings: SyntheticSettings) -> Self {
        let (w, h) = (f64::from(settings.width), f64::from(settings.height));
        // 60° horizontal field of view, no distortion.
        let f = w / 2.0 / (30f64.to_radians()).tan();
        let camera = Pinhole {
            width: settings.width,
            height: settings.height,
            fx: f,
            fy: f,
            cx: (w - 1.0) / 2.0,
            cy: (h - 1.0) / 2.0,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        };
        let s = f64::from(settings.probe_size);
        // Equidistant fish-eye (k = 0): θ = π/2 lands on the image circle's rim.
        let probe = KannalaBrandt {
            width: settings.probe_size,
            height: settings.probe_size,
            fx: s / 2.0 / std::f64::consts::FRAC_PI_2,
            fy: s / 2.0 / std::f64::consts::FRAC_PI_2,
            cx: (s - 1.0) / 2.0,
            cy: (s - 1.0) / 2.0,
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        };
        Self {
            settings,
            camera,
            probe,
        }
    }

    pub fn settings(&self) -> &SyntheticSettings {
        &self.settings
    }

    /// The rig's calibration: depth registered to colour (same camera), probe looking up.
    pub fn calibration(&self) -> RigCalibration {
        RigCalibration {
            name: "synthetic-desk".into(),
            depth: Some(CameraModel::Pinhole(self.camera)),
            color: Some(CameraModel::Pinhole(self.camera)),
            probe: Some(CameraModel::KannalaBrandt(self.probe)),
            world_from_probe: Pose::new(
                Quat::from_rotation_x(FRAC_PI_2),
                Vec3::new(0.0, 0.6, -0.6),
            ),
            ..RigCalibration::default()
        }
    }

    /// Pose of the colour (and depth) camera at frame `i`: a slow orbit around the ball.
    pub fn world_from_camera(&self, i: u32) -> Pose {
        let angle = 0.35 * self.time_s(i);
        let eye = Vec3::new(1.2 * angle.sin(), 0.8, 1.2 * angle.cos());
        Pose::look_at(eye, BALL_CENTER, Vec3::Y)
    }

    /// The lamp's position at frame `i`: circling above the desk.
    pub fn lamp(&self, i: u32) -> LampState {
        let angle = 1.2 * self.time_s(i);
        LampState {
            on: true,
            position_in_world: Vec3::new(0.5 * angle.cos(), 0.9, 0.5 * angle.sin()),
            intensity: Vec3::new(1.0, 0.95, 0.85),
        }
    }

    fn time_s(&self, i: u32) -> f32 {
        i as f32 / self.settings.fps.max(1) as f32
    }

    fn stamp(&self, i: u32, offset_ns: u64) -> Timestamp {
        let period_ns = 1_000_000_000 / u64::from(self.settings.fps.max(1));
        let host_ns = self.settings.start_ns + u64::from(i) * period_ns + offset_ns;
        // A device clock with its own origin, as real sensors have.
        Timestamp::new(host_ns - self.settings.start_ns + 12_345_678, host_ns)
    }

    /// Every message of the recording in host-time order.
    pub fn messages(&self) -> impl Iterator<Item = StreamMessage> + '_ {
        (0..self.settings.frames).flat_map(move |i| self.frame_messages(i))
    }

    fn frame_messages(&self, i: u32) -> Vec<StreamMessage> {
        let seq = u64::from(i);
        let (depth, color) = self.render_camera(i);
        // Colour arrives a little after depth, markers after colour (detected on it).
        let mut out = vec![
            StreamMessage::Depth(Arc::new(Frame::new(seq, self.stamp(i, 0), depth))),
            StreamMessage::Color(Arc::new(Frame::new(seq, self.stamp(i, 2_000_000), color))),
            StreamMessage::Markers(Arc::new(Frame::new(
                seq,
                self.stamp(i, 3_000_000),
                self.markers(i),
            ))),
        ];
        let probe_every = self.settings.probe_every.max(1);
        if i.is_multiple_of(probe_every) && !self.settings.probe_exposures_us.is_empty() {
            let n = i / probe_every;
            let exposures = &self.settings.probe_exposures_us;
            let exposure_us = exposures[n as usize % exposures.len()];
            out.push(StreamMessage::Probe(Arc::new(Frame::new(
                u64::from(n),
                self.stamp(i, 5_000_000),
                self.render_probe(exposure_us),
            ))));
        }
        let lamp_every = self.settings.lamp_every.max(1);
        if i.is_multiple_of(lamp_every) {
            out.push(StreamMessage::Lamp(Arc::new(Frame::new(
                u64::from(i / lamp_every),
                self.stamp(i, 7_000_000),
                self.lamp(i),
            ))));
        }
        out
    }

    /// Ray-cast the desk: depth (mm, holes at grazing angles) and the lamp-lit colour image.
    fn render_camera(&self, i: u32) -> (Image, Image) {
        let (w, h) = (self.settings.width, self.settings.height);
        let world_from_camera = self.world_from_camera(i);
        let origin = world_from_camera.translation;
        let lamp = self.lamp(i).position_in_world;
        let mut depth = Image::new(w, h, PixelFormat::DepthU16Mm);
        let mut color = Image::new(w, h, PixelFormat::Rgb8);
        for y in 0..h {
            for x in 0..w {
                // Optical ray (+Z forward, +Y down) → glTF camera frame (−Z forward, +Y up).
                let ray_optical = Vec3::new(
                    ((f64::from(x) - self.camera.cx) / self.camera.fx) as f32,
                    ((f64::from(y) - self.camera.cy) / self.camera.fy) as f32,
                    1.0,
                );
                let ray_in_camera = Vec3::new(ray_optical.x, -ray_optical.y, -ray_optical.z);
                let dir = world_from_camera
                    .transform_vector(ray_in_camera)
                    .normalize();
                let i_px = (y * w + x) as usize;
                let Some((t, normal, albedo)) = cast(origin, dir) else {
                    continue;
                };
                let point = origin + dir * t;
                // Depth along the optical axis; Kinect-like holes where the surface is grazing.
                let z_m = t * dir.dot(world_from_camera.transform_vector(-Vec3::Z));
                let grazing = normal.dot(-dir) < 0.12;
                if let Some(d) = depth.as_u16_mut()
                    && !grazing
                {
                    d[i_px] = (z_m * 1000.0).round().clamp(0.0, 65535.0) as u16;
                }
                let to_lamp = lamp - point;
                let dist2 = to_lamp.length_squared().max(1e-4);
                let l = to_lamp / dist2.sqrt();
                let lit = cast(point + normal * 1e-3, l).is_none_or(|(tl, _, _)| tl * tl > dist2);
                let irradiance = if lit {
                    normal.dot(l).max(0.0) / dist2
                } else {
                    0.0
                };
                let radiance = albedo * (0.08 + 0.6 * irradiance);
                if let Some(c) = color.as_u8_mut() {
                    for (k, v) in radiance.to_array().into_iter().enumerate() {
                        c[3 * i_px + k] = linear_to_srgb(v);
                    }
                }
            }
        }
        projector_shadow(&mut depth);
        (depth, color)
    }

    /// The probe's view of the sky: a dim ceiling with a bright window, at one exposure.
    fn render_probe(&self, exposure_us: u32) -> ProbeImage {
        let s = self.settings.probe_size;
        let mut image = Image::new(s, s, PixelFormat::Rgb8);
        let gain = exposure_us as f32 * 1e-3;
        if let Some(px) = image.as_u8_mut() {
            for y in 0..s {
                for x in 0..s {
                    let u = (f64::from(x) - self.probe.cx) / self.probe.fx;
                    let v = (f64::from(y) - self.probe.cy) / self.probe.fy;
                    let theta = (u * u + v * v).sqrt() as f32;
                    if theta > FRAC_PI_2 {
                        continue;
                    }
                    let phi = (v.atan2(u) as f32).rem_euclid(TAU);
                    let window = theta > 0.5 && theta < 0.9 && phi < PI / 4.0;
                    let radiance = if window {
                        Vec3::new(40.0, 40.0, 36.0)
                    } else {
                        Vec3::new(0.05, 0.05, 0.06) * (1.0 + theta.cos())
                    };
                    let i = 3 * (y * s + x) as usize;
                    for (k, value) in (radiance * gain).to_array().into_iter().enumerate() {
                        px[i + k] = linear_to_srgb(value);
                    }
                }
            }
        }
        ProbeImage {
            image,
            exposure_us,
            gain_db: 0.0,
        }
    }

    /// The floor marker as a detector would report it (exact corners, zero reprojection error).
    fn markers(&self, i: u32) -> MarkerSet {
        let camera_from_world = self.world_from_camera(i).inverse();
        let world_from_marker = Pose::new(Quat::from_rotation_x(-FRAC_PI_2), MARKER_CENTER);
        let corners_in_marker = [
            Vec3::new(-MARKER_HALF_EDGE, -MARKER_HALF_EDGE, 0.0),
            Vec3::new(MARKER_HALF_EDGE, -MARKER_HALF_EDGE, 0.0),
            Vec3::new(MARKER_HALF_EDGE, MARKER_HALF_EDGE, 0.0),
            Vec3::new(-MARKER_HALF_EDGE, MARKER_HALF_EDGE, 0.0),
        ];
        let mut corners_px = [Vec2::ZERO; 4];
        for (corner_px, corner) in corners_px.iter_mut().zip(corners_in_marker) {
            let p = camera_from_world.transform_point(world_from_marker.transform_point(corner));
            let p = DVec3::new(f64::from(p.x), f64::from(-p.y), f64::from(-p.z));
            if p.z <= 0.0 {
                return MarkerSet::default();
            }
            let px = DVec2::new(
                self.camera.fx * p.x / p.z + self.camera.cx,
                self.camera.fy * p.y / p.z + self.camera.cy,
            );
            *corner_px = px.as_vec2();
        }
        MarkerSet {
            detections: vec![MarkerDetection {
                family: "tag36h11".into(),
                marker_id: 7,
                corners_px,
                camera_from_marker: camera_from_world * world_from_marker,
                reprojection_rms_px: 0.0,
            }],
        }
    }
}

/// Kinect-like holes beside foreground edges: the IR projector sits to one side of the depth
/// camera, so a surface just right of a nearer edge gets no pattern and no depth.
fn projector_shadow(depth: &mut Image) {
    const SHADOW_PX: usize = 2;
    const STEP_MM: u16 = 50;
    let w = depth.width() as usize;
    let Some(d) = depth.as_u16_mut() else { return };
    for row in d.chunks_mut(w.max(1)) {
        let original = row.to_vec();
        for x in 0..w {
            let occluded = (1..=SHADOW_PX.min(x)).any(|k| {
                let near = original[x - k];
                near != 0 && original[x] > near.saturating_add(STEP_MM)
            });
            if occluded {
                row[x] = 0;
            }
        }
    }
}

/// Nearest hit of the ball or the floor: distance, normal, albedo.
fn cast(origin: Vec3, dir: Vec3) -> Option<(f32, Vec3, Vec3)> {
    let mut best: Option<(f32, Vec3, Vec3)> = None;
    let oc = origin - BALL_CENTER;
    let b = oc.dot(dir);
    let disc = b * b - (oc.length_squared() - BALL_RADIUS * BALL_RADIUS);
    if disc >= 0.0 {
        let t = -b - disc.sqrt();
        if t > 1e-4 {
            let normal = (origin + dir * t - BALL_CENTER) / BALL_RADIUS;
            best = Some((t, normal, Vec3::new(0.8, 0.1, 0.08)));
        }
    }
    if dir.y.abs() > 1e-6 {
        let t = (FLOOR_Y - origin.y) / dir.y;
        let p = origin + dir * t;
        if t > 1e-4 && best.is_none_or(|(tb, _, _)| t < tb) && p.x.abs() < 1.5 && p.z.abs() < 1.5 {
            let in_marker = (p.x - MARKER_CENTER.x).abs() < MARKER_HALF_EDGE
                && (p.z - MARKER_CENTER.z).abs() < MARKER_HALF_EDGE;
            let checker = ((p.x * 5.0).floor() as i32 + (p.z * 5.0).floor() as i32).rem_euclid(2);
            let albedo = if in_marker {
                Vec3::splat(0.05)
            } else if checker == 0 {
                Vec3::splat(0.7)
            } else {
                Vec3::new(0.45, 0.5, 0.55)
            };
            best = Some((t, Vec3::Y, albedo));
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::StreamKind;

    #[test]
    fn generation_is_deterministic_and_time_ordered() {
        let rig = SyntheticRig::new(SyntheticSettings {
            frames: 6,
            ..Default::default()
        });
        let a: Vec<_> = rig.messages().collect();
        let b: Vec<_> = rig.messages().collect();
        assert_eq!(a, b);
        assert!(
            a.windows(2)
                .all(|w| w[0].stamp().host_ns <= w[1].stamp().host_ns)
        );
        let count = |k| a.iter().filter(|m| m.kind() == k).count();
        assert_eq!(count(StreamKind::Depth), 6);
        assert_eq!(count(StreamKind::Color), 6);
        assert_eq!(count(StreamKind::Probe), 2);
        assert_eq!(count(StreamKind::Lamp), 2);
    }

    #[test]
    fn ball_is_in_front_of_the_floor_and_holes_exist() {
        let rig = SyntheticRig::new(SyntheticSettings::default());
        let (depth, color) = rig.render_camera(0);
        let (w, h) = (depth.width(), depth.height());
        // The camera looks at the ball's centre: the centre pixel sees the ball.
        let centre_m = depth.depth_m(w / 2, h / 2).unwrap();
        let eye = rig.world_from_camera(0).translation;
        let expected = (eye - BALL_CENTER).length() - BALL_RADIUS;
        assert!(
            (centre_m - expected).abs() < 0.002,
            "{centre_m} vs {expected}"
        );
        // Kinect-like holes: invalid pixels right of the ball's edge, with valid floor beyond.
        let d = depth.as_u16().unwrap();
        let holes = (0..d.len() - 3)
            .filter(|&i| d[i] != 0 && d[i + 1] == 0 && d[i + 3] != 0)
            .count();
        assert!(holes > 4, "{holes} holes inside the image");
        let c = 3 * ((h / 2) * w + w / 2) as usize;
        let rgb = &color.as_u8().unwrap()[c..c + 3];
        assert!(
            rgb[0] > rgb[1] && rgb[0] > rgb[2],
            "the ball is red: {rgb:?}"
        );
    }

    #[test]
    fn marker_corners_project_onto_the_dark_marker() {
        let rig = SyntheticRig::new(SyntheticSettings::default());
        let (_, color) = rig.render_camera(0);
        let set = rig.markers(0);
        let centre = set.detections[0].corners_px.iter().copied().sum::<Vec2>() / 4.0;
        let i = 3 * (centre.y.round() as u32 * color.width() + centre.x.round() as u32) as usize;
        assert!(color.as_u8().unwrap()[i] < 60, "marker centre is dark");
    }
}
