//! The merged fish-eye probe resampled into an equirectangular [`EnvironmentMap`] in world
//! directions, through the calibrated Kannala–Brandt model and the probe's pose; and the map
//! geometry (texel directions, exact texel solid angles, energy) the other light modules share.
//!
//! Map convention ([`EnvironmentMap`]): +Y up, longitude `φ = atan2(x, −z)` from −Z towards +X
//! over the width, polar angle `θ` from +Y over the height; texel `(x, y)` covers
//! `φ ∈ [2π x / w, 2π (x + 1) / w]`, `θ ∈ [π y / h, π (y + 1) / h]`, so its solid angle is exactly
//! `(2π / w) (cos θ₀ − cos θ₁)`.
//!
//! Every function of the light modules reads a non-finite or negative radiance channel as zero,
//! so one bad texel cannot turn a light, an SH coefficient or an energy into NaN.

use glam::{DVec2, DVec3, Vec3};
use rayon::prelude::*;
use relight_core::Pose;
use relight_core::camera::{CameraError, KannalaBrandt, optical_from_gl};
use relight_core::scene::EnvironmentMap;

use crate::hdr::HdrImage;

/// Why a map cannot be built or read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EnvMapError {
    #[error("environment map size {width}×{height} is empty")]
    EmptyMap { width: u32, height: u32 },
    #[error("environment map {width}×{height} holds {len} texels")]
    MalformedMap { width: u32, height: u32, len: usize },
    #[error(
        "HDR probe image is {width}×{height} with {len} pixels, the lens is {lens_width}×{lens_height}"
    )]
    ProbeSize {
        width: u32,
        height: u32,
        len: usize,
        lens_width: u32,
        lens_height: u32,
    },
    #[error("probe lens: {0}")]
    Lens(#[from] CameraError),
    #[error("probe field of view {0}° is not in (0, 360]")]
    FieldOfView(f64),
}

/// Checks that `map` holds `width × height > 0` texels.
pub fn check_map(map: &EnvironmentMap) -> Result<(), EnvMapError> {
    if map.width == 0 || map.height == 0 {
        return Err(EnvMapError::EmptyMap {
            width: map.width,
            height: map.height,
        });
    }
    if map.radiance.len() != map.width as usize * map.height as usize {
        return Err(EnvMapError::MalformedMap {
            width: map.width,
            height: map.height,
            len: map.radiance.len(),
        });
    }
    Ok(())
}

/// World direction at polar angle `theta` from +Y and longitude `phi` (map convention).
pub fn direction(theta: f64, phi: f64) -> DVec3 {
    let (sin_theta, cos_theta) = theta.sin_cos();
    let (sin_phi, cos_phi) = phi.sin_cos();
    DVec3::new(sin_theta * sin_phi, cos_theta, -sin_theta * cos_phi)
}

/// Unit world direction through the centre of texel `(x, y)` of a `width × height` map.
pub fn texel_direction(width: u32, height: u32, x: u32, y: u32) -> Vec3 {
    let theta = std::f64::consts::PI * (f64::from(y) + 0.5) / f64::from(height);
    let phi = std::f64::consts::TAU * (f64::from(x) + 0.5) / f64::from(width);
    direction(theta, phi).as_vec3()
}

/// Exact solid angle (sr) of a texel in row `y` of a `width × height` map:
/// `(2π / w) (cos θ₀ − cos θ₁)`. The whole map sums to 4π.
pub fn texel_solid_angle(width: u32, height: u32, y: u32) -> f64 {
    let band = std::f64::consts::PI / f64::from(height);
    let (theta0, theta1) = (band * f64::from(y), band * f64::from(y + 1));
    std::f64::consts::TAU / f64::from(width) * (theta0.cos() - theta1.cos())
}

/// A radiance with every non-finite or negative channel replaced by zero.
pub fn sanitized(radiance: Vec3) -> Vec3 {
    Vec3::from_array(
        radiance
            .to_array()
            .map(|c| if c.is_finite() { c.max(0.0) } else { 0.0 }),
    )
}

