//! Light types shared by estimators and engines.
//!
//! All quantities are linear RGB in the units of each field's doc; positions and directions are
//! in the world frame (metres, glTF axes). In TOML a light is a table tagged by `type`:
//!
//! ```toml
//! type = "spot"
//! position_in_world = [0.0, 2.0, 0.0]
//! direction_in_world = [0.0, -1.0, 0.0]
//! intensity = [10.0, 10.0, 9.0]
//! inner_angle_rad = 0.3
//! outer_angle_rad = 0.5
//! ```

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::sh::Sh9Rgb;

/// How far from 1 a direction's length may be before [`Light::validate`] rejects it.
const UNIT_TOLERANCE: f32 = 1e-3;

/// A light source of the real or virtual scene.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Light {
    /// Isotropic point light.
    Point {
        position_in_world: Vec3,
        /// Radiant intensity, W/sr per channel.
        intensity: Vec3,
    },
    /// Point light restricted to a cone, full intensity within `inner_angle_rad` of the axis,
    /// smoothly (Hermite smoothstep in cos θ) falling to zero at `outer_angle_rad`.
    Spot {
        position_in_world: Vec3,
        /// Unit axis of the cone, the direction the light shines.
        direction_in_world: Vec3,
        /// Radiant intensity on the axis, W/sr per channel.
        intensity: Vec3,
        inner_angle_rad: f32,
        outer_angle_rad: f32,
    },
    /// Distant light (sun, or a far lamp).
    Directional {
        /// Unit direction the light travels (from the light towards the scene).
        direction_in_world: Vec3,
        /// Irradiance on a surface facing the light, W/m² per channel.
        irradiance: Vec3,
    },
    /// Distant environment lighting as L2 SH radiance, e.g. from the fish-eye probe.
    ///
    /// The environment map image itself (for IBL and median-cut) is added by the light-estimation
    /// work; this variant carries only its SH projection.
    Environment {
        /// Radiance, W/(m²·sr) per channel, in world directions.
        sh: Sh9Rgb,
        /// Multiplies `sh` (exposure compensation, user dimmer).
        #[serde(default = "unit_scale")]
        intensity_scale: f32,
    },
}

fn unit_scale() -> f32 {
    1.0
}

/// Light arriving at a point from a light with a single direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Incident {
    /// Unit vector from the point towards the light.
    pub direction_to_light: Vec3,
    /// Distance to the light, metres; `f32::INFINITY` for a directional light. Shadow rays stop here.
    pub distance_m: f32,
    /// Irradiance on a surface facing the light (normal incidence), W/m² per channel; multiply by
    /// `max(0, n · direction_to_light)` for a surface with normal `n`.
    pub irradiance: Vec3,
}

/// Why a light's parameters are unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LightError {
    #[error("light field `{field}` is not finite")]
    NonFinite { field: &'static str },
    #[error("light field `{field}` must be a unit vector, its length is {length}")]
    NotUnit { field: &'static str, length: f32 },
    #[error("light field `{field}` must not be negative")]
    Negative { field: &'static str },
    #[error(
        "spot angles must satisfy 0 ≤ inner ≤ outer < π/2, got inner = {inner_angle_rad}, \
         outer = {outer_angle_rad}"
    )]
    SpotAngles {
        inner_angle_rad: f32,
        outer_angle_rad: f32,
    },
}

