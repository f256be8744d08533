//! The lighting estimate the daemon publishes (`lights.get`, `lights.subscribe`), in the spirit
//! of ARCore's light estimation: enough for another renderer on the rig to light its own content
//! consistently with the real scene, without the full environment map.

use glam::Vec3;
use relight_core::Timestamp;
use relight_core::light::Light;
use relight_core::sh::Sh9Rgb;
use serde::{Deserialize, Serialize};

/// Rec. 709 / linear sRGB luminance weights.
const LUMINANCE: Vec3 = Vec3::new(0.2126, 0.7152, 0.0722);

/// The strongest light of the estimate, as a distant light.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MainLight {
    /// Unit direction the light travels (from the light towards the scene), world frame.
    pub direction_in_world: Vec3,
    /// Chromaticity: the irradiance divided by its largest channel (so the largest is 1).
    pub color: Vec3,
    /// Largest channel of the irradiance on a surface facing the light, W/m².
    pub intensity: f32,
}

impl MainLight {
    /// The distant light that delivers `irradiance` (W/m² per channel, on a surface facing it)
    /// travelling along `direction_in_world`. Negative channels (SH ringing) count as zero.
    /// `None` when the direction is degenerate or the irradiance is not finite and positive.
    pub fn from_irradiance(direction_in_world: Vec3, irradiance: Vec3) -> Option<Self> {
        let direction_in_world = direction_in_world.try_normalize()?;
        let irradiance = irradiance.max(Vec3::ZERO);
        let intensity = irradiance.max_element();
        (irradiance.is_finite() && intensity > 0.0).then(|| Self {
            direction_in_world,
            color: irradiance / intensity,
            intensity,
        })
    }

    /// The irradiance on a surface facing the light, W/m² per channel.
    pub fn irradiance(&self) -> Vec3 {
        self.color * self.intensity
    }

    /// Luminance of [`Self::irradiance`] (Rec. 709 weights), what "strongest" compares.
    pub fn luminance(&self) -> f32 {
        self.irradiance().dot(LUMINANCE)
    }
}

/// Everything known about the real scene's light at one moment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LightingEstimate {
    /// Timestamp of the newest probe frame the environment map was merged from; `None` when no
    /// probe contributed (lights from the scene file and the lamp only).
    pub environment_stamp: Option<Timestamp>,
    /// The strongest of `lights` (by irradiance luminance), if any.
    pub main_light: Option<MainLight>,
    /// Radiance of the environment as L2 SH, world directions: from the probe, else the scene
    /// file's environment map; zero without either.
    pub sh9: Sh9Rgb,
    /// Radiance of everything that lights the reference point, as L2 SH: `sh9`, the
    /// environment lights, and every other light as a distant light from where it stands (the
    /// projection `E · Y_lm(ω)` of its irradiance `E` from the direction `ω` towards it).
    /// XR_ANDROID_light_estimation's `TOTAL` spherical harmonics.
    #[serde(default)]
    pub sh9_total: Sh9Rgb,
    /// `sh9_total` without the main light: `sh9_ambient` plus `main_light` (projected as above)
    /// is `sh9_total`, so a renderer that draws the main light as a directional light with
    /// shadows and the rest from SH counts every light once. XR_ANDROID_light_estimation's
    /// `AMBIENT` spherical harmonics, ARCore's ambient spherical harmonics.
    #[serde(default)]
    pub sh9_ambient: Sh9Rgb,
    /// The lights: one directional light per median-cut region of the probe's environment (or
    /// the scene file's lights without a probe), then the lamp.
    pub lights: Vec<Light>,
    /// True when the probe's part is in relative units: the rig calibration has no radiance
    /// scale for the probe, so its lights and SH9 are right in shape and colour, not in level.
    #[serde(default)]
    pub relative_units: bool,
}

