//! Real spherical harmonics: L2 (9 coefficients) for environment lighting and irradiance, L1
//! (4 coefficients) for light-propagation-volume cells.
//!
//! Basis and ordering follow Ramamoorthi & Hanrahan 2001, "An Efficient Representation for
//! Irradiance Environment Maps", eq. 3, without the Condon–Shortley phase. Coefficient `i` holds
//! `Y_lm` with `i = l(l + 1) + m`:
//!
//! | i | Y_lm  | value at unit `(x, y, z)` |
//! |---|-------|---------------------------|
//! | 0 | Y_00  | 0.282095                  |
//! | 1 | Y_1-1 | 0.488603 y                |
//! | 2 | Y_10  | 0.488603 z                |
//! | 3 | Y_11  | 0.488603 x                |
//! | 4 | Y_2-2 | 1.092548 xy               |
//! | 5 | Y_2-1 | 1.092548 yz               |
//! | 6 | Y_20  | 0.315392 (3z² − 1)        |
//! | 7 | Y_21  | 1.092548 xz               |
//! | 8 | Y_22  | 0.546274 (x² − y²)        |
//!
//! Directions are in whatever frame the caller projects in (relight: world, +Y up); the basis
//! treats the frame's +Z as the zonal axis. The L1 types are the first four coefficients of the
//! L2 ones, so truncating an [`Sh9`] gives the matching [`Sh4`].

use std::f32::consts::PI;
use std::ops::{Add, AddAssign, Mul, MulAssign, Sub};

use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};

/// `Y_00 = 1 / (2√π)`.
pub const SH_Y00: f32 = 0.282_094_8;
/// `Y_1m = √(3 / 4π) · {y, z, x}`.
pub const SH_Y1: f32 = 0.488_602_5;
/// `Y_2-2, Y_2-1, Y_21 = √(15 / 4π) · {xy, yz, xz}`.
pub const SH_Y2_PRODUCT: f32 = 1.092_548_4;
/// `Y_20 = √(5 / 16π) · (3z² − 1)`.
pub const SH_Y20: f32 = 0.315_391_57;
/// `Y_22 = √(15 / 16π) · (x² − y²)`.
pub const SH_Y22: f32 = 0.546_274_2;

/// Â_l, the clamped-cosine kernel `max(0, cos θ)` convolved per band (R&H 2001 eq. 8):
/// irradiance `E_lm = Â_l L_lm`.
pub const CLAMPED_COSINE_CONVOLUTION: [f32; 3] = [PI, 2.0 * PI / 3.0, PI / 4.0];

/// Zonal coefficients of `max(0, z)`: `√π / 2`, `√(π / 3)`, `√(5π) / 8` for l = 0, 1, 2. These are
/// the lobe constants `c0`, `c1` of LPV injection (Kaplanyan & Dachsbacher 2010) and DLPV.
pub const CLAMPED_COSINE_ZONAL: [f32; 3] = [0.886_226_9, 1.023_326_7, 0.495_415_9];

/// Band `l` of each coefficient index.
const BAND_OF_INDEX: [usize; 9] = [0, 1, 1, 1, 2, 2, 2, 2, 2];

/// The 9 real L2 basis functions at `dir` (unit length), in the order of the module table.
pub fn sh9_basis(dir: Vec3) -> [f32; 9] {
    let Vec3 { x, y, z } = dir;
    [
        SH_Y00,
        SH_Y1 * y,
        SH_Y1 * z,
        SH_Y1 * x,
        SH_Y2_PRODUCT * x * y,
        SH_Y2_PRODUCT * y * z,
        SH_Y20 * (3.0 * z * z - 1.0),
        SH_Y2_PRODUCT * x * z,
        SH_Y22 * (x * x - y * y),
    ]
}

/// The 4 real L1 basis functions at `dir` (unit length): the first four of [`sh9_basis`].
pub fn sh4_basis(dir: Vec3) -> [f32; 4] {
    let Vec3 { x, y, z } = dir;
    [SH_Y00, SH_Y1 * y, SH_Y1 * z, SH_Y1 * x]
}

