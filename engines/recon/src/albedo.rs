//! Diffuse albedo of the real pixels from the reconstructed lights (DLPV, Franke 2013, eq. 1),
//! skipping shadowed and highlight pixels, smoothed over time.
//!
//! A Lambertian surface under irradiance E reflects radiance L_o = k_d/π · E, so per channel
//!
//! k_d = π · I_p / E(p),  E(p) = Σ_i V_i(p) E_i ⟨n_p, ω_i⟩₊ + E_env(n_p),
//!
//! where I_p is the pixel's linear radiance (the camera's response and exposure undone by a
//! [`ColorDecoding`]), E_i the irradiance light i delivers at normal incidence
//! ([`Light::incident`]), ω_i the direction to it, V_i ∈ [0, 1] its visibility (supplied by the
//! caller, see [`ShadowQuery`]), and E_env the irradiance of an environment light
//! ([`Light::environment_irradiance`]; not shadowed — its occlusion is not known per pixel).
//! DLPV's eq. 1 writes the same ratio with the π absorbed into the light's units.
//!
//! The ratio only holds where the lights are the light: the pixel's indirect light (bounces
//! off the rest of the real scene) is not in E unless the caller supplies it
//! ([`AlbedoInput::indirect_irradiance`], e.g. [`crate::bounce`]), and what it misses is read as
//! albedo. So pixels where the direct light is weak or blocked are skipped, as are pixels whose
//! colour is not diffuse reflection (see [`PixelClass`]); the indirect term only enters the
//! ratio, never the classification. A pixel that is skipped keeps its estimate from earlier
//! frames.
//!
//! Temporal smoothing is a per-pixel running mean that follows the surface: like the depth
//! merge ([`crate::temporal`]), each pixel's point is warped into the previous view and the
//! history of the nearest previous pixel is taken over when that pixel saw the same surface
//! (depth within `max_depth_difference`). A new estimate that differs from the mean by more
//! than `reset_relative_difference` restarts the pixel (the surface or its light changed); a
//! camera jump or changed intrinsics restart every pixel.

use std::f32::consts::PI;

use glam::{Vec2, Vec3};
use relight_core::camera::Pinhole;
use relight_core::light::{Incident, Light};
use relight_core::srgb::srgb_to_linear;
use relight_core::{Image, PixelFormat, Pose};

use crate::depth::{DepthError, DepthMap};
use crate::normals::{NormalMap, PositionMap};
use crate::temporal::{ResetReason, Warp, motion};

/// Why albedo cannot be estimated from the inputs.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AlbedoError {
    #[error("colour image is {format:?}; expected Rgb8")]
    ColorFormat { format: PixelFormat },
    #[error("{what} is {actual_width}×{actual_height}, but the colour image is {width}×{height}")]
    SizeMismatch {
        what: &'static str,
        width: u32,
        height: u32,
        actual_width: u32,
        actual_height: u32,
    },
    #[error(
        "inverse response needs 256 finite, non-negative entries and a positive exposure \
         (got {entries} entries, exposure {exposure})"
    )]
    BadDecoding { entries: usize, exposure: f32 },
    #[error("albedo setting `{setting}` {reason}")]
    Setting {
        setting: &'static str,
        reason: &'static str,
    },
    #[error(transparent)]
    Depth(#[from] DepthError),
}

/// 8-bit colour codes → linear radiance: `radiance = inverse_response[code] / exposure` per
/// channel.
///
/// `inverse_response` maps each code to the camera's relative linear exposure (what
/// photometric calibration recovers, e.g. Robertson's curve, or sRGB decoding for a camera that
/// writes sRGB); `exposure` is that exposure per unit scene radiance (exposure time × gain ×
/// the calibration's scale). With the wrong scale every albedo is off by the same factor.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorDecoding {
    inverse_response: Vec<f32>,
    exposure: f32,
}

