//! The simulated rig: a [`Scene`] seen by a registered colour + depth camera on a trajectory,
//! a fish-eye probe bracketing exposures, a marker board, and a pocket lamp moving over the
//! scene and reporting over its serial line, with the ground truth of every frame.
//!
//! Only the scene's **real** meshes are sensed; the virtual object exists for the engines alone.
//! Per frame `i` (time i / fps):
//! - **colour**: L^μ path-traced by the reference renderer (`color_spp` samples, the scene's
//!   lights plus the lamp), times `exposure`, plus sensor noise (shot + read, Gaussian), through
//!   the [`CameraResponse`] to 8-bit. The board's print is applied as an albedo ratio at the
//!   first hit (exact for the light the print reflects directly; the light it bounces onwards is
//!   that of the surface it is printed on), averaged over 4 × 4 sub-pixel rays.
//! - **depth**: the [`KinectModel`] applied to the true surface (pixel-centre rays).
//! - **markers**: each board tag whose four corners are in the image and whose centre is not
//!   occluded, with exact corners and pose (a detector's ideal output; detectors themselves run
//!   on the colour image).
//! - **probe**: every `every` frames, the next exposure of the bracket; the probe sees the
//!   environment map and every light as a small disc of the lamp's radius whose radiance gives
//!   the light's true irradiance at the probe (occlusion by the scene is not modelled: the probe
//!   sits above it).
//! - **lamp**: every `every` frames, a serial [`LampReport`] (its line is
//!   [`SimFrame::lamp_line`]) and the [`LampState`] a tracker would publish from it.
//! - **truth** (every `truth_every` frames): true depth, world normals, albedo, and the
//!   [`TruthState`] (poses, lights, markers).
//!
//! Everything is a pure function of the settings, the scene and the frame index.

use std::f32::consts::{PI, TAU};
use std::sync::Arc;

use glam::{DVec2, DVec3, Vec3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_pcg::Pcg64Mcg;
use relight_core::camera::{CameraModel, KannalaBrandt, Pinhole, optical_from_gl};
use relight_core::light::Light;
use relight_core::recording::truth::{TruthKind, TruthMessage, TruthState};
use relight_core::recording::{
    RecordingError, RecordingMeta, RecordingOptions, RecordingSummary, RecordingWriter,
};
use relight_core::rig::RigCalibration;
use relight_core::scene::Scene;
use relight_core::{
    Frame, Image, LampState, MarkerDetection, MarkerSet, PixelFormat, Pose, StreamMessage,
    Timestamp,
};
use relight_reference::accel::Geometry;
use relight_reference::{ReferenceError, ReferenceRenderer, ReferenceSettings};

use crate::kinect::{KinectModel, TrueSurface};
use crate::markers::{MarkerBoard, corners_in_marker};
use crate::probe::{ProbeLens, environment_radiance, render_probe};
use crate::response::CameraResponse;
use crate::trajectory::Trajectory;
use relight_backends::lamp_protocol::LampReport;
use relight_backends::markers::pose::{PoseSettings, estimate_square_pose};

/// The fish-eye probe of the rig.
#[derive(Debug, Clone, PartialEq)]
pub struct SimProbe {
    pub lens: ProbeLens,
    /// glTF convention (the lens looks down its −Z).
    pub world_from_probe: Pose,
    /// The bracket, cycled: one exposure per probe frame.
    pub exposures_us: Vec<u32>,
    /// A probe frame every `every` camera frames.
    pub every: u32,
    /// Radiance × exposure time (s) → the response's [0, 1] input.
    pub exposure_scale: f32,
}

/// The pocket lamp: carried on a circle above the scene, dimmed and switched over time.
#[derive(Debug, Clone, PartialEq)]
pub struct SimLamp {
    pub center: Vec3,
    pub radius_m: f32,
    pub period_s: f32,
    /// Radiant intensity at level 1, W/sr (luminance).
    pub max_intensity: f32,
    pub cct_k: u32,
    /// Dimmer level; the lamp breathes between `level` and `level / 2` once per `period_s`.
    pub level: f32,
    /// Frames `[from, to)` during which the lamp is switched off (none when empty).
    pub off_frames: std::ops::Range<u32>,
    /// Radius of the bulb as the probe sees it, metres.
    pub bulb_radius_m: f32,
    /// A serial report every `every` camera frames.
    pub every: u32,
}

/// What to simulate.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSettings {
    /// Colour and depth resolution (the depth is registered to the colour camera).
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub frames: u32,
    /// Camera path; `None` keeps the scene's camera still.
    pub trajectory: Option<Trajectory>,
    /// Path-traced samples per pixel of each colour frame.
    pub color_spp: u32,
    /// Radiance → the response's [0, 1] input.
    pub exposure: f32,
    pub response: CameraResponse,
    /// Sensor noise on the response's input: σ² = `shot_noise` · x + `read_noise`².
    pub shot_noise: f32,
    pub read_noise: f32,
    /// Gaussian noise on each detected tag corner, pixels per coordinate (0: a detector's ideal
    /// output). With noise, each tag's pose is fitted to its noisy corners as a detector would.
    pub marker_corner_sigma_px: f32,
    /// Depth sensor model; its focal length is replaced by the camera's at this resolution.
    pub kinect: KinectModel,
    pub probe: Option<SimProbe>,
    pub board: Option<MarkerBoard>,
    pub lamp: Option<SimLamp>,
    /// Ground truth every `truth_every` frames (0: none).
    pub truth_every: u32,
    pub seed: u64,
    /// Host time of frame 0, ns.
    pub start_ns: u64,
}

