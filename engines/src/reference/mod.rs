//! The reference: a CPU path tracer of L^μ (real scene only), L^ρ (real + virtual) and
//! Δ = L^ρ − L^μ, the ground truth every engine is scored against.
//!
//! Both images come from the same random numbers per pixel sample (correlated sampling), so Δ
//! is exactly zero wherever the virtual object does not touch a path, and its variance is
//! that of the object's influence alone rather than of two independent renders. Δ's mean and
//! variance are accumulated per sample (Welford), so [`ReferenceImages::delta_std_error`] is
//! the standard error of the Δ estimate itself; tests use it to know how converged a render is.

mod accel;
mod brdf;
mod integrator;
mod sampling;

use std::f32::consts::PI;

use glam::Vec3;
use rayon::prelude::*;
use relight_core::scene::Scene;

use self::accel::Geometry;
use self::integrator::{PathContext, radiance};
use self::sampling::{EnvSampler, SampleRng};

/// How the reference renders.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceSettings {
    pub spp: u32,
    /// Bounces after the first hit (0 = direct light only).
    pub max_bounces: u32,
    /// Russian roulette from this bounce on.
    pub rr_start_bounce: u32,
    pub seed: u64,
    /// Jitter camera rays within the pixel (antialiasing); off gives pixel-centre rays.
    pub pixel_jitter: bool,
    /// Render size; the scene camera's when `None`.
    pub size: Option<(u32, u32)>,
}