impl ColorDecoding {
    /// A table of 256 finite, non-negative entries and a positive finite exposure.
    pub fn from_table(inverse_response: &[f32], exposure: f32) -> Result<Self, AlbedoError> {
        let table_ok = inverse_response.len() == 256
            && inverse_response.iter().all(|v| v.is_finite() && *v >= 0.0);
        if !(table_ok && exposure.is_finite() && exposure > 0.0) {
            return Err(AlbedoError::BadDecoding {
                entries: inverse_response.len(),
                exposure,
            });
        }
        Ok(Self {
            inverse_response: inverse_response.to_vec(),
            exposure,
        })
    }

    /// A camera writing sRGB-encoded codes (IEC 61966-2-1).
    pub fn srgb(exposure: f32) -> Result<Self, AlbedoError> {
        let table: Vec<f32> = (0..=255u8).map(srgb_to_linear).collect();
        Self::from_table(&table, exposure)
    }

    /// Linear radiance of one pixel's codes, W/(m²·sr).
    pub fn radiance(&self, codes: [u8; 3]) -> Vec3 {
        let channel = |c: u8| {
            self.inverse_response
                .get(usize::from(c))
                .copied()
                .unwrap_or(0.0)
        };
        Vec3::new(channel(codes[0]), channel(codes[1]), channel(codes[2])) / self.exposure
    }
}

/// What the caller's visibility function is asked: how much of light `light_index`'s direct
/// light reaches `point_in_world`, as a fraction in [0, 1] (1 = unoccluded, values between for
/// penumbrae; NaN counts as 0).
///
/// Answer it from whatever knows the occluders: a shadow ray against the proxy or depth mesh
/// (start it a little along `normal_in_world` to avoid hitting the surface itself, end it at
/// `incident.distance_m`), a lookup in a shadow map, or a per-pixel mask by `pixel_index`.
/// [`fully_visible`] answers 1 everywhere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadowQuery {
    /// Row-major index of the pixel in the colour image.
    pub pixel_index: usize,
    pub point_in_world: Vec3,
    /// Unit, facing the camera.
    pub normal_in_world: Vec3,
    /// Index into the lights passed in [`AlbedoInput::lights`].
    pub light_index: usize,
    pub incident: Incident,
}

/// A visibility function that sees no occluders.
pub fn fully_visible(_: &ShadowQuery) -> f32 {
    1.0
}

/// Settings of [`AlbedoEstimator`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlbedoSettings {
    /// A pixel with any channel at or above this code is clipped: its radiance is unknown.
    pub saturated_code: u8,
    /// Estimates above this in any channel are not diffuse reflection (a highlight, or light
    /// the model misses) and are skipped.
    pub max_albedo: f32,
    /// Pixels whose mirror direction of the view ray is within this angle of a visible light's
    /// direction are skipped as highlights. 15° covers the Phong lobe of a glossy surface
    /// (k_s = 0.4, n = 200: its term falls below 5 % of k_d = 0.5 at 15.5°).
    pub highlight_cone_rad: f32,
    /// Pixels that receive less than this share of their unoccluded direct light are in shadow
    /// or penumbra: there the unmodelled indirect light dominates.
    pub shadow_ratio: f32,
    /// Pixels whose direct irradiance (luminance) is below this share of the frame's 90th
    /// percentile are too dimly lit for the direct light to dominate. (A percentile rather than
    /// the maximum, so one pixel under the lamp does not decide for the frame.)
    pub min_relative_irradiance: f32,
    /// The running mean holds at most this many frames (older ones then fade exponentially).
    pub max_samples: u32,
    /// A new estimate further than this from the running mean (‖e − m‖ / ‖m‖) restarts the
    /// pixel.
    pub reset_relative_difference: f32,
    /// A previous pixel carries its history to the current one when their depths differ by at
    /// most this share of the depth.
    pub max_depth_difference: f32,
    /// Camera motion between two frames beyond which all history is dropped.
    pub max_translation_m: f32,
    pub max_rotation_rad: f32,
}

impl Default for AlbedoSettings {
    fn default() -> Self {
        Self {
            saturated_code: 250,
            max_albedo: 1.0,
            highlight_cone_rad: 15f32.to_radians(),
            shadow_ratio: 0.9,
            min_relative_irradiance: 0.05,
            max_samples: 30,
            reset_relative_difference: 0.3,
            max_depth_difference: 0.05,
            max_translation_m: 0.05,
            max_rotation_rad: 5f32.to_radians(),
        }
    }
}