impl Default for SimSettings {
    fn default() -> Self {
        Self {
            width: 320,
            height: 240,
            fps: 30,
            frames: 90,
            trajectory: None,
            color_spp: 16,
            exposure: 1.0,
            response: CameraResponse::default(),
            shot_noise: 2e-4,
            read_noise: 2e-3,
            marker_corner_sigma_px: 0.0,
            kinect: KinectModel::default(),
            probe: None,
            board: None,
            lamp: None,
            truth_every: 1,
            seed: 1,
            start_ns: 1_700_000_000_000_000_000,
        }
    }
}

/// Camera paths relative to a scene's camera (what `relightd simulate --trajectory` offers).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraPath {
    /// The scene camera on a tripod.
    Static,
    /// The scene camera held by hand: 1 cm and 0.5° of tremor.
    Shake,
    /// An arc around the virtual object at the camera's height, swinging
    /// ±[`ORBIT_SWEEP_DEG`] about the scene camera's azimuth, always facing the object and
    /// always inside the room (see [`CameraPath::trajectory`]).
    Orbit,
    /// The orbit, held by hand (the shake's tremor on top): a person walking around the desk.
    Walk,
}

/// Half-angle of the orbit's swing: at ±25° a desk scene's side walls stay in front of the camera
/// and a board beside the object stays in view.
pub const ORBIT_SWEEP_DEG: f32 = 25.0;
/// Azimuth rate at the middle of the swing, degrees per second: a slow walk.
const ORBIT_RATE_DEG_S: f32 = 18.0;
/// Fraction of the distance to the nearest real surface behind the camera that the orbit's
/// radius may use.
const ORBIT_WALL_MARGIN: f32 = 0.9;

impl CameraPath {
    /// The path in `scene`. The orbit's radius is the scene camera's horizontal distance from the
    /// object, shortened where some real surface (a wall) lies between the object and a point of
    /// the arc, so the camera never sees the room from behind its walls.
    pub fn trajectory(self, scene: &Scene) -> Trajectory {
        let camera = scene.camera.world_from_camera;
        let shake = |base| Trajectory::Shake {
            base: Box::new(base),
            amplitude_m: 0.01,
            amplitude_deg: 0.5,
        };
        match self {
            CameraPath::Static => Trajectory::Static(camera),
            CameraPath::Shake => shake(Trajectory::Static(camera)),
            CameraPath::Orbit => orbit_in(scene),
            CameraPath::Walk => shake(orbit_in(scene)),
        }
    }
}

fn orbit_in(scene: &Scene) -> Trajectory {
    let camera = scene.camera.world_from_camera;
    let target = scene
        .virtual_bounds()
        .map_or(camera.translation, |(lo, hi)| (lo + hi) / 2.0);
    let offset = camera.translation - target;
    let sweep_rad = ORBIT_SWEEP_DEG.to_radians();
    let start_rad = offset.x.atan2(offset.z);
    let real = Geometry::new(&scene.without_virtual(), false);
    let mut radius_m = offset.with_y(0.0).length();
    for k in 0..=32 {
        let azimuth = start_rad + sweep_rad * (k as f32 / 16.0 - 1.0);
        let eye = Vec3::new(radius_m * azimuth.sin(), offset.y, radius_m * azimuth.cos());
        let length = eye.length();
        if let Some(hit) = real.intersect(target, eye / length, 1e-4, length) {
            radius_m *= ORBIT_WALL_MARGIN * hit.t / length;
        }
    }
    Trajectory::Orbit {
        center: target,
        radius_m,
        height_m: offset.y,
        period_s: TAU * ORBIT_SWEEP_DEG / ORBIT_RATE_DEG_S,
        start_rad,
        sweep_rad,
    }
}

impl SimSettings {
    /// Settings with the props placed where a lab would put them in `scene`: the probe looking
    /// up from the top of the virtual object's place (where the papers put it), the lamp
    /// circling 0.5 m above that, and a 3 × 3 board of 12 cm tags (45 cm, an A2 print) on the first upward-facing real
    /// surface the camera sees right of and below the image centre (none if there is none).
    pub fn placed_in(scene: &Scene) -> Self {
        let (lo, hi) = scene
            .virtual_bounds()
            .or_else(|| scene.real_bounds())
            .unwrap_or((Vec3::ZERO, Vec3::ZERO));
        let top = Vec3::new((lo.x + hi.x) / 2.0, hi.y, (lo.z + hi.z) / 2.0);
        let probe = SimProbe {
            lens: equidistant_probe(128, 185.0),
            world_from_probe: Pose::new(
                glam::Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
                top + Vec3::Y * 0.01,
            ),
            exposures_us: vec![250, 2_000, 16_000],
            every: 3,
            exposure_scale: 1.0,
        };
        let lamp = SimLamp {
            center: top + Vec3::Y * 0.5,
            radius_m: 0.3,
            period_s: 4.0,
            max_intensity: 1.0,
            cct_k: 3200,
            level: 0.8,
            off_frames: 0..0,
            bulb_radius_m: 0.02,
            every: 3,
        };
        let mut settings = Self {
            probe: Some(probe),
            lamp: Some(lamp),
            ..Self::default()
        };
        settings.board = board_in_view(scene, &settings);
        settings
    }
}

