//! Synthetic calibration views with known truth: a target's print (and, for the lamp, a bright
//! sphere) seen through a [`CameraModel`] at a known pose, rendered by inverse mapping.
//!
//! Every pixel is the mean of the print over its footprint (a box filter, so the symmetric
//! chessboard saddle stays where it is). The print is looked up at the pixel's four corners;
//! where they agree the pixel is uniform (a straight edge through a pixel always separates two of
//! its corners), elsewhere it is the mean of `supersample²` stratified, jittered samples (at 16²
//! the jitter's noise on an edge pixel is below 1 % of the contrast, where 4² gave 6 % and
//! biased detected corners by 0.05 px). Each sample's ray comes from the camera's own
//! `unproject`, evaluated exactly at the pixel corners once per camera and interpolated
//! bilinearly inside a pixel (the ray field is smooth on that scale: the interpolation error is
//! far below 10⁻³ px); the ray is intersected with the target plane (or the sphere) and the
//! print looked up. Optional Gaussian blur, vignetting,
//! exposure and Gaussian noise follow, then 8-bit quantisation into a [`relight_core::Image`].
//!
//! All poses here are OpenCV's: `camera_from_target` maps the target frame
//! ([`crate::target`]) into the camera's optical frame (+Z forward, +Y down).
//!
//! [`plan_views`] proposes poses that a calibration needs (tilts, targets in the image corners,
//! near a fish-eye's rim) and [`model_difference`] measures how far a recovered camera model
//! reprojects from the truth over the whole image.

use glam::{DMat3, DQuat, DVec2, DVec3};
use relight_core::camera::CameraModel;
use relight_core::{Image, PixelFormat};

use crate::detect::Detection;
use crate::error::CalibrationError;
use crate::rigid::Rigid;
use crate::target::TargetGeometry;

/// How a synthetic view is exposed and degraded.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// Samples along each axis of a pixel that an edge crosses (stratified, jittered).
    pub supersample: u32,
    /// Standard deviation of a Gaussian blur (defocus, motion) in pixels; 0: none.
    pub blur_sigma_px: f64,
    /// Standard deviation of additive Gaussian noise in 8-bit levels; 0: none.
    pub noise_sigma: f64,
    /// Relative darkening at the image corners (`1 − v (r / r_corner)²`); 0: none.
    pub vignetting: f64,
    /// 8-bit level of white paper at the image centre, divided by 255.
    pub exposure: f64,
    /// Reflectance of the black ink relative to the paper.
    pub black: f64,
    /// Reflectance of whatever lies around the target, relative to the paper.
    pub background: f64,
    /// `Mono8` or `Rgb8` (grey in all three channels).
    pub format: PixelFormat,
    /// Seed of the jitter and the noise: the same settings render the same image.
    pub seed: u64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            supersample: 16,
            blur_sigma_px: 0.0,
            noise_sigma: 0.0,
            vignetting: 0.0,
            exposure: 0.85,
            black: 0.06,
            background: 0.3,
            format: PixelFormat::Mono8,
            seed: 1,
        }
    }
}

/// A target placed in front of the camera.
#[derive(Debug, Clone, Copy)]
pub struct PlacedTarget<'a> {
    pub geometry: &'a TargetGeometry,
    pub camera_from_target: Rigid,
}

/// A uniformly bright sphere (a lamp's bulb), optical frame; `radiance` relative to white paper
/// (values above `1 / exposure` saturate).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sphere {
    pub centre_in_camera: DVec3,
    pub radius_m: f64,
    pub radiance: f64,
}

/// What one synthetic view shows.
#[derive(Debug, Clone, Default)]
pub struct Scene<'a> {
    pub targets: Vec<PlacedTarget<'a>>,
    pub spheres: Vec<Sphere>,
}

/// A camera that renders synthetic views; holds the rays through its pixel corners.
#[derive(Debug, Clone)]
pub struct SynthCamera {
    camera: CameraModel,
    settings: RenderSettings,
    /// Rays through pixel corners `(i − ½, j − ½)`, `(width + 1) × (height + 1)`, row-major;
    /// NaN where the lens has no ray.
    corner_rays: Vec<[f32; 3]>,
}

impl SynthCamera {
    pub fn new(camera: CameraModel, settings: RenderSettings) -> Result<Self, CalibrationError> {
        camera.validate()?;
        if !matches!(settings.format, PixelFormat::Mono8 | PixelFormat::Rgb8) {
            return Err(CalibrationError::UnsupportedFormat {
                view: "synthetic view".into(),
                format: settings.format,
            });
        }
        let (w, h) = (camera.width() as usize, camera.height() as usize);
        let mut corner_rays = Vec::with_capacity((w + 1) * (h + 1));
        for j in 0..=h {
            for i in 0..=w {
                let pixel = DVec2::new(i as f64 - 0.5, j as f64 - 0.5);
                corner_rays.push(match camera.unproject(pixel) {
                    Some(ray) => ray.as_vec3().to_array(),
                    None => [f32::NAN; 3],
                });
            }
        }
        Ok(Self {
            camera,
            settings: RenderSettings {
                supersample: settings.supersample.max(1),
                ..settings
            },
            corner_rays,
        })
    }

