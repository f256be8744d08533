//! SH9 irradiance of an environment map (Ramamoorthi & Hanrahan 2001) against brute-force
//! integration: within 1% on a smooth map, within the derived worst-case bound (3/32 of the
//! map's energy) on a 1e6:1 sun, exact on a constant map, zero on a dark one.

mod light_support;

use glam::Vec3;
use light_support::*;
use relight_core::scene::EnvironmentMap;
use relight_recon::envmap::map_energy;
use relight_recon::irradiance::{SH9_IRRADIANCE_ERROR_BOUND, irradiance_brute_force, project_sh9};

/// Unit normals spread over the sphere (a Fibonacci lattice).
fn normals(count: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..count)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f32 + 0.5) / count as f32;
            let r = (1.0 - y * y).sqrt();
            let phi = golden * i as f32;
            Vec3::new(r * phi.cos(), y, r * phi.sin())
        })
        .collect()
}

/// Per normal: |E_SH − E| per channel (max), and E (max channel).
fn sh_vs_brute_force(map: &EnvironmentMap) -> Vec<(f32, f32)> {
    let sh = project_sh9(map).unwrap();
    assert!(sh.is_finite());
    normals(80)
        .into_iter()
        .map(|n| {
            let exact = irradiance_brute_force(map, n).unwrap();
            let approx = sh.irradiance(n);
            assert!(approx.is_finite() && exact.is_finite());
            ((approx - exact).abs().max_element(), exact.max_element())
        })
        .collect()
}

#[test]
fn constant_radiance_gives_pi_times_radiance_everywhere() {
    let map = map_from_fn(64, 32, |_| Vec3::new(1.0, 0.5, 0.25));
    let sh = project_sh9(&map).unwrap();
    for n in normals(50) {
        let expected = Vec3::new(1.0, 0.5, 0.25) * std::f32::consts::PI;
        assert!((sh.irradiance(n) - expected).abs().max_element() < 1e-4 * expected.x);
        // The brute-force sum's only error is sampling the cosine at texel centres.
        let brute = irradiance_brute_force(&map, n).unwrap();
        assert!(
            (brute - expected).abs().max_element() < 2e-3 * expected.x,
            "{brute}"
        );
    }
}

#[test]
fn sh9_irradiance_is_within_one_percent_on_a_smooth_sky() {
    let sun = Vec3::new(0.4, 0.7, -0.6).normalize();
    // A smooth sky: brighter overhead, a broad warm glow around the sun's direction (no sharp
    // horizon or disc, whose higher SH bands L2 cannot hold).
    let sky = |d: Vec3| {
        let glow = (2.0 * (d.dot(sun) - 1.0)).exp();
        Vec3::new(0.5, 0.6, 0.8) * (0.6 + 0.4 * d.y) + Vec3::new(1.5, 1.3, 1.0) * glow
    };
    for (w, h) in [(64, 32), (256, 128)] {
        let map = map_from_fn(w, h, sky);
        let errors = sh_vs_brute_force(&map);
        let relative: Vec<f32> = errors.iter().map(|(e, exact)| e / exact).collect();
        let (mean, worst) = (
            relative.iter().sum::<f32>() / relative.len() as f32,
            quantile(&relative, 1.0),
        );
        println!(
            "smooth sky {w}×{h}: SH9 vs brute force relative error mean {mean:.5}, max {worst:.5}"
        );
        assert!(worst < 0.01);
    }
}