/// A 3 × 3 tag board lying on the first upward-facing real surface seen at 70 % / 75 % of the
/// image (right of and below the centre).
fn board_in_view(scene: &Scene, settings: &SimSettings) -> Option<MarkerBoard> {
    let probe_rig = SimRig::new(
        scene,
        SimSettings {
            board: None,
            ..settings.clone()
        },
    )
    .ok()?;
    let pose = scene.camera.world_from_camera;
    let pixel = DVec2::new(
        0.7 * f64::from(settings.width),
        0.75 * f64::from(settings.height),
    );
    let dir = probe_rig.ray(&pose, pixel);
    let (t, normal, ..) = probe_rig.cast(pose.translation, dir)?;
    (normal.y > 0.95).then(|| {
        // Board +z along the surface normal (world +Y), printed +y pointing away from the camera.
        let forward = Vec3::new(dir.x, 0.0, dir.z).normalize_or(Vec3::NEG_Z);
        let rotation = glam::Quat::from_mat3(&glam::Mat3::from_cols(
            forward.cross(Vec3::Y).normalize_or(Vec3::X),
            forward,
            Vec3::Y,
        ));
        MarkerBoard {
            first_id: 0,
            cols: 3,
            rows: 3,
            tag_size_m: 0.12,
            gap_m: 0.03,
            world_from_board: Pose::new(rotation, pose.translation + dir * t),
            white_albedo: 0.8,
            black_albedo: 0.04,
        }
    })
}

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("simulation setting `{setting}` {reason}")]
    Setting {
        setting: &'static str,
        reason: String,
    },
    #[error("scene `{scene}`: {reason}")]
    Scene { scene: String, reason: String },
    #[error(transparent)]
    Recording(#[from] RecordingError),
}

/// Everything one camera frame produces.
#[derive(Debug, Clone, PartialEq)]
pub struct SimFrame {
    /// Sensor messages in host-time order.
    pub messages: Vec<StreamMessage>,
    pub truth: Vec<TruthMessage>,
    /// The serial line the lamp sent this frame, if it sent one.
    pub lamp_line: Option<String>,
}

/// The simulated rig over one scene.
#[derive(Debug)]
pub struct SimRig {
    scene: Scene,
    settings: SimSettings,
    camera: Pinhole,
    real: Geometry,
}

/// Sub-pixel rays per axis for the print of the marker board.
const BOARD_SUPERSAMPLING: u32 = 4;
/// How close (m) a surface must be to the board's plane to carry its print.
const BOARD_TOLERANCE_M: f32 = 0.003;

/// The largest image side the simulator renders: a larger one (4096² and up is already a
/// minutes-long path trace) is a typo, and its buffers would not fit in memory.
const MAX_IMAGE_SIDE: u32 = 8192;
const MAX_FPS: u32 = 1000;
const MAX_COLOR_SPP: u32 = 65_536;

impl SimRig {
    pub fn new(scene: &Scene, settings: SimSettings) -> Result<Self, SimError> {
        let bad = |setting, reason: &str| SimError::Setting {
            setting,
            reason: reason.into(),
        };
        if !(1..=MAX_IMAGE_SIDE).contains(&settings.width)
            || !(1..=MAX_IMAGE_SIDE).contains(&settings.height)
        {
            return Err(bad("width/height", "must be in 1..=8192"));
        }
        if !(1..=MAX_FPS).contains(&settings.fps) {
            return Err(bad("fps", "must be in 1..=1000"));
        }
        if !(1..=MAX_COLOR_SPP).contains(&settings.color_spp) {
            return Err(bad("color_spp", "must be in 1..=65536"));
        }
        if !(settings.exposure.is_finite() && settings.exposure > 0.0) {
            return Err(bad("exposure", "must be a positive number"));
        }
        if let Some(probe) = &settings.probe {
            if probe.exposures_us.is_empty() || probe.every == 0 {
                return Err(bad("probe", "needs exposures and a positive `every`"));
            }
            probe
                .lens
                .model
                .validate()
                .map_err(|e| bad("probe.lens", &e.to_string()))?;
        }
        if settings.lamp.as_ref().is_some_and(|lamp| lamp.every == 0) {
            return Err(bad("lamp.every", "must be positive"));
        }
        let yfov = scene.camera.yfov_rad;
        if !(yfov > 0.0 && yfov < PI) {
            return Err(SimError::Scene {
                scene: scene.name.clone(),
                reason: format!("camera field of view {yfov} rad is not in (0, π)"),
            });
        }
        // Same pixel geometry as the reference renderer: pixel centres at integer coordinates,
        // square pixels, the vertical field of view of the scene's camera.
        let (w, h) = (f64::from(settings.width), f64::from(settings.height));
        let f = h / 2.0 / (f64::from(yfov) / 2.0).tan();
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
        let scene = scene.without_virtual();
        let real = Geometry::new(&scene, false);
        Ok(Self {
            scene,
            settings,
            camera,
            real,
        })
    }

