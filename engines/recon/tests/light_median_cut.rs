//! Median cut (Debevec 2005) and variance-minimising median cut (Viriyothai & Debevec 2009):
//! lights where the true lights are, regions that split the energy evenly, and the sum of the
//! lights equal to the map's energy — for any light count and for hostile maps.

mod light_support;

use glam::Vec3;
use light_support::*;
use relight_core::light::Light;
use relight_core::scene::EnvironmentMap;
use relight_recon::envmap::{EnvMapError, map_energy, texel_solid_angle};
use relight_recon::median_cut::{CutMethod, MedianCutSettings, RegionLight, extract_lights};

const METHODS: [CutMethod; 2] = [CutMethod::MedianCut, CutMethod::VarianceMinimizing];

/// A disc light: axis, angular radius (degrees), radiance.
type Disc = (Vec3, f32, Vec3);

fn disc_map(width: u32, height: u32, discs: &[Disc], background: Vec3) -> EnvironmentMap {
    map_from_fn(width, height, |d| {
        discs
            .iter()
            .filter(|(axis, radius_deg, _)| {
                d.dot(axis.normalize()) >= radius_deg.to_radians().cos()
            })
            .fold(background, |sum, (_, _, radiance)| sum + *radiance)
    })
}

/// Energy (red) the map holds in a disc light above the background: its texels × `radiance`.
fn disc_energy(map: &EnvironmentMap, axis: Vec3, radius_deg: f32, radiance: f32) -> f32 {
    let cos_radius = radius_deg.to_radians().cos();
    (0..map.width * map.height)
        .filter(|i| {
            let dir = relight_recon::envmap::texel_direction(
                map.width,
                map.height,
                i % map.width,
                i / map.width,
            );
            dir.dot(axis) >= cos_radius
        })
        .map(|i| radiance * texel_solid_angle(map.width, map.height, i / map.width) as f32)
        .sum()
}

fn extract(map: &EnvironmentMap, method: CutMethod, light_count: usize) -> Vec<RegionLight> {
    extract_lights(
        map,
        &MedianCutSettings {
            method,
            light_count,
        },
    )
    .unwrap()
}

/// For each true light, the angle to the nearest extracted light.
fn nearest_errors(lights: &[RegionLight], truths: &[Vec3]) -> Vec<f32> {
    truths
        .iter()
        .map(|t| {
            lights
                .iter()
                .map(|l| angle_deg(l.direction_to_light, *t))
                .fold(f32::INFINITY, f32::min)
        })
        .collect()
}

fn four_lamps() -> Vec<Disc> {
    vec![
        (Vec3::new(0.4, 0.8, -0.3), 3.0, Vec3::splat(1000.0)),
        (
            Vec3::new(-0.7, 0.5, 0.2),
            3.0,
            Vec3::new(600.0, 500.0, 400.0),
        ),
        (Vec3::new(0.1, 0.3, 0.9), 3.0, Vec3::splat(250.0)),
        (Vec3::new(-0.2, 0.95, -0.6), 3.0, Vec3::splat(120.0)),
    ]
}

#[test]
fn variance_minimisation_puts_a_light_on_every_lamp() {
    let lamps = four_lamps();
    let map = disc_map(256, 128, &lamps, Vec3::splat(0.01));
    let truths: Vec<Vec3> = lamps.iter().map(|(d, ..)| d.normalize()).collect();
    for method in METHODS {
        for count in [4, 8, 16] {
            let errors = nearest_errors(&extract(&map, method, count), &truths);
            println!("{method:?}, {count} lights for 4 lamps: angular errors {errors:.3?}°");
        }
    }
    // With lights to spare for the dim background (its energy, 0.13, is an eighth of the
    // faintest lamp's), every lamp is covered: the lights on its disc (a bright lamp may be cut
    // in two in the last round) together sit on it and carry its energy.
    for count in [8, 16] {
        let lights = extract(&map, CutMethod::VarianceMinimizing, count);
        for (axis, radius_deg, radiance) in &lamps {
            let axis = axis.normalize();
            let on_disc: Vec<&RegionLight> = lights
                .iter()
                .filter(|l| angle_deg(l.direction_to_light, axis) < radius_deg + 1.0)
                .collect();
            let irradiance: Vec3 = on_disc.iter().map(|l| l.irradiance).sum();
            let direction: Vec3 = on_disc
                .iter()
                .map(|l| l.direction_to_light * luminance(l.irradiance))
                .sum();
            let disc = disc_energy(&map, axis, *radius_deg, radiance.x);
            let (ratio, angle) = (irradiance.x / disc, angle_deg(direction, axis));
            println!(
                "  {count} lights, lamp at {axis:.2}: {} light(s) on it, {angle:.3}° off, \
                 irradiance / the disc's energy in the map = {ratio:.4}",
                on_disc.len()
            );
            assert!(angle < 0.3 && (ratio - 1.0).abs() < 0.05);
        }
    }
}

