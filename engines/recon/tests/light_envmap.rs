//! Fish-eye probe → world environment map through the Kannala–Brandt model and the probe's pose:
//! radiance where the probe sees, exactly the probe's energy (a lamp of a few pixels included),
//! black and uncovered where it does not see.

mod light_support;

use glam::{Quat, Vec3};
use light_support::*;
use relight_core::Pose;
use relight_core::camera::KannalaBrandt;
use relight_core::scene::EnvironmentMap;
use relight_recon::envmap::{
    EnvMapError, EnvMapSettings, map_energy, probe_energy, probe_to_environment, texel_direction,
    texel_solid_angle,
};
use relight_sim::probe::ProbeLens;
use relight_sim::rig::equidistant_probe;

/// A smooth coloured sky: brighter towards +Y and towards +X.
fn smooth_world(d: Vec3) -> Vec3 {
    Vec3::new(1.0, 0.9, 0.7) * (1.5 + d.y + 0.5 * d.x + 0.3 * d.z * d.z)
}

/// Mean of `world` over a texel (8 × 8 directions of equal solid angle).
fn texel_mean(map_w: u32, map_h: u32, x: u32, y: u32, world: impl Fn(Vec3) -> Vec3) -> Vec3 {
    let n = 8;
    let (z0, z1) = (
        (std::f64::consts::PI * f64::from(y) / f64::from(map_h)).cos(),
        (std::f64::consts::PI * f64::from(y + 1) / f64::from(map_h)).cos(),
    );
    let mut sum = Vec3::ZERO;
    for i in 0..n {
        let theta = (z0 + (z1 - z0) * (f64::from(i) + 0.5) / f64::from(n)).acos();
        for j in 0..n {
            let phi = std::f64::consts::TAU * (f64::from(x) + (f64::from(j) + 0.5) / f64::from(n))
                / f64::from(map_w);
            sum += world(relight_recon::envmap::direction(theta, phi).as_vec3());
        }
    }
    sum / (n * n) as f32
}

/// Relative errors of fully covered texels against the world's texel means.
fn resampling_errors(lens: &ProbeLens, pose: &Pose, settings: &EnvMapSettings) -> Vec<f32> {
    let hdr = true_probe_radiance(&smooth_world, lens, pose);
    let env = probe_to_environment(&hdr, &lens.model, pose, settings).unwrap();
    assert_finite(&env.map.radiance, "map");
    let (w, h) = (settings.width, settings.height);
    (0..w * h)
        .filter(|&i| env.coverage[i as usize] == 1.0)
        .map(|i| {
            let truth = texel_mean(w, h, i % w, i / w, smooth_world);
            ((env.map.radiance[i as usize] - truth).abs() / truth).max_element()
        })
        .collect()
}

#[test]
fn the_map_shows_the_world_the_probe_saw() {
    let lens = equidistant_probe(128, 185.0);
    let settings = EnvMapSettings {
        width: 128,
        height: 64,
        ..EnvMapSettings::default()
    };
    let sideways = Pose::new(
        Quat::from_rotation_y(-std::f32::consts::FRAC_PI_2) * Quat::from_rotation_x(0.4),
        Vec3::new(0.3, 1.0, -2.0),
    );
    for (name, pose) in [("upward", upward_probe()), ("sideways, tilted", sideways)] {
        let errors = resampling_errors(&lens, &pose, &settings);
        let (mean, p99, worst) = (
            errors.iter().sum::<f32>() / errors.len() as f32,
            quantile(&errors, 0.99),
            quantile(&errors, 1.0),
        );
        println!(
            "{name} probe: {} fully covered texels, relative error mean {mean:.5}, p99 {p99:.5}, max {worst:.5}",
            errors.len()
        );
        assert!(
            errors.len() > 128 * 64 * 4 / 10,
            "about half the sphere is seen"
        );
        assert!(mean < 0.005 && worst < 0.03);
    }
}

/// Black world with one disc of angular radius `radius_deg` around `dir` of radiance 1e4.
fn lamp(dir: Vec3, radius_deg: f32) -> impl Fn(Vec3) -> Vec3 + Sync {
    let cos_radius = radius_deg.to_radians().cos();
    move |d: Vec3| {
        if d.dot(dir) >= cos_radius {
            Vec3::new(1e4, 8e3, 5e3)
        } else {
            Vec3::ZERO
        }
    }
}