    /// Lock the exposures the way a rig's auto-exposure would before a session: the colour
    /// camera's so that the 95th percentile of frame 0's radiance (1 spp) lands at 0.8 of the
    /// response's input, and the probe's so that the brightest direction it sees at frame 0 (a
    /// window, a lamp's bulb) just stays below saturation in the shortest exposure of the
    /// bracket. Returns the rig with those exposures.
    pub fn metered(mut self) -> Self {
        let lights = self.lights(0);
        let radiance = self.radiance(&self.world_from_camera(0), &lights, 1, self.settings.seed);
        if let Ok(radiance) = radiance {
            let mut values: Vec<f32> = radiance
                .iter()
                .map(|l| l.max_element())
                .filter(|v| v.is_finite() && *v > 0.0)
                .collect();
            if !values.is_empty() {
                let k = (values.len() * 95 / 100).min(values.len() - 1);
                let (_, p95, _) = values.select_nth_unstable_by(k, f32::total_cmp);
                self.settings.exposure = 0.8 / *p95;
            }
        }
        if let Some(mut probe) = self.settings.probe.clone() {
            let model = probe.lens.model;
            let mut brightest = 0.0f32;
            for y in 0..model.height {
                for x in 0..model.width {
                    let Some(ray) = model.unproject(DVec2::new(f64::from(x), f64::from(y))) else {
                        continue;
                    };
                    let dir = probe
                        .world_from_probe
                        .transform_vector(relight_core::camera::gl_from_optical(ray).as_vec3());
                    let radiance = self.probe_radiance(&probe, &lights, dir.normalize());
                    brightest = brightest.max(radiance.max_element());
                }
            }
            // Discs a pixel cannot resolve are averaged down by the sensor; the unresolved peak
            // may saturate, which is what a real bracket does with a bulb too.
            let shortest_s = probe.exposures_us.iter().copied().min().unwrap_or(1) as f32 * 1e-6;
            if brightest.is_finite() && brightest > 0.0 {
                probe.exposure_scale = 0.9 / (brightest * shortest_s);
                self.settings.probe = Some(probe);
            }
        }
        self
    }

    pub fn settings(&self) -> &SimSettings {
        &self.settings
    }

    pub fn camera(&self) -> &Pinhole {
        &self.camera
    }

    /// The rig's calibration (what a lab would have measured): one registered camera for
    /// colour and depth, the probe's lens and pose, and both cameras' true inverse response and
    /// radiance scale.
    pub fn calibration(&self) -> RigCalibration {
        let probe = self.settings.probe.as_ref();
        RigCalibration {
            name: format!("simulated-{}", self.scene.name),
            depth: Some(CameraModel::Pinhole(self.camera)),
            color: Some(CameraModel::Pinhole(self.camera)),
            probe: probe.map(|p| CameraModel::KannalaBrandt(p.lens.model)),
            world_from_probe: probe.map_or(Pose::IDENTITY, |p| p.world_from_probe),
            probe_response: probe
                .map(|_| self.settings.response.inverse_table())
                .unwrap_or_default(),
            probe_radiance_scale: probe.map_or(1.0, |p| 1.0 / p.exposure_scale),
            world_from_board: self
                .settings
                .board
                .as_ref()
                .map_or(Pose::IDENTITY, |b| b.world_from_board),
            board: self.settings.board.as_ref().map(MarkerBoard::layout),
            color_response: self.settings.response.inverse_table(),
            color_radiance_scale: 1.0 / self.settings.exposure,
            ..RigCalibration::default()
        }
    }

    fn time_s(&self, i: u32) -> f32 {
        i as f32 / self.settings.fps as f32
    }

    /// Camera pose at frame `i` (glTF convention).
    pub fn world_from_camera(&self, i: u32) -> Pose {
        match &self.settings.trajectory {
            Some(trajectory) => trajectory.pose_at(self.time_s(i)),
            None => self.scene.camera.world_from_camera,
        }
    }

    /// The lamp's report and position at frame `i`.
    pub fn lamp(&self, i: u32) -> Option<(LampReport, Vec3)> {
        let lamp = self.settings.lamp.as_ref()?;
        let phase = TAU * self.time_s(i) / lamp.period_s.max(1e-3);
        let position = lamp.center + lamp.radius_m * Vec3::new(phase.cos(), 0.0, phase.sin());
        let report = LampReport {
            seq: i / lamp.every,
            on: !lamp.off_frames.contains(&i),
            // The firmware reports (and drives) its level in the protocol's 4 decimals.
            level: (lamp.level * (0.75 + 0.25 * phase.cos()) * 1e4).round() / 1e4,
            cct_k: lamp.cct_k,
            orientation: None,
        };
        Some((report, position))
    }

    /// The real scene's lights at frame `i`, the lamp (when on) included.
    pub fn lights(&self, i: u32) -> Vec<Light> {
        let mut lights = self.scene.lights.clone();
        if let (Some((report, position)), Some(lamp)) = (self.lamp(i), &self.settings.lamp) {
            let state = report.state(position, lamp.max_intensity);
            if state.on {
                lights.push(Light::Point {
                    position_in_world: position,
                    intensity: state.intensity,
                });
            }
        }
        lights
    }

    fn stamp(&self, i: u32, offset_ns: u64) -> Timestamp {
        let period_ns = 1_000_000_000 / u64::from(self.settings.fps);
        let host_ns = self.settings.start_ns + u64::from(i) * period_ns + offset_ns;
        // Each sensor's own clock: a fixed offset from the host, as real devices have.
        Timestamp::new(host_ns - self.settings.start_ns + 12_345_678, host_ns)
    }