/// `Σ L ΔΩ` over the map (f64 accumulation), W/m² per channel: the irradiance a surface would
/// receive if every direction shone on it head-on — what the lights of a median cut sum to.
pub fn map_energy(map: &EnvironmentMap) -> Result<Vec3, EnvMapError> {
    check_map(map)?;
    let w = map.width as usize;
    let total = map
        .radiance
        .par_chunks_exact(w)
        .enumerate()
        .map(|(y, row)| {
            let solid_angle = texel_solid_angle(map.width, map.height, y as u32);
            row.iter()
                .fold(DVec3::ZERO, |sum, &l| sum + sanitized(l).as_dvec3())
                * solid_angle
        })
        .reduce(|| DVec3::ZERO, |a, b| a + b);
    Ok(total.as_vec3())
}

/// How [`probe_to_environment`] resamples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvMapSettings {
    pub width: u32,
    pub height: u32,
    /// Full field of view of the probe's usable image circle, degrees: directions more than half
    /// of it from the optical axis are not seen. 180° by default (a 185° lens's rim is vignetted).
    pub field_of_view_deg: f64,
    /// Sample directions per texel along θ; `None` chooses about four per probe pixel (at the
    /// image centre), between 2 and 16. Along φ a row gets proportionally fewer (× sin θ).
    /// A probe image fine enough that a texel spans more than two pixels is first box-filtered
    /// (see [`probe_to_environment`]).
    pub samples_per_axis: Option<u32>,
}

impl Default for EnvMapSettings {
    fn default() -> Self {
        Self {
            width: 256,
            height: 128,
            field_of_view_deg: 180.0,
            samples_per_axis: None,
        }
    }
}

/// The probe's view of the world as an environment map.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeEnvironment {
    /// World-direction radiance, in the HDR image's units. Unseen directions are zero.
    pub map: EnvironmentMap,
    /// Fraction of each texel's solid angle the probe sees, in [0, 1] (row-major like the map).
    pub coverage: Vec<f32>,
}

/// A probe pixel's reconstruction weight is renormalised by at most this factor (see
/// [`probe_to_environment`]).
const MAX_RENORMALISATION: f64 = 4.0;

/// Resamples a merged probe image into a world-direction environment map.
///
/// Each texel is covered by stratified directions of equal solid angle (uniform in cos θ and φ);
/// a direction seen by the probe (within half the field of view of the optical axis, and inside
/// the lens model's valid field) is projected through the Kannala–Brandt model, from world to
/// probe by `world_from_probe` (glTF convention: the lens looks down its −Z), and the image is
/// read there bilinearly.
///
/// Energy: bilinear reconstruction conserves `Σ_p L_p ΔΩ_p` (`ΔΩ_p` the pixel's solid angle,
/// from the model's Jacobian) only in the limit of infinitely many samples; with a few per pixel
/// a one-pixel sun could gain or lose several percent. So each pixel's reconstruction weight is
/// renormalised: a first pass sums the solid angle `W_p` the samples give pixel `p`, the second
/// scales its contribution by `ΔΩ_p / W_p`, which makes the map's energy exactly the probe's for
/// every pixel away from the rim of the field of view. The first pass also counts samples up to
/// two pixels beyond the rim, so that the rim's cut is not "corrected": a pixel straddling it
/// keeps only the share of its energy that falls inside. The factor is capped at 4, for pixels at
/// the edge of the lens model's valid field that samples barely reach.
///
/// Resolution: the map cannot show detail finer than a texel, so a probe image fine enough that a
/// texel spans more than two of its pixels (a 1280 × 1024 probe against a 128 × 64 map) is first
/// box-filtered by an integer factor (energy-preserving, cropping fewer than `factor` rows and
/// columns at the right and bottom, outside any image circle) with the lens scaled to match;
/// the cost then stays that of a probe of about the map's resolution.
///
/// Unseen directions: a texel's radiance is the energy seen in it divided by its *whole* solid
/// angle, so the map holds exactly the energy the probe saw and nothing invented (below the
/// horizon of an upward probe is black); [`ProbeEnvironment::coverage`] says how much of each
/// texel was seen (divide by it for the radiance of the seen part).
pub fn probe_to_environment(
    hdr: &HdrImage,
    lens: &KannalaBrandt,
    world_from_probe: &Pose,
    settings: &EnvMapSettings,
) -> Result<ProbeEnvironment, EnvMapError> {
    ProbeResampler::new(lens, world_from_probe, settings)?.resample(hdr)
}

