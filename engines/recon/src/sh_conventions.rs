//! The lighting estimate in the conventions of the renderers that consume it: Unity's
//! `SphericalHarmonicsL2` and three.js's `LightProbe` (`docs/lighting-estimate.md` is the
//! guide).
//!
//! relight's SH ([`relight_core::sh`]) are radiance coefficients `L_lm = ∫ L(ω) Y_lm(ω) dω` in
//! the real basis of Ramamoorthi & Hanrahan 2001 (eq. 3, no Condon–Shortley phase), in the world
//! frame (glTF: right-handed, +y up).
//!
//! - **three.js** (`SphericalHarmonics3`) uses the same basis, the same order and radiance
//!   coefficients: its `shGetIrradianceAt` is R&H eq. 13, the irradiance `E(n)`, which
//!   `BRDF_Lambert` divides by π. Its world is right-handed +y up like glTF's, so the
//!   coefficients go over as they are, flattened coefficient by coefficient for
//!   `LightProbe.sh.fromArray`. A `DirectionalLight`'s `intensity` (physically based lighting)
//!   is the irradiance on a surface facing it.
//! - **Unity** stores `SphericalHarmonicsL2[channel, i]` premultiplied, so that its shader
//!   (`ShadeSH9`, from `unity_SHAr…unity_SHC`) evaluates `Σ sh_i P_i(n)` with the bare
//!   polynomials `P = (1, y, z, x, xy, yz, 3z² − 1, xz, x² − y²)` and gets `E(n) / π`, what it
//!   multiplies by the albedo: `sh_i = L_i · Â_l · N_i / π` (`N_i` the basis constant, `Â_l` the
//!   clamped-cosine convolution, R&H eq. 8). A constant radiance `c` becomes `sh_0 = c`, as
//!   `SphericalHarmonicsL2.AddAmbientLight(c)` makes it. Unity's world is left-handed; relight's
//!   goes into it as UnityGLTF imports glTF, with x negated, which flips the coefficients odd in
//!   x (`x`, `xy`, `xz`). Unity's light units carry no π: a directional light's
//!   `color · intensity` is the irradiance over π.
//!
//! Units stay relight's (W/(m²·sr) and W/m², or relative units): a lab scales them to its
//! renderer's exposure.

use glam::Vec3;
use relight_core::sh::{
    CLAMPED_COSINE_CONVOLUTION, SH_Y00, SH_Y1, SH_Y2_PRODUCT, SH_Y20, SH_Y22, Sh9Rgb,
};
use serde::{Deserialize, Serialize};

use crate::estimate::{LightingEstimate, MainLight};

/// `N_i`: the constant of basis function `i` (its polynomial part is Unity's `P_i`).
const BASIS_CONSTANT: [f32; 9] = [
    SH_Y00,
    SH_Y1,
    SH_Y1,
    SH_Y1,
    SH_Y2_PRODUCT,
    SH_Y2_PRODUCT,
    SH_Y20,
    SH_Y2_PRODUCT,
    SH_Y22,
];

/// Band `l` of coefficient `i`.
const BAND: [usize; 9] = [0, 1, 1, 1, 2, 2, 2, 2, 2];

/// The sign each coefficient takes when x is negated (odd in x: `x`, `xy`, `xz`).
const X_MIRROR: [f32; 9] = [1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0, -1.0, 1.0];

/// A direction in Unity's world: relight's with x negated.
pub fn unity_direction(direction_in_world: Vec3) -> Vec3 {
    Vec3::new(
        -direction_in_world.x,
        direction_in_world.y,
        direction_in_world.z,
    )
}

/// `sh` as Unity's `SphericalHarmonicsL2`, `[channel][coefficient]` as `sh[channel, i]` indexes
/// it: premultiplied and mirrored as the module docs say.
pub fn unity_spherical_harmonics_l2(sh: &Sh9Rgb) -> [[f32; 9]; 3] {
    let mut out = [[0.0; 9]; 3];
    for (i, coefficient) in sh.coeffs.iter().enumerate() {
        let factor = X_MIRROR[i] * CLAMPED_COSINE_CONVOLUTION[BAND[i]] * BASIS_CONSTANT[i]
            / std::f32::consts::PI;
        for (channel, value) in coefficient.to_array().into_iter().enumerate() {
            out[channel][i] = value * factor;
        }
    }
    out
}

