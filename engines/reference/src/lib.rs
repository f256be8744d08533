//! The reference: a CPU path tracer of L^μ (real scene only), L^ρ (real + virtual) and
//! Δ = L^ρ − L^μ, the ground truth every engine is scored against.
//!
//! Both images come from the same random numbers per pixel sample (correlated sampling), so Δ
//! is exactly zero wherever the virtual object does not touch a path, and its variance is
//! that of the object's influence alone rather than of two independent renders. Δ's mean and
//! variance are accumulated per sample (Welford), so [`ReferenceImages::delta_std_error`] is
//! the standard error of the Δ estimate itself; tests use it to know how converged a render is.
//!
//! What it models, and where it stops:
//! - Camera: [`relight_core::scene::SceneCamera`], glTF convention (−Z forward, +Y up, vertical
//!   field of view, aspect = width/height); pixel (0, 0) is top-left; rays jittered in the pixel.
//! - Reflectance: Lambert k_d/π plus normalised Phong k_s (n+1)/(2π) cosⁿα, α measured from the
//!   mirror direction, as [`relight_core::scene::Material`] documents. (The reflection-map paper
//!   divides the Phong term by |n·ω_i|; the scene format fixes the form without that division.)
//!   Sampling picks a lobe in proportion to the lobes' albedos (luminance), then
//!   cosine-weighted or Phong-lobe directions; the pdf is the mixture of both.
//! - Light: next-event estimation with shadow rays for point, spot and directional lights, and
//!   for the environment map, which is importance-sampled by luminance × sin θ (piecewise
//!   constant: marginal over rows, conditional per row) and combined with BSDF-sampled escapes by
//!   MIS with the power heuristic, so a 1e4:1 window makes no fireflies. The map is looked up
//!   nearest-texel (piecewise constant), matching the sampling density. Emissive materials are
//!   not light-sampled: their emission counts where camera and BSDF rays hit them, so small
//!   bright emitters converge slowly.
//! - Paths: up to `max_bounces` scattering events, Russian roulette from `rr_start_bounce`.
//!   Nothing is clamped: bad inputs (NaN, negative radiance, invalid lights, zero-area
//!   triangles, zero normals) are removed or replaced on construction, never fireflies.
//!   Interpolated shading normals are honoured; directions they send below the facet end the
//!   path (the usual shading-normal energy loss, about 1% on a 24×12 sphere).
//! - Geometry: two BVHs from the `bvh` crate (all meshes; real meshes only), built once per
//!   renderer; see `accel.rs` for why the triangle test and closest-hit choice are ours.

pub mod accel;
pub mod brdf;
mod integrator;
mod sampling;

pub use sampling::{EnvSampler, env_radiance};
pub mod shapes;

use std::f32::consts::PI;

use glam::Vec3;
use rayon::prelude::*;
use relight_core::scene::Scene;

use self::accel::Geometry;
use self::integrator::{PathContext, radiance};
use self::sampling::SampleRng;

/// Changes whenever what the estimator converges to changes (a fix in the integrator, a new
/// BRDF): references cached on disk are keyed by it, so a stale one is never read as truth.
/// 2: the last vertex counts both halves of the environment's MIS.
pub const REVISION: u32 = 2;

/// How the reference renders.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceSettings {
    /// Samples per pixel that [`render_reference`] traces (the progressive
    /// [`ReferenceRenderer`] ignores it and traces what [`ReferenceRenderer::add_samples`] asks).
    pub spp: u32,
    /// Scattering events after the first hit (0 = emission and direct light at the first hit
    /// only). Paths are cut here, so keep it high enough that a^(max_bounces+1) is negligible
    /// for the scene's albedo a; Russian roulette ends most paths long before.
    pub max_bounces: u32,
    /// Russian roulette from this bounce on (survival probability min(max throughput, 0.95)).
    pub rr_start_bounce: u32,
    /// Seeds every pixel sample's random stream together with the pixel and sample index.
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