/// A value SH coefficients can hold: one channel (`f32`) or linear RGB (`Vec3`).
trait ShValue:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<f32, Output = Self> + AddAssign
{
    const ZERO: Self;
    /// Scalar used to pick a dominant direction: the value itself, or Rec. 709 luminance.
    fn luminance(self) -> f32;
}

impl ShValue for f32 {
    const ZERO: Self = 0.0;
    fn luminance(self) -> f32 {
        self
    }
}

impl ShValue for Vec3 {
    const ZERO: Self = Vec3::ZERO;
    fn luminance(self) -> f32 {
        self.dot(Vec3::new(0.2126, 0.7152, 0.0722))
    }
}

macro_rules! sh_type {
    ($(#[$doc:meta])* $name:ident, $value:ty, $count:literal, $basis:ident) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
        #[serde(transparent)]
        pub struct $name {
            pub coeffs: [$value; $count],
        }

        impl Default for $name {
            fn default() -> Self {
                Self::ZERO
            }
        }

        impl $name {
            pub const ZERO: Self = Self {
                coeffs: [<$value as ShValue>::ZERO; $count],
            };

            pub fn new(coeffs: [$value; $count]) -> Self {
                Self { coeffs }
            }

            /// The represented function at `dir` (unit length): `Σ c_i Y_i(dir)`.
            pub fn evaluate(&self, dir: Vec3) -> $value {
                self.coeffs
                    .iter()
                    .zip($basis(dir))
                    .fold(<$value as ShValue>::ZERO, |sum, (&c, y)| sum + c * y)
            }

            /// Accumulates one sample of a projection: `c_i += value · Y_i(dir) · weight`, where
            /// `weight` is the sample's solid angle (sr), e.g. an environment-map texel's.
            pub fn add_sample(&mut self, dir: Vec3, value: $value, weight: f32) {
                for (c, y) in self.coeffs.iter_mut().zip($basis(dir)) {
                    *c += value * (y * weight);
                }
            }

            /// Projects `f` onto the basis, `c_i = ∫ f(ω) Y_i(ω) dω`, by the deterministic
            /// product-Gauss rule of [`sphere_quadrature`] with about `samples` directions.
            pub fn project_fn(f: impl Fn(Vec3) -> $value, samples: usize) -> Self {
                let mut sh = Self::ZERO;
                for (dir, weight) in sphere_quadrature(samples) {
                    sh.add_sample(dir, f(dir), weight);
                }
                sh
            }

            /// Irradiance at a surface with unit `normal` lit by the radiance this SH represents:
            /// the convolution with the clamped cosine, `E(n) = Σ Â_l L_lm Y_lm(n)` (R&H 2001
            /// eq. 7–8, `Â = (π, 2π/3, π/4)`).
            pub fn irradiance(&self, normal: Vec3) -> $value {
                self.coeffs
                    .iter()
                    .zip($basis(normal))
                    .zip(BAND_OF_INDEX)
                    .fold(<$value as ShValue>::ZERO, |sum, ((&c, y), band)| {
                        sum + c * (y * CLAMPED_COSINE_CONVOLUTION[band])
                    })
            }

            /// Direction of the band-1 gradient, where the light mostly comes from (Sloan 2008,
            /// "Stupid Spherical Harmonics Tricks"); RGB uses luminance. `None` when band 1 is
            /// zero up to rounding (below 1e-6 of the band-0 term), i.e. the light has no direction.
            pub fn dominant_direction(&self) -> Option<Vec3> {
                let gradient = Vec3::new(
                    self.coeffs[3].luminance(),
                    self.coeffs[1].luminance(),
                    self.coeffs[2].luminance(),
                );
                let magnitude = gradient.length();
                if magnitude <= 1e-6 * self.coeffs[0].luminance().abs() {
                    return None;
                }
                gradient.try_normalize()
            }

            /// The function rotated by `rotation`: `g(ω) = f(rotation⁻¹ ω)`. Exact (to rounding):
            /// the integrand has degree ≤ 4, which an 18-point product-Gauss rule integrates
            /// exactly.
            pub fn rotated(&self, rotation: Quat) -> Self {
                let inverse = rotation.inverse();
                Self::project_fn(|dir| self.evaluate(inverse * dir), ROTATION_SAMPLES)
            }

            /// Every coefficient multiplied by `factor`.
            pub fn scaled(&self, factor: f32) -> Self {
                Self {
                    coeffs: self.coeffs.map(|c| c * factor),
                }
            }

            pub fn is_finite(&self) -> bool {
                self.coeffs.iter().all(|c| c.is_finite())
            }
        }

        impl Add for $name {
            type Output = Self;
            fn add(mut self, rhs: Self) -> Self {
                self += rhs;
                self
            }
        }

        impl AddAssign for $name {
            fn add_assign(&mut self, rhs: Self) {
                for (a, b) in self.coeffs.iter_mut().zip(rhs.coeffs) {
                    *a += b;
                }
            }
        }

        impl Sub for $name {
            type Output = Self;
            fn sub(self, rhs: Self) -> Self {
                let mut coeffs = self.coeffs;
                for (a, b) in coeffs.iter_mut().zip(rhs.coeffs) {
                    *a -= b;
                }
                Self { coeffs }
            }
        }

        impl Mul<f32> for $name {
            type Output = Self;
            fn mul(self, factor: f32) -> Self {
                self.scaled(factor)
            }
        }

        impl MulAssign<f32> for $name {
            fn mul_assign(&mut self, factor: f32) {
                *self = self.scaled(factor);
            }
        }
    };
}

/// Samples for [`Sh9::rotated`]: 3 Gauss–Legendre nodes in z × 6 in φ, exact for degree ≤ 5.
const ROTATION_SAMPLES: usize = 18;

sh_type!(
    /// One channel of L2 spherical harmonics.
    Sh9, f32, 9, sh9_basis
);
sh_type!(
    /// Linear RGB L2 spherical harmonics: environment lighting (radiance, W/(m²·sr)).
    Sh9Rgb, Vec3, 9, sh9_basis
);
sh_type!(
    /// One channel of L1 spherical harmonics (a DLPV cell's per-channel coefficients).
    Sh4, f32, 4, sh4_basis
);
sh_type!(
    /// Linear RGB L1 spherical harmonics.
    Sh4Rgb, Vec3, 4, sh4_basis
);

impl Sh9 {
    /// The band-0 and band-1 coefficients.
    pub fn truncate_l1(&self) -> Sh4 {
        let [c0, c1, c2, c3, ..] = self.coeffs;
        Sh4::new([c0, c1, c2, c3])
    }
}

impl Sh9Rgb {
    /// The band-0 and band-1 coefficients.
    pub fn truncate_l1(&self) -> Sh4Rgb {
        let [c0, c1, c2, c3, ..] = self.coeffs;
        Sh4Rgb::new([c0, c1, c2, c3])
    }

    /// One colour channel (0 red, 1 green, 2 blue).
    ///
    /// # Panics
    /// If `channel > 2` (a programming error).
    pub fn channel(&self, channel: usize) -> Sh9 {
        Sh9::new(self.coeffs.map(|c| c[channel]))
    }

    pub fn from_channels(red: &Sh9, green: &Sh9, blue: &Sh9) -> Self {
        Self::new(std::array::from_fn(|i| {
            Vec3::new(red.coeffs[i], green.coeffs[i], blue.coeffs[i])
        }))
    }
}

/// Projection of the clamped-cosine lobe `max(0, normal · ω)`: `Â_l Y_lm(normal)`.
/// Multiplying by a flux gives a surfel's emission lobe; the dot product with a radiance SH gives
/// irradiance (the same thing as [`Sh9::irradiance`]).
pub fn clamped_cosine_sh9(normal: Vec3) -> Sh9 {
    let basis = sh9_basis(normal);
    Sh9::new(std::array::from_fn(|i| {
        CLAMPED_COSINE_CONVOLUTION[BAND_OF_INDEX[i]] * basis[i]
    }))
}

/// L1 projection of the clamped-cosine lobe `max(0, normal · ω)`:
/// `(c0, c1 n_y, c1 n_z, c1 n_x)` with `c0 = √π / 2`, `c1 = √(π / 3)` — the lobe used for LPV
/// injection (Kaplanyan & Dachsbacher 2010, in this module's sign convention).
pub fn clamped_cosine_sh4(normal: Vec3) -> Sh4 {
    let [c0, c1, _] = CLAMPED_COSINE_ZONAL;
    Sh4::new([c0, c1 * normal.y, c1 * normal.z, c1 * normal.x])
}

/// Deterministic quadrature over the unit sphere: Gauss–Legendre nodes in `z = cos θ` times
/// uniform azimuths, about `samples` directions (at least 2) with weights (sr) summing to 4π.
/// With `n` nodes in z and `2n` azimuths it integrates every polynomial of degree < 2n in
/// `(x, y, z)` exactly, so SH projections of smooth functions converge quickly.
pub fn sphere_quadrature(samples: usize) -> Vec<(Vec3, f32)> {
    let z_count = ((samples as f64 / 2.0).sqrt().round() as usize).max(1);
    let phi_count = 2 * z_count;
    let phi_weight = std::f64::consts::TAU / phi_count as f64;
    let mut out = Vec::with_capacity(z_count * phi_count);
    for (z, z_weight) in gauss_legendre(z_count) {
        let ring_radius = (1.0 - z * z).max(0.0).sqrt();
        for j in 0..phi_count {
            let phi = phi_weight * (j as f64 + 0.5);
            let dir = Vec3::new(
                (ring_radius * phi.cos()) as f32,
                (ring_radius * phi.sin()) as f32,
                z as f32,
            );
            out.push((dir, (z_weight * phi_weight) as f32));
        }
    }
    out
}

/// Gauss–Legendre nodes and weights on [−1, 1], by Newton iteration on `P_n` from the
/// Chebyshev-like initial guesses (Numerical Recipes §4.6).
fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut derivative = 1.0;
        for _ in 0..100 {
            let (p, dp) = legendre(n, x);
            derivative = dp;
            let step = p / dp;
            x -= step;
            if step.abs() < 1e-15 {
                break;
            }
        }
        let (_, dp) = legendre(n, x);
        if dp != 0.0 {
            derivative = dp;
        }
        out.push((x, 2.0 / ((1.0 - x * x) * derivative * derivative)));
    }
    out
}