#[test]
fn variance_minimisation_does_not_cut_through_the_brighter_of_two_sources() {
    // Viriyothai & Debevec's Fig. 2: two sources of different power in one region. Median cut
    // halves the energy, so its cut crosses the brighter source and neither light sits on a
    // source; variance minimisation separates them.
    let sources = [
        (Vec3::new(0.5, 0.6, -0.6), 4.0, Vec3::splat(900.0)),
        (Vec3::new(-0.5, 0.6, -0.6), 4.0, Vec3::splat(300.0)),
    ];
    let map = disc_map(128, 64, &sources, Vec3::ZERO);
    let truths: Vec<Vec3> = sources.iter().map(|(d, ..)| d.normalize()).collect();
    let worst = |method| {
        let errors = nearest_errors(&extract(&map, method, 2), &truths);
        println!("{method:?}, 2 lights: angular errors {errors:.3?}°");
        errors.into_iter().fold(0.0f32, f32::max)
    };
    let (median, variance) = (
        worst(CutMethod::MedianCut),
        worst(CutMethod::VarianceMinimizing),
    );
    assert!(variance < 0.5, "{variance}°");
    assert!(
        median > 5.0 * variance.max(0.1),
        "median cut {median}° vs {variance}°"
    );
}

#[test]
fn lights_sum_to_the_map_energy_for_any_count() {
    let mut lamps = four_lamps();
    lamps.push((Vec3::new(0.2, -0.5, 0.4), 20.0, Vec3::new(0.5, 0.2, 0.1)));
    let map = map_from_fn(256, 128, |d| {
        let sky = Vec3::new(0.3, 0.4, 0.6) * (1.0 + d.y).max(0.05);
        lamps
            .iter()
            .filter(|(axis, r, _)| d.dot(axis.normalize()) >= r.to_radians().cos())
            .fold(sky, |sum, (_, _, l)| sum + *l)
    });
    let energy = map_energy(&map).unwrap();
    let mut worst: f32 = 0.0;
    for method in METHODS {
        for count in [1, 2, 3, 5, 8, 12, 16, 31, 64, 256] {
            let lights = extract(&map, method, count);
            assert_eq!(lights.len(), count, "{method:?}");
            let sum: Vec3 = lights.iter().map(|l| l.irradiance).sum();
            let error = ((sum - energy).abs() / energy).max_element();
            worst = worst.max(error);
            assert!(lights.iter().all(|l| l.direction_to_light.is_normalized()));
            // Brightest first.
            assert!(
                lights
                    .windows(2)
                    .all(|w| luminance(w[0].irradiance) >= luminance(w[1].irradiance))
            );
        }
    }
    println!("Σ lights vs map energy: worst relative error {worst:.2e}");
    assert!(worst < 1e-4);
}

#[test]
fn median_cut_rounds_split_the_energy_evenly() {
    // A smooth map: every median-cut region of 2^n should hold about 1/2^n of the energy.
    let map = map_from_fn(256, 128, |d| Vec3::splat(1.0 + 0.8 * d.y + 0.3 * d.x));
    let total = luminance(map_energy(&map).unwrap());
    for count in [2, 4, 8, 16, 32] {
        let lights = extract(&map, CutMethod::MedianCut, count);
        let share = |l: &RegionLight| luminance(l.irradiance) / total * count as f32;
        let (lo, hi) = lights
            .iter()
            .map(share)
            .fold((f32::INFINITY, 0.0f32), |(lo, hi), s| {
                (lo.min(s), hi.max(s))
            });
        println!("median cut, {count} regions: energy share × {count} in [{lo:.3}, {hi:.3}]");
        assert!(lo > 0.85 && hi < 1.15);
    }
}

#[test]
fn a_1e6_to_1_sun_becomes_the_brightest_light_in_its_place() {
    let sun = Vec3::new(0.3, 0.8, -0.5).normalize();
    // 1e6 × the sky's radiance, on a disc of 0.5° (a few texels' worth at 1024 × 512 would be
    // needed to resolve it; at 256 × 128 it falls on one or two texels).
    let map = map_from_fn(256, 128, |d| {
        if d.dot(sun) >= 0.7f32.to_radians().cos() {
            Vec3::splat(1e6)
        } else {
            Vec3::splat(1.0)
        }
    });
    let sun_texels = map.radiance.iter().filter(|l| l.x > 1.0).count();
    let energy = map_energy(&map).unwrap();
    for method in METHODS {
        let lights = extract(&map, method, 16);
        assert!(
            lights
                .iter()
                .all(|l| l.irradiance.is_finite() && l.direction_to_light.is_finite())
        );
        let sum: Vec3 = lights.iter().map(|l| l.irradiance).sum();
        let brightest = lights[0];
        let angle = angle_deg(brightest.direction_to_light, sun);
        let share = brightest.irradiance.x / energy.x;
        println!(
            "{method:?}: sun on {sun_texels} texels, brightest light {angle:.3}° off the sun with \
             {share:.4} of the energy; Σ lights / energy − 1 = {:.2e}",
            (sum.x - energy.x) / energy.x
        );
        assert!(angle < 0.8, "half a texel is 0.7°");
        assert!(((sum - energy).abs() / energy).max_element() < 1e-4);
    }
}