/// Why a reference render cannot start.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReferenceError {
    #[error("reference render size {width}×{height} is empty")]
    EmptyImage { width: u32, height: u32 },
    #[error("camera vertical field of view {yfov_rad} rad is not in (0, π)")]
    BadFieldOfView { yfov_rad: f32 },
    #[error("camera pose is not finite or its rotation is not a rotation")]
    BadCameraPose,
}

/// A copy of `scene` the integrator can trust: lights that fail
/// [`relight_core::light::Light::validate`] are dropped
/// (with a warning), and non-finite or negative albedo, specular, shininess, emission and
/// environment radiance become zero. These are physical bounds, not firefly clamps: nothing
/// finite and non-negative is changed. The GPU path tracer (`pt`) traces the same copy.
pub fn sanitized(scene: &Scene) -> Scene {
    let clean = |v: Vec3| {
        Vec3::from_array(
            v.to_array()
                .map(|c| if c.is_finite() && c > 0.0 { c } else { 0.0 }),
        )
    };
    let mut scene = scene.clone();
    scene.lights.retain(|light| match light.validate() {
        Ok(()) => true,
        Err(error) => {
            tracing::warn!(%error, "reference renderer skips an invalid light");
            false
        }
    });
    for material in &mut scene.materials {
        material.albedo = clean(material.albedo);
        material.specular = clean(material.specular);
        material.emission = clean(material.emission);
        if !(material.shininess.is_finite() && material.shininess > 0.0) {
            material.shininess = 0.0;
        }
    }
    if let Some(env) = &mut scene.environment {
        for texel in &mut env.radiance {
            *texel = clean(*texel);
        }
    }
    scene
}