fn energy_centroid(map: &EnvironmentMap) -> Vec3 {
    (0..map.width * map.height)
        .map(|i| {
            let (x, y) = (i % map.width, i / map.width);
            texel_direction(map.width, map.height, x, y)
                * luminance(map.radiance[i as usize])
                * texel_solid_angle(map.width, map.height, y) as f32
        })
        .sum::<Vec3>()
        .normalize()
}

/// Energy-weighted mean direction of the probe image's pixels (their centres' rays).
fn probe_centroid(hdr: &relight_recon::hdr::HdrImage, lens: &ProbeLens, pose: &Pose) -> Vec3 {
    let width = hdr.width as usize;
    hdr.radiance
        .iter()
        .enumerate()
        .filter_map(|(i, l)| {
            let pixel = glam::DVec2::new((i % width) as f64, (i / width) as f64);
            let ray = lens.model.unproject(pixel)?;
            let dir = pose.transform_vector(relight_core::camera::gl_from_optical(ray).as_vec3());
            Some(dir * luminance(*l))
        })
        .sum::<Vec3>()
        .normalize()
}

#[test]
fn a_lamp_a_few_pixels_wide_keeps_its_energy_and_direction() {
    let lens = equidistant_probe(128, 185.0);
    let pose = upward_probe();
    let settings = EnvMapSettings::default();
    let mut worst_energy: f32 = 0.0;
    let mut worst_angle: f32 = 0.0;
    for (dir, radius_deg) in [
        (Vec3::new(0.3, 1.0, -0.2), 2.3),  // the rig's lamp bulb at 0.5 m
        (Vec3::new(-0.8, 0.5, 0.4), 2.3),  // low, where pixels stretch
        (Vec3::new(0.05, 1.0, 0.02), 1.0), // near the zenith (the map's pole)
        (Vec3::new(0.6, 0.7, 0.3), 0.27),  // a sun: well under a pixel
        (Vec3::new(-0.2, 0.9, -0.6), 0.27),
    ] {
        let dir = dir.normalize();
        let world = lamp(dir, radius_deg);
        let hdr = true_probe_radiance(&world, &lens, &pose);
        let env = probe_to_environment(&hdr, &lens.model, &pose, &settings).unwrap();
        let seen = probe_energy(&hdr, &lens.model, settings.field_of_view_deg).unwrap();
        let mapped = map_energy(&env.map).unwrap();
        let analytic = Vec3::new(1e4, 8e3, 5e3)
            * (std::f32::consts::TAU * (1.0 - radius_deg.to_radians().cos()));
        let energy_error = ((mapped - seen).abs() / seen).max_element();
        let centroid = energy_centroid(&env.map);
        let (from_probe, from_truth) = (
            angle_deg(centroid, probe_centroid(&hdr, &lens, &pose)),
            angle_deg(centroid, dir),
        );
        println!(
            "lamp r = {radius_deg}° at {dir:.2}: map/probe energy − 1 = {energy_error:.2e}, \
             probe/analytic = {:.4}, map centroid off the probe's by {from_probe:.3}°, off the \
             truth by {from_truth:.3}°",
            seen.x / analytic.x
        );
        worst_energy = worst_energy.max(energy_error);
        worst_angle = worst_angle.max(from_probe);
        // A sub-pixel sun reaches the image through one of the simulator's 4 × 4 rays per
        // pixel, so the probe itself only knows its direction to within a pixel (1.45°).
        assert!(from_truth < if radius_deg > 2.0 { 0.1 } else { 1.45 });
        // The simulator integrates a pixel with 4 × 4 rays: only discs wider than a pixel
        // (1.45° here) come out of it with their analytic energy.
        if radius_deg > 2.0 {
            assert!(((seen - analytic).abs() / analytic).max_element() < 0.02);
        }
    }
    assert!(worst_energy < 1e-4, "energy error {worst_energy}");
    assert!(worst_angle < 0.1, "direction error {worst_angle}°");
}