/// `(P_n(x), P_n'(x))` by the three-term recurrence.
fn legendre(n: usize, x: f64) -> (f64, f64) {
    let (mut previous, mut current) = (1.0, x);
    if n == 0 {
        return (1.0, 0.0);
    }
    for k in 2..=n {
        let k = k as f64;
        let next = ((2.0 * k - 1.0) * x * current - (k - 1.0) * previous) / k;
        previous = current;
        current = next;
    }
    let n = n as f64;
    (current, n * (x * current - previous) / (x * x - 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_close(actual: f32, expected: f32, tolerance: f32, what: &str) {
        assert!(
            (actual - expected).abs() <= tolerance,
            "{what}: {actual} vs {expected} (tolerance {tolerance})"
        );
    }

    fn unit(x: f32, y: f32, z: f32) -> Vec3 {
        Vec3::new(x, y, z).normalize()
    }

    #[test]
    fn constants_match_their_closed_forms() {
        let sqrt_pi = PI.sqrt();
        assert_close(SH_Y00, 0.5 / sqrt_pi, 1e-7, "Y00");
        assert_close(SH_Y1, (3.0 / (4.0 * PI)).sqrt(), 1e-7, "Y1");
        assert_close(
            SH_Y2_PRODUCT,
            (15.0 / (4.0 * PI)).sqrt(),
            1e-6,
            "Y2 products",
        );
        assert_close(SH_Y20, (5.0 / (16.0 * PI)).sqrt(), 1e-7, "Y20");
        assert_close(SH_Y22, (15.0 / (16.0 * PI)).sqrt(), 1e-7, "Y22");
        assert_close(CLAMPED_COSINE_ZONAL[0], sqrt_pi / 2.0, 1e-7, "c0");
        assert_close(CLAMPED_COSINE_ZONAL[1], (PI / 3.0).sqrt(), 1e-7, "c1");
        assert_close(CLAMPED_COSINE_ZONAL[2], (5.0 * PI).sqrt() / 8.0, 1e-7, "c2");
    }

    #[test]
    fn quadrature_weights_cover_the_sphere() {
        for samples in [2, 18, 200, 5000] {
            let total: f32 = sphere_quadrature(samples).iter().map(|(_, w)| w).sum();
            assert_close(total, 4.0 * PI, 1e-4, "Σ weights");
        }
        for (x, _) in gauss_legendre(7) {
            assert!(legendre(7, x).0.abs() < 1e-14);
        }
    }

    #[test]
    fn basis_is_orthonormal() {
        let quadrature = sphere_quadrature(32 * 16);
        for i in 0..9 {
            for j in 0..9 {
                let integral: f32 = quadrature
                    .iter()
                    .map(|&(dir, w)| sh9_basis(dir)[i] * sh9_basis(dir)[j] * w)
                    .sum();
                let expected = if i == j { 1.0 } else { 0.0 };
                assert_close(integral, expected, 1e-5, &format!("<Y{i}, Y{j}>"));
            }
        }
        let dir = unit(0.3, -0.5, 0.8);
        assert_eq!(sh4_basis(dir), sh9_basis(dir)[..4]);
    }

    #[test]
    fn constant_projects_onto_band_zero_only() {
        let c = 1.7;
        let sh = Sh9::project_fn(|_| c, 200);
        assert_close(sh.coeffs[0], c * 2.0 * PI.sqrt(), 1e-5, "c00");
        for (i, &coeff) in sh.coeffs.iter().enumerate().skip(1) {
            assert_close(coeff, 0.0, 1e-5, &format!("c{i}"));
        }
    }

    #[test]
    fn clamped_cosine_projects_to_known_zonal_values() {
        // The kink at z = 0 limits Gauss–Legendre to O(n⁻²): 1e-4 needs ~100 nodes in z.
        let sh = Sh9::project_fn(|dir| dir.z.max(0.0), 20_000);
        let mut expected = [0.0; 9];
        expected[0] = PI.sqrt() / 2.0;
        expected[2] = (PI / 3.0).sqrt();
        expected[6] = (5.0 * PI).sqrt() / 8.0;
        for (i, (&actual, expected)) in sh.coeffs.iter().zip(expected).enumerate() {
            assert_close(actual, expected, 1e-4, &format!("c{i}"));
        }
        let sh4 = Sh4::project_fn(|dir| dir.z.max(0.0), 20_000);
        assert_eq!(sh4, sh.truncate_l1());
    }

    #[test]
    fn rotated_clamped_cosine_lobes_match_projection() {
        for normal in [unit(0.3, -0.5, 0.8), unit(-1.0, 0.2, -0.1), Vec3::Y] {
            let projected = Sh9::project_fn(|dir| dir.dot(normal).max(0.0), 20_000);
            let lobe = clamped_cosine_sh9(normal);
            let lobe4 = clamped_cosine_sh4(normal);
            for i in 0..9 {
                assert_close(lobe.coeffs[i], projected.coeffs[i], 2e-4, &format!("c{i}"));
            }
            for i in 0..4 {
                assert_close(lobe4.coeffs[i], lobe.coeffs[i], 1e-6, &format!("L1 c{i}"));
            }
        }
    }

    #[test]
    fn constant_environment_gives_pi_l_everywhere() {
        let radiance = Vec3::new(0.5, 1.0, 2.0);
        let env = Sh9Rgb::project_fn(|_| radiance, 200);
        for normal in [Vec3::X, Vec3::NEG_Y, Vec3::Z, unit(1.0, 1.0, -1.0)] {
            let irradiance = env.irradiance(normal);
            assert!(
                (irradiance - radiance * PI).abs().max_element() < 1e-4,
                "{irradiance}"
            );
            let l1 = env.truncate_l1().irradiance(normal);
            assert!((l1 - radiance * PI).abs().max_element() < 1e-4, "{l1}");
        }
    }

    #[test]
    fn band_limited_lighting_gives_exact_irradiance() {
        // L(ω) = (ω·d)² = 1/3 + (2/3) P2(ω·d) lies in L2, so Funk–Hecke gives
        // E(n) = π/3 + (π/6) P2(cos γ) with no truncation error.
        let d = unit(0.2, 0.9, -0.4);
        let env = Sh9::project_fn(|dir| dir.dot(d).powi(2), 200);
        for normal in [d, -d, unit(1.0, 0.0, 0.0), unit(-0.3, 0.4, 0.5)] {
            let cos = normal.dot(d);
            let expected = PI / 3.0 + PI / 6.0 * 0.5 * (3.0 * cos * cos - 1.0);
            assert_close(env.irradiance(normal), expected, 1e-5, "E(n)");
        }
    }

    #[test]
    fn directional_light_error_is_the_l2_truncation_bound() {
        // A distant source of irradiance E0 from d has L_lm = E0 Y_lm(d). Truncated at L2 its
        // irradiance is E0 (1/4 + cos γ / 2 + 5/32 (3cos²γ − 1)) (R&H 2001 §3): worst case for
        // L2, with max error 3/32 ≈ 9.4% of E0 at γ = 90° and mean error ≈ 3.07% over the sphere.
        let e0 = 3.0;
        let d = unit(-0.4, 0.7, 0.2);
        let mut env = Sh9::ZERO;
        env.add_sample(d, e0, 1.0);
        let quadrature = sphere_quadrature(5000);
        let (mut max_error, mut mean_error) = (0.0_f32, 0.0_f32);
        for &(normal, weight) in &quadrature {
            let cos = normal.dot(d);
            let truncated = e0 * (0.25 + cos / 2.0 + 5.0 / 32.0 * (3.0 * cos * cos - 1.0));
            assert_close(env.irradiance(normal), truncated, 1e-5, "truncated E");
            let error = (env.irradiance(normal) - e0 * cos.max(0.0)).abs();
            max_error = max_error.max(error);
            mean_error += error * weight / (4.0 * PI);
        }
        assert!(max_error <= 0.094 * e0, "max error {max_error}");
        assert!(mean_error <= 0.031 * e0, "mean error {mean_error}");
    }

    #[test]
    fn smooth_lighting_irradiance_within_one_percent() {
        // A broad sky-like lobe plus ambient; reference by brute-force quadrature of
        // ∫ L(ω) max(0, n·ω) dω, independent of the SH code.
        let d = unit(0.3, 0.9, 0.1);
        let sky =
            |dir: Vec3| Vec3::new(0.2, 0.25, 0.3) + Vec3::new(1.0, 0.9, 0.7) * dir.dot(d).max(0.0);
        let env = Sh9Rgb::project_fn(sky, 20_000);
        let quadrature = sphere_quadrature(20_000);
        let reference = |normal: Vec3| {
            quadrature.iter().fold(Vec3::ZERO, |sum, &(dir, w)| {
                sum + sky(dir) * (normal.dot(dir).max(0.0) * w)
            })
        };
        let peak = reference(d).max_element();
        for normal in [
            d,
            -d,
            unit(1.0, 0.0, 0.0),
            unit(0.0, 0.0, -1.0),
            unit(-0.5, 0.2, 0.8),
        ] {
            let error = (env.irradiance(normal) - reference(normal))
                .abs()
                .max_element();
            assert!(
                error < 0.01 * peak,
                "normal {normal}: error {error} vs peak {peak}"
            );
        }
    }

    #[test]
    fn texel_accumulation_equals_projection() {
        let f = |dir: Vec3| Vec3::new(dir.x.max(0.0), 1.0 + dir.y, dir.z * dir.z);
        let mut accumulated = Sh9Rgb::ZERO;
        for (dir, weight) in sphere_quadrature(800) {
            accumulated.add_sample(dir, f(dir), weight);
        }
        assert_eq!(accumulated, Sh9Rgb::project_fn(f, 800));
    }

    #[test]
    fn rotation_moves_the_function() {
        let f = |dir: Vec3| 1.0 + 2.0 * dir.x - dir.y * dir.z + 0.5 * dir.z * dir.z;
        let sh = Sh9::project_fn(f, 200);
        let rotation = Quat::from_axis_angle(unit(1.0, 2.0, 3.0), 1.1);
        let rotated = sh.rotated(rotation);
        for dir in [Vec3::X, unit(0.3, -0.5, 0.8), unit(-1.0, -1.0, 0.2)] {
            assert_close(rotated.evaluate(rotation * dir), f(dir), 1e-5, "rotated");
        }
        let identity = sh.rotated(Quat::IDENTITY);
        for i in 0..9 {
            assert_close(identity.coeffs[i], sh.coeffs[i], 1e-5, "identity");
        }
    }

    #[test]
    fn dominant_direction_points_at_the_light() {
        let d = unit(0.5, -0.2, 0.7);
        let mut env = Sh9Rgb::ZERO;
        env.add_sample(d, Vec3::new(1.0, 0.8, 0.5), 2.0);
        env.add_sample(-d, Vec3::splat(0.1), 1.0);
        let dominant = env.dominant_direction().unwrap();
        assert!(dominant.dot(d) > 1.0 - 1e-6, "{dominant}");
        assert_eq!(Sh9::project_fn(|_| 1.0, 50).dominant_direction(), None);
        assert!(clamped_cosine_sh4(d).dominant_direction().unwrap().dot(d) > 1.0 - 1e-6);
    }

    #[test]
    fn arithmetic_and_channels() {
        let a = Sh9::project_fn(|dir| dir.x, 50);
        let b = Sh9::project_fn(|dir| dir.y * dir.y, 50);
        let dir = unit(0.1, 0.7, -0.2);
        assert_close(
            (a + b * 2.0).evaluate(dir),
            dir.x + 2.0 * dir.y * dir.y,
            1e-5,
            "a + 2b",
        );
        assert_close((a - a).evaluate(dir), 0.0, 0.0, "a - a");
        let rgb = Sh9Rgb::from_channels(&a, &b, &(a * 3.0));
        assert_eq!(rgb.channel(1), b);
        assert!(rgb.is_finite());
        let mut broken = rgb;
        broken.coeffs[5].y = f32::NAN;
        assert!(!broken.is_finite());
    }

    #[test]
    fn serde_layout_is_an_array_of_rgb_triples() {
        let mut sh = Sh9Rgb::ZERO;
        sh.coeffs[0] = Vec3::new(1.0, 2.0, 3.0);
        let json = serde_json::to_string(&sh).unwrap();
        assert!(json.starts_with("[[1.0,2.0,3.0],[0.0,0.0,0.0]"), "{json}");
        assert_eq!(serde_json::from_str::<Sh9Rgb>(&json).unwrap(), sh);
        assert!(serde_json::from_str::<Sh9Rgb>("[[1.0,2.0,3.0]]").is_err());
    }
}