/// [`probe_to_environment`] for one lens, pose and map, with everything that depends on them
/// alone computed once: where each texel's sample directions land in the probe image, and the
/// pixels' renormalised weights, as one sparse weight per (texel, probe pixel). A probe fixed in
/// the room then costs a weighted sum per texel for each merged bracket. Projecting every
/// sample through the lens model had been most of a bracket's 70 ms on two cores, and ran on
/// every bracket although the lens and the pose never change.
#[derive(Debug, Clone)]
pub struct ProbeResampler {
    lens: KannalaBrandt,
    /// The box filter's factor (1: none) and the lens that sees the filtered image.
    factor: u32,
    filtered_lens: KannalaBrandt,
    width: u32,
    height: u32,
    /// Per texel, row-major: (filtered probe pixel, weight) pairs whose weighted sum of the
    /// pixels' radiance is the texel's energy, and the share of the texel the probe sees.
    weights: Vec<Vec<(u32, f64)>>,
    coverage: Vec<f32>,
}

impl ProbeResampler {
    pub fn new(
        lens: &KannalaBrandt,
        world_from_probe: &Pose,
        settings: &EnvMapSettings,
    ) -> Result<Self, EnvMapError> {
        lens.validate()?;
        let (width, height) = (settings.width, settings.height);
        if width == 0 || height == 0 {
            return Err(EnvMapError::EmptyMap { width, height });
        }
        let fov = settings.field_of_view_deg;
        if !(fov > 0.0 && fov <= 360.0) {
            return Err(EnvMapError::FieldOfView(fov));
        }
        let factor = downsampling_factor(lens, height);
        let filtered_lens = if factor > 1 {
            filtered_lens(lens, factor)
        } else {
            *lens
        };
        let sampler = Sampler::new(&filtered_lens, world_from_probe, settings, fov);
        let pixel_solid_angle = pixel_solid_angles(&filtered_lens);

        let rows: Vec<u32> = (0..height).collect();
        let chunk = (height as usize)
            .div_ceil(4 * rayon::current_num_threads().max(1))
            .max(1);
        let pixels = pixel_solid_angle.len();
        let reached = rows
            .par_chunks(chunk)
            .map(|rows| {
                let mut weights = vec![0.0f64; pixels];
                for &y in rows {
                    for x in 0..width {
                        sampler.for_each_sample(x, y, |sample| {
                            for (p, w) in sample.taps.into_iter().flatten() {
                                weights[p] += w * sample.solid_angle;
                            }
                        });
                    }
                }
                weights
            })
            .reduce(
                || vec![0.0f64; pixels],
                |mut a, b| {
                    for (x, y) in a.iter_mut().zip(b) {
                        *x += y;
                    }
                    a
                },
            );
        let renormalisation: Vec<f64> = pixel_solid_angle
            .iter()
            .zip(&reached)
            .map(|(&solid_angle, &w)| {
                if solid_angle > 0.0 && w > 0.0 {
                    (solid_angle / w).min(MAX_RENORMALISATION)
                } else {
                    1.0
                }
            })
            .collect();

        let texels: Vec<(Vec<(u32, f64)>, f32)> = (0..width as usize * height as usize)
            .into_par_iter()
            .map(|i| {
                let (x, y) = ((i % width as usize) as u32, (i / width as usize) as u32);
                let mut taps: Vec<(u32, f64)> = Vec::new();
                let mut seen = 0.0f64;
                let total = sampler.for_each_sample(x, y, |sample| {
                    if sample.seen {
                        seen += sample.solid_angle;
                        for (p, w) in sample.taps.into_iter().flatten() {
                            taps.push((p as u32, renormalisation[p] * w * sample.solid_angle));
                        }
                    }
                });
                taps.sort_unstable_by_key(|&(p, _)| p);
                let mut merged: Vec<(u32, f64)> = Vec::with_capacity(taps.len().min(64));
                for (p, w) in taps {
                    match merged.last_mut() {
                        Some((last, sum)) if *last == p => *sum += w,
                        _ => merged.push((p, w)),
                    }
                }
                merged.shrink_to_fit();
                let coverage = if total > 0.0 { seen / total } else { 0.0 };
                (merged, coverage.clamp(0.0, 1.0) as f32)
            })
            .collect();
        let (weights, coverage) = texels.into_iter().unzip();
        Ok(Self {
            lens: *lens,
            factor,
            filtered_lens,
            width,
            height,
            weights,
            coverage,
        })
    }