    /// Everything frame `i` produces.
    pub fn frame(&self, i: u32) -> SimFrame {
        let seq = u64::from(i);
        let world_from_camera = self.world_from_camera(i);
        let lights = self.lights(i);
        let surface = self.cast_camera(&world_from_camera);
        let color = self.render_color(i, &world_from_camera, &lights, &surface);
        let mut depth = Image::new(1, 1, PixelFormat::DepthU16Mm);
        let kinect = KinectModel {
            focal_px: self.camera.fx as f32,
            ..self.settings.kinect
        };
        kinect.measure(
            &surface.kinect_truth(
                self.settings.width,
                self.settings.height,
                &world_from_camera,
            ),
            &self.camera,
            self.settings
                .seed
                .wrapping_mul(0x9e37_79b9)
                .wrapping_add(seq),
            &mut depth,
        );

        // Colour arrives a little after depth, markers after colour (detected on it).
        let mut messages = vec![
            StreamMessage::Depth(Arc::new(Frame::new(seq, self.stamp(i, 0), depth))),
            StreamMessage::Color(Arc::new(Frame::new(seq, self.stamp(i, 2_000_000), color))),
        ];
        if self.settings.board.is_some() {
            messages.push(StreamMessage::Markers(Arc::new(Frame::new(
                seq,
                self.stamp(i, 3_000_000),
                self.markers(i, &world_from_camera),
            ))));
        }
        if let Some(probe) = &self.settings.probe
            && i.is_multiple_of(probe.every)
        {
            let n = i / probe.every;
            let exposure_us = probe.exposures_us[n as usize % probe.exposures_us.len()];
            let radiance = |dir: Vec3| self.probe_radiance(probe, &lights, dir);
            let image = render_probe(
                &radiance,
                &probe.lens,
                &probe.world_from_probe,
                exposure_us,
                probe.exposure_scale,
                &self.settings.response,
            );
            messages.push(StreamMessage::Probe(Arc::new(Frame::new(
                u64::from(n),
                self.stamp(i, 5_000_000),
                image,
            ))));
        }
        let mut lamp_line = None;
        if let (Some(lamp), Some((report, position))) = (&self.settings.lamp, self.lamp(i))
            && i.is_multiple_of(lamp.every)
        {
            lamp_line = Some(report.to_line());
            let state: LampState = report.state(position, lamp.max_intensity);
            messages.push(StreamMessage::Lamp(Arc::new(Frame::new(
                u64::from(report.seq),
                self.stamp(i, 7_000_000),
                state,
            ))));
        }

        let mut truth = Vec::new();
        if self.settings.truth_every > 0 && i.is_multiple_of(self.settings.truth_every) {
            let stamp = self.stamp(i, 0);
            let (depth, normals, albedo) =
                surface.truth_images(self.settings.width, self.settings.height);
            truth.push(TruthMessage::Image(
                TruthKind::Depth,
                Frame::new(seq, stamp, depth),
            ));
            truth.push(TruthMessage::Image(
                TruthKind::Normals,
                Frame::new(seq, stamp, normals),
            ));
            truth.push(TruthMessage::Image(
                TruthKind::Albedo,
                Frame::new(seq, stamp, albedo),
            ));
            let state = TruthState {
                world_from_camera,
                world_from_probe: self.settings.probe.as_ref().map(|p| p.world_from_probe),
                lights,
                markers: self
                    .settings
                    .board
                    .as_ref()
                    .map(MarkerBoard::tags)
                    .unwrap_or_default(),
            };
            truth.push(TruthMessage::State(Frame::new(seq, stamp, state)));
        }
        SimFrame {
            messages,
            truth,
            lamp_line,
        }
    }

    /// World ray through pixel coordinates `pixel` (centre of pixel (x, y) at (x, y)).
    fn ray(&self, world_from_camera: &Pose, pixel: DVec2) -> Vec3 {
        let optical = DVec3::new(
            (pixel.x - self.camera.cx) / self.camera.fx,
            (pixel.y - self.camera.cy) / self.camera.fy,
            1.0,
        );
        let gl = Vec3::new(optical.x as f32, -optical.y as f32, -1.0);
        world_from_camera.transform_vector(gl).normalize()
    }

    /// First real surface along a ray: distance, shading normal (facing the ray), albedo,
    /// specular luminance.
    fn cast(&self, origin: Vec3, dir: Vec3) -> Option<(f32, Vec3, Vec3, f32)> {
        let hit = self.real.intersect(origin, dir, 0.0, f32::INFINITY)?;
        let tri = self.real.triangles().get(hit.triangle)?;
        let w = 1.0 - hit.u - hit.v;
        let shading = (tri.normals[0] * w + tri.normals[1] * hit.u + tri.normals[2] * hit.v)
            .normalize_or(tri.geometric_normal);
        let normal = if shading.dot(dir) > 0.0 {
            -shading
        } else {
            shading
        };
        let material = self.scene.materials.get(tri.material);
        let albedo = material.map_or(Vec3::ZERO, |m| m.albedo);
        let specular = material.map_or(0.0, |m| luminance(m.specular));
        Some((hit.t, normal, albedo, specular))
    }