impl Light {
    /// Light arriving at `point_in_world`: inverse-square falloff for point and spot lights, the
    /// cone falloff for spots (zero irradiance outside the cone), constant for directional.
    /// `None` for the environment (it has no single direction; use
    /// [`Self::environment_irradiance`]) and for a point exactly at a light's position.
    pub fn incident(&self, point_in_world: Vec3) -> Option<Incident> {
        match *self {
            Self::Point {
                position_in_world,
                intensity,
            } => point_incident(position_in_world, intensity, point_in_world),
            Self::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                inner_angle_rad,
                outer_angle_rad,
            } => {
                let incident = point_incident(position_in_world, intensity, point_in_world)?;
                let cos_angle = direction_in_world.dot(-incident.direction_to_light);
                let falloff = spot_falloff(cos_angle, inner_angle_rad, outer_angle_rad);
                Some(Incident {
                    irradiance: incident.irradiance * falloff,
                    ..incident
                })
            }
            Self::Directional {
                direction_in_world,
                irradiance,
            } => Some(Incident {
                direction_to_light: -direction_in_world.normalize_or_zero(),
                distance_m: f32::INFINITY,
                irradiance,
            }),
            Self::Environment { .. } => None,
        }
    }

    /// Irradiance from an environment light at a surface with unit `normal` (SH convolution with
    /// the clamped cosine, R&H 2001); `None` for the other lights.
    pub fn environment_irradiance(&self, normal: Vec3) -> Option<Vec3> {
        match self {
            Self::Environment {
                sh,
                intensity_scale,
            } => Some(sh.irradiance(normal) * *intensity_scale),
            _ => None,
        }
    }

    /// Checks finiteness, unit directions, non-negative intensities and the spot cone
    /// `0 ≤ inner ≤ outer < π/2`.
    pub fn validate(&self) -> Result<(), LightError> {
        match *self {
            Self::Point {
                position_in_world,
                intensity,
            } => {
                check_finite("position_in_world", position_in_world)?;
                check_non_negative("intensity", intensity)
            }
            Self::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                inner_angle_rad,
                outer_angle_rad,
            } => {
                check_finite("position_in_world", position_in_world)?;
                check_unit("direction_in_world", direction_in_world)?;
                check_non_negative("intensity", intensity)?;
                let ordered = 0.0 <= inner_angle_rad
                    && inner_angle_rad <= outer_angle_rad
                    && outer_angle_rad < std::f32::consts::FRAC_PI_2;
                if ordered {
                    Ok(())
                } else {
                    Err(LightError::SpotAngles {
                        inner_angle_rad,
                        outer_angle_rad,
                    })
                }
            }
            Self::Directional {
                direction_in_world,
                irradiance,
            } => {
                check_unit("direction_in_world", direction_in_world)?;
                check_non_negative("irradiance", irradiance)
            }
            Self::Environment {
                sh,
                intensity_scale,
            } => {
                if !sh.is_finite() {
                    return Err(LightError::NonFinite { field: "sh" });
                }
                if !intensity_scale.is_finite() {
                    return Err(LightError::NonFinite {
                        field: "intensity_scale",
                    });
                }
                if intensity_scale < 0.0 {
                    return Err(LightError::Negative {
                        field: "intensity_scale",
                    });
                }
                Ok(())
            }
        }
    }
}

fn point_incident(
    position_in_world: Vec3,
    intensity: Vec3,
    point_in_world: Vec3,
) -> Option<Incident> {
    let to_light = position_in_world - point_in_world;
    let distance_sq = to_light.length_squared();
    let direction_to_light = to_light.try_normalize()?;
    let irradiance = intensity / distance_sq;
    irradiance.is_finite().then_some(Incident {
        direction_to_light,
        distance_m: distance_sq.sqrt(),
        irradiance,
    })
}

/// 1 inside the inner cone, 0 outside the outer one, Hermite smoothstep in cos θ between; a hard
/// edge when the two angles are equal.
fn spot_falloff(cos_angle: f32, inner_angle_rad: f32, outer_angle_rad: f32) -> f32 {
    let (cos_inner, cos_outer) = (inner_angle_rad.cos(), outer_angle_rad.cos());
    if cos_angle >= cos_inner {
        return 1.0;
    }
    if cos_angle <= cos_outer || cos_inner <= cos_outer {
        return 0.0;
    }
    let t = (cos_angle - cos_outer) / (cos_inner - cos_outer);
    t * t * (3.0 - 2.0 * t)
}

fn check_finite(field: &'static str, value: Vec3) -> Result<(), LightError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(LightError::NonFinite { field })
    }
}

fn check_non_negative(field: &'static str, value: Vec3) -> Result<(), LightError> {
    check_finite(field, value)?;
    if value.min_element() < 0.0 {
        Err(LightError::Negative { field })
    } else {
        Ok(())
    }
}

