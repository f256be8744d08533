//! The real scene's own bounce light, measured by the colour camera: the indirect irradiance a
//! surface point receives from the other surfaces in view, each seen as a diffuse emitter of
//! the radiance the camera measured there.
//!
//! DLPV's eq. 1 ([`crate::albedo`]) divides a pixel's radiance by the irradiance the
//! reconstructed lights deliver. In a room the walls and the floor light each other: a wall
//! beside a lit floor receives a large share of its light from the floor, and eq. 1 with direct
//! light alone reads that share as albedo (on the simulated desk room, white walls came out
//! 0.91 for 0.75). Every visible surface patch j of the depth grid emits its measured radiance
//! L_j; the irradiance it delivers at a point p is the radiosity form factor's
//!
//! dE(p) = L_j · cos θ_p · cos θ_j · A_j / r²,
//!
//! with A_j the patch's area (its pixel footprint at its depth, over the cosine to the view ray).
//! Surfaces the camera does not see (behind it, the ceiling) are missing, so the bounce is a
//! lower bound; visibility between patches is not tested (a room's surfaces mostly see each
//! other).
//!
//! A dense gather is O(cells²). The emitters are every `step`-th cell in each axis (weighted by
//! step²), and the gather runs at every `step`-th receiver into SH9 radiance
//! ([`Sh9Rgb`], Ramamoorthi & Hanrahan 2001): each cell then evaluates the irradiance of the
//! receiver of its block for its own normal, so a wall cell next to the floor still turns to the
//! wall's incoming light.

use glam::Vec3;
use relight_core::camera::Pinhole;
use relight_core::sh::Sh9Rgb;

/// Inputs on one grid of cells (row-major, `camera.width × camera.height`), world frame.
#[derive(Debug, Clone, Copy)]
pub struct BounceInput<'a> {
    pub camera: &'a Pinhole,
    pub eye_in_world: Vec3,
    pub points_in_world: &'a [Option<Vec3>],
    /// Unit, facing the camera.
    pub normals_in_world: &'a [Option<Vec3>],
    /// Measured radiance per cell, W/(m²·sr) (`None`: unknown, e.g. saturated).
    pub radiance: &'a [Option<Vec3>],
}

/// A patch's cosine to the view ray is clamped to this, so a grazing patch does not get an
/// unbounded area from one noisy normal.
const MIN_VIEW_COSINE: f32 = 0.2;

/// Indirect irradiance per cell (`Vec3::ZERO` where there is no surface), W/m², with emitters and
/// receivers every `step` cells (≥ 1).
pub fn bounce_irradiance(input: &BounceInput, step: u32) -> Vec<Vec3> {
    let (w, h) = (input.camera.width as usize, input.camera.height as usize);
    let n = w * h;
    let step = step.max(1) as usize;
    let mut out = vec![Vec3::ZERO; n];
    if [
        input.points_in_world.len(),
        input.normals_in_world.len(),
        input.radiance.len(),
    ] != [n; 3]
    {
        return out;
    }
    let cell = |x: usize, y: usize| y * w + x;
    let footprint = 1.0 / (input.camera.fx * input.camera.fy) as f32 * (step * step) as f32;
    // Emitters: (point, normal, L, A).
    let mut emitters = Vec::new();
    for y in (0..h).step_by(step) {
        for x in (0..w).step_by(step) {
            let i = cell(x, y);
            let (Some(p), Some(normal), Some(radiance)) = (
                input.points_in_world[i],
                input.normals_in_world[i],
                input.radiance[i],
            ) else {
                continue;
            };
            let to_eye = input.eye_in_world - p;
            let distance = to_eye.length();
            let view_cos = normal.dot(to_eye / distance).max(MIN_VIEW_COSINE);
            let area = distance * distance * footprint / view_cos;
            if area.is_finite() && radiance.is_finite() {
                emitters.push((p, normal, radiance, area));
            }
        }
    }
    // Receivers: SH9 incident radiance at each block's first cell.
    let blocks_x = w.div_ceil(step);
    let mut blocks = vec![None; blocks_x * h.div_ceil(step)];
    for (b, block) in blocks.iter_mut().enumerate() {
        let (x, y) = ((b % blocks_x) * step, (b / blocks_x) * step);
        let Some(p) = input.points_in_world[cell(x, y)] else {
            continue;
        };
        let mut sh = Sh9Rgb::ZERO;
        for (q, normal, radiance, area) in &emitters {
            let d = *q - p;
            let r2 = d.length_squared();
            if r2 < 1e-8 {
                continue;
            }
            let dir = d / r2.sqrt();
            let emitter_cos = -normal.dot(dir);
            if emitter_cos <= 0.0 {
                continue;
            }
            // Radiance L_j over the solid angle A_j cos θ_j / r²; nearer than the patch's own
            // size the point-emitter model breaks down, so r² is at least A_j.
            sh.add_sample(dir, *radiance, area * emitter_cos / r2.max(*area));
        }
        *block = Some(sh);
    }
    for y in 0..h {
        for x in 0..w {
            let i = cell(x, y);
            let (Some(normal), Some(Some(sh))) = (
                input.normals_in_world[i],
                blocks.get((y / step) * blocks_x + x / step),
            ) else {
                continue;
            };
            let e = sh.irradiance(normal).max(Vec3::ZERO);
            if e.is_finite() {
                out[i] = e;
            }
        }
    }
    out
}