    /// The environment map of one merged probe image (as [`probe_to_environment`]).
    pub fn resample(&self, hdr: &HdrImage) -> Result<ProbeEnvironment, EnvMapError> {
        check_probe_size(hdr, &self.lens)?;
        let filtered;
        let hdr = if self.factor > 1 {
            filtered = box_filtered(hdr, &self.filtered_lens, self.factor);
            &filtered
        } else {
            hdr
        };
        let radiance: Vec<DVec3> = hdr
            .radiance
            .iter()
            .map(|&l| sanitized(l).as_dvec3())
            .collect();
        let (width, height) = (self.width, self.height);
        let radiance = self
            .weights
            .par_iter()
            .enumerate()
            .map(|(i, taps)| {
                let energy = taps
                    .iter()
                    .fold(DVec3::ZERO, |sum, &(p, w)| sum + radiance[p as usize] * w);
                let texel = texel_solid_angle(width, height, (i / width as usize) as u32);
                sanitized((energy / texel).as_vec3())
            })
            .collect();
        Ok(ProbeEnvironment {
            map: EnvironmentMap {
                width,
                height,
                radiance,
            },
            coverage: self.coverage.clone(),
        })
    }
}

/// That `hdr` is the size of the image `lens` sees, and holds a value per pixel.
fn check_probe_size(hdr: &HdrImage, lens: &KannalaBrandt) -> Result<(), EnvMapError> {
    if (hdr.width, hdr.height) != (lens.width, lens.height)
        || hdr.radiance.len() != hdr.width as usize * hdr.height as usize
    {
        return Err(EnvMapError::ProbeSize {
            width: hdr.width,
            height: hdr.height,
            len: hdr.radiance.len(),
            lens_width: lens.width,
            lens_height: lens.height,
        });
    }
    Ok(())
}

/// Most probe pixels a texel may span (along θ) before the probe image is box-filtered.
const MAX_PIXELS_PER_TEXEL: f64 = 2.0;

/// Integer factor by which to box-filter the probe image so that a texel of a map `height` rows
/// high spans at most [`MAX_PIXELS_PER_TEXEL`] pixels at the image centre (1: none).
fn downsampling_factor(lens: &KannalaBrandt, height: u32) -> u32 {
    let texel_px = std::f64::consts::PI / f64::from(height) * lens.fx.max(lens.fy);
    let factor = (texel_px / MAX_PIXELS_PER_TEXEL).floor().max(1.0);
    (factor as u32).min(lens.width.min(lens.height).max(1))
}

/// The lens that sees the image box-filtered by `factor` ([`box_filtered`]).
fn filtered_lens(lens: &KannalaBrandt, factor: u32) -> KannalaBrandt {
    let (width, height) = (lens.width / factor, lens.height / factor);
    let cropped = KannalaBrandt {
        width: width * factor,
        height: height * factor,
        ..*lens
    };
    cropped.resized(width, height)
}

/// The image box-filtered by `factor` into `filtered`'s size (each pixel the mean of
/// `factor²`, which keeps `Σ L ΔΩ`), cropped to a multiple of `factor`.
fn box_filtered(hdr: &HdrImage, filtered: &KannalaBrandt, factor: u32) -> HdrImage {
    let (width, height) = (filtered.width, filtered.height);
    let k = factor as usize;
    let old_width = hdr.width as usize;
    let radiance = (0..width as usize * height as usize)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % width as usize, i / width as usize);
            let mut sum = DVec3::ZERO;
            for dy in 0..k {
                let row = (y * k + dy) * old_width + x * k;
                for l in &hdr.radiance[row..row + k] {
                    sum += sanitized(*l).as_dvec3();
                }
            }
            (sum / (k * k) as f64).as_vec3()
        })
        .collect();
    HdrImage {
        width,
        height,
        radiance,
        saturated: vec![false; width as usize * height as usize],
    }
}

/// Bilinear taps: up to four (pixel index, weight).
type Taps = [Option<(usize, f64)>; 4];

/// One sample direction of a texel that lands in the probe image.
struct Sample {
    taps: Taps,
    /// Solid angle (sr) the sample stands for.
    solid_angle: f64,
    /// Within the field of view (otherwise only within the margin beyond it).
    seen: bool,
}

/// How far beyond the field of view the first pass samples, in probe pixels at the image centre
/// (a bilinear tent reaches one pixel; one more for the stretch of the lens).
const RIM_MARGIN_PX: f64 = 2.0;