fn check_unit(field: &'static str, value: Vec3) -> Result<(), LightError> {
    check_finite(field, value)?;
    let length = value.length();
    if (length - 1.0).abs() <= UNIT_TOLERANCE {
        Ok(())
    } else {
        Err(LightError::NotUnit { field, length })
    }
}

/// Linear sRGB colour of a black body at `kelvin`, scaled to luminance Y = 1: Planck's law
/// integrated against the CIE 1931 2° colour-matching functions (the multi-lobe Gaussian fit of
/// Wyman, Sloan & Shirley 2013, accurate to the tables' own precision) from 380 to 780 nm, then
/// XYZ → linear sRGB (D65). Used for lamps that report a colour temperature. Channels can go
/// slightly negative far from D65 (outside the sRGB gamut); they are clamped at 0.
pub fn blackbody_rgb(kelvin: f32) -> Vec3 {
    let t = f64::from(kelvin.clamp(500.0, 40_000.0));
    let g = |x: f64, mu: f64, s1: f64, s2: f64| {
        let s = if x < mu { s1 } else { s2 };
        (-0.5 * ((x - mu) / s).powi(2)).exp()
    };
    let (mut x, mut y, mut z) = (0.0, 0.0, 0.0);
    for step in 0..=80 {
        let nm = 380.0 + 5.0 * f64::from(step);
        // Planck's law up to a constant factor (it cancels in the normalisation).
        let lambda = nm * 1e-9;
        let c2 = 1.438_776_877e-2;
        let radiance = 1.0 / (lambda.powi(5) * ((c2 / (lambda * t)).exp() - 1.0));
        let xb = 1.056 * g(nm, 599.8, 37.9, 31.0) + 0.362 * g(nm, 442.0, 16.0, 26.7)
            - 0.065 * g(nm, 501.1, 20.4, 26.2);
        let yb = 0.821 * g(nm, 568.8, 46.9, 40.5) + 0.286 * g(nm, 530.9, 16.3, 31.1);
        let zb = 1.217 * g(nm, 437.0, 11.8, 36.0) + 0.681 * g(nm, 459.0, 26.0, 13.8);
        x += radiance * xb;
        y += radiance * yb;
        z += radiance * zb;
    }
    let (x, z) = (x / y, z / y);
    let rgb = Vec3::new(
        (3.240_454_2 * x - 1.537_138_5 - 0.498_531_4 * z) as f32,
        (-0.969_266_0 * x + 1.876_010_8 + 0.041_556_0 * z) as f32,
        (0.055_643_4 * x - 0.204_025_9 + 1.057_225_2 * z) as f32,
    );
    rgb.max(Vec3::ZERO)
}

#[cfg(test)]
mod tests {
    #[test]
    fn blackbody_colours_follow_the_planckian_locus() {
        // D65 is close to a 6504 K black body: nearly white in sRGB.
        let d65 = blackbody_rgb(6504.0);
        assert!(
            (d65 - Vec3::splat(d65.y)).abs().max_element() < 0.06,
            "{d65}"
        );
        let warm = blackbody_rgb(2700.0);
        assert!(warm.x > warm.y && warm.y > warm.z, "{warm}");
        let cold = blackbody_rgb(12_000.0);
        assert!(cold.z > cold.x, "{cold}");
        // Luminance (Rec. 709 weights) is 1.
        for rgb in [d65, warm, cold] {
            let y = 0.2126 * rgb.x + 0.7152 * rgb.y + 0.0722 * rgb.z;
            assert!((y - 1.0).abs() < 0.02, "{rgb}: Y = {y}");
        }
    }

    use super::*;

    fn spot() -> Light {
        Light::Spot {
            position_in_world: Vec3::new(0.0, 2.0, 0.0),
            direction_in_world: Vec3::NEG_Y,
            intensity: Vec3::new(10.0, 10.0, 9.0),
            inner_angle_rad: 0.3,
            outer_angle_rad: 0.5,
        }
    }

    /// A floor point below the spot (at 2 m) seen at `angle_rad` from the spot's axis.
    fn floor_point_at(angle_rad: f32) -> Vec3 {
        Vec3::new(2.0 * angle_rad.tan(), 0.0, 0.0)
    }