#[test]
fn an_overcast_room_shows_what_l2_misses() {
    // Sky over a darker ground with a sharper horizon: not smooth, reported for reference.
    let sun = Vec3::new(0.4, 0.7, -0.6).normalize();
    let map = map_from_fn(128, 64, |d: Vec3| {
        let glow = (3.0 * (d.dot(sun) - 1.0)).exp();
        let above =
            Vec3::new(0.5, 0.6, 0.8) * (0.6 + 0.4 * d.y.max(0.0)) + Vec3::new(2.0, 1.8, 1.5) * glow;
        let ground = Vec3::new(0.25, 0.2, 0.15) * (1.0 + 0.5 * d.y);
        ground.lerp(above, (0.5 + 4.0 * d.y).clamp(0.0, 1.0))
    });
    let energy = map_energy(&map).unwrap().max_element();
    let errors = sh_vs_brute_force(&map);
    let relative: Vec<f32> = errors.iter().map(|(e, exact)| e / exact).collect();
    let of_energy = errors
        .iter()
        .map(|(e, _)| e / energy)
        .fold(0.0f32, f32::max);
    println!(
        "sky over ground: SH9 relative error mean {:.5}, max {:.5}; max error {of_energy:.5} of the map energy",
        relative.iter().sum::<f32>() / relative.len() as f32,
        quantile(&relative, 1.0)
    );
    assert!(of_energy <= SH9_IRRADIANCE_ERROR_BOUND as f32);
}

#[test]
fn sh9_irradiance_of_a_1e6_to_1_sun_stays_within_the_derived_bound() {
    // Nearly all the energy in one point-like source: the L2 truncation's worst case. The
    // bound: |E_SH − E| ≤ (3/32) Σ L ΔΩ for every normal (irradiance module docs).
    let sun = Vec3::new(0.3, 0.8, -0.5).normalize();
    let map = map_from_fn(256, 128, |d| {
        if d.dot(sun) >= 0.7f32.to_radians().cos() {
            Vec3::splat(1e6)
        } else {
            Vec3::splat(1.0)
        }
    });
    let energy = map_energy(&map).unwrap().max_element();
    let errors = sh_vs_brute_force(&map);
    let worst = errors
        .iter()
        .map(|(e, _)| e / energy)
        .fold(0.0f32, f32::max);
    println!(
        "1e6:1 sun: max |E_SH − E| = {worst:.5} of the map energy (bound 3/32 = {:.5})",
        SH9_IRRADIANCE_ERROR_BOUND
    );
    assert!(worst <= SH9_IRRADIANCE_ERROR_BOUND as f32 * 1.001);
    // It is a tight bound: the sun's own grazing normals come close to it.
    assert!(worst > 0.8 * SH9_IRRADIANCE_ERROR_BOUND as f32);
    // Facing the sun, L2 overshoots by 2/32 of the sun's irradiance: A₂(1) = 34/32.
    let sh = project_sh9(&map).unwrap();
    let facing = sh.irradiance(sun).x / irradiance_brute_force(&map, sun).unwrap().x;
    println!("facing the sun: E_SH / E = {facing:.4} (34/32 = 1.0625 for a point source)");
    assert!((facing - 1.0625).abs() < 0.01);
}

#[test]
fn dark_and_poisoned_maps_give_finite_irradiance() {
    let dark = map_from_fn(32, 16, |_| Vec3::ZERO);
    let sh = project_sh9(&dark).unwrap();
    assert!(sh.coeffs.iter().all(|c| *c == Vec3::ZERO));
    assert_eq!(irradiance_brute_force(&dark, Vec3::Y).unwrap(), Vec3::ZERO);
    let mut poisoned = map_from_fn(32, 16, |_| Vec3::ONE);
    poisoned.radiance[10] = Vec3::splat(f32::NAN);
    poisoned.radiance[20] = Vec3::splat(f32::NEG_INFINITY);
    let sh = project_sh9(&poisoned).unwrap();
    assert!(sh.is_finite());
    assert!(
        irradiance_brute_force(&poisoned, Vec3::X)
            .unwrap()
            .is_finite()
    );
    // A zero normal has no irradiance rather than NaN.
    assert_eq!(
        irradiance_brute_force(&poisoned, Vec3::ZERO).unwrap(),
        Vec3::ZERO
    );
    let broken = EnvironmentMap {
        width: 0,
        height: 4,
        radiance: Vec::new(),
    };
    assert!(project_sh9(&broken).is_err());
}