/// Where each texel's sample directions land in the probe image.
struct Sampler<'a> {
    lens: &'a KannalaBrandt,
    probe_from_world: Pose,
    width: u32,
    height: u32,
    cos_half_fov: f64,
    /// Cosine of the half field of view plus the rim margin.
    cos_reach: f64,
    samples_theta: u32,
    /// Optical axis in world directions and the reach (half field of view plus margin), for
    /// culling texels.
    axis_in_world: DVec3,
    reach: f64,
}

impl<'a> Sampler<'a> {
    fn new(
        lens: &'a KannalaBrandt,
        world_from_probe: &Pose,
        settings: &EnvMapSettings,
        fov_deg: f64,
    ) -> Self {
        let half_fov = (fov_deg / 2.0).to_radians();
        let texel_angle = std::f64::consts::PI / f64::from(settings.height);
        let pixel_angle = 1.0 / lens.fx.max(lens.fy);
        let samples_theta = settings
            .samples_per_axis
            .unwrap_or_else(|| (4.0 * texel_angle / pixel_angle).ceil().clamp(2.0, 16.0) as u32)
            .max(1);
        let reach = (half_fov + RIM_MARGIN_PX / lens.fx.min(lens.fy)).min(std::f64::consts::PI);
        Self {
            lens,
            probe_from_world: world_from_probe.inverse(),
            width: settings.width,
            height: settings.height,
            cos_half_fov: half_fov.cos(),
            cos_reach: reach.cos(),
            samples_theta,
            axis_in_world: world_from_probe
                .transform_vector(-Vec3::Z)
                .as_dvec3()
                .normalize(),
            reach,
        }
    }

    /// Calls `visit` for each sample direction of texel `(x, y)` that lands in the probe image
    /// within the reach; returns the texel's solid angle (all its samples, landing or not).
    fn for_each_sample(&self, x: u32, y: u32, mut visit: impl FnMut(Sample)) -> f64 {
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        let band = std::f64::consts::PI / h;
        let (theta0, theta1) = (band * f64::from(y), band * f64::from(y + 1));
        let (z0, z1) = (theta0.cos(), theta1.cos());
        let d_phi = std::f64::consts::TAU / w;
        let phi0 = d_phi * f64::from(x);
        let texel_solid_angle = d_phi * (z0 - z1);
        // Cull texels entirely out of reach (centre angle minus the half-diagonal).
        let centre = direction(0.5 * (theta0 + theta1), phi0 + 0.5 * d_phi);
        let max_sin =
            if theta0 < std::f64::consts::FRAC_PI_2 && theta1 > std::f64::consts::FRAC_PI_2 {
                1.0
            } else {
                theta0.sin().max(theta1.sin())
            };
        let half_diagonal = 0.5 * (band + d_phi * max_sin);
        if centre.dot(self.axis_in_world).clamp(-1.0, 1.0).acos() > self.reach + half_diagonal {
            return texel_solid_angle;
        }
        let n_theta = self.samples_theta;
        let n_phi = ((f64::from(n_theta) * max_sin * d_phi / band).ceil() as u32).max(1);
        let solid_angle = texel_solid_angle / f64::from(n_theta * n_phi);
        for i in 0..n_theta {
            let z = z0 + (z1 - z0) * (f64::from(i) + 0.5) / f64::from(n_theta);
            let theta = z.clamp(-1.0, 1.0).acos();
            for j in 0..n_phi {
                let phi = phi0 + d_phi * (f64::from(j) + 0.5) / f64::from(n_phi);
                if let Some((taps, seen)) = self.taps(direction(theta, phi)) {
                    visit(Sample {
                        taps,
                        solid_angle,
                        seen,
                    });
                }
            }
        }
        texel_solid_angle
    }

    /// Bilinear taps of the probe pixel that sees world direction `dir`, and whether it is seen
    /// (within the field of view and the image); `None` beyond the reach or outside the model's
    /// valid field.
    fn taps(&self, dir_in_world: DVec3) -> Option<(Taps, bool)> {
        let dir_in_probe = self
            .probe_from_world
            .transform_vector(dir_in_world.as_vec3())
            .as_dvec3();
        let ray_in_optical = optical_from_gl(dir_in_probe).normalize();
        if ray_in_optical.z < self.cos_reach {
            return None;
        }
        let pixel = self.lens.project(ray_in_optical)?;
        Some((
            bilinear_taps(pixel, self.lens.width, self.lens.height),
            ray_in_optical.z >= self.cos_half_fov && self.lens.contains_pixel(pixel),
        ))
    }
}