impl AlbedoSettings {
    fn validate(&self) -> Result<(), AlbedoError> {
        let positive = |v: f32| v.is_finite() && v > 0.0;
        let fraction = |v: f32| (0.0..=1.0).contains(&v);
        let ok = positive(self.max_albedo)
            && self.highlight_cone_rad.is_finite()
            && self.highlight_cone_rad >= 0.0
            && fraction(self.shadow_ratio)
            && fraction(self.min_relative_irradiance)
            && self.max_samples >= 1
            && positive(self.reset_relative_difference)
            && positive(self.max_depth_difference)
            && positive(self.max_translation_m)
            && positive(self.max_rotation_rad);
        if ok {
            Ok(())
        } else {
            Err(AlbedoError::Setting {
                setting: "albedo",
                reason: "needs positive thresholds, shares in [0, 1] and max_samples ≥ 1",
            })
        }
    }
}

/// One frame's inputs, all registered to the colour camera's pixels.
#[derive(Debug, Clone, Copy)]
pub struct AlbedoInput<'a> {
    /// `Rgb8` codes.
    pub color: &'a Image,
    /// Filtered (and merged) geometry of the same frame, glTF camera frame.
    pub positions: &'a PositionMap,
    pub normals: &'a NormalMap,
    pub camera: &'a Pinhole,
    pub world_from_camera: Pose,
    /// The reconstructed lights, world frame.
    pub lights: &'a [Light],
    /// Indirect irradiance per pixel, W/m² (row-major; empty: none known), added to E.
    pub indirect_irradiance: &'a [Vec3],
}

/// What became of one pixel this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PixelClass {
    /// No depth or no normal.
    NoSurface,
    /// A channel at or above [`AlbedoSettings::saturated_code`].
    Saturated,
    /// Direct light below [`AlbedoSettings::min_relative_irradiance`] of the frame's reference.
    Unlit,
    /// Visible direct light below [`AlbedoSettings::shadow_ratio`] of the unoccluded.
    Shadowed,
    /// Mirror direction near a light.
    Highlight,
    /// k_d above [`AlbedoSettings::max_albedo`].
    AboveOne,
    Estimated,
}

/// How many pixels of a frame fell in each class, and how many restarted their history.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AlbedoCensus {
    pub no_surface: usize,
    pub saturated: usize,
    pub unlit: usize,
    pub shadowed: usize,
    pub highlight: usize,
    pub above_one: usize,
    pub estimated: usize,
    /// Estimated pixels whose history disagreed and was restarted.
    pub restarted: usize,
    /// Estimated pixels that continued a history.
    pub continued: usize,
}

impl AlbedoCensus {
    fn count(&mut self, class: PixelClass) {
        let counter = match class {
            PixelClass::NoSurface => &mut self.no_surface,
            PixelClass::Saturated => &mut self.saturated,
            PixelClass::Unlit => &mut self.unlit,
            PixelClass::Shadowed => &mut self.shadowed,
            PixelClass::Highlight => &mut self.highlight,
            PixelClass::AboveOne => &mut self.above_one,
            PixelClass::Estimated => &mut self.estimated,
        };
        *counter += 1;
    }
}

/// The albedo after one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct AlbedoFrame {
    pub width: u32,
    pub height: u32,
    /// Temporally smoothed k_d per pixel (linear RGB); `None` where no frame has estimated it.
    pub albedo: Vec<Option<Vec3>>,
    /// This frame's eq. 1 estimate alone, before smoothing.
    pub this_frame: Vec<Option<Vec3>>,
    pub class: Vec<PixelClass>,
    pub census: AlbedoCensus,
    /// `Some` when all history was dropped before this frame.
    pub reset: Option<ResetReason>,
}

/// k_d = π · L / E per channel (DLPV eq. 1 for a Lambertian surface); `None` unless every
/// channel of E is positive and the result is finite.
pub fn lambertian_albedo(radiance: Vec3, irradiance: Vec3) -> Option<Vec3> {
    if irradiance.min_element() > 0.0 {
        let albedo = PI * radiance / irradiance;
        albedo.is_finite().then_some(albedo)
    } else {
        None
    }
}