impl Default for ReferenceSettings {
    fn default() -> Self {
        Self {
            spp: 64,
            max_bounces: 8,
            rr_start_bounce: 3,
            seed: 0,
            pixel_jitter: true,
            size: None,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReferenceError {
    #[error("reference render size {width}×{height} is empty")]
    EmptyImage { width: u32, height: u32 },
    #[error("camera vertical field of view {yfov_rad} rad is not in (0, π)")]
    BadFieldOfView { yfov_rad: f32 },
}

/// Per-pixel means and standard errors after `spp` samples, row-major from the top-left.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceImages {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub l_rho: Vec<Vec3>,
    pub l_mu: Vec<Vec3>,
    pub delta: Vec<Vec3>,
    pub delta_std_error: Vec<Vec3>,
    pub l_rho_std_error: Vec<Vec3>,
    /// True where the pixel centre sees the virtual object first (virtual pixels).
    pub virtual_mask: Vec<bool>,
}

/// Running mean and variance (Welford) of one RGB quantity, in f64.
#[derive(Debug, Clone, Copy, Default)]
struct Welford {
    mean: [f64; 3],
    m2: [f64; 3],
}

impl Welford {
    fn add(&mut self, n: u32, x: Vec3) {
        for (c, v) in x.to_array().into_iter().enumerate() {
            let v = f64::from(v);
            let delta = v - self.mean[c];
            self.mean[c] += delta / f64::from(n);
            self.m2[c] += delta * (v - self.mean[c]);
        }
    }
    fn mean(&self) -> Vec3 {
        Vec3::new(
            self.mean[0] as f32,
            self.mean[1] as f32,
            self.mean[2] as f32,
        )
    }
    fn std_error(&self, n: u32) -> Vec3 {
        if n < 2 {
            return Vec3::splat(f32::INFINITY);
        }
        let n = f64::from(n);
        let se = |m2: f64| ((m2 / (n - 1.0)) / n).sqrt() as f32;
        Vec3::new(se(self.m2[0]), se(self.m2[1]), se(self.m2[2]))
    }
}

#[derive(Debug, Clone, Copy, Default)]
struct PixelStats {
    rho: Welford,
    mu: Welford,
    delta: Welford,
}

/// A progressive reference render: add samples, read the images at any time.
#[derive(Debug)]
pub struct ReferenceRenderer {
    scene: Scene,
    full: Geometry,
    /// `None` when the scene has no virtual object (then L^μ uses `full`).
    real: Option<Geometry>,
    env: Option<EnvSampler>,
    settings: ReferenceSettings,
    width: u32,
    height: u32,
    spp: u32,
    stats: Vec<PixelStats>,
    virtual_mask: Vec<bool>,
}

impl ReferenceRenderer {
    pub fn new(scene: &Scene, settings: ReferenceSettings) -> Result<Self, ReferenceError> {
        let (width, height) = settings
            .size
            .unwrap_or((scene.camera.width, scene.camera.height));
        if width == 0 || height == 0 {
            return Err(ReferenceError::EmptyImage { width, height });
        }
        let yfov_rad = scene.camera.yfov_rad;
        if !(yfov_rad > 0.0 && yfov_rad < PI) {
            return Err(ReferenceError::BadFieldOfView { yfov_rad });
        }
        let has_virtual = scene.meshes.iter().any(|m| m.is_virtual);
        let full = Geometry::new(scene, true);
        let real = has_virtual.then(|| Geometry::new(scene, false));
        let mut renderer = Self {
            scene: scene.clone(),
            full,
            real,
            env: scene.environment.as_ref().and_then(EnvSampler::new),
            settings,
            width,
            height,
            spp: 0,
            stats: vec![PixelStats::default(); width as usize * height as usize],
            virtual_mask: Vec::new(),
        };
        renderer.virtual_mask = (0..width * height)
            .map(|i| {
                let (origin, dir) = renderer.camera_ray(i % width, i / width, 0.5, 0.5);
                renderer
                    .full
                    .intersect(origin, dir, 0.0, f32::INFINITY)
                    .and_then(|hit| renderer.full.triangles().get(hit.triangle))
                    .is_some_and(|tri| tri.is_virtual)
            })
            .collect();
        Ok(renderer)
    }

    /// World-space ray through pixel (x, y) at sub-pixel offset (jx, jy) ∈ [0, 1)².
    fn camera_ray(&self, x: u32, y: u32, jx: f32, jy: f32) -> (Vec3, Vec3) {
        let camera = &self.scene.camera;
        let tan_half = (camera.yfov_rad / 2.0).tan();
        let aspect = self.width as f32 / self.height as f32;
        let ndc_x = (2.0 * (x as f32 + jx) / self.width as f32 - 1.0) * tan_half * aspect;
        let ndc_y = (1.0 - 2.0 * (y as f32 + jy) / self.height as f32) * tan_half;
        let dir_in_camera = Vec3::new(ndc_x, ndc_y, -1.0).normalize();
        (
            camera.world_from_camera.translation,
            camera
                .world_from_camera
                .transform_vector(dir_in_camera)
                .normalize(),
        )
    }

    /// Trace `n` more samples per pixel (in parallel over rows).
    pub fn add_samples(&mut self, n: u32) {
        let (width, first, seed, jitter) = (
            self.width,
            self.spp,
            self.settings.seed,
            self.settings.pixel_jitter,
        );
        let mut stats = std::mem::take(&mut self.stats);
        {
            let this = &*self;
            let ctx = PathContext {
                scene: &this.scene,
                env: this.env.as_ref(),
                max_bounces: this.settings.max_bounces,
                rr_start_bounce: this.settings.rr_start_bounce,
            };
            let full = &this.full;
            let real = this.real.as_ref().unwrap_or(full);
            stats
                .par_chunks_mut(width as usize)
                .enumerate()
                .for_each(|(y, row)| {
                    for (x, pixel) in row.iter_mut().enumerate() {
                        let pixel_index = y as u64 * u64::from(width) + x as u64;
                        for s in first..first + n {
                            let mut rng = SampleRng::new(seed, pixel_index, u64::from(s));
                            let (jx, jy) = if jitter {
                                (rng.next(), rng.next())
                            } else {
                                (0.5, 0.5)
                            };
                            let (origin, dir) = this.camera_ray(x as u32, y as u32, jx, jy);
                            let mut rng_mu = rng.clone();
                            let l_rho = radiance(&ctx, full, origin, dir, &mut rng);
                            let l_mu = radiance(&ctx, real, origin, dir, &mut rng_mu);
                            pixel.rho.add(s + 1, l_rho);
                            pixel.mu.add(s + 1, l_mu);
                            pixel.delta.add(s + 1, l_rho - l_mu);
                        }
                    }
                });
        }
        self.stats = stats;
        self.spp += n;
    }

    pub fn spp(&self) -> u32 {
        self.spp
    }

    pub fn images(&self) -> ReferenceImages {
        let n = self.spp;
        ReferenceImages {
            width: self.width,
            height: self.height,
            spp: n,
            l_rho: self.stats.iter().map(|p| p.rho.mean()).collect(),
            l_mu: self.stats.iter().map(|p| p.mu.mean()).collect(),
            delta: self.stats.iter().map(|p| p.delta.mean()).collect(),
            delta_std_error: self.stats.iter().map(|p| p.delta.std_error(n)).collect(),
            l_rho_std_error: self.stats.iter().map(|p| p.rho.std_error(n)).collect(),
            virtual_mask: self.virtual_mask.clone(),
        }
    }
}

/// Render `settings.spp` samples per pixel.
pub fn render_reference(
    scene: &Scene,
    settings: ReferenceSettings,
) -> Result<ReferenceImages, ReferenceError> {
    let mut renderer = ReferenceRenderer::new(scene, settings)?;
    renderer.add_samples(settings.spp);
    Ok(renderer.images())
}