#[test]
fn directions_the_probe_cannot_see_are_black_and_uncovered() {
    let lens = equidistant_probe(64, 185.0);
    let pose = upward_probe();
    let hdr = true_probe_radiance(&|_| Vec3::ONE, &lens, &pose);
    let settings = EnvMapSettings {
        width: 64,
        height: 32,
        field_of_view_deg: 180.0,
        samples_per_axis: None,
    };
    let env = probe_to_environment(&hdr, &lens.model, &pose, &settings).unwrap();
    for y in 0..32u32 {
        for x in 0..64u32 {
            let i = (y * 64 + x) as usize;
            let (coverage, radiance) = (env.coverage[i], env.map.radiance[i]);
            if y < 16 {
                assert_eq!(coverage, 1.0, "texel ({x}, {y}) above the horizon");
                assert!(
                    (radiance - Vec3::ONE).abs().max_element() < 0.02,
                    "{radiance}"
                );
            } else {
                assert_eq!(coverage, 0.0, "texel ({x}, {y}) below the horizon");
                assert_eq!(radiance, Vec3::ZERO);
            }
        }
    }
    // A 185° field reaches 2.5° below the horizon: the first row below is partly seen, and its
    // texels hold the seen energy over their whole solid angle.
    let wider = EnvMapSettings {
        field_of_view_deg: 185.0,
        ..settings
    };
    let env = probe_to_environment(&hdr, &lens.model, &pose, &wider).unwrap();
    let coverage = env.coverage[16 * 64];
    // Share of the row's solid angle (θ from 90° to 95.625°) above θ = 92.5°.
    let expected = 2.5f32.to_radians().sin() / (std::f32::consts::PI / 32.0).sin();
    let radiance = env.map.radiance[16 * 64].x;
    println!(
        "row below the horizon: coverage {coverage:.4} (the band's share: {expected:.4}), \
         radiance {radiance:.4} (1 where seen)"
    );
    // Coverage is counted in the texel's 8 strata along θ; the radiance is the seen energy over
    // the whole texel, a little less than the coverage because the rim pixels are partly black.
    assert!((coverage - expected).abs() <= 1.0 / 8.0);
    assert!(radiance > 0.5 * expected && radiance <= coverage * 1.02);
}

#[test]
fn bad_inputs_are_refused() {
    let lens = equidistant_probe(32, 185.0);
    let pose = upward_probe();
    let hdr = true_probe_radiance(&|_| Vec3::ONE, &lens, &pose);
    let other = KannalaBrandt {
        width: 64,
        ..lens.model
    };
    assert!(matches!(
        probe_to_environment(&hdr, &other, &pose, &EnvMapSettings::default()),
        Err(EnvMapError::ProbeSize { .. })
    ));
    for fov in [0.0, -10.0, f64::NAN, 400.0] {
        let settings = EnvMapSettings {
            field_of_view_deg: fov,
            ..EnvMapSettings::default()
        };
        assert!(matches!(
            probe_to_environment(&hdr, &lens.model, &pose, &settings),
            Err(EnvMapError::FieldOfView(_))
        ));
    }
    let empty = EnvMapSettings {
        width: 0,
        ..EnvMapSettings::default()
    };
    assert!(matches!(
        probe_to_environment(&hdr, &lens.model, &pose, &empty),
        Err(EnvMapError::EmptyMap { .. })
    ));
    let broken_lens = KannalaBrandt {
        fx: f64::NAN,
        ..lens.model
    };
    assert!(matches!(
        probe_to_environment(&hdr, &broken_lens, &pose, &EnvMapSettings::default()),
        Err(EnvMapError::Lens(_))
    ));
    // NaN and negative radiance in the probe read as zero.
    let mut poisoned = hdr.clone();
    poisoned.radiance[32 * 16 + 16] = Vec3::new(f32::NAN, f32::INFINITY, -5.0);
    let env =
        probe_to_environment(&poisoned, &lens.model, &pose, &EnvMapSettings::default()).unwrap();
    assert_finite(&env.map.radiance, "map from a poisoned probe");
}

#[test]
fn resampling_time_for_a_256_by_128_map() {
    let lens = equidistant_probe(128, 185.0);
    let pose = upward_probe();
    let hdr = true_probe_radiance(&smooth_world, &lens, &pose);
    let start = std::time::Instant::now();
    let env = probe_to_environment(&hdr, &lens.model, &pose, &EnvMapSettings::default()).unwrap();
    println!(
        "128² probe → 256×128 map in {:?} ({} threads)",
        start.elapsed(),
        rayon::current_num_threads()
    );
    assert_eq!(env.map.radiance.len(), 256 * 128);
}