/// Per-pixel means and standard errors after `spp` samples: linear RGB radiance,
/// W/(sr·m²), `width × height` pixels row-major from the top-left.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceImages {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    /// L^ρ: the real scene with the virtual object(s).
    pub l_rho: Vec<Vec3>,
    /// L^μ: the real scene alone.
    pub l_mu: Vec<Vec3>,
    /// Δ = L^ρ − L^μ, the mean of the per-sample differences (may be negative).
    pub delta: Vec<Vec3>,
    /// Standard error of `delta`, from the sample variance of the per-sample differences
    /// (not from the two means' variances, which would ignore the correlation); ∞ below 2 spp.
    pub delta_std_error: Vec<Vec3>,
    /// Standard error of `l_rho`; ∞ below 2 spp.
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
    /// Validates the camera and render size, cleans the scene (drops invalid lights, zeroes
    /// non-finite or negative material and environment values) and builds the two BVHs (all
    /// meshes for L^ρ, real meshes for L^μ) once.
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
        let pose = scene.camera.world_from_camera;
        if !(pose.translation.is_finite() && pose.rotation.is_finite())
            || pose.rotation.length_squared() < 1e-12
        {
            return Err(ReferenceError::BadCameraPose);
        }
        let scene = sanitized(scene);
        let has_virtual = scene.meshes.iter().any(|m| m.is_virtual);
        let full = Geometry::new(&scene, true);
        let real = has_virtual.then(|| Geometry::new(&scene, false));
        let env = scene.environment.as_ref().and_then(EnvSampler::new);
        tracing::debug!(
            scene = %scene.name,
            triangles = full.triangles().len(),
            width,
            height,
            "reference renderer ready"
        );
        let mut renderer = Self {
            scene,
            full,
            real,
            env,
            settings,
            width,
            height,
            spp: 0,
            stats: vec![PixelStats::default(); width as usize * height as usize],
            virtual_mask: Vec::new(),
        };
        let pixels = width as usize * height as usize;
        renderer.virtual_mask = (0..pixels)
            .into_par_iter()
            .map(|i| {
                let (x, y) = ((i % width as usize) as u32, (i / width as usize) as u32);
                let (origin, dir) = renderer.camera_ray(x, y, 0.5, 0.5);
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

    /// Traces `n` more samples per pixel, in parallel over rows, and folds them into the
    /// running means and variances. The result does not depend on the thread schedule, nor on
    /// how the samples are split between calls: sample `s` of pixel `i` always uses the random
    /// stream seeded from `(seed, i, s)`.
    pub fn add_samples(&mut self, n: u32) {
        let first = self.spp;
        let last = first.saturating_add(n);
        let width = self.width as usize;
        let mut stats = std::mem::take(&mut self.stats);
        {
            let this = &*self;
            stats
                .par_chunks_mut(width)
                .enumerate()
                .for_each(|(y, row)| {
                    for (x, pixel) in row.iter_mut().enumerate() {
                        for s in first..last {
                            let (l_rho, l_mu) = this.sample(x as u32, y as u32, s, false);
                            pixel.rho.add(s + 1, l_rho);
                            pixel.mu.add(s + 1, l_mu);
                            pixel.delta.add(s + 1, l_rho - l_mu);
                        }
                    }
                });
        }
        self.stats = stats;
        self.spp = last;
    }

    /// Sample `s` of pixel (x, y): (L^ρ, L^μ) from one random stream.
    ///
    /// L^μ is traced through the real-only geometry only when the L^ρ path touched the virtual
    /// object (see [`integrator::PathResult::touched_virtual`]); otherwise it is bitwise the
    /// same as L^ρ and is copied, which halves the work wherever the object has no influence.
    /// `always_trace_real` turns that shortcut off (the unit tests check it changes nothing).
    fn sample(&self, x: u32, y: u32, s: u32, always_trace_real: bool) -> (Vec3, Vec3) {
        let ctx = PathContext {
            scene: &self.scene,
            env: self.env.as_ref(),
            max_bounces: self.settings.max_bounces,
            rr_start_bounce: self.settings.rr_start_bounce,
        };
        let pixel_index = u64::from(y) * u64::from(self.width) + u64::from(x);
        let mut rng = SampleRng::new(self.settings.seed, pixel_index, u64::from(s));
        let (jx, jy) = if self.settings.pixel_jitter {
            (rng.next(), rng.next())
        } else {
            (0.5, 0.5)
        };
        let (origin, dir) = self.camera_ray(x, y, jx, jy);
        let mut rng_mu = rng.clone();
        let rho = radiance(&ctx, &self.full, origin, dir, &mut rng);
        let l_mu = match &self.real {
            Some(real) if rho.touched_virtual || always_trace_real => {
                radiance(&ctx, real, origin, dir, &mut rng_mu).radiance
            }
            _ => rho.radiance,
        };
        (rho.radiance, l_mu)
    }

    /// Samples per pixel traced so far.
    pub fn spp(&self) -> u32 {
        self.spp
    }

    /// The current estimates (cheap enough to call after every batch of samples).
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

/// Renders `settings.spp` samples per pixel of L^ρ, L^μ and Δ in one go.
pub fn render_reference(
    scene: &Scene,
    settings: ReferenceSettings,
) -> Result<ReferenceImages, ReferenceError> {
    let mut renderer = ReferenceRenderer::new(scene, settings)?;
    renderer.add_samples(settings.spp);
    Ok(renderer.images())
}

#[cfg(test)]
mod tests {
    use glam::Quat;
    use relight_core::Pose;
    use relight_core::light::Light;
    use relight_core::scene::{EnvironmentMap, Material, SceneCamera};

    use super::shapes::{cuboid, quad, uv_sphere};
    use super::*;

    /// A glossy floor, a real box, a virtual sphere and a virtual box, a point light and a
    /// small environment with a bright spot: every kind of interaction the shortcut must get
    /// right.
    fn busy_scene() -> Scene {
        let materials = vec![
            Material {
                albedo: Vec3::new(0.6, 0.5, 0.4),
                specular: Vec3::splat(0.3),
                shininess: 40.0,
                ..Material::default()
            },
            Material {
                albedo: Vec3::new(0.2, 0.7, 0.3),
                ..Material::default()
            },
        ];
        let environment = EnvironmentMap {
            width: 8,
            height: 4,
            radiance: (0..32)
                .map(|i| Vec3::splat(if i == 9 { 500.0 } else { 0.2 }))
                .collect(),
        };
        Scene {
            name: "busy".into(),
            meshes: vec![
                quad(
                    "floor",
                    Vec3::ZERO,
                    Vec3::X * 3.0,
                    Vec3::NEG_Z * 3.0,
                    0,
                    false,
                ),
                cuboid(
                    "crate",
                    Vec3::new(-1.5, 0.0, -1.5),
                    Vec3::new(-0.9, 0.5, -0.9),
                    1,
                    false,
                ),
                uv_sphere("ball", Vec3::new(0.3, 0.4, 0.0), 0.4, 10, 6, 1, true),
                cuboid(
                    "block",
                    Vec3::new(0.8, 0.0, -0.6),
                    Vec3::new(1.2, 0.6, -0.2),
                    0,
                    true,
                ),
            ],
            materials,
            camera: SceneCamera {
                world_from_camera: Pose::look_at(Vec3::new(0.0, 2.0, 3.0), Vec3::ZERO, Vec3::Y),
                yfov_rad: 0.9,
                width: 12,
                height: 9,
            },
            lights: vec![Light::Point {
                position_in_world: Vec3::new(1.0, 3.0, 1.0),
                intensity: Vec3::splat(20.0),
            }],
            environment: Some(environment),
            environment_lights: Vec::new(),
            shadow_proxy: None,
            surface_revision: None,
        }
    }

    #[test]
    fn copying_untouched_paths_equals_tracing_them() {
        let renderer = ReferenceRenderer::new(&busy_scene(), ReferenceSettings::default()).unwrap();
        let mut touched = 0;
        for y in 0..9 {
            for x in 0..12 {
                for s in 0..8 {
                    let shortcut = renderer.sample(x, y, s, false);
                    let traced = renderer.sample(x, y, s, true);
                    assert_eq!(
                        shortcut.0.to_array().map(f32::to_bits),
                        traced.0.to_array().map(f32::to_bits)
                    );
                    assert_eq!(
                        shortcut.1.to_array().map(f32::to_bits),
                        traced.1.to_array().map(f32::to_bits)
                    );
                    touched += usize::from(shortcut.0 != shortcut.1);
                }
            }
        }
        assert!(
            touched > 50,
            "the virtual objects should change many paths, changed {touched}"
        );
    }

    #[test]
    fn result_does_not_depend_on_batches() {
        let settings = ReferenceSettings::default();
        let mut batched = ReferenceRenderer::new(&busy_scene(), settings).unwrap();
        batched.add_samples(3);
        batched.add_samples(5);
        let mut whole = ReferenceRenderer::new(&busy_scene(), settings).unwrap();
        whole.add_samples(8);
        assert_eq!(batched.images(), whole.images());
        assert_eq!(whole.spp(), 8);
        let images = whole.images();
        assert!(images.virtual_mask.iter().any(|&v| v));
        assert!(images.delta.iter().any(|d| d.max_element() > 0.0));
        assert!(images.delta.iter().any(|d| d.min_element() < 0.0));
    }

    #[test]
    fn bad_cameras_are_errors() {
        let mut scene = busy_scene();
        scene.camera.yfov_rad = 0.0;
        assert_eq!(
            ReferenceRenderer::new(&scene, ReferenceSettings::default()).err(),
            Some(ReferenceError::BadFieldOfView { yfov_rad: 0.0 })
        );
        let mut scene = busy_scene();
        scene.camera.world_from_camera = Pose {
            rotation: Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
            translation: Vec3::ZERO,
        };
        assert_eq!(
            ReferenceRenderer::new(&scene, ReferenceSettings::default()).err(),
            Some(ReferenceError::BadCameraPose)
        );
        let settings = ReferenceSettings {
            size: Some((0, 4)),
            ..ReferenceSettings::default()
        };
        assert_eq!(
            ReferenceRenderer::new(&busy_scene(), settings).err(),
            Some(ReferenceError::EmptyImage {
                width: 0,
                height: 4
            })
        );
    }
}