    /// The true surface seen by every pixel, with the board's print.
    fn cast_camera(&self, world_from_camera: &Pose) -> SurfaceImage {
        let (w, h) = (self.settings.width, self.settings.height);
        let origin = world_from_camera.translation;
        let forward = world_from_camera.transform_vector(-Vec3::Z);
        let mut out = SurfaceImage::new(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                let dir = self.ray(world_from_camera, DVec2::new(f64::from(x), f64::from(y)));
                let Some((t, normal, albedo, specular)) = self.cast(origin, dir) else {
                    continue;
                };
                out.depth_m[i] = t * dir.dot(forward);
                out.normal[i] = normal;
                out.specular[i] = specular;
                out.albedo[i] = albedo;
                out.print_ratio[i] = Vec3::ONE;
                if let Some(board) = &self.settings.board {
                    let printed = self.printed_albedo(board, world_from_camera, x, y);
                    if let Some(printed) = printed {
                        out.print_ratio[i] = Vec3::select(
                            albedo.cmpgt(Vec3::ZERO),
                            printed / albedo.max(Vec3::splat(1e-6)),
                            Vec3::ONE,
                        );
                        out.albedo[i] = printed;
                    }
                }
            }
        }
        out
    }

    /// Mean albedo over a pixel where the board's print shows in it, `None` where it does not.
    fn printed_albedo(
        &self,
        board: &MarkerBoard,
        world_from_camera: &Pose,
        x: u32,
        y: u32,
    ) -> Option<Vec3> {
        let origin = world_from_camera.translation;
        let n = BOARD_SUPERSAMPLING;
        let mut sum = Vec3::ZERO;
        let mut any_print = false;
        for s in 0..n * n {
            let offset = DVec2::new(
                (f64::from(s % n) + 0.5) / f64::from(n) - 0.5,
                (f64::from(s / n) + 0.5) / f64::from(n) - 0.5,
            );
            let dir = self.ray(
                world_from_camera,
                DVec2::new(f64::from(x), f64::from(y)) + offset,
            );
            let Some((t, _, albedo, _)) = self.cast(origin, dir) else {
                continue;
            };
            let print = board
                .hit(origin, dir)
                .filter(|(tb, _)| (tb - t).abs() < BOARD_TOLERANCE_M)
                .and_then(|(_, p)| board.albedo_at(p));
            match print {
                Some(a) => {
                    any_print = true;
                    sum += Vec3::splat(a);
                }
                None => sum += albedo,
            }
        }
        any_print.then(|| sum / (n * n) as f32)
    }

    /// Path-traced L^μ with the print, exposure, noise and response.
    fn render_color(
        &self,
        i: u32,
        world_from_camera: &Pose,
        lights: &[Light],
        surface: &SurfaceImage,
    ) -> Image {
        let (w, h) = (self.settings.width, self.settings.height);
        let seed = self.settings.seed ^ (u64::from(i) << 32);
        let radiance = self
            .radiance(world_from_camera, lights, self.settings.color_spp, seed)
            // Checked in `new`: the camera is valid and the size positive.
            .unwrap_or_else(|e| {
                tracing::error!(error = %e, "reference renderer refused the simulated frame");
                vec![Vec3::ZERO; w as usize * h as usize]
            });
        let mut rng =
            Pcg64Mcg::seed_from_u64(self.settings.seed.wrapping_add(0x51_7cc1) ^ u64::from(i));
        let unit = Normal::new(0.0f32, 1.0).unwrap_or_else(|_| unreachable!("σ = 1 is valid"));
        let mut image = Image::new(w, h, PixelFormat::Rgb8);
        if let Some(px) = image.as_u8_mut() {
            for (k, rgb) in px.chunks_exact_mut(3).enumerate() {
                let linear = radiance[k] * surface.print_ratio[k] * self.settings.exposure;
                for (c, value) in rgb.iter_mut().zip(linear.to_array()) {
                    let sigma = (self.settings.shot_noise * value.max(0.0)
                        + self.settings.read_noise * self.settings.read_noise)
                        .sqrt();
                    let noisy = value + sigma * unit.sample(&mut rng);
                    *c = self.settings.response.to_code(noisy);
                }
            }
        }
        image
    }

    /// L^μ as the colour camera at `world_from_camera` sees it under `lights`: `spp` path-traced
    /// samples per pixel of the real scene.
    fn radiance(
        &self,
        world_from_camera: &Pose,
        lights: &[Light],
        spp: u32,
        seed: u64,
    ) -> Result<Vec<Vec3>, ReferenceError> {
        let mut scene = self.scene.clone();
        scene.camera.world_from_camera = *world_from_camera;
        scene.lights = lights.to_vec();
        let settings = ReferenceSettings {
            spp,
            seed,
            size: Some((self.settings.width, self.settings.height)),
            ..ReferenceSettings::default()
        };
        let mut renderer = ReferenceRenderer::new(&scene, settings)?;
        renderer.add_samples(spp);
        Ok(renderer.images().l_mu)
    }

    /// What the probe sees in `dir`: the environment plus each light as a small disc.
    fn probe_radiance(&self, probe: &SimProbe, lights: &[Light], dir: Vec3) -> Vec3 {
        let mut radiance = self
            .scene
            .environment
            .as_ref()
            .map_or(Vec3::ZERO, |env| environment_radiance(env, dir));
        let bulb = self
            .settings
            .lamp
            .as_ref()
            .map_or(0.02, |l| l.bulb_radius_m);
        let origin = probe.world_from_probe.translation;
        for light in lights {
            let Some(incident) = light.incident(origin) else {
                continue;
            };
            // A distant light is a disc of the sun's angular radius (0.27°).
            let sin_radius = if incident.distance_m.is_finite() {
                (bulb / incident.distance_m.max(bulb)).min(1.0)
            } else {
                0.27f32.to_radians().sin()
            };
            let cos_radius = (1.0 - sin_radius * sin_radius).sqrt();
            if dir.dot(incident.direction_to_light) >= cos_radius {
                // Uniform disc radiance whose integral over its solid angle is the irradiance.
                let solid_angle = TAU * (1.0 - cos_radius);
                radiance += incident.irradiance / solid_angle.max(1e-12);
            }
        }
        radiance
    }

    /// The board's tags a detector would find in frame `i`'s image: those whose four corners are
    /// in the image and whose centre is not occluded, with the corners' noise.
    fn markers(&self, i: u32, world_from_camera: &Pose) -> MarkerSet {
        let Some(board) = &self.settings.board else {
            return MarkerSet::default();
        };
        let camera_from_world = world_from_camera.inverse();
        let origin = world_from_camera.translation;
        let sigma = f64::from(self.settings.marker_corner_sigma_px.max(0.0));
        let mut rng =
            Pcg64Mcg::seed_from_u64(self.settings.seed.wrapping_add(0x7a9_b0a2d) ^ u64::from(i));
        let unit = Normal::new(0.0f64, 1.0).unwrap_or_else(|_| unreachable!("σ = 1 is valid"));
        let model = CameraModel::Pinhole(self.camera);
        let detections = board
            .tags()
            .into_iter()
            .filter_map(|tag| {
                let mut corners_px = [DVec2::ZERO; 4];
                for (px, corner) in corners_px.iter_mut().zip(corners_in_marker(tag.size_m)) {
                    let in_camera = camera_from_world
                        .transform_point(tag.world_from_marker.transform_point(corner));
                    *px = self
                        .camera
                        .project(optical_from_gl(in_camera.as_dvec3()))
                        .filter(|p| self.camera.contains_pixel(*p))?;
                }
                let centre = tag.world_from_marker.translation;
                let to_centre = centre - origin;
                let distance = to_centre.length();
                let visible = self
                    .cast(origin, to_centre / distance)
                    .is_some_and(|(t, ..)| (t - distance).abs() < 0.01);
                if !visible {
                    return None;
                }
                let camera_from_marker = camera_from_world * tag.world_from_marker;
                if sigma == 0.0 {
                    return Some(MarkerDetection {
                        family: tag.family.clone(),
                        marker_id: tag.marker_id,
                        corners_px: corners_px.map(|c| c.as_vec2()),
                        camera_from_marker,
                        reprojection_rms_px: 0.0,
                    });
                }
                for c in &mut corners_px {
                    *c += DVec2::new(unit.sample(&mut rng), unit.sample(&mut rng)) * sigma;
                }
                let settings = PoseSettings {
                    corner_sigma_px: sigma,
                    ..PoseSettings::default()
                };
                estimate_square_pose(&corners_px, f64::from(tag.size_m), &model, &settings)
                    .ok()
                    .map(|fit| {
                        fit.detection(&tag.family, tag.marker_id, corners_px.map(|c| c.as_vec2()))
                    })
            })
            .collect();
        MarkerSet { detections }
    }

    /// Every frame's sensor messages (host-time order) and truth.
    pub fn frames(&self) -> impl Iterator<Item = SimFrame> + '_ {
        (0..self.settings.frames).map(|i| self.frame(i))
    }
}