#[test]
fn hostile_maps_give_no_nan_and_documented_results() {
    // All dark: no lights.
    let dark = map_from_fn(64, 32, |_| Vec3::ZERO);
    for method in METHODS {
        assert!(extract(&dark, method, 8).is_empty());
    }
    // NaN, infinite and negative texels read as zero.
    let mut poisoned = map_from_fn(64, 32, |d| Vec3::splat(1.0 + d.y));
    poisoned.radiance[5] = Vec3::new(f32::NAN, 1.0, 1.0);
    poisoned.radiance[700] = Vec3::splat(f32::INFINITY);
    poisoned.radiance[900] = Vec3::splat(-1e9);
    let energy = map_energy(&poisoned).unwrap();
    assert!(energy.is_finite());
    for method in METHODS {
        let lights = extract(&poisoned, method, 8);
        assert_eq!(lights.len(), 8);
        let sum: Vec3 = lights.iter().map(|l| l.irradiance).sum();
        assert!(sum.is_finite() && ((sum - energy).abs() / energy).max_element() < 1e-4);
    }
    // One lit texel: one light, whatever the count asked for.
    let mut single = map_from_fn(16, 8, |_| Vec3::ZERO);
    single.radiance[3 * 16 + 5] = Vec3::splat(2.0);
    for method in METHODS {
        let lights = extract(&single, method, 7);
        assert_eq!(lights.len(), 1);
        let expected = 2.0 * texel_solid_angle(16, 8, 3) as f32;
        assert!((lights[0].irradiance.x - expected).abs() < 1e-6);
        assert!(
            angle_deg(
                lights[0].direction_to_light,
                relight_recon::envmap::texel_direction(16, 8, 5, 3)
            ) < 1e-3
        );
    }
    // A uniform whole sphere with one light: the centroid is undefined, the light still has a
    // direction and all the energy.
    let uniform = map_from_fn(32, 16, |_| Vec3::ONE);
    let lights = extract(&uniform, CutMethod::MedianCut, 1);
    assert_eq!(lights.len(), 1);
    assert!(lights[0].direction_to_light.is_normalized());
    assert!((lights[0].irradiance.x - 4.0 * std::f32::consts::PI).abs() < 1e-4);
    // No light asked for.
    assert!(extract(&uniform, CutMethod::VarianceMinimizing, 0).is_empty());
    // Malformed maps are errors.
    let broken = EnvironmentMap {
        width: 4,
        height: 2,
        radiance: vec![Vec3::ONE; 3],
    };
    assert!(matches!(
        extract_lights(&broken, &MedianCutSettings::default()),
        Err(EnvMapError::MalformedMap { .. })
    ));
}

#[test]
fn a_region_light_is_a_directional_light_shining_from_it() {
    let map = disc_map(64, 32, &[(Vec3::Y, 10.0, Vec3::splat(5.0))], Vec3::ZERO);
    let lights = extract(&map, CutMethod::VarianceMinimizing, 1);
    let Light::Directional {
        direction_in_world,
        irradiance,
    } = lights[0].to_light()
    else {
        panic!("a directional light");
    };
    assert!(
        angle_deg(direction_in_world, -Vec3::Y) < 1e-3,
        "it shines down"
    );
    assert_eq!(irradiance, lights[0].irradiance);
    assert!(lights[0].to_light().validate().is_ok());
}

#[test]
fn extraction_time_on_a_256_by_128_map() {
    let mut lamps = four_lamps();
    lamps.push((Vec3::new(0.0, 1.0, 0.0), 30.0, Vec3::splat(2.0)));
    let map = disc_map(256, 128, &lamps, Vec3::splat(0.05));
    for method in METHODS {
        for count in [16, 64] {
            let start = std::time::Instant::now();
            let lights = extract(&map, method, count);
            println!(
                "{method:?}, {count} lights on 256×128: {:?}",
                start.elapsed()
            );
            assert_eq!(lights.len(), count);
        }
    }
}