/// Direct irradiance at a surface point, with and without the caller's visibility, and whether
/// the mirror direction of the view ray is within the highlight cone of a visible light.
struct Lighting {
    visible: Vec3,
    unoccluded: Vec3,
    indirect: Vec3,
    mirror_hits_light: bool,
}

#[derive(Debug, Clone)]
struct History {
    world_from_camera: Pose,
    camera: Pinhole,
    depth: DepthMap,
    mean: Vec<Vec3>,
    count: Vec<u32>,
}

/// Per-pixel diffuse albedo with temporal smoothing; see the module docs.
#[derive(Debug, Clone)]
pub struct AlbedoEstimator {
    settings: AlbedoSettings,
    decoding: ColorDecoding,
    history: Option<History>,
}

/// Percentile of the frame's direct irradiance that [`AlbedoSettings::min_relative_irradiance`]
/// is relative to.
const REFERENCE_PERCENTILE: f32 = 0.9;

/// The `q`-quantile of `values` (reordered); 0 when empty.
fn percentile(values: &mut [f32], q: f32) -> f32 {
    if values.is_empty() {
        return 0.0;
    }
    let k = ((values.len() - 1) as f32 * q.clamp(0.0, 1.0)).round() as usize;
    let (_, value, _) = values.select_nth_unstable_by(k, f32::total_cmp);
    *value
}

fn luminance(rgb: Vec3) -> f32 {
    0.2126 * rgb.x + 0.7152 * rgb.y + 0.0722 * rgb.z
}

impl AlbedoEstimator {
    pub fn new(settings: AlbedoSettings, decoding: ColorDecoding) -> Self {
        Self {
            settings,
            decoding,
            history: None,
        }
    }

    pub fn settings(&self) -> &AlbedoSettings {
        &self.settings
    }

    pub fn decoding(&self) -> &ColorDecoding {
        &self.decoding
    }

    /// Forget every pixel's history.
    pub fn reset(&mut self) {
        self.history = None;
    }

    fn check_inputs(&self, input: &AlbedoInput) -> Result<(), AlbedoError> {
        self.settings.validate()?;
        let color = input.color;
        if color.format() != PixelFormat::Rgb8 {
            return Err(AlbedoError::ColorFormat {
                format: color.format(),
            });
        }
        let (width, height) = (color.width(), color.height());
        let n = color.pixel_count();
        let sizes = [
            ("camera", input.camera.width, input.camera.height, n),
            (
                "position map",
                input.positions.width,
                input.positions.height,
                input.positions.points_in_camera.len(),
            ),
            (
                "normal map",
                input.normals.width,
                input.normals.height,
                input.normals.normals_in_camera.len(),
            ),
        ];
        for (what, w, h, len) in sizes {
            if (w, h) != (width, height) || len != n {
                return Err(AlbedoError::SizeMismatch {
                    what,
                    width,
                    height,
                    actual_width: w,
                    actual_height: h,
                });
            }
        }
        Ok(())
    }