/// Simulate every frame of `rig` into an MCAP recording at `path` (sensor streams, ground truth,
/// the rig's calibration); `progress(frame)` is called after each frame.
pub fn write_recording(
    rig: &SimRig,
    path: &std::path::Path,
    mut progress: impl FnMut(u32),
) -> Result<RecordingSummary, SimError> {
    let meta = RecordingMeta {
        calibration: Some(rig.calibration()),
        source: format!(
            "relight simulator {} (scene `{}`)",
            env!("CARGO_PKG_VERSION"),
            rig.scene.name
        ),
    };
    let options = RecordingOptions {
        compression_level: 19,
        ..RecordingOptions::default()
    };
    let mut writer = RecordingWriter::create_with_options(path, &meta, &options)?;
    for i in 0..rig.settings.frames {
        let frame = rig.frame(i);
        for msg in &frame.messages {
            writer.write(msg)?;
        }
        for truth in &frame.truth {
            writer.write_truth(truth)?;
        }
        progress(i);
    }
    Ok(writer.finish()?)
}

/// Per-pixel truth of the camera's view.
struct SurfaceImage {
    depth_m: Vec<f32>,
    /// World space, facing the camera; zero where there is no surface.
    normal: Vec<Vec3>,
    albedo: Vec<Vec3>,
    specular: Vec<f32>,
    /// Print albedo / surface albedo, per channel (1 off the board).
    print_ratio: Vec<Vec3>,
}

impl SurfaceImage {
    fn new(n: usize) -> Self {
        Self {
            depth_m: vec![0.0; n],
            normal: vec![Vec3::ZERO; n],
            albedo: vec![Vec3::ZERO; n],
            specular: vec![0.0; n],
            print_ratio: vec![Vec3::ONE; n],
        }
    }

    /// What the depth model needs: normals in the optical frame, IR albedo as luminance.
    fn kinect_truth(&self, width: u32, height: u32, world_from_camera: &Pose) -> TrueSurface {
        let camera_from_world = world_from_camera.inverse();
        TrueSurface {
            width,
            height,
            depth_m: self.depth_m.clone(),
            normal: self
                .normal
                .iter()
                .map(|nw| {
                    optical_from_gl(camera_from_world.transform_vector(*nw).as_dvec3()).as_vec3()
                })
                .collect(),
            ir_albedo: self.albedo.iter().map(|a| luminance(*a)).collect(),
            specular: self.specular.clone(),
        }
    }

    fn truth_images(&self, width: u32, height: u32) -> (Image, Image, Image) {
        let mut depth = Image::new(width, height, PixelFormat::DepthF32M);
        if let Some(d) = depth.as_f32_mut() {
            d.copy_from_slice(&self.depth_m);
        }
        let rgba = |values: Vec<[f32; 4]>| {
            let mut image = Image::new(width, height, PixelFormat::Rgba16F);
            if let Some(px) = image.as_u16_mut() {
                for (out, v) in px.chunks_exact_mut(4).zip(values) {
                    for (o, x) in out.iter_mut().zip(v) {
                        *o = half::f16::from_f32(x).to_bits();
                    }
                }
            }
            image
        };
        let valid = |i: usize| if self.depth_m[i] > 0.0 { 1.0 } else { 0.0 };
        let normals = rgba(
            self.normal
                .iter()
                .enumerate()
                .map(|(i, n)| [n.x, n.y, n.z, valid(i)])
                .collect(),
        );
        let albedo = rgba(
            self.albedo
                .iter()
                .zip(&self.specular)
                .map(|(a, s)| [a.x, a.y, a.z, *s])
                .collect(),
        );
        (depth, normals, albedo)
    }
}