/// `sh` as three.js's `SphericalHarmonics3` coefficients, flattened for `fromArray`:
/// `[L_0.r, L_0.g, L_0.b, L_1.r, …]`.
pub fn threejs_light_probe(sh: &Sh9Rgb) -> [f32; 27] {
    let mut out = [0.0; 27];
    for (i, coefficient) in sh.coeffs.iter().enumerate() {
        out[3 * i..3 * i + 3].copy_from_slice(&coefficient.to_array());
    }
    out
}

/// A directional light as a renderer sets one up.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DirectionalLight {
    /// The way the light travels, in the renderer's world (Unity: the light's
    /// `transform.forward`; three.js: from `position` towards `target`).
    pub direction: Vec3,
    /// Largest channel 1.
    pub color: Vec3,
    /// Unity: `Light.intensity` (irradiance / π); three.js: `DirectionalLight.intensity`
    /// (irradiance).
    pub intensity: f32,
}

/// The estimate for Unity: `ambient_probe` for `RenderSettings.ambientProbe` (or a light
/// probe), the main light for a directional light with shadows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UnityLighting {
    /// `SphericalHarmonicsL2[channel, i]` of the estimate's ambient SH (the main light
    /// excluded).
    pub ambient_probe: [[f32; 9]; 3],
    /// The same of the total SH, for a renderer without a main light.
    pub total_probe: [[f32; 9]; 3],
    pub main_light: Option<DirectionalLight>,
}

/// The estimate for three.js: `LightProbe.sh.fromArray(ambient_probe)` and a
/// `DirectionalLight`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ThreejsLighting {
    pub ambient_probe: Vec<f32>,
    pub total_probe: Vec<f32>,
    pub main_light: Option<DirectionalLight>,
}

pub fn unity_lighting(estimate: &LightingEstimate) -> UnityLighting {
    UnityLighting {
        ambient_probe: unity_spherical_harmonics_l2(&estimate.sh9_ambient),
        total_probe: unity_spherical_harmonics_l2(&estimate.sh9_total),
        main_light: estimate.main_light.map(|main| DirectionalLight {
            direction: unity_direction(main.direction_in_world),
            color: main.color,
            intensity: main.intensity / std::f32::consts::PI,
        }),
    }
}