#[test]
fn a_fine_real_probe_is_filtered_to_the_map_and_keeps_its_energy() {
    // A 1280 × 1024, 185° lens with distortion (the camera tests' probe) at 2/5 scale against a
    // 64 × 32 map: a texel spans ~6 of its pixels, so the image is box-filtered ×3 first.
    let model = KannalaBrandt {
        width: 1280,
        height: 1024,
        fx: 330.0,
        fy: 331.0,
        cx: 639.5,
        cy: 511.5,
        k1: -0.01,
        k2: 0.005,
        k3: -0.002,
        k4: 0.0005,
    }
    .resized(512, 410);
    let pose = Pose::new(
        Quat::from_rotation_x(std::f32::consts::FRAC_PI_2),
        Vec3::ZERO,
    );
    let lamp_dir = Vec3::new(0.3, 0.9, -0.2).normalize();
    let lamp_world = lamp(lamp_dir, 2.0);
    let world = |d: Vec3| smooth_world(d) + lamp_world(d);
    // Pixel-centre radiance over the lens's 185° (no supersampling: the world is smooth, the
    // lamp 5 pixels wide).
    let width = model.width as usize;
    let radiance: Vec<Vec3> = (0..width * model.height as usize)
        .map(|i| {
            let pixel = glam::DVec2::new((i % width) as f64, (i / width) as f64);
            model
                .unproject(pixel)
                .filter(|ray| ray.z >= 92.5f64.to_radians().cos())
                .map_or(Vec3::ZERO, |ray| {
                    world(
                        pose.transform_vector(relight_core::camera::gl_from_optical(ray).as_vec3()),
                    )
                })
        })
        .collect();
    let hdr = relight_recon::hdr::HdrImage {
        width: model.width,
        height: model.height,
        saturated: vec![false; radiance.len()],
        radiance,
    };
    let settings = EnvMapSettings {
        width: 64,
        height: 32,
        ..EnvMapSettings::default()
    };
    let start = std::time::Instant::now();
    let env = probe_to_environment(&hdr, &model, &pose, &settings).unwrap();
    let elapsed = start.elapsed();
    let seen = probe_energy(&hdr, &model, 180.0).unwrap();
    let mapped = map_energy(&env.map).unwrap();
    let energy_error = ((mapped - seen).abs() / seen).max_element();
    let errors: Vec<f32> = (0..64 * 32u32)
        .filter(|&i| {
            env.coverage[i as usize] == 1.0 && {
                let d = texel_direction(64, 32, i % 64, i / 64);
                d.dot(lamp_dir) < 10f32.to_radians().cos()
            }
        })
        .map(|i| {
            let truth = texel_mean(64, 32, i % 64, i / 64, smooth_world);
            ((env.map.radiance[i as usize] - truth).abs() / truth).max_element()
        })
        .collect();
    let angle = angle_deg(
        energy_centroid_of(&env.map, &|d| d.dot(lamp_dir) > 0.98),
        lamp_dir,
    );
    println!(
        "512×410 distorted probe → 64×32 map in {elapsed:?}: map/probe energy − 1 = \
         {energy_error:.2e}; sky texels relative error mean {:.4}, max {:.4}; lamp centroid {angle:.3}° off",
        errors.iter().sum::<f32>() / errors.len() as f32,
        quantile(&errors, 1.0)
    );
    assert!(energy_error < 2e-3);
    assert!(quantile(&errors, 1.0) < 0.03);
    assert!(angle < 0.5);
}

/// Energy centroid of the texels whose direction passes `keep`.
fn energy_centroid_of(map: &EnvironmentMap, keep: &dyn Fn(Vec3) -> bool) -> Vec3 {
    (0..map.width * map.height)
        .filter_map(|i| {
            let (x, y) = (i % map.width, i / map.width);
            let d = texel_direction(map.width, map.height, x, y);
            keep(d).then(|| {
                d * luminance(map.radiance[i as usize])
                    * texel_solid_angle(map.width, map.height, y) as f32
            })
        })
        .sum::<Vec3>()
        .normalize()
}