fn luminance(rgb: Vec3) -> f32 {
    0.2126 * rgb.x + 0.7152 * rgb.y + 0.0722 * rgb.z
}

/// A fish-eye lens of `size` × `size` pixels whose `field_of_view_deg` circle fills the image
/// (equidistant Kannala–Brandt, k = 0).
pub fn equidistant_probe(size: u32, field_of_view_deg: f64) -> ProbeLens {
    let s = f64::from(size);
    let f = s / 2.0 / (field_of_view_deg.to_radians() / 2.0);
    ProbeLens {
        model: KannalaBrandt {
            width: size,
            height: size,
            fx: f,
            fy: f,
            cx: (s - 1.0) / 2.0,
            cy: (s - 1.0) / 2.0,
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        },
        field_of_view_deg,
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use relight_core::scene::SceneCamera;

    use super::*;

    fn empty_scene() -> Scene {
        Scene {
            name: "empty".into(),
            meshes: Vec::new(),
            materials: Vec::new(),
            camera: SceneCamera {
                world_from_camera: Pose::IDENTITY,
                yfov_rad: 1.0,
                width: 8,
                height: 6,
            },
            lights: Vec::new(),
            environment: None,
            environment_lights: Vec::new(),
            shadow_proxy: None,
            surface_revision: None,
        }
    }

    /// Integrating the probe's view over the sphere gives each light's irradiance back.
    #[test]
    fn light_discs_carry_the_irradiance_of_their_light() {
        let probe = SimProbe {
            lens: equidistant_probe(16, 185.0),
            world_from_probe: Pose::IDENTITY,
            exposures_us: vec![1],
            every: 1,
            exposure_scale: 1.0,
        };
        let rig = SimRig::new(&empty_scene(), SimSettings::default()).unwrap();
        let axis = Vec3::new(0.3, 2.0, -0.4);
        let lights = [
            Light::Point {
                position_in_world: axis,
                intensity: Vec3::splat(3.0),
            },
            Light::Directional {
                direction_in_world: -axis.normalize(),
                irradiance: Vec3::splat(5.0),
            },
        ];
        for light in lights {
            let expected = light.incident(Vec3::ZERO).unwrap().irradiance.x;
            let (u, v) = axis.normalize().any_orthonormal_pair();
            let (n_theta, n_phi, max_theta) = (800, 64, 1.5f32.to_radians());
            let mut sum = 0.0;
            for i in 0..n_theta {
                let theta = (i as f32 + 0.5) / n_theta as f32 * max_theta;
                for j in 0..n_phi {
                    let phi = (j as f32 + 0.5) / n_phi as f32 * TAU;
                    let dir = axis.normalize() * theta.cos()
                        + (u * phi.cos() + v * phi.sin()) * theta.sin();
                    let d_omega = theta.sin() * (max_theta / n_theta as f32) * (TAU / n_phi as f32);
                    sum += rig.probe_radiance(&probe, &[light], dir).x * d_omega;
                }
            }
            assert!(
                (sum - expected).abs() < 0.02 * expected,
                "{light:?}: {sum} vs {expected}"
            );
        }
    }

    #[test]
    fn bad_settings_name_the_setting() {
        let scene = empty_scene();
        let err = |settings| SimRig::new(&scene, settings).unwrap_err().to_string();
        assert!(
            err(SimSettings {
                fps: 0,
                ..SimSettings::default()
            })
            .contains("fps")
        );
        assert!(
            err(SimSettings {
                color_spp: 0,
                ..SimSettings::default()
            })
            .contains("color_spp")
        );
        assert!(
            err(SimSettings {
                exposure: f32::NAN,
                ..SimSettings::default()
            })
            .contains("exposure")
        );
        let mut bad_fov = scene.clone();
        bad_fov.camera.yfov_rad = 0.0;
        assert!(
            SimRig::new(&bad_fov, SimSettings::default())
                .unwrap_err()
                .to_string()
                .contains("field of view")
        );
    }

    /// A lit floor seen from above at an angle: the smallest scene with every stream.
    pub(crate) fn tiny_scene() -> Scene {
        let mut scene = empty_scene();
        scene.meshes.push(relight_reference::shapes::quad(
            "floor",
            Vec3::new(0.0, -1.0, 0.0),
            Vec3::X * 3.0,
            -Vec3::Z * 3.0,
            0,
            false,
        ));
        scene
            .materials
            .push(relight_core::scene::Material::default());
        scene.lights.push(Light::Point {
            position_in_world: Vec3::new(0.0, 1.0, -1.0),
            intensity: Vec3::ONE,
        });
        scene.camera.world_from_camera =
            Pose::look_at(Vec3::ZERO, Vec3::new(0.0, -1.0, -2.0), Vec3::Y);
        scene
    }

    #[test]
    fn frames_are_deterministic() {
        let scene = tiny_scene();
        let settings = SimSettings {
            width: 16,
            height: 12,
            color_spp: 2,
            ..SimSettings::placed_in(&scene)
        };
        let rig = SimRig::new(&scene, settings).unwrap();
        assert_eq!(rig.frame(3), rig.frame(3));
        assert_ne!(
            rig.frame(1).messages[1],
            rig.frame(2).messages[1],
            "noise differs per frame"
        );
    }
}