pub fn threejs_lighting(estimate: &LightingEstimate) -> ThreejsLighting {
    let directional = |main: MainLight| DirectionalLight {
        direction: main.direction_in_world,
        color: main.color,
        intensity: main.intensity,
    };
    ThreejsLighting {
        ambient_probe: threejs_light_probe(&estimate.sh9_ambient).to_vec(),
        total_probe: threejs_light_probe(&estimate.sh9_total).to_vec(),
        main_light: estimate.main_light.map(directional),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::sh::sphere_quadrature;

    /// An environment with every coefficient in play: a coloured cap, a gradient, a rest.
    fn environment() -> Sh9Rgb {
        let towards = Vec3::new(0.3, 0.8, -0.5).normalize();
        Sh9Rgb::project_fn(
            |dir| {
                let cap = if dir.dot(towards) > 0.8 {
                    Vec3::new(6.0, 4.0, 2.0)
                } else {
                    Vec3::ZERO
                };
                cap + Vec3::new(0.2, 0.3, 0.4) * (1.0 + dir.x * dir.z)
                    + Vec3::splat(0.5 * dir.y.max(0.0))
            },
            2000,
        )
    }

    /// Unity's `ShadeSH9` as its shader computes it from the constants its
    /// `SphericalHarmonicsL2` is packed into: `unity_SHAr = (sh_3, sh_1, sh_2, sh_0 − sh_6)`,
    /// `unity_SHBr = (sh_4, sh_5, 3 sh_6, sh_7)`, `unity_SHC.r = sh_8`, against
    /// `(n, 1)`, `(xy, yz, zz, zx)` and `x² − y²`.
    fn unity_shade_sh9(sh: &[[f32; 9]; 3], normal: Vec3) -> Vec3 {
        let Vec3 { x, y, z } = normal;
        let channel = |c: &[f32; 9]| {
            let a = c[3] * x + c[1] * y + c[2] * z + (c[0] - c[6]);
            let b = c[4] * x * y + c[5] * y * z + 3.0 * c[6] * z * z + c[7] * z * x;
            a + b + c[8] * (x * x - y * y)
        };
        Vec3::new(channel(&sh[0]), channel(&sh[1]), channel(&sh[2]))
    }

    /// three.js's `shGetIrradianceAt` (R&H eq. 13 with its constants c1…c5).
    fn threejs_irradiance(sh: &[f32; 27], normal: Vec3) -> Vec3 {
        let c = |i: usize| Vec3::from_slice(&sh[3 * i..3 * i + 3]);
        let Vec3 { x, y, z } = normal;
        c(0) * 0.886_227
            + c(1) * (2.0 * 0.511_664 * y)
            + c(2) * (2.0 * 0.511_664 * z)
            + c(3) * (2.0 * 0.511_664 * x)
            + c(4) * (2.0 * 0.429_043 * x * y)
            + c(5) * (2.0 * 0.429_043 * y * z)
            + c(6) * (0.743_125 * z * z - 0.247_708)
            + c(7) * (2.0 * 0.429_043 * x * z)
            + c(8) * (0.429_043 * (x * x - y * y))
    }

    fn assert_close(a: Vec3, b: Vec3, tolerance: f32) {
        assert!((a - b).abs().max_element() <= tolerance, "{a} vs {b}");
    }

    /// Unity's shader on the converted coefficients gives relight's irradiance over π at the
    /// mirrored normal, everywhere on the sphere.
    #[test]
    fn unity_shade_sh9_of_the_conversion_is_relight_irradiance_over_pi() {
        let sh = environment();
        let unity = unity_spherical_harmonics_l2(&sh);
        for (normal, _) in sphere_quadrature(200) {
            let expected = sh.irradiance(normal) / std::f32::consts::PI;
            assert_close(
                unity_shade_sh9(&unity, unity_direction(normal)),
                expected,
                1e-5,
            );
        }
    }

    /// `AddAmbientLight(c)` adds `c` to coefficient 0: a constant radiance `c` converts so.
    #[test]
    fn a_constant_radiance_is_unity_s_ambient_light() {
        let c = Vec3::new(0.25, 0.5, 1.0);
        let unity = unity_spherical_harmonics_l2(&Sh9Rgb::project_fn(|_| c, 400));
        for (channel, row) in unity.iter().enumerate() {
            assert!((row[0] - c[channel]).abs() < 1e-5, "{row:?}");
            assert!(row[1..].iter().all(|v| v.abs() < 1e-5), "{row:?}");
        }
    }

    #[test]
    fn threejs_irradiance_of_the_conversion_is_relight_irradiance() {
        let sh = environment();
        let three = threejs_light_probe(&sh);
        for (normal, _) in sphere_quadrature(200) {
            // R&H's constants have six digits: a relative 1e-6 on values up to ~10 W/m², summed.
            assert_close(
                threejs_irradiance(&three, normal),
                sh.irradiance(normal),
                1e-4,
            );
        }
    }

    #[test]
    fn the_main_light_goes_over_in_each_renderer_s_units_and_frame() {
        let lights = vec![relight_core::light::Light::Directional {
            direction_in_world: Vec3::new(0.6, -0.8, 0.0),
            irradiance: Vec3::new(3.0, 1.5, 0.75),
        }];
        let estimate = LightingEstimate::from_lights(lights, 0, Sh9Rgb::ZERO, None, Vec3::ZERO);
        let unity = unity_lighting(&estimate).main_light.unwrap();
        assert_close(unity.direction, Vec3::new(-0.6, -0.8, 0.0), 1e-6);
        assert!((unity.intensity - 3.0 / std::f32::consts::PI).abs() < 1e-6);
        assert_close(unity.color, Vec3::new(1.0, 0.5, 0.25), 1e-6);
        let three = threejs_lighting(&estimate).main_light.unwrap();
        assert_close(three.direction, Vec3::new(0.6, -0.8, 0.0), 1e-6);
        assert_eq!(three.intensity, 3.0);
        assert_eq!(threejs_lighting(&estimate).ambient_probe.len(), 27);
    }
}