impl LightingEstimate {
    /// The estimate for content at `reference_point` (world frame, e.g. the centre of the
    /// virtual object): `main_light` is the light delivering the most irradiance luminance there,
    /// each light seen as a distant light from where it stands:
    ///
    /// - point and spot lights become the direction from the light towards the point, with the
    ///   irradiance `I / r²` (times the spot's cone falloff) of [`Light::incident`];
    /// - directional lights are taken as they are;
    /// - the environment (`sh9`, and any [`Light::Environment`] in `lights`, scaled) takes part
    ///   through its dominant direction ([`Sh9Rgb::dominant_direction`]) with the irradiance it
    ///   gives a surface facing that way ([`Sh9Rgb::irradiance`]).
    ///
    /// Lights that deliver nothing there (outside a spot's cone, exactly at the point, zero or
    /// non-finite intensity) are never the main light; `main_light` is `None` when nothing
    /// lights the point. Ties go to the first candidate, `sh9` last.
    ///
    /// The first `lights_in_sh9` of `lights` are `sh9` cut into lights (the probe's median
    /// cut): they count once in `sh9_total`, through `sh9`.
    pub fn from_lights(
        lights: Vec<Light>,
        lights_in_sh9: usize,
        sh9: Sh9Rgb,
        environment_stamp: Option<Timestamp>,
        reference_point: Vec3,
    ) -> Self {
        let environments = lights.iter().filter_map(|light| match *light {
            Light::Environment {
                sh,
                intensity_scale,
            } => Some(sh.scaled(intensity_scale)),
            _ => None,
        });
        let main_light = lights
            .iter()
            .filter_map(|light| light.incident(reference_point))
            .filter_map(|incident| {
                MainLight::from_irradiance(-incident.direction_to_light, incident.irradiance)
            })
            .chain(
                environments
                    .chain(std::iter::once(sh9))
                    .filter_map(|sh| environment_main_light(&sh)),
            )
            .fold(None, |best: Option<MainLight>, candidate| match best {
                Some(best) if best.luminance() >= candidate.luminance() => Some(best),
                _ => Some(candidate),
            });
        let mut sh9_total = sh9;
        for light in lights.iter().skip(lights_in_sh9) {
            match *light {
                Light::Environment {
                    sh,
                    intensity_scale,
                } => sh9_total += sh.scaled(intensity_scale),
                _ => {
                    if let Some(incident) = light.incident(reference_point)
                        && incident.irradiance.is_finite()
                    {
                        sh9_total.add_sample(incident.direction_to_light, incident.irradiance, 1.0);
                    }
                }
            }
        }
        let mut sh9_ambient = sh9_total;
        if let Some(main) = &main_light {
            sh9_ambient.add_sample(-main.direction_in_world, main.irradiance(), -1.0);
        }
        Self {
            environment_stamp,
            main_light,
            sh9,
            sh9_total,
            sh9_ambient,
            lights,
            relative_units: false,
        }
    }
}

