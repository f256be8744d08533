//! The fish-eye light probe: what a Kannala–Brandt camera at `world_from_probe` sees of the
//! environment, at one exposure, through the camera's response curve. Brackets of several
//! exposures are what HDR merging (Robertson) recovers radiance from.

use glam::{DVec2, Vec3};
use relight_core::camera::{KannalaBrandt, gl_from_optical};
use relight_core::scene::EnvironmentMap;
use relight_core::{Image, PixelFormat, Pose, ProbeImage};

use crate::response::CameraResponse;

/// Radiance of `env` in world direction `dir` (unit), bilinear. Longitude φ = atan2(x, −z)
/// from −Z towards +X, v = 0 straight up (the convention of [`EnvironmentMap`]).
pub fn environment_radiance(env: &EnvironmentMap, dir: Vec3) -> Vec3 {
    let (w, h) = (env.width as usize, env.height as usize);
    if w == 0 || h == 0 || env.radiance.len() != w * h || !dir.is_finite() {
        return Vec3::ZERO;
    }
    let phi = dir.x.atan2(-dir.z).rem_euclid(std::f32::consts::TAU);
    let theta = dir.y.clamp(-1.0, 1.0).acos();
    let u = phi / std::f32::consts::TAU * w as f32 - 0.5;
    let v = (theta / std::f32::consts::PI * h as f32 - 0.5).clamp(0.0, (h - 1) as f32);
    let (u0, v0) = (u.floor(), v.floor());
    let (fu, fv) = (u - u0, v - v0);
    let texel = |x: f32, y: f32| {
        let x = (x as isize).rem_euclid(w as isize) as usize;
        let y = (y as usize).min(h - 1);
        env.radiance[y * w + x]
    };
    let top = texel(u0, v0).lerp(texel(u0 + 1.0, v0), fu);
    let bottom = texel(u0, v0 + 1.0).lerp(texel(u0 + 1.0, v0 + 1.0), fu);
    top.lerp(bottom, fv)
}

/// The probe: its lens model and the full field of view of its image circle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeLens {
    pub model: KannalaBrandt,
    /// Full field of view, degrees (e.g. 185 for a typical circular fish-eye).
    pub field_of_view_deg: f64,
}

/// Sub-pixel samples per axis: a pocket lamp is a few pixels wide in the probe, so pixel centres
/// alone would miss part of its energy.
const PROBE_SUPERSAMPLING: u32 = 4;

/// Render one probe exposure of the world radiance `radiance(direction)`: 8-bit RGB through
/// `response`, black outside the image circle, each pixel the mean of 4 × 4 sub-pixel rays in
/// linear radiance (as the sensor integrates). `exposure_scale` converts radiance × exposure
/// time (s) into the response's [0, 1] input.
pub fn render_probe(
    radiance: &(dyn Fn(Vec3) -> Vec3 + Sync),
    lens: &ProbeLens,
    world_from_probe: &Pose,
    exposure_us: u32,
    exposure_scale: f32,
    response: &CameraResponse,
) -> ProbeImage {
    let model = &lens.model;
    let mut image = Image::new(model.width, model.height, PixelFormat::Rgb8);
    let gain = exposure_us as f32 * 1e-6 * exposure_scale;
    let width = model.width as usize;
    let cos_half_fov = (lens.field_of_view_deg.to_radians() / 2.0).cos();
    let n = PROBE_SUPERSAMPLING;
    if let Some(px) = image.as_u8_mut() {
        for (i, rgb) in px.chunks_exact_mut(3).enumerate() {
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
            let mean = sum / (n * n) as f32;
            for (c, value) in rgb.iter_mut().zip(mean.to_array()) {
                *c = response.to_code(value * gain);
            }
        }
    }
    ProbeImage {
        image,
        exposure_us,
        gain_db: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;
    use relight_core::camera::optical_from_gl;

    fn lens() -> ProbeLens {
        ProbeLens {
            model: model(),
            field_of_view_deg: 185.0,
        }
    }

    fn model() -> KannalaBrandt {
        KannalaBrandt {
            width: 64,
            height: 64,
            fx: 20.0,
            fy: 20.0,
            cx: 31.5,
            cy: 31.5,
            k1: 0.0,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        }
    }

    /// A dim sky with one bright patch around `window_dir`.
    fn sky(window_dir: Vec3) -> EnvironmentMap {
        let (w, h) = (128, 64);
        let radiance = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                let phi = x / w as f32 * std::f32::consts::TAU;
                let theta = y / h as f32 * std::f32::consts::PI;
                let dir = Vec3::new(
                    theta.sin() * phi.sin(),
                    theta.cos(),
                    -theta.sin() * phi.cos(),
                );
                if dir.dot(window_dir) > 0.97 {
                    Vec3::splat(1e4)
                } else {
                    Vec3::splat(1.0)
                }
            })
            .collect();
        EnvironmentMap {
            width: w as u32,
            height: h as u32,
            radiance,
        }
    }

    #[test]
    fn lookup_follows_the_documented_convention() {
        let env = sky(Vec3::new(1.0, 0.0, 0.0));
        assert_eq!(environment_radiance(&env, Vec3::X), Vec3::splat(1e4));
        assert_eq!(environment_radiance(&env, -Vec3::X), Vec3::splat(1.0));
        assert_eq!(
            environment_radiance(&env, Vec3::new(f32::NAN, 0.0, 0.0)),
            Vec3::ZERO
        );
    }

    #[test]
    fn the_window_appears_where_the_lens_projects_it_and_brackets_scale() {
        let window_dir = Vec3::new(0.5, 0.8, -0.3).normalize();
        let env = sky(window_dir);
        // Probe looking straight up (its −Z axis along world +Y).
        let world_from_probe = Pose::new(
            Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
            Vec3::ZERO,
        );
        let response = CameraResponse::default();
        let dark = render_probe(
            &|d| environment_radiance(&env, d),
            &lens(),
            &world_from_probe,
            1_000,
            1.0,
            &response,
        );
        let bright = render_probe(
            &|d| environment_radiance(&env, d),
            &lens(),
            &world_from_probe,
            100_000,
            1.0,
            &response,
        );
        let dir_in_probe = world_from_probe.inverse().transform_vector(window_dir);
        let pixel = model()
            .project(optical_from_gl(dir_in_probe.as_dvec3()))
            .unwrap();
        let at = |p: &ProbeImage, px: DVec2| {
            let i = 3 * (px.y.round() as usize * 64 + px.x.round() as usize);
            p.image.as_u8().unwrap()[i]
        };
        // Window: 1e4 × 1 ms = 10 → saturated in both; sky: 1 × 1 ms is dark, × 100 ms is mid-grey.
        assert_eq!(at(&dark, pixel), 255);
        let sky_pixel = DVec2::new(63.0 - pixel.x, 63.0 - pixel.y);
        assert_eq!(at(&dark, sky_pixel), response.to_code(1e-3));
        assert_eq!(at(&bright, sky_pixel), response.to_code(0.1));
        assert_eq!(bright.exposure_us, 100_000);
        // Outside the 180° image circle there is nothing.
        assert_eq!(at(&dark, DVec2::new(0.0, 0.0)), 0);
    }
}