    #[test]
    fn point_light_falls_off_with_inverse_square() {
        let light = Light::Point {
            position_in_world: Vec3::new(1.0, 2.0, 3.0),
            intensity: Vec3::new(4.0, 8.0, 12.0),
        };
        let near = light.incident(Vec3::new(1.0, 2.0, 1.0)).unwrap();
        let far = light.incident(Vec3::new(1.0, 2.0, -1.0)).unwrap();
        assert_eq!(near.distance_m, 2.0);
        assert_eq!(near.direction_to_light, Vec3::Z);
        assert_eq!(near.irradiance, Vec3::new(1.0, 2.0, 3.0));
        assert_eq!(far.irradiance, near.irradiance / 4.0);
        assert_eq!(light.incident(Vec3::new(1.0, 2.0, 3.0)), None);
    }

    #[test]
    fn spot_falloff_is_full_inside_inner_and_zero_outside_outer() {
        let light = spot();
        let on_axis = light.incident(floor_point_at(0.0)).unwrap();
        assert_eq!(on_axis.irradiance, Vec3::new(10.0, 10.0, 9.0) / 4.0);
        assert_eq!(on_axis.direction_to_light, Vec3::Y);
        let irradiance_at = |angle_rad: f32| {
            let point = floor_point_at(angle_rad);
            let full =
                Vec3::new(10.0, 10.0, 9.0) / point.distance_squared(Vec3::new(0.0, 2.0, 0.0));
            light.incident(point).unwrap().irradiance.x / full.x
        };
        assert!((irradiance_at(0.299) - 1.0).abs() < 1e-5);
        assert!((irradiance_at(0.3) - 1.0).abs() < 1e-3);
        let middle = irradiance_at(0.4);
        assert!(middle > 0.3 && middle < 0.7, "{middle}");
        assert!(irradiance_at(0.35) > middle && middle > irradiance_at(0.45));
        assert!(irradiance_at(0.499) < 1e-3);
        assert_eq!(irradiance_at(0.501), 0.0);
        assert_eq!(
            light.incident(Vec3::new(0.0, 3.0, 0.0)).unwrap().irradiance,
            Vec3::ZERO
        );
    }