/// An environment as a distant light: from its dominant direction, with the irradiance it gives a
/// surface facing that way.
fn environment_main_light(sh: &Sh9Rgb) -> Option<MainLight> {
    let direction_to_light = sh.dominant_direction()?;
    MainLight::from_irradiance(-direction_to_light, sh.irradiance(direction_to_light))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_close(a: Vec3, b: Vec3) {
        assert!((a - b).abs().max_element() < 1e-5, "{a} vs {b}");
    }

    /// Radiance `radiance` from the cap of directions within `half_angle_rad` of `towards`.
    fn cap_sh(towards: Vec3, half_angle_rad: f32, radiance: Vec3) -> Sh9Rgb {
        let cos_max = half_angle_rad.cos();
        Sh9Rgb::project_fn(
            |dir| {
                if dir.dot(towards) >= cos_max {
                    radiance
                } else {
                    Vec3::ZERO
                }
            },
            4000,
        )
    }

    #[test]
    fn a_near_point_light_beats_a_dimmer_directional_light() {
        let reference_point = Vec3::new(0.0, 0.5, 0.0);
        let lamp = Light::Point {
            position_in_world: Vec3::new(0.0, 1.5, 0.0),
            intensity: Vec3::new(4.0, 2.0, 1.0),
        };
        let window = Light::Directional {
            direction_in_world: Vec3::X,
            irradiance: Vec3::splat(1.0),
        };
        let estimate = LightingEstimate::from_lights(
            vec![window, lamp],
            0,
            Sh9Rgb::ZERO,
            None,
            reference_point,
        );
        let main = estimate.main_light.expect("a main light");
        // 1 m below the lamp: E = I / 1², luminance 2.37 against the window's 1.
        assert_close(main.direction_in_world, Vec3::NEG_Y);
        assert_eq!(main.intensity, 4.0);
        assert_close(main.color, Vec3::new(1.0, 0.5, 0.25));
        assert_eq!(estimate.lights, vec![window, lamp]);
        assert_eq!(estimate.environment_stamp, None);

        // 3 m below, the lamp gives a ninth: the window wins.
        let far = LightingEstimate::from_lights(
            vec![window, lamp],
            0,
            Sh9Rgb::ZERO,
            None,
            Vec3::new(0.0, -1.5, 0.0),
        );
        let main = far.main_light.expect("a main light");
        assert_close(main.direction_in_world, Vec3::X);
        assert_eq!(main.intensity, 1.0);
        assert_close(main.color, Vec3::ONE);
    }

    #[test]
    fn a_spot_light_that_misses_the_point_is_not_the_main_light() {
        let spot = Light::Spot {
            position_in_world: Vec3::new(0.0, 2.0, 0.0),
            direction_in_world: Vec3::X,
            intensity: Vec3::splat(100.0),
            inner_angle_rad: 0.2,
            outer_angle_rad: 0.3,
        };
        let dim = Light::Directional {
            direction_in_world: Vec3::NEG_Y,
            irradiance: Vec3::splat(0.01),
        };
        let estimate =
            LightingEstimate::from_lights(vec![spot, dim], 0, Sh9Rgb::ZERO, None, Vec3::ZERO);
        assert_close(
            estimate
                .main_light
                .expect("the directional light")
                .direction_in_world,
            Vec3::NEG_Y,
        );
    }

    #[test]
    fn environment_alone_gives_its_dominant_direction() {
        // A bright patch overhead and slightly towards +X: light travels down and towards −X.
        let towards = Vec3::new(0.3, 1.0, 0.0).normalize();
        let sh9 = cap_sh(towards, 0.4, Vec3::new(2.0, 1.0, 1.0));
        let stamp = Timestamp::new(5, 6);
        let estimate = LightingEstimate::from_lights(Vec::new(), 0, sh9, Some(stamp), Vec3::ZERO);
        let main = estimate.main_light.expect("the environment's light");
        assert!(
            main.direction_in_world.dot(-towards) > 0.99,
            "{}",
            main.direction_in_world
        );
        assert_close(main.color, Vec3::new(1.0, 0.5, 0.5));
        assert!(main.intensity > 0.0);
        assert_eq!(estimate.environment_stamp, Some(stamp));
        assert_eq!(estimate.sh9, sh9);
        assert!(estimate.lights.is_empty());
    }

    #[test]
    fn a_bright_environment_beats_a_dim_point_light() {
        let sh9 = cap_sh(Vec3::Y, 0.5, Vec3::splat(50.0));
        let candle = Light::Point {
            position_in_world: Vec3::new(1.0, 0.0, 0.0),
            intensity: Vec3::splat(0.1),
        };
        let estimate = LightingEstimate::from_lights(vec![candle], 0, sh9, None, Vec3::ZERO);
        let main = estimate.main_light.expect("a main light");
        assert!(main.direction_in_world.dot(Vec3::NEG_Y) > 0.99, "{main:?}");

        // The same environment as a scaled-down light of the list loses to the candle.
        let as_light = Light::Environment {
            sh: sh9,
            intensity_scale: 1e-4,
        };
        let estimate = LightingEstimate::from_lights(
            vec![as_light, candle],
            0,
            Sh9Rgb::ZERO,
            None,
            Vec3::ZERO,
        );
        let main = estimate.main_light.expect("a main light");
        assert_close(main.direction_in_world, Vec3::NEG_X);
    }

    #[test]
    fn no_lights_no_main_light() {
        let estimate = LightingEstimate::from_lights(Vec::new(), 0, Sh9Rgb::ZERO, None, Vec3::ZERO);
        assert_eq!(estimate.main_light, None);
        let black = Light::Point {
            position_in_world: Vec3::Y,
            intensity: Vec3::ZERO,
        };
        // A uniform environment has no direction.
        let uniform = Sh9Rgb::project_fn(|_| Vec3::ONE, 200);
        let estimate = LightingEstimate::from_lights(vec![black], 0, uniform, None, Vec3::ZERO);
        assert_eq!(estimate.main_light, None);
    }

    #[test]
    fn a_light_at_the_reference_point_gives_no_nan() {
        let at_point = Light::Point {
            position_in_world: Vec3::new(1.0, 2.0, 3.0),
            intensity: Vec3::splat(10.0),
        };
        let spot_at_point = Light::Spot {
            position_in_world: Vec3::new(1.0, 2.0, 3.0),
            direction_in_world: Vec3::NEG_Y,
            intensity: Vec3::splat(10.0),
            inner_angle_rad: 0.3,
            outer_angle_rad: 0.5,
        };
        let estimate = LightingEstimate::from_lights(
            vec![at_point, spot_at_point],
            0,
            Sh9Rgb::ZERO,
            None,
            Vec3::new(1.0, 2.0, 3.0),
        );
        assert_eq!(estimate.main_light, None);
        assert!(estimate.sh9_total.is_finite() && estimate.sh9_ambient.is_finite());

        // Next to another light, the other light is the main light, and everything is finite.
        let other = Light::Directional {
            direction_in_world: Vec3::NEG_Z,
            irradiance: Vec3::splat(0.5),
        };
        let estimate = LightingEstimate::from_lights(
            vec![at_point, other],
            0,
            Sh9Rgb::ZERO,
            None,
            Vec3::new(1.0, 2.0, 3.0),
        );
        let main = estimate.main_light.expect("the directional light");
        assert_close(main.direction_in_world, Vec3::NEG_Z);
        assert!(
            main.direction_in_world.is_finite() && main.color.is_finite(),
            "{main:?}"
        );

        // A non-finite reference point lights nothing rather than producing NaN.
        let estimate = LightingEstimate::from_lights(
            vec![at_point],
            0,
            Sh9Rgb::ZERO,
            None,
            Vec3::splat(f32::NAN),
        );
        assert_eq!(estimate.main_light, None);
    }

    /// Irradiance a surface facing a distant light of irradiance `E` gets from its L2
    /// projection: `E Σ_l Â_l (2l + 1) / 4π = 17/16 E` (the truncated delta overshoots).
    const L2_DELTA_PEAK: f32 = 17.0 / 16.0;

    #[test]
    fn total_sh_holds_each_light_once_and_ambient_is_total_without_the_main_light() {
        // A window (directional) alone: the total is its delta, the ambient nothing.
        let window = Light::Directional {
            direction_in_world: Vec3::NEG_Y,
            irradiance: Vec3::new(2.0, 1.0, 0.5),
        };
        let alone = LightingEstimate::from_lights(vec![window], 0, Sh9Rgb::ZERO, None, Vec3::ZERO);
        assert_close(
            alone.sh9_total.irradiance(Vec3::Y),
            Vec3::new(2.0, 1.0, 0.5) * L2_DELTA_PEAK,
        );
        assert!(
            alone
                .sh9_ambient
                .coeffs
                .iter()
                .all(|c| c.abs().max_element() < 1e-6),
            "{:?}",
            alone.sh9_ambient
        );

        // A probe's sky (a bright cap above, a dim rest) cut into one light, plus the lamp,
        // which the probe's map does not hold: the total is the sky plus the lamp.
        let sky =
            cap_sh(Vec3::Y, 0.4, Vec3::splat(5.0)) + Sh9Rgb::project_fn(|_| Vec3::splat(0.05), 400);
        let cut = Light::Directional {
            direction_in_world: Vec3::NEG_Y,
            irradiance: sky.irradiance(Vec3::Y),
        };
        let lamp = Light::Point {
            position_in_world: Vec3::new(1.0, 0.0, 0.0),
            intensity: Vec3::splat(0.5),
        };
        let probe = LightingEstimate::from_lights(vec![cut, lamp], 1, sky, None, Vec3::ZERO);
        let lamp_only =
            LightingEstimate::from_lights(vec![lamp], 0, Sh9Rgb::ZERO, None, Vec3::ZERO);
        let total_minus_sky = probe.sh9_total - sky;
        for (a, b) in total_minus_sky
            .coeffs
            .iter()
            .zip(lamp_only.sh9_total.coeffs)
        {
            assert_close(*a, b);
        }
        // The sky's cut is the main light; taking it out leaves the lamp and the dim rest:
        // facing the lamp the ambient gets the lamp's 0.5 W/m² (and the rest's), facing down
        // little but the rest's π · 0.05.
        let main = probe.main_light.expect("the sky's cut");
        assert_close(main.direction_in_world, Vec3::NEG_Y);
        let mut rebuilt = probe.sh9_ambient;
        rebuilt.add_sample(-main.direction_in_world, main.irradiance(), 1.0);
        for (a, b) in rebuilt.coeffs.iter().zip(probe.sh9_total.coeffs) {
            assert_close(*a, b);
        }
        let below = probe.sh9_ambient.irradiance(Vec3::NEG_Y);
        assert!(below.x < 0.3, "{below}");
        assert!(probe.sh9_ambient.irradiance(Vec3::X).x > 0.5, "{probe:?}");
    }

    #[test]
    fn estimate_round_trips_through_json() {
        let estimate = LightingEstimate::from_lights(
            vec![Light::Point {
                position_in_world: Vec3::new(0.0, 1.0, 0.0),
                intensity: Vec3::splat(2.0),
            }],
            0,
            cap_sh(Vec3::Y, 0.5, Vec3::ONE),
            Some(Timestamp::new(1, 2)),
            Vec3::ZERO,
        );
        let json = serde_json::to_value(&estimate).expect("serialises");
        assert_eq!(
            json["main_light"]["direction_in_world"],
            serde_json::json!([0.0, -1.0, 0.0])
        );
        assert_eq!(json["lights"][0]["type"], "point");
        let back: LightingEstimate = serde_json::from_value(json).expect("deserialises");
        assert_eq!(back, estimate);
    }
}