    fn lighting(
        &self,
        input: &AlbedoInput,
        pixel_index: usize,
        point_in_world: Vec3,
        normal_in_world: Vec3,
        visibility: &mut impl FnMut(&ShadowQuery) -> f32,
    ) -> Lighting {
        let eye = input.world_from_camera.translation;
        let to_eye = (eye - point_in_world).normalize_or_zero();
        let mirror = 2.0 * normal_in_world.dot(to_eye) * normal_in_world - to_eye;
        let cone_cos = self.settings.highlight_cone_rad.cos();
        let indirect = input
            .indirect_irradiance
            .get(pixel_index)
            .copied()
            .filter(|e| e.is_finite())
            .unwrap_or(Vec3::ZERO)
            .max(Vec3::ZERO);
        let mut lighting = Lighting {
            visible: Vec3::ZERO,
            unoccluded: Vec3::ZERO,
            indirect,
            mirror_hits_light: false,
        };
        for (light_index, light) in input.lights.iter().enumerate() {
            if let Some(environment) = light.environment_irradiance(normal_in_world) {
                let environment = environment.max(Vec3::ZERO);
                if environment.is_finite() {
                    lighting.visible += environment;
                    lighting.unoccluded += environment;
                }
                continue;
            }
            let Some(incident) = light.incident(point_in_world) else {
                continue;
            };
            let cos = normal_in_world.dot(incident.direction_to_light);
            let direct = incident.irradiance.max(Vec3::ZERO) * cos.max(0.0);
            if !(direct.is_finite() && direct.max_element() > 0.0) {
                continue;
            }
            let query = ShadowQuery {
                pixel_index,
                point_in_world,
                normal_in_world,
                light_index,
                incident,
            };
            let v = visibility(&query);
            let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
            lighting.unoccluded += direct;
            lighting.visible += direct * v;
            if v > 0.0 && mirror.dot(incident.direction_to_light) >= cone_cos {
                lighting.mirror_hits_light = true;
            }
        }
        lighting
    }

    /// Estimate this frame's albedo and fold it into the running mean. `visibility` answers
    /// [`ShadowQuery`]s (use [`fully_visible`] when nothing can occlude).
    pub fn estimate(
        &mut self,
        input: &AlbedoInput,
        mut visibility: impl FnMut(&ShadowQuery) -> f32,
    ) -> Result<AlbedoFrame, AlbedoError> {
        self.check_inputs(input)?;
        let codes = input.color.as_u8().unwrap_or(&[]);
        let n = input.color.pixel_count();
        let world_from_camera = input.world_from_camera;

        // Pass 1: direct lighting per pixel with a surface.
        let mut lit: Vec<Option<(Lighting, [u8; 3])>> = Vec::with_capacity(n);
        for i in 0..n {
            let surface =
                input.positions.points_in_camera[i].zip(input.normals.normals_in_camera[i]);
            let pixel = codes
                .get(3 * i..3 * i + 3)
                .and_then(|c| <[u8; 3]>::try_from(c).ok());
            let entry = surface.zip(pixel).map(|((point, normal), pixel)| {
                let point_in_world = world_from_camera.transform_point(point);
                let normal_in_world = world_from_camera
                    .transform_vector(normal)
                    .normalize_or_zero();
                let lighting =
                    self.lighting(input, i, point_in_world, normal_in_world, &mut visibility);
                (lighting, pixel)
            });
            lit.push(entry);
        }
        let mut irradiances: Vec<f32> = lit
            .iter()
            .flatten()
            .map(|(l, _)| luminance(l.visible))
            .filter(|e| e.is_finite())
            .collect();
        let reference = percentile(&mut irradiances, REFERENCE_PERCENTILE);

        // Pass 2: classify and apply eq. 1.
        let mut census = AlbedoCensus::default();
        let mut class = Vec::with_capacity(n);
        let mut this_frame = Vec::with_capacity(n);
        for entry in &lit {
            let (c, estimate) = self.classify(entry.as_ref(), reference);
            census.count(c);
            class.push(c);
            this_frame.push(estimate);
        }

        // Pass 3: temporal smoothing.
        let (width, height) = (input.color.width(), input.color.height());
        let depth = DepthMap {
            width,
            height,
            metres: input
                .positions
                .points_in_camera
                .iter()
                .map(|p| p.map_or(0.0, |p| -p.z))
                .collect(),
        };
        let reset = self.reset_reason(input.camera, &world_from_camera);
        let history = if reset.is_none() {
            self.history.take()
        } else {
            None
        };
        let warp = history.as_ref().map(|h| Warp {
            previous_from_current: h.world_from_camera.inverse() * world_from_camera,
            previous_camera: &h.camera,
        });
        let mut mean = vec![Vec3::ZERO; n];
        let mut count = vec![0u32; n];
        for i in 0..n {
            let previous = match (&history, &warp, input.positions.points_in_camera[i]) {
                (Some(h), Some(warp), Some(point)) => self.previous_of(h, warp, point),
                _ => None,
            };
            let (m, k) = match (this_frame[i], previous) {
                (Some(e), Some((m, k))) => {
                    let difference = (e - m).length() / m.length().max(1e-6);
                    if difference > self.settings.reset_relative_difference {
                        census.restarted += 1;
                        (e, 1)
                    } else {
                        census.continued += 1;
                        let k = (k + 1).min(self.settings.max_samples);
                        (m + (e - m) / k as f32, k)
                    }
                }
                (Some(e), None) => (e, 1),
                (None, Some((m, k))) => (m, k),
                (None, None) => (Vec3::ZERO, 0),
            };
            mean[i] = m;
            count[i] = k;
        }
        let albedo = mean
            .iter()
            .zip(&count)
            .map(|(m, k)| (*k > 0).then_some(*m))
            .collect();
        self.history = Some(History {
            world_from_camera,
            camera: *input.camera,
            depth,
            mean,
            count,
        });
        Ok(AlbedoFrame {
            width,
            height,
            albedo,
            this_frame,
            class,
            census,
            reset,
        })
    }