/// Bilinear weights of the (up to) four pixels around `pixel` (centres at integer coordinates);
/// neighbours outside the image are left out.
fn bilinear_taps(pixel: DVec2, width: u32, height: u32) -> Taps {
    let (x0, y0) = (pixel.x.floor(), pixel.y.floor());
    let (fx, fy) = (pixel.x - x0, pixel.y - y0);
    let tap = |dx: f64, dy: f64, weight: f64| {
        let (x, y) = (x0 + dx, y0 + dy);
        let inside = x >= 0.0 && y >= 0.0 && x < f64::from(width) && y < f64::from(height);
        (inside && weight > 0.0).then(|| (y as usize * width as usize + x as usize, weight))
    };
    [
        tap(0.0, 0.0, (1.0 - fx) * (1.0 - fy)),
        tap(1.0, 0.0, fx * (1.0 - fy)),
        tap(0.0, 1.0, (1.0 - fx) * fy),
        tap(1.0, 1.0, fx * fy),
    ]
}

/// Solid angle (sr) of every probe pixel: `|∂ω/∂u × ∂ω/∂v|` by central differences over the
/// pixel (unit steps), zero where the model has no ray.
fn pixel_solid_angles(lens: &KannalaBrandt) -> Vec<f64> {
    let width = lens.width as usize;
    (0..width * lens.height as usize)
        .into_par_iter()
        .map(|i| {
            let centre = DVec2::new((i % width) as f64, (i / width) as f64);
            let ray = |dx: f64, dy: f64| lens.unproject(centre + DVec2::new(dx, dy));
            match (ray(0.5, 0.0), ray(-0.5, 0.0), ray(0.0, 0.5), ray(0.0, -0.5)) {
                (Some(r), Some(l), Some(d), Some(u)) => (r - l).cross(d - u).length(),
                _ => 0.0,
            }
        })
        .collect()
}

/// Energy `Σ_p L_p ΔΩ_p` (per channel) of the probe pixels whose centre is seen within half of
/// `field_of_view_deg` of the optical axis: what [`probe_to_environment`] preserves.
pub fn probe_energy(
    hdr: &HdrImage,
    lens: &KannalaBrandt,
    field_of_view_deg: f64,
) -> Result<Vec3, EnvMapError> {
    lens.validate()?;
    check_probe_size(hdr, lens)?;
    let cos_half_fov = (field_of_view_deg / 2.0).to_radians().cos();
    let width = lens.width as usize;
    let solid_angles = pixel_solid_angles(lens);
    let total = hdr
        .radiance
        .iter()
        .zip(solid_angles)
        .enumerate()
        .filter(|(i, _)| {
            let pixel = DVec2::new((i % width) as f64, (i / width) as f64);
            lens.unproject(pixel)
                .is_some_and(|ray| ray.z >= cos_half_fov)
        })
        .fold(DVec3::ZERO, |sum, (_, (&l, solid_angle))| {
            sum + sanitized(l).as_dvec3() * solid_angle
        });
    Ok(total.as_vec3())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texel_solid_angles_sum_to_the_sphere() {
        for (w, h) in [(64, 32), (7, 5), (256, 128)] {
            let total: f64 = (0..h)
                .map(|y| texel_solid_angle(w, h, y) * f64::from(w))
                .sum();
            assert!(
                (total - 4.0 * std::f64::consts::PI).abs() < 1e-9,
                "{w}×{h}: {total}"
            );
        }
    }

    #[test]
    fn texel_directions_follow_the_map_convention() {
        // u = 0.5 is +Z (φ = π), the top row is near +Y, u = 0.25 is +X.
        let d = texel_direction(5, 2, 2, 1);
        assert!(d.z > 0.0 && d.x.abs() < 1e-6 && d.y < 0.0);
        assert!(texel_direction(64, 32, 16, 0).y > 0.99);
        assert!(texel_direction(64, 32, 16, 16).x > 0.99);
    }

    #[test]
    fn bilinear_taps_sum_to_one_inside() {
        let taps = bilinear_taps(DVec2::new(2.25, 3.5), 8, 8);
        let sum: f64 = taps.iter().flatten().map(|(_, w)| w).sum();
        assert!((sum - 1.0).abs() < 1e-12);
        assert_eq!(taps[0], Some((3 * 8 + 2, 0.375)));
        let corner = bilinear_taps(DVec2::new(-0.25, -0.25), 8, 8);
        assert_eq!(corner.iter().flatten().count(), 1);
    }
}