    #[test]
    fn spot_with_equal_angles_has_a_hard_edge() {
        let light = match spot() {
            Light::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                ..
            } => Light::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                inner_angle_rad: 0.4,
                outer_angle_rad: 0.4,
            },
            other => other,
        };
        assert!(light.incident(floor_point_at(0.39)).unwrap().irradiance.x > 0.0);
        assert_eq!(
            light.incident(floor_point_at(0.41)).unwrap().irradiance,
            Vec3::ZERO
        );
    }

    #[test]
    fn directional_and_environment() {
        let sun = Light::Directional {
            direction_in_world: Vec3::new(0.0, -1.0, 0.0),
            irradiance: Vec3::splat(800.0),
        };
        let incident = sun.incident(Vec3::new(5.0, 0.0, -3.0)).unwrap();
        assert_eq!(incident.direction_to_light, Vec3::Y);
        assert_eq!(incident.distance_m, f32::INFINITY);
        assert_eq!(incident.irradiance, Vec3::splat(800.0));
        assert_eq!(sun.environment_irradiance(Vec3::Y), None);

        let radiance = Vec3::new(0.1, 0.2, 0.3);
        let env = Light::Environment {
            sh: Sh9Rgb::project_fn(|_| radiance, 200),
            intensity_scale: 2.0,
        };
        assert_eq!(env.incident(Vec3::ZERO), None);
        let irradiance = env.environment_irradiance(Vec3::X).unwrap();
        assert!(
            (irradiance - radiance * 2.0 * std::f32::consts::PI)
                .abs()
                .max_element()
                < 1e-5
        );
    }

    #[test]
    fn toml_round_trip_of_every_variant() {
        #[derive(Debug, PartialEq, Serialize, Deserialize)]
        struct Scene {
            lights: Vec<Light>,
        }
        let mut sh = Sh9Rgb::ZERO;
        sh.coeffs[0] = Vec3::new(1.0, 0.5, 0.25);
        sh.coeffs[2] = Vec3::new(-0.1, 0.0, 0.1);
        let scene = Scene {
            lights: vec![
                Light::Point {
                    position_in_world: Vec3::new(1.0, 2.0, 3.0),
                    intensity: Vec3::splat(5.0),
                },
                spot(),
                Light::Directional {
                    direction_in_world: Vec3::NEG_Y,
                    irradiance: Vec3::splat(3.0),
                },
                Light::Environment {
                    sh,
                    intensity_scale: 0.5,
                },
            ],
        };
        let text = toml::to_string(&scene).unwrap();
        assert!(text.contains("type = \"directional\""), "{text}");
        assert_eq!(toml::from_str::<Scene>(&text).unwrap(), scene);
    }

    #[test]
    fn toml_as_documented_parses() {
        let light: Light = toml::from_str(
            "type = \"spot\"\n\
             position_in_world = [0.0, 2.0, 0.0]\n\
             direction_in_world = [0.0, -1.0, 0.0]\n\
             intensity = [10.0, 10.0, 9.0]\n\
             inner_angle_rad = 0.3\n\
             outer_angle_rad = 0.5\n",
        )
        .unwrap();
        assert_eq!(light, spot());
        let env: Light = toml::from_str(&format!(
            "type = \"environment\"\nsh = [{}]\n",
            ["[0.0, 0.0, 0.0]"; 9].join(", ")
        ))
        .unwrap();
        assert_eq!(
            env,
            Light::Environment {
                sh: Sh9Rgb::ZERO,
                intensity_scale: 1.0
            }
        );
        assert!(toml::from_str::<Light>("type = \"area\"\n").is_err());
        let misspelt = "type = \"point\"\nposition_in_world = [0.0, 0.0, 0.0]\n\
                        intensity = [1.0, 1.0, 1.0]\nintensity_scale = 2.0\n";
        assert!(toml::from_str::<Light>(misspelt).is_err());
        assert!(
            toml::from_str::<Light>("type = \"point\"\nposition_in_world = [0.0, 0.0, 0.0]\n")
                .is_err()
        );
    }

    #[test]
    fn validation_errors() {
        assert_eq!(spot().validate(), Ok(()));
        let with_angles = |inner_angle_rad, outer_angle_rad| match spot() {
            Light::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                ..
            } => Light::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                inner_angle_rad,
                outer_angle_rad,
            },
            other => other,
        };
        for (inner, outer) in [(0.5, 0.3), (-0.1, 0.3), (0.2, 1.6)] {
            assert_eq!(
                with_angles(inner, outer).validate(),
                Err(LightError::SpotAngles {
                    inner_angle_rad: inner,
                    outer_angle_rad: outer
                })
            );
        }
        assert_eq!(with_angles(0.4, 0.4).validate(), Ok(()));
        assert_eq!(
            Light::Directional {
                direction_in_world: Vec3::new(0.0, -2.0, 0.0),
                irradiance: Vec3::ONE,
            }
            .validate(),
            Err(LightError::NotUnit {
                field: "direction_in_world",
                length: 2.0
            })
        );
        assert_eq!(
            Light::Point {
                position_in_world: Vec3::new(f32::NAN, 0.0, 0.0),
                intensity: Vec3::ONE,
            }
            .validate(),
            Err(LightError::NonFinite {
                field: "position_in_world"
            })
        );
        assert_eq!(
            Light::Point {
                position_in_world: Vec3::ZERO,
                intensity: Vec3::new(1.0, -0.1, 1.0),
            }
            .validate(),
            Err(LightError::Negative { field: "intensity" })
        );
        let mut sh = Sh9Rgb::ZERO;
        sh.coeffs[4].z = f32::INFINITY;
        assert_eq!(
            Light::Environment {
                sh,
                intensity_scale: 1.0
            }
            .validate(),
            Err(LightError::NonFinite { field: "sh" })
        );
        assert_eq!(
            Light::Environment {
                sh: Sh9Rgb::ZERO,
                intensity_scale: -1.0
            }
            .validate(),
            Err(LightError::Negative {
                field: "intensity_scale"
            })
        );
    }
}
