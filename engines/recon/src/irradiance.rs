//! Diffuse lighting of an environment map: its L2 spherical-harmonic projection (Ramamoorthi &
//! Hanrahan, "An Efficient Representation for Irradiance Environment Maps", SIGGRAPH 2001), from
//! which `Sh9Rgb::irradiance` gives E(n) with nine coefficients; and the brute-force irradiance
//! integral the projection is tested against.
//!
//! # Accuracy of L2 irradiance
//!
//! Irradiance is radiance convolved with the clamped cosine `A(x) = max(0, x)`, `x = n·ω`. Keeping
//! bands l ≤ 2 replaces `A` by its truncation (R&H eq. 7–8, `Â = (π, 2π/3, π/4)`):
//! `A₂(x) = Σ_{l≤2} Â_l (2l+1)/(4π) P_l(x) = 3/32 + x/2 + 15x²/32`.
//! The error `A₂ − A` is largest at grazing incidence, `A₂(0) − A(0) = 3/32`, and `E_SH − E`
//! is the radiance integrated against it, so for any non-negative radiance
//! `|E_SH(n) − E(n)| ≤ (3/32) ∫ L dω` per channel, whatever the normal. A map whose energy
//! is a single point source reaches that bound at normals perpendicular to the source (where
//! the truth is 0 and L2 gives 3/32 of the head-on irradiance; facing the source it is 6.25% too
//! bright, `A₂(1) = 34/32`); smooth maps, whose higher bands are small, stay far below it (0.4%
//! at worst on the smooth sky of the tests).

use glam::{DVec3, Vec3};
use rayon::prelude::*;
use relight_core::scene::EnvironmentMap;
use relight_core::sh::{Sh9Rgb, sh9_basis};

use crate::envmap::{EnvMapError, check_map, direction, sanitized, texel_solid_angle};

/// Worst-case error of L2-SH irradiance for a non-negative radiance, as a fraction of the
/// radiance integrated over the sphere (`Σ L ΔΩ`): `max |A₂ − A| = A₂(0) = 3/32` (module docs).
pub const SH9_IRRADIANCE_ERROR_BOUND: f64 = 3.0 / 32.0;

/// The map's radiance projected onto the L2 basis of `relight_core::sh`, in world directions:
/// `L_lm = Σ_texels L ∫_texel Y_lm dω`, the map read as piecewise-constant radiance and each
/// texel's basis integral taken over 4 × 4 sub-directions of equal solid angle (a constant map
/// gives πL to 1e-4 at every normal), accumulated in f64. `Sh9Rgb::irradiance(n)` gives the
/// irradiance (R&H eq. 7–8).
pub fn project_sh9(map: &EnvironmentMap) -> Result<Sh9Rgb, EnvMapError> {
    check_map(map)?;
    let coeffs = map
        .radiance
        .par_chunks_exact(map.width as usize)
        .enumerate()
        .map(|(y, row)| {
            let mut sums = [DVec3::ZERO; 9];
            let sub_solid_angle = texel_solid_angle(map.width, map.height, y as u32)
                / f64::from(SUBSAMPLES * SUBSAMPLES);
            for (x, &radiance) in row.iter().enumerate() {
                let radiance = sanitized(radiance).as_dvec3();
                if radiance == DVec3::ZERO {
                    continue;
                }
                let mut basis_integral = [0.0f64; 9];
                for dir in sub_directions(map, x as u32, y as u32) {
                    for (sum, b) in basis_integral.iter_mut().zip(sh9_basis(dir.as_vec3())) {
                        *sum += f64::from(b);
                    }
                }
                for (sum, b) in sums.iter_mut().zip(basis_integral) {
                    *sum += radiance * (b * sub_solid_angle);
                }
            }
            sums
        })
        .reduce(
            || [DVec3::ZERO; 9],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        );
    Ok(Sh9Rgb::new(coeffs.map(|c| c.as_vec3())))
}

/// Sub-directions per texel axis of [`project_sh9`] and [`irradiance_brute_force`].
const SUBSAMPLES: u32 = 4;

/// The `SUBSAMPLES²` directions of equal solid angle (midpoints in cos θ and φ) of texel `(x, y)`.
fn sub_directions(map: &EnvironmentMap, x: u32, y: u32) -> impl Iterator<Item = DVec3> {
    let (w, h) = (f64::from(map.width), f64::from(map.height));
    let (z0, z1) = (
        (std::f64::consts::PI * f64::from(y) / h).cos(),
        (std::f64::consts::PI * f64::from(y + 1) / h).cos(),
    );
    let n = f64::from(SUBSAMPLES);
    (0..SUBSAMPLES * SUBSAMPLES).map(move |s| {
        let theta = (z0 + (z1 - z0) * (f64::from(s / SUBSAMPLES) + 0.5) / n).acos();
        let phi =
            std::f64::consts::TAU * (f64::from(x) + (f64::from(s % SUBSAMPLES) + 0.5) / n) / w;
        direction(theta, phi)
    })
}

/// Irradiance at a surface with unit `normal` by direct summation over the texels,
/// `E(n) = Σ L ∫_texel max(0, n·ω) dω` (f64), the map read as piecewise-constant radiance and the
/// cosine integrated over 4 × 4 sub-directions per texel (a single sample at the centre would be
/// off by up to 0.3% at 64 × 32 from the cosine's kink at the horizon): the oracle for
/// [`project_sh9`]. A zero normal receives nothing.
pub fn irradiance_brute_force(map: &EnvironmentMap, normal: Vec3) -> Result<Vec3, EnvMapError> {
    check_map(map)?;
    let normal = normal.as_dvec3().normalize_or_zero();
    let total = map
        .radiance
        .par_chunks_exact(map.width as usize)
        .enumerate()
        .map(|(y, row)| {
            let sub_solid_angle = texel_solid_angle(map.width, map.height, y as u32)
                / f64::from(SUBSAMPLES * SUBSAMPLES);
            row.iter()
                .enumerate()
                .fold(DVec3::ZERO, |sum, (x, &radiance)| {
                    let cosines: f64 = sub_directions(map, x as u32, y as u32)
                        .map(|dir| normal.dot(dir).max(0.0))
                        .sum();
                    sum + sanitized(radiance).as_dvec3() * (cosines * sub_solid_angle)
                })
        })
        .reduce(|| DVec3::ZERO, |a, b| a + b);
    Ok(total.as_vec3())
}
