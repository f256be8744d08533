//! Environment light as directional lights (Knecht et al. 2012, Sec. 5: VPLs on a hemisphere
//! placed by importance sampling the fish-eye image). Directions come from the exact
//! piecewise-constant inversion of the map's luminance · sin θ (the reference's own sampler; an
//! exact equivalent of hierarchical warping) at a fixed Hammersley point set, so the lights do
//! not move from frame to frame. Each light carries the estimator's share of the irradiance,
//! E_i = L(ω_i) / (N p(ω_i)), and travels towards the scene along −ω_i; the shared passes give it
//! shadow maps and RSM VPLs like any other light.

use relight_core::light::Light;
use relight_core::scene::EnvironmentMap;
use relight_reference::{EnvSampler, env_radiance};

/// `count` directional lights standing in for `env` (none for an empty or black map).
pub fn environment_lights(env: &EnvironmentMap, count: u32) -> Vec<Light> {
    let Some(sampler) = EnvSampler::new(env) else {
        return Vec::new();
    };
    (0..count)
        .filter_map(|i| {
            let u1 = (i as f32 + 0.5) / count as f32;
            let u2 = i.reverse_bits() as f32 / 4_294_967_296.0;
            let (dir, pdf) = sampler.sample(u1, u2);
            let irradiance = env_radiance(env, dir) / (count as f32 * pdf);
            (pdf > 0.0 && irradiance.is_finite() && irradiance.max_element() > 0.0).then_some(
                Light::Directional {
                    direction_in_world: -dir,
                    irradiance,
                },
            )
        })
        .collect()
}

/// [`environment_lights`] kept with the map and count they were cut from, and cut again only
/// when either changes: a live scene is a new `Arc<Scene>` every frame (a new depth mesh), while
/// its environment map rarely changes, so keying by the scene would re-cut it every frame.
#[derive(Debug, Default)]
pub struct EnvironmentLights {
    source: Option<(EnvironmentMap, u32)>,
    lights: Vec<Light>,
}

impl EnvironmentLights {
    /// `count` lights for `env` (none without a map). Returns whether they changed.
    pub fn update(&mut self, env: Option<&EnvironmentMap>, count: u32) -> bool {
        let unchanged = match (&self.source, env) {
            (Some((map, n)), Some(env)) => *n == count && map == env,
            (None, None) => true,
            _ => false,
        };
        if !unchanged {
            self.lights = env.map_or_else(Vec::new, |env| environment_lights(env, count));
            self.source = env.map(|env| (env.clone(), count));
        }
        !unchanged
    }

    pub fn lights(&self) -> &[Light] {
        &self.lights
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn lights_are_cut_again_only_when_the_map_or_the_count_changes() {
        let sky = |l: f32| EnvironmentMap {
            width: 8,
            height: 4,
            radiance: vec![Vec3::splat(l); 32],
        };
        let mut cache = EnvironmentLights::default();
        assert!(!cache.update(None, 8), "nothing to nothing");
        assert!(cache.update(Some(&sky(1.0)), 8));
        assert_eq!(cache.lights(), environment_lights(&sky(1.0), 8).as_slice());
        assert!(
            !cache.update(Some(&sky(1.0)), 8),
            "an equal map in a new scene"
        );
        assert!(cache.update(Some(&sky(2.0)), 8));
        assert!(cache.update(Some(&sky(2.0)), 4));
        assert_eq!(cache.lights().len(), 4);
        assert!(cache.update(None, 4));
        assert!(cache.lights().is_empty());
    }

    /// A uniform sky of radiance L gives a horizontal surface E = π L: the lights' irradiance
    /// projected on +Y over the upper hemisphere must sum to that.
    #[test]
    fn uniform_sky_irradiance_is_pi_l() {
        let env = EnvironmentMap {
            width: 64,
            height: 32,
            radiance: vec![Vec3::splat(0.5); 64 * 32],
        };
        let lights = environment_lights(&env, 256);
        assert_eq!(lights.len(), 256);
        let e: f32 = lights
            .iter()
            .map(|l| match l {
                Light::Directional {
                    direction_in_world,
                    irradiance,
                } => irradiance.x * (-direction_in_world.y).max(0.0),
                _ => 0.0,
            })
            .sum();
        let expected = std::f32::consts::PI * 0.5;
        assert!(
            (e - expected).abs() < 0.03 * expected,
            "E = {e}, expected {expected}"
        );
    }

    /// A bright window takes the lights: nearly all land on it, and their irradiance sums to
    /// the window's (its radiance × solid angle).
    #[test]
    fn bright_window_draws_the_lights() {
        let (w, h) = (64usize, 32usize);
        let mut radiance = vec![Vec3::splat(1e-3); w * h];
        for y in 10..14 {
            for x in 20..24 {
                radiance[y * w + x] = Vec3::splat(1e3);
            }
        }
        let env = EnvironmentMap {
            width: w as u32,
            height: h as u32,
            radiance,
        };
        let lights = environment_lights(&env, 64);
        let on_window = lights
            .iter()
            .filter(|l| matches!(l, Light::Directional { irradiance, .. } if irradiance.x > 1.0))
            .count();
        assert!(on_window >= 60, "{on_window} of 64 on the window");
    }

    #[test]
    fn black_map_gives_no_lights() {
        let env = EnvironmentMap {
            width: 8,
            height: 4,
            radiance: vec![Vec3::ZERO; 32],
        };
        assert!(environment_lights(&env, 16).is_empty());
    }
}