    pub fn camera(&self) -> &CameraModel {
        &self.camera
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// One target alone.
    pub fn render_target(&self, geometry: &TargetGeometry, camera_from_target: &Rigid) -> Image {
        self.render(&Scene {
            targets: vec![PlacedTarget {
                geometry,
                camera_from_target: *camera_from_target,
            }],
            spheres: Vec::new(),
        })
    }

    /// Renders a scene.
    pub fn render(&self, scene: &Scene<'_>) -> Image {
        let (w, h) = (self.camera.width() as usize, self.camera.height() as usize);
        let placed: Vec<PlacedPlane<'_>> = scene
            .targets
            .iter()
            .map(|t| {
                let target_from_camera = t.camera_from_target.inverse();
                PlacedPlane {
                    geometry: t.geometry,
                    rotation: DMat3::from_quat(target_from_camera.rotation),
                    origin: target_from_camera.translation,
                }
            })
            .collect();
        let radiance = |ray: DVec3| self.radiance(ray, &placed, &scene.spheres);
        let corner_ray = |i: usize, j: usize| {
            let [x, y, z] = self.corner_rays[j * (w + 1) + i];
            DVec3::new(f64::from(x), f64::from(y), f64::from(z))
        };
        // Radiance at every pixel corner; NaN where the lens has no ray.
        let mut corner_radiance = Vec::with_capacity((w + 1) * (h + 1));
        for j in 0..=h {
            for i in 0..=w {
                let ray = corner_ray(i, j);
                corner_radiance.push(if ray.is_finite() {
                    radiance(ray)
                } else {
                    f64::NAN
                });
            }
        }

        let s = self.settings.supersample as usize;
        let inv = 1.0 / s as f64;
        let mut linear = vec![0.0f64; w * h];
        for j in 0..h {
            for i in 0..w {
                let at = |di: usize, dj: usize| corner_radiance[(j + dj) * (w + 1) + i + di];
                let corners = [at(0, 0), at(1, 0), at(0, 1), at(1, 1)];
                // A straight edge that crosses a pixel separates two of its corners, so a pixel
                // whose corners agree lies in one region of the print (only the tip of a
                // pattern corner smaller than a pixel can hide in it).
                if corners.iter().all(|&c| c == corners[0]) {
                    linear[j * w + i] = corners[0];
                    continue;
                }
                let rays = [
                    corner_ray(i, j),
                    corner_ray(i + 1, j),
                    corner_ray(i, j + 1),
                    corner_ray(i + 1, j + 1),
                ];
                let exact = !rays.iter().all(|r| r.is_finite());
                let mut sum = 0.0;
                for b in 0..s {
                    for a in 0..s {
                        let jitter =
                            hash2(self.settings.seed, (j * w + i) as u64, (b * s + a) as u64);
                        let fx = (a as f64 + jitter.x) * inv;
                        let fy = (b as f64 + jitter.y) * inv;
                        let ray = if exact {
                            let pixel = DVec2::new(i as f64 - 0.5 + fx, j as f64 - 0.5 + fy);
                            match self.camera.unproject(pixel) {
                                Some(ray) => ray,
                                // Outside the lens's image circle: no light.
                                None => continue,
                            }
                        } else {
                            rays[0]
                                .lerp(rays[1], fx)
                                .lerp(rays[2].lerp(rays[3], fx), fy)
                        };
                        sum += radiance(ray);
                    }
                }
                linear[j * w + i] = sum * inv * inv;
            }
        }
        if self.settings.blur_sigma_px > 0.0 {
            gaussian_blur(&mut linear, w, h, self.settings.blur_sigma_px);
        }
        let centre = DVec2::new((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let corner_sq = centre.length_squared().max(1.0);
        let mut noise = SplitMix64::new(self.settings.seed ^ 0x5eed_0f5e_ed00);
        let mut out = Image::new(w as u32, h as u32, self.settings.format);
        let channels = self.settings.format.channels();
        let Some(bytes) = out.as_u8_mut() else {
            return out;
        };
        for j in 0..h {
            for i in 0..w {
                let r_sq = (DVec2::new(i as f64, j as f64) - centre).length_squared();
                let vignette = 1.0 - self.settings.vignetting * r_sq / corner_sq;
                let mut level = 255.0 * self.settings.exposure * vignette * linear[j * w + i];
                if self.settings.noise_sigma > 0.0 {
                    level += self.settings.noise_sigma * noise.gaussian();
                }
                let byte = level.round().clamp(0.0, 255.0) as u8;
                let at = (j * w + i) * channels;
                bytes[at..at + channels].fill(byte);
            }
        }
        out
    }

    /// Light along one ray: the nearest target's print or sphere, else the background.
    fn radiance(&self, ray: DVec3, planes: &[PlacedPlane<'_>], spheres: &[Sphere]) -> f64 {
        let mut nearest = f64::INFINITY;
        let mut value = self.settings.background;
        for plane in planes {
            let d = plane.rotation * ray;
            if d.z == 0.0 {
                continue;
            }
            let t = -plane.origin.z / d.z;
            if !(t > 0.0 && t < nearest) {
                continue;
            }
            let hit = plane.origin + d * t;
            if let Some(white) = plane.geometry.print().is_white(hit.truncate()) {
                nearest = t;
                value = if white { 1.0 } else { self.settings.black };
            }
        }
        for sphere in spheres {
            let c = sphere.centre_in_camera;
            let a = ray.length_squared();
            let b = ray.dot(c);
            let disc = b * b - a * (c.length_squared() - sphere.radius_m * sphere.radius_m);
            if disc < 0.0 {
                continue;
            }
            let t = (b - disc.sqrt()) / a;
            if t > 0.0 && t < nearest {
                nearest = t;
                value = sphere.radiance;
            }
        }
        value
    }

    /// True pixels of the target's points that lie in front of the camera, inside the image and
    /// on the side of the print the camera sees: what a perfect detector would return.
    pub fn visible_points(
        &self,
        geometry: &TargetGeometry,
        camera_from_target: &Rigid,
    ) -> Vec<(u32, DVec2)> {
        let normal = camera_from_target.transform_vector(DVec3::Z);
        geometry
            .ids()
            .iter()
            .zip(geometry.points())
            .filter_map(|(&id, &p)| {
                let p = camera_from_target.transform_point(p);
                if p.dot(normal) <= 0.0 {
                    return None;
                }
                let pixel = self.camera.project(p)?;
                self.camera.contains_pixel(pixel).then_some((id, pixel))
            })
            .collect()
    }
}

impl SynthCamera {
    /// The detection a perfect detector would return for a view: the true pixels of
    /// [`Self::visible_points`], no image needed.
    pub fn ideal_detection(
        &self,
        view: &str,
        geometry: &TargetGeometry,
        camera_from_target: &Rigid,
    ) -> Detection {
        let visible = self.visible_points(geometry, camera_from_target);
        Detection {
            view: view.to_owned(),
            width: self.camera.width(),
            height: self.camera.height(),
            ids: visible.iter().map(|&(id, _)| id).collect(),
            image_points: visible.iter().map(|&(_, pixel)| pixel).collect(),
            object_points: visible
                .iter()
                .filter_map(|&(id, _)| geometry.point(id))
                .collect(),
        }
    }
}

/// A detection with independent Gaussian noise of `sigma_px` on each coordinate of each point
/// (deterministic for a seed).
pub fn with_noise(detection: &Detection, sigma_px: f64, seed: u64) -> Detection {
    let mut rng = SplitMix64::new(seed);
    Detection {
        image_points: detection
            .image_points
            .iter()
            .map(|p| *p + sigma_px * DVec2::new(rng.gaussian(), rng.gaussian()))
            .collect(),
        ..detection.clone()
    }
}

struct PlacedPlane<'a> {
    geometry: &'a TargetGeometry,
    /// `target_from_camera` rotation and the camera's centre in the target frame.
    rotation: DMat3,
    origin: DVec3,
}

/// Separable Gaussian blur, edges clamped.
fn gaussian_blur(image: &mut [f64], w: usize, h: usize, sigma: f64) {
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-((k * k) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = kernel.iter().sum();
    let kernel: Vec<f64> = kernel.iter().map(|k| k / total).collect();
    let mut tmp = vec![0.0; image.len()];
    for j in 0..h {
        for i in 0..w {
            tmp[j * w + i] = kernel
                .iter()
                .enumerate()
                .map(|(k, weight)| {
                    let x = (i as isize + k as isize - radius).clamp(0, w as isize - 1) as usize;
                    weight * image[j * w + x]
                })
                .sum();
        }
    }
    for j in 0..h {
        for i in 0..w {
            image[j * w + i] = kernel
                .iter()
                .enumerate()
                .map(|(k, weight)| {
                    let y = (j as isize + k as isize - radius).clamp(0, h as isize - 1) as usize;
                    weight * tmp[y * w + i]
                })
                .sum();
        }
    }
}

/// SplitMix64 (Steele, Lea & Flood 2014): a tiny, good-enough generator for synthetic noise.
#[derive(Debug, Clone)]
struct SplitMix64(u64);

impl SplitMix64 {
    fn new(seed: u64) -> Self {
        Self(seed)
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        mix64(self.0)
    }

    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal by Box–Muller.
    fn gaussian(&mut self) -> f64 {
        let u = 1.0 - self.uniform();
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Two uniform numbers in [0, 1) from a seed, a pixel and a sample index.
fn hash2(seed: u64, pixel: u64, sample: u64) -> DVec2 {
    let z = mix64(seed ^ mix64(pixel.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ sample));
    let unit = |bits: u64| (bits & 0xffff_ffff) as f64 / 4_294_967_296.0;
    DVec2::new(unit(z), unit(z >> 32))
}

/// What [`plan_views`] aims for.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewPlan {
    pub count: usize,
    /// The target's angular width as a fraction of the image's smaller side (pinhole) or of the
    /// field of view (fish-eye).
    pub fill: f64,
    /// Largest tilt of the target away from facing the camera, degrees.
    pub max_tilt_deg: f64,
    /// Keep the target's outline this many pixels inside the image.
    pub margin_px: f64,
    /// Steepest angle between a line of sight and the target's normal, degrees (detectors
    /// lose a target seen more obliquely).
    pub max_incidence_deg: f64,
    /// Fish-eye: keep every point of the target this far from the optical axis, degrees
    /// (OpenCV's fish-eye model ends at 90°).
    pub max_theta_deg: f64,
}

impl Default for ViewPlan {
    fn default() -> Self {
        Self {
            count: 18,
            fill: 0.45,
            max_tilt_deg: 40.0,
            margin_px: 6.0,
            max_incidence_deg: 70.0,
            max_theta_deg: 84.0,
        }
    }
}

/// Poses (`camera_from_target`, optical frame) for a calibration: the target tilted up to
/// `max_tilt_deg` about both axes and turned, at varying distances, pushed as far as it fits
/// towards the image's corners and edges (pinhole) or rings out to the rim (fish-eye), so that
/// every part of the image, and for a fish-eye the largest angles it can see, hold corners.
pub fn plan_views(camera: &CameraModel, target: &TargetGeometry, plan: &ViewPlan) -> Vec<Rigid> {
    let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
    let outline = target.outline(8);
    let (lo, hi) = outline.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), &p| (lo.min(p), hi.max(p)),
    );
    let centre_in_target = 0.5 * (lo + hi);
    let width_m = (hi - lo).max_element();
    let k = camera.intrinsics();
    let (cx, cy) = (k.z_axis.x, k.z_axis.y);

    let (anchors, base_distance): (Vec<DVec3>, f64) = match camera {
        CameraModel::Pinhole(p) => {
            let reach = if target.partial_views() { 1.0 } else { 0.95 };
            let order = [
                (0.0, 0.0),
                (-1.0, -1.0),
                (1.0, 1.0),
                (1.0, -1.0),
                (-1.0, 1.0),
                (0.0, -1.0),
                (1.0, 0.0),
                (0.0, 1.0),
                (-1.0, 0.0),
            ];
            let anchors = order
                .iter()
                .filter_map(|&(ax, ay)| {
                    camera.unproject(DVec2::new(
                        cx + ax * reach * (w / 2.0),
                        cy + ay * reach * (h / 2.0),
                    ))
                })
                .collect();
            let distance = width_m * p.fx / (plan.fill * w.min(h));
            (anchors, distance)
        }
        CameraModel::KannalaBrandt(_) => {
            let field = fisheye_field_rad(camera).min(plan.max_theta_deg.to_radians());
            let mut anchors = vec![DVec3::Z];
            let ring = |theta: f64, count: usize, phase: f64| {
                (0..count).map(move |i| {
                    let phi = phase + std::f64::consts::TAU * i as f64 / count as f64;
                    DVec3::new(
                        theta.sin() * phi.cos(),
                        theta.sin() * phi.sin(),
                        theta.cos(),
                    )
                })
            };
            anchors.extend(ring(field, 8, 0.0));
            anchors.extend(ring(0.5 * field, 4, std::f64::consts::FRAC_PI_4));
            anchors.extend(ring(0.8 * field, 8, std::f64::consts::PI / 8.0));
            let angular_width = (plan.fill * 2.0 * field).clamp(0.2, 1.6);
            let distance = 0.5 * width_m / (0.5 * angular_width).tan();
            (anchors, distance)
        }
    };
    if anchors.is_empty() {
        return Vec::new();
    }

    let tilt = plan.max_tilt_deg.to_radians();
    let diagonal = std::f64::consts::FRAC_1_SQRT_2 * tilt;
    let tilts = [
        (tilt, 0.0),
        (0.0, tilt),
        (-tilt, 0.0),
        (0.0, -tilt),
        (diagonal, diagonal),
        (-diagonal, diagonal),
        (diagonal, -diagonal),
        (-diagonal, -diagonal),
        (0.3 * tilt, -0.3 * tilt),
    ];
    let rolls_deg: [f64; 7] = [0.0, 15.0, -15.0, 90.0, 30.0, -30.0, 180.0];
    let distance_factors = [1.0, 0.85, 1.2];

    // Targets whose points carry their own ids (ChArUco, AprilTag grids) are detected in part,
    // so they may hang over the image's edges and put points into its very corners; a
    // chessboard must be seen whole.
    let partial = target.partial_views();
    let margin = plan.margin_px;
    let in_image = |px: DVec2| {
        px.x >= margin - 0.5
            && px.y >= margin - 0.5
            && px.x <= w - 0.5 - margin
            && px.y <= h - 0.5 - margin
    };
    let fits_with = |pose: &Rigid, min_visible: f64| -> bool {
        let normal = pose.transform_vector(DVec3::Z);
        let max_cos_incidence = plan.max_incidence_deg.to_radians().cos();
        let min_cos_theta = plan.max_theta_deg.to_radians().cos();
        let fisheye = matches!(camera, CameraModel::KannalaBrandt(_));
        // The points stay within `max_theta_deg`; a partial target's margin may reach to
        // just short of 90° (behind which OpenCV's model cannot go).
        let outline_cos_theta = if partial {
            89.0f64.to_radians().cos()
        } else {
            min_cos_theta
        };
        if fisheye
            && target
                .points()
                .iter()
                .any(|&p| pose.transform_point(p).normalize_or_zero().z < min_cos_theta)
        {
            return false;
        }
        let outline_fits = outline.iter().all(|&p| {
            let p = pose.transform_point(p);
            let sight = p.normalize_or_zero();
            if fisheye && sight.z < outline_cos_theta {
                return false;
            }
            let pixel = camera.project(p).filter(|&px| in_image(px));
            if partial && pixel.is_none() {
                return true;
            }
            sight.dot(normal) >= max_cos_incidence && pixel.is_some()
        });
        if !outline_fits {
            return false;
        }
        if !partial {
            return true;
        }
        let points = target.points();
        let visible = points
            .iter()
            .filter(|&&p| {
                camera
                    .project(pose.transform_point(p))
                    .is_some_and(in_image)
            })
            .count();
        visible as f64 >= min_visible * points.len() as f64
    };
    let fits = |pose: &Rigid| fits_with(pose, PARTIAL_VIEW_FRACTION);

    let mut poses = Vec::with_capacity(plan.count);
    for view in 0..plan.count {
        let anchor = anchors[view % anchors.len()];
        let (tilt_x, tilt_y) = tilts[(view * 2 + view / anchors.len()) % tilts.len()];
        // Towards an image corner the target stays square to the image so that its own corner
        // can reach into the image's.
        let corner = anchor.x.abs() > 0.1 * anchor.z && anchor.y.abs() > 0.1 * anchor.z;
        let roll = if corner && matches!(camera, CameraModel::Pinhole(_)) {
            [0.0f64, 180.0, 90.0][(view / anchors.len()) % 3].to_radians()
        } else {
            rolls_deg[view % rolls_deg.len()].to_radians()
        };
        let mut distance = base_distance * distance_factors[view % distance_factors.len()];
        let orientation = |direction: DVec3| {
            DQuat::from_rotation_arc(DVec3::Z, direction)
                * DQuat::from_rotation_z(roll)
                * DQuat::from_rotation_x(tilt_x)
                * DQuat::from_rotation_y(tilt_y)
        };
        let pose_at = |direction: DVec3, distance: f64| {
            let rotation = orientation(direction);
            Rigid::new(rotation, direction * distance - rotation * centre_in_target)
        };
        for _ in 0..12 {
            if fits(&pose_at(DVec3::Z, distance)) {
                break;
            }
            distance *= 1.2;
        }
        // The largest step from the optical axis towards the anchor that still fits.
        let (mut inside, mut outside) = (0.0, 1.0);
        if fits(&pose_at(anchor, distance)) {
            inside = 1.0;
        } else {
            for _ in 0..24 {
                let mid = 0.5 * (inside + outside);
                if fits(&pose_at(DVec3::Z.slerp(anchor, mid), distance)) {
                    inside = mid;
                } else {
                    outside = mid;
                }
            }
        }
        let mut pose = pose_at(DVec3::Z.slerp(anchor, inside), distance);
        // A partially detectable target then slides, parallel to the image, until its point
        // nearest the image corner sits in that corner: corners of the image hold points.
        if partial && corner && matches!(camera, CameraModel::Pinhole(_)) {
            let corner_pixel = DVec2::new(
                if anchor.x < 0.0 { 0.0 } else { w - 1.0 },
                if anchor.y < 0.0 { 0.0 } else { h - 1.0 },
            );
            let inset = (plan.margin_px + 4.0) * DVec2::new(-anchor.x.signum(), -anchor.y.signum());
            let goal = corner_pixel + inset;
            let nearest = target
                .points()
                .iter()
                .map(|&p| pose.transform_point(p))
                .filter_map(|q| Some((q, camera.project(q)?)))
                .min_by(|a, b| a.1.distance(goal).total_cmp(&b.1.distance(goal)));
            if let (Some((q, _)), Some(ray)) = (nearest, camera.unproject(goal)) {
                let moved = ray / ray.z * q.z;
                let slid = Rigid::new(pose.rotation, pose.translation + (moved - q));
                if fits_with(&slid, CORNER_VIEW_FRACTION) {
                    pose = slid;
                }
            }
        }
        poses.push(pose);
    }
    poses
}

/// Fewest of a partially detectable target's points a view placed in an image corner keeps.
const CORNER_VIEW_FRACTION: f64 = 0.5;

/// Fewest of a partially detectable target's points a planned view keeps in the image.
const PARTIAL_VIEW_FRACTION: f64 = 0.85;

/// A fish-eye's field half-angle within the image: the smallest angle off the axis at the four
/// edge midpoints of the image (or the lens's own limit), radians.
pub fn fisheye_field_rad(camera: &CameraModel) -> f64 {
    let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
    let k = camera.intrinsics();
    let (cx, cy) = (k.z_axis.x, k.z_axis.y);
    let lens_limit = match camera {
        CameraModel::KannalaBrandt(kb) => kb.max_theta(),
        CameraModel::Pinhole(_) => std::f64::consts::FRAC_PI_2,
    };
    [
        DVec2::new(-0.5, cy),
        DVec2::new(w - 0.5, cy),
        DVec2::new(cx, -0.5),
        DVec2::new(cx, h - 0.5),
    ]
    .iter()
    .map(|&edge| {
        camera
            .unproject(edge)
            .map_or(lens_limit, |ray| ray.truncate().length().atan2(ray.z))
    })
    .fold(lens_limit, f64::min)
}

/// How far a recovered model's pixels lie from the truth's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelDifference {
    pub max_px: f64,
    pub rms_px: f64,
    /// Pixel of the largest difference.
    pub worst_pixel: DVec2,
    /// Pixels compared.
    pub samples: usize,
    /// Pixels whose true ray the recovered model cannot project (counted as infinitely far).
    pub unprojectable: usize,
    /// The rotation of the recovered camera frame that best aligns the two models, degrees
    /// (0 when not aligned).
    pub alignment_deg: f64,
}

/// How [`model_difference`] treats the camera frame's orientation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Alignment {
    /// Compare the models as they are.
    None,
    /// First rotate the rays by the small rotation that best aligns the models. Intrinsic
    /// calibration fixes the camera frame only up to such a rotation: a principal point off by
    /// δ pixels and every view's pose turned by δ / f radians explain the images equally well,
    /// so this compares what the images determine (focal length, distortion) and leaves the
    /// principal point to its own check.
    Rotation,
}

/// Projects, with `recovered`, the true ray of every `step_px`-th pixel of the image and
/// measures the distance to that pixel: the reprojection difference over the whole image.
/// Rays more than `max_theta_rad` off the optical axis are skipped (`None`: none skipped).
pub fn model_difference(
    truth: &CameraModel,
    recovered: &CameraModel,
    step_px: f64,
    max_theta_rad: Option<f64>,
    alignment: Alignment,
) -> ModelDifference {
    let (w, h) = (f64::from(truth.width()), f64::from(truth.height()));
    let step = step_px.max(0.5);
    let mut pairs = Vec::new();
    let mut y = -0.5;
    while y <= h - 0.5 {
        let mut x = -0.5;
        while x <= w - 0.5 {
            let pixel = DVec2::new(x, y);
            x += step;
            let Some(ray) = truth.unproject(pixel) else {
                continue;
            };
            if max_theta_rad.is_some_and(|max| ray.truncate().length().atan2(ray.z) > max) {
                continue;
            }
            pairs.push((ray, pixel));
        }
        y += step;
    }
    let rotation = match alignment {
        Alignment::None => DQuat::IDENTITY,
        Alignment::Rotation => best_rotation(recovered, &pairs),
    };
    let mut result = ModelDifference {
        max_px: 0.0,
        rms_px: 0.0,
        worst_pixel: DVec2::ZERO,
        samples: pairs.len(),
        unprojectable: 0,
        alignment_deg: rotation.angle_between(DQuat::IDENTITY).to_degrees(),
    };
    let mut sum_sq = 0.0;
    for (ray, pixel) in pairs {
        match recovered.project(rotation * ray) {
            Some(p) => {
                let d = p.distance(pixel);
                sum_sq += d * d;
                if d > result.max_px {
                    result.max_px = d;
                    result.worst_pixel = pixel;
                }
            }
            None => {
                result.unprojectable += 1;
                result.max_px = f64::INFINITY;
                result.worst_pixel = pixel;
            }
        }
    }
    result.rms_px = (sum_sq / result.samples.max(1) as f64).sqrt();
    result
}

/// The rotation `R` minimising `Σ |recovered.project(R ray) − pixel|²` (Gauss–Newton on the
/// rotation vector, numeric Jacobian, a subset of the pairs).
fn best_rotation(recovered: &CameraModel, pairs: &[(DVec3, DVec2)]) -> DQuat {
    let subset: Vec<&(DVec3, DVec2)> = pairs.iter().step_by((pairs.len() / 2000).max(1)).collect();
    let mut rotation = DQuat::IDENTITY;
    const H: f64 = 1e-7;
    for _ in 0..8 {
        let mut normal = [[0.0; 3]; 3];
        let mut rhs = [0.0; 3];
        for &&(ray, pixel) in &subset {
            let Some(base) = recovered.project(rotation * ray) else {
                continue;
            };
            let mut jacobian = [DVec2::ZERO; 3];
            let mut usable = true;
            for (axis, column) in jacobian.iter_mut().enumerate() {
                let mut delta = DVec3::ZERO;
                delta[axis] = H;
                match recovered.project(DQuat::from_scaled_axis(delta) * rotation * ray) {
                    Some(moved) => *column = (moved - base) / H,
                    None => usable = false,
                }
            }
            if !usable {
                continue;
            }
            let residual = pixel - base;
            for i in 0..3 {
                for j in 0..3 {
                    normal[i][j] += jacobian[i].dot(jacobian[j]);
                }
                rhs[i] += jacobian[i].dot(residual);
            }
        }
        let Some(step) = crate::linalg::solve(normal, rhs) else {
            break;
        };
        let step = DVec3::from(step);
        rotation = (DQuat::from_scaled_axis(step) * rotation).normalize();
        if step.length() < 1e-12 {
            break;
        }
    }
    rotation
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::target::{Chessboard, Target};
    use relight_core::camera::{KannalaBrandt, Pinhole};

    fn pinhole() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 160,
            height: 120,
            fx: 150.0,
            fy: 150.0,
            cx: 79.5,
            cy: 59.5,
            k1: -0.1,
            k2: 0.02,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })
    }

    fn board() -> TargetGeometry {
        Target::Chessboard(Chessboard {
            inner_cols: 5,
            inner_rows: 4,
            square_m: 0.02,
        })
        .geometry()
        .unwrap()
    }

    #[test]
    fn frontal_view_shows_the_print_where_the_model_projects_it() {
        let camera = SynthCamera::new(
            pinhole(),
            RenderSettings {
                supersample: 2,
                ..RenderSettings::default()
            },
        )
        .unwrap();
        let geometry = board();
        // Corner 0 straight ahead, 0.5 m away, board facing the camera.
        let pose = Rigid::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, 0.5));
        let image = camera.render_target(&geometry, &pose);
        let bytes = image.as_u8().unwrap();
        let level = |pixel: DVec2| bytes[pixel.y.round() as usize * 160 + pixel.x.round() as usize];
        // Centre of the square beyond corner 0 (black) and of its right neighbour (white).
        let black = camera
            .camera()
            .project(DVec3::new(-0.01, -0.01, 0.5))
            .unwrap();
        let white = camera
            .camera()
            .project(DVec3::new(0.01, -0.01, 0.5))
            .unwrap();
        assert!(level(black) < 30, "{}", level(black));
        assert!(level(white) > 200, "{}", level(white));
        // Off the sheet: background.
        let off = camera
            .camera()
            .project(DVec3::new(-0.1, -0.1, 0.5))
            .unwrap();
        assert!((60..100).contains(&level(off)), "{}", level(off));
        let visible = camera.visible_points(&geometry, &pose);
        assert_eq!(visible.len(), 20);
        // Seen from behind, no point is visible.
        let behind = Rigid::new(
            DQuat::from_rotation_y(std::f64::consts::PI),
            pose.translation,
        );
        assert!(camera.visible_points(&geometry, &behind).is_empty());
    }

    #[test]
    fn blur_and_noise_change_the_image_deterministically() {
        let settings = RenderSettings {
            supersample: 1,
            blur_sigma_px: 1.5,
            noise_sigma: 2.0,
            ..RenderSettings::default()
        };
        let camera = SynthCamera::new(pinhole(), settings).unwrap();
        let pose = Rigid::new(DQuat::IDENTITY, DVec3::new(-0.04, -0.03, 0.4));
        let a = camera.render_target(&board(), &pose);
        let b = camera.render_target(&board(), &pose);
        assert_eq!(a, b);
        let sharp = SynthCamera::new(pinhole(), RenderSettings::default())
            .unwrap()
            .render_target(&board(), &pose);
        assert_ne!(a, sharp);
    }

    #[test]
    fn planned_views_keep_the_target_inside_and_reach_the_corners() {
        let geometry = board();
        let camera = pinhole();
        let plan = ViewPlan::default();
        let poses = plan_views(&camera, &geometry, &plan);
        assert_eq!(poses.len(), plan.count);
        let synth = SynthCamera::new(camera, RenderSettings::default()).unwrap();
        // Some point lands within a fifth of the image's width and height of each corner.
        let mut reached = [false; 4];
        for pose in &poses {
            let visible = synth.visible_points(&geometry, pose);
            assert_eq!(visible.len(), geometry.ids().len(), "{pose:?}");
            for (_, p) in visible {
                let (left, right) = (p.x < 32.0, p.x > 127.0);
                let (top, bottom) = (p.y < 24.0, p.y > 95.0);
                for (corner, inside) in [left && top, right && top, left && bottom, right && bottom]
                    .into_iter()
                    .enumerate()
                {
                    reached[corner] |= inside;
                }
            }
        }
        assert_eq!(reached, [true; 4], "corners reached: {reached:?}");
    }

    #[test]
    fn fisheye_plan_reaches_the_rim() {
        let camera = CameraModel::KannalaBrandt(KannalaBrandt {
            width: 320,
            height: 240,
            fx: 75.0,
            fy: 75.0,
            cx: 159.5,
            cy: 119.5,
            k1: -0.01,
            k2: 0.005,
            k3: -0.002,
            k4: 0.0005,
        });
        let geometry = board();
        let plan = ViewPlan::default();
        let poses = plan_views(&camera, &geometry, &plan);
        let max_theta = poses
            .iter()
            .flat_map(|pose| {
                geometry
                    .points()
                    .iter()
                    .map(move |&p| pose.transform_point(p))
            })
            .map(|p| p.truncate().length().atan2(p.z).to_degrees())
            .fold(0.0, f64::max);
        assert!(max_theta > 75.0 && max_theta <= 84.0, "{max_theta}");
    }

    #[test]
    fn model_difference_sees_focal_changes_and_aligns_principal_point_shifts() {
        let truth = pinhole();
        let same = model_difference(&truth, &truth, 4.0, None, Alignment::Rotation);
        assert!(same.max_px < 1e-6 && same.samples > 1000, "{same:?}");
        let CameraModel::Pinhole(p) = truth else {
            unreachable!()
        };
        let longer = CameraModel::Pinhole(Pinhole { fx: 151.5, ..p });
        let diff = model_difference(&truth, &longer, 4.0, None, Alignment::None);
        // 1 % more focal length moves the image edge (80 px from the centre) by ~0.8 px, and
        // no rotation can undo that.
        assert!(diff.max_px > 0.7 && diff.max_px < 1.2, "{diff:?}");
        let aligned = model_difference(&truth, &longer, 4.0, None, Alignment::Rotation);
        assert!(
            aligned.max_px > 0.7 && aligned.alignment_deg < 1e-3,
            "{aligned:?}"
        );
        // A principal point δ = 0.5 px off is, to first order, a turn of δ / f = 0.19°; what
        // is left is second order, below (r / f)² δ = 0.22 px at the corners.
        let undistorted = Pinhole {
            k1: 0.0,
            k2: 0.0,
            ..p
        };
        let shifted = CameraModel::Pinhole(Pinhole {
            cx: 80.0,
            ..undistorted
        });
        let undistorted = CameraModel::Pinhole(undistorted);
        let raw = model_difference(&undistorted, &shifted, 4.0, None, Alignment::None);
        let aligned = model_difference(&undistorted, &shifted, 4.0, None, Alignment::Rotation);
        assert!((raw.max_px - 0.5).abs() < 1e-9, "{raw:?}");
        assert!(aligned.max_px < 0.5 * raw.max_px, "{aligned:?}");
        // The best turn matches δ / f to first order: the second-order terms (up to (r / f)² =
        // 0.44 of it at the corners) pull the least-squares turn by ~10 %.
        let turn_deg = (0.5f64 / 150.0).to_degrees();
        assert!(
            (aligned.alignment_deg - turn_deg).abs() < 0.2 * turn_deg,
            "{aligned:?}"
        );
    }
}
