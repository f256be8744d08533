//! Shared by the light-estimation tests: synthetic maps, brackets rendered by the simulator's
//! probe, angles and errors.
#![allow(dead_code)]

use std::path::Path;

use glam::{DVec2, Vec3};
use relight_core::camera::gl_from_optical;
use relight_core::scene::{EnvironmentMap, Scene};
use relight_core::{Pose, ProbeImage};
use relight_recon::envmap::texel_direction;
use relight_recon::hdr::HdrImage;
use relight_sim::probe::{ProbeLens, render_probe};
use relight_sim::response::CameraResponse;

pub fn load_scene(name: &str) -> Scene {
    Scene::load(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/scenes")
            .join(name),
    )
    .unwrap()
}

/// A `width × height` map whose texels hold `radiance(direction of the texel centre)`.
pub fn map_from_fn(width: u32, height: u32, radiance: impl Fn(Vec3) -> Vec3) -> EnvironmentMap {
    EnvironmentMap {
        width,
        height,
        radiance: (0..width * height)
            .map(|i| radiance(texel_direction(width, height, i % width, i / width)))
            .collect(),
    }
}

/// Angle between two directions, degrees (accurate near zero).
pub fn angle_deg(a: Vec3, b: Vec3) -> f32 {
    let (a, b) = (a.as_dvec3().normalize(), b.as_dvec3().normalize());
    a.cross(b).length().atan2(a.dot(b)).to_degrees() as f32
}

pub fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.2126, 0.7152, 0.0722))
}

/// Probe looking straight up from the origin (its −Z along world +Y), as the rig places it.
pub fn upward_probe() -> Pose {
    Pose::new(
        glam::Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        Vec3::ZERO,
    )
}

/// The simulator's exposures of `radiance` at each of `exposures_us`.
pub fn bracket(
    radiance: &(dyn Fn(Vec3) -> Vec3 + Sync),
    lens: &ProbeLens,
    world_from_probe: &Pose,
    exposures_us: &[u32],
    exposure_scale: f32,
) -> Vec<ProbeImage> {
    exposures_us
        .iter()
        .map(|&t| {
            render_probe(
                radiance,
                lens,
                world_from_probe,
                t,
                exposure_scale,
                &CameraResponse::default(),
            )
        })
        .collect()
}

/// The radiance each probe pixel integrates (the simulator's 4 × 4 sub-pixel mean, black outside
/// the field of view), as an HDR image: what a perfect merge would give.
pub fn true_probe_radiance(
    radiance: &(dyn Fn(Vec3) -> Vec3 + Sync),
    lens: &ProbeLens,
    world_from_probe: &Pose,
) -> HdrImage {
    let model = &lens.model;
    let cos_half_fov = (lens.field_of_view_deg.to_radians() / 2.0).cos();
    let n = 4u32;
    let width = model.width as usize;
    let pixels = width * model.height as usize;
    let radiance = (0..pixels)
        .map(|i| {
            let mut sum = Vec3::ZERO;
            for s in 0..n * n {
                let offset = DVec2::new(
                    (f64::from(s % n) + 0.5) / f64::from(n) - 0.5,
                    (f64::from(s / n) + 0.5) / f64::from(n) - 0.5,
                );
                let pixel = DVec2::new((i % width) as f64, (i / width) as f64) + offset;
                let Some(ray) = model.unproject(pixel).filter(|ray| ray.z >= cos_half_fov) else {
                    continue;
                };
                let dir = world_from_probe.transform_vector(gl_from_optical(ray).as_vec3());
                sum += radiance(dir.normalize());
            }
            sum / (n * n) as f32
        })
        .collect();
    HdrImage {
        width: model.width,
        height: model.height,
        radiance,
        saturated: vec![false; pixels],
    }
}

/// `q`-quantile (0..=1) of `values`.
pub fn quantile(values: &[f32], q: f32) -> f32 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f32::total_cmp);
    let k = ((sorted.len() - 1) as f32 * q).round() as usize;
    sorted[k]
}

pub fn assert_finite(values: &[Vec3], what: &str) {
    assert!(values.iter().all(|v| v.is_finite()), "{what} has NaN/Inf");
}