    fn classify(
        &self,
        entry: Option<&(Lighting, [u8; 3])>,
        reference: f32,
    ) -> (PixelClass, Option<Vec3>) {
        let settings = &self.settings;
        let Some((lighting, codes)) = entry else {
            return (PixelClass::NoSurface, None);
        };
        if codes.iter().any(|c| *c >= settings.saturated_code) {
            return (PixelClass::Saturated, None);
        }
        let visible = luminance(lighting.visible);
        let unoccluded = luminance(lighting.unoccluded);
        // Finite by construction: non-finite contributions are dropped in `lighting`.
        if unoccluded <= 0.0 {
            return (PixelClass::Unlit, None);
        }
        if visible < settings.shadow_ratio * unoccluded {
            return (PixelClass::Shadowed, None);
        }
        if visible <= settings.min_relative_irradiance * reference {
            return (PixelClass::Unlit, None);
        }
        if lighting.mirror_hits_light {
            return (PixelClass::Highlight, None);
        }
        let radiance = self.decoding.radiance(*codes);
        match lambertian_albedo(radiance, lighting.visible + lighting.indirect) {
            Some(k_d) if k_d.max_element() <= settings.max_albedo => {
                (PixelClass::Estimated, Some(k_d))
            }
            Some(_) => (PixelClass::AboveOne, None),
            None => (PixelClass::Unlit, None),
        }
    }

    /// The history of the previous pixel nearest to where `point_in_camera` lands in the
    /// previous view, if that pixel saw the same surface.
    fn previous_of(
        &self,
        history: &History,
        warp: &Warp,
        point_in_camera: Vec3,
    ) -> Option<(Vec3, u32)> {
        let landing = warp.land(point_in_camera)?;
        let nearest: Vec2 = landing.pixel.round();
        let (x, y) = (nearest.x as i64, nearest.y as i64);
        let (w, h) = (
            i64::from(history.depth.width),
            i64::from(history.depth.height),
        );
        if x < 0 || y < 0 || x >= w || y >= h {
            return None;
        }
        let j = (y * w + x) as usize;
        let k = *history.count.get(j)?;
        let previous_z = history.depth.get(x as u32, y as u32)?;
        let predicted_z = -landing.point_in_previous.z;
        let agrees =
            (previous_z - predicted_z).abs() <= self.settings.max_depth_difference * predicted_z;
        (k > 0 && agrees).then(|| (history.mean[j], k))
    }

    fn reset_reason(&self, camera: &Pinhole, world_from_camera: &Pose) -> Option<ResetReason> {
        let Some(history) = &self.history else {
            return Some(ResetReason::FirstFrame);
        };
        if history.camera != *camera {
            return Some(ResetReason::CameraChanged);
        }
        let Some((translation_m, rotation_rad)) =
            motion(&history.world_from_camera, world_from_camera)
        else {
            return Some(ResetReason::NonFinitePose);
        };
        (translation_m > self.settings.max_translation_m
            || rotation_rad > self.settings.max_rotation_rad)
            .then_some(ResetReason::PoseJump {
                translation_m,
                rotation_rad,
            })
    }
}
