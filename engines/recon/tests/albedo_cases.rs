//! DLPV eq. 1 on hand-made frames where the answer is known in closed form: the value and its
//! units (k_d = π L / E), every skip rule (saturated, unlit, shadowed by a caller's mask,
//! highlight, above one, no surface), the temporal mean and its resets, and inputs that must be
//! errors rather than panics.

use std::f32::consts::PI;

use glam::Vec3;
use relight_core::camera::Pinhole;
use relight_core::light::Light;
use relight_core::srgb::srgb_to_linear;
use relight_core::{Image, PixelFormat, Pose};
use relight_recon::albedo::{
    AlbedoError, AlbedoEstimator, AlbedoInput, AlbedoSettings, ColorDecoding, PixelClass,
    ShadowQuery, fully_visible, lambertian_albedo,
};
use relight_recon::depth::DepthMap;
use relight_recon::normals::{NormalMap, NormalSettings, PositionMap, normals, positions};
use relight_recon::temporal::ResetReason;

const W: u32 = 12;
const H: u32 = 9;
const EXPOSURE: f32 = 0.5;

fn camera() -> Pinhole {
    Pinhole {
        width: W,
        height: H,
        fx: 6.0,
        fy: 6.0,
        cx: f64::from(W - 1) / 2.0,
        cy: f64::from(H - 1) / 2.0,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    }
}

/// A wall 1 m in front of the camera (at the world origin, looking down −Z).
fn wall(depth_m: f32) -> (PositionMap, NormalMap) {
    let depth = DepthMap {
        width: W,
        height: H,
        metres: vec![depth_m; (W * H) as usize],
    };
    let points = positions(&depth, &camera()).unwrap();
    let normal_map = normals(&points, &NormalSettings::default());
    (points, normal_map)
}

fn colour(code: impl Fn(usize) -> [u8; 3]) -> Image {
    let mut image = Image::new(W, H, PixelFormat::Rgb8);
    for (i, px) in image.as_u8_mut().unwrap().chunks_exact_mut(3).enumerate() {
        px.copy_from_slice(&code(i));
    }
    image
}

/// A distant light at 60° from the wall's normal, in the x–z plane: the mirror direction of
/// every view ray is far from it.
fn oblique_light(irradiance: Vec3) -> Light {
    let to_light = Vec3::new(60f32.to_radians().sin(), 0.0, 60f32.to_radians().cos());
    Light::Directional {
        direction_in_world: -to_light,
        irradiance,
    }
}

fn estimator() -> AlbedoEstimator {
    AlbedoEstimator::new(
        AlbedoSettings::default(),
        ColorDecoding::srgb(EXPOSURE).unwrap(),
    )
}

#[test]
fn eq1_gives_pi_radiance_over_irradiance() {
    let (points, normal_map) = wall(1.0);
    let irradiance = Vec3::new(10.0, 8.0, 6.0);
    let lights = [oblique_light(irradiance)];
    let codes = [150u8, 120, 90];
    let image = colour(|_| codes);
    let input = AlbedoInput {
        color: &image,
        positions: &points,
        normals: &normal_map,
        camera: &camera(),
        world_from_camera: Pose::IDENTITY,
        lights: &lights,
        indirect_irradiance: &[],
    };
    let frame = estimator().estimate(&input, fully_visible).unwrap();
    let radiance = Vec3::from_array(codes.map(srgb_to_linear)) / EXPOSURE;
    let expected = PI * radiance / (irradiance * 0.5);
    assert_eq!(frame.census.estimated, (W * H) as usize);
    for a in &frame.albedo {
        assert!(
            (a.unwrap() - expected).abs().max_element() < 1e-4,
            "{a:?} vs {expected}"
        );
    }
    assert_eq!(lambertian_albedo(Vec3::ONE, Vec3::new(1.0, 0.0, 1.0)), None);
    assert_eq!(
        lambertian_albedo(Vec3::ONE, Vec3::splat(PI)),
        Some(Vec3::ONE)
    );
}

#[test]
fn every_skip_rule_has_its_pixel() {
    let (mut points, mut normal_map) = wall(1.0);
    let lights = [
        oblique_light(Vec3::splat(8.0)),
        // From behind the camera: its mirror direction is the view ray's at the image centre.
        Light::Directional {
            direction_in_world: -Vec3::Z,
            irradiance: Vec3::splat(0.2),
        },
    ];
    let centre = (H / 2 * W + W / 2) as usize;
    let (saturated, dark, too_bright, shadowed, no_depth, no_normal) = (0, 1, 2, 3, 4, 5);
    points.points_in_camera[no_depth] = None;
    normal_map.normals_in_camera[no_depth] = None;
    normal_map.normals_in_camera[no_normal] = None;
    let image = colour(|i| match i {
        _ if i == saturated => [255, 100, 100],
        _ if i == too_bright => [249, 249, 249],
        _ => [120, 120, 120],
    });
    // An unlit pixel: a normal facing away from both lights (only a bounce could light it).
    normal_map.normals_in_camera[dark] = Some(Vec3::new(-1.0, 0.0, 0.0));
    let input = AlbedoInput {
        color: &image,
        positions: &points,
        normals: &normal_map,
        camera: &camera(),
        world_from_camera: Pose::IDENTITY,
        lights: &lights,
        indirect_irradiance: &[],
    };
    // The caller's shadow mask: pixel `shadowed` is in the oblique light's shadow.
    let mask = |q: &ShadowQuery| {
        if q.pixel_index == shadowed && q.light_index == 0 {
            0.0
        } else {
            1.0
        }
    };
    let frame = estimator().estimate(&input, mask).unwrap();
    assert_eq!(frame.class[saturated], PixelClass::Saturated);
    assert_eq!(frame.class[dark], PixelClass::Unlit);
    assert_eq!(frame.class[too_bright], PixelClass::AboveOne);
    assert_eq!(frame.class[shadowed], PixelClass::Shadowed);
    assert_eq!(frame.class[no_depth], PixelClass::NoSurface);
    assert_eq!(frame.class[no_normal], PixelClass::NoSurface);
    assert_eq!(frame.class[centre], PixelClass::Highlight);
    assert_eq!(frame.class[W as usize * 2 + 1], PixelClass::Estimated);
    for k in [
        saturated, dark, too_bright, shadowed, no_depth, no_normal, centre,
    ] {
        assert_eq!(frame.albedo[k], None, "pixel {k}");
    }
    // A visibility function returning NaN or out-of-range values is clamped, not propagated.
    let frame = estimator().estimate(&input, |_| f32::NAN).unwrap();
    assert!(frame.albedo.iter().flatten().all(|a| a.is_finite()));
    let frame = estimator().estimate(&input, |_| 7.0).unwrap();
    assert!(frame.albedo.iter().flatten().all(|a| a.is_finite()));
}

#[test]
fn the_temporal_mean_averages_agreeing_frames_and_restarts_on_change() {
    let (points, normal_map) = wall(1.0);
    let lights = [oblique_light(Vec3::splat(8.0))];
    let mut estimator = estimator();
    let mut run = |code: u8, pose: Pose| {
        let image = colour(|_| [code; 3]);
        let input = AlbedoInput {
            color: &image,
            positions: &points,
            normals: &normal_map,
            camera: &camera(),
            world_from_camera: pose,
            lights: &lights,
            indirect_irradiance: &[],
        };
        estimator.estimate(&input, fully_visible).unwrap()
    };
    let first = run(120, Pose::IDENTITY);
    assert_eq!(first.reset, Some(ResetReason::FirstFrame));
    let a = first.albedo[0].unwrap();
    // A slightly brighter frame (within the noise) is averaged in.
    let second = run(123, Pose::IDENTITY);
    let b = second.this_frame[0].unwrap();
    assert!((second.albedo[0].unwrap() - (a + b) / 2.0).length() < 1e-5);
    assert_eq!(second.census.continued, (W * H) as usize);
    // The wall was repainted: the estimate restarts at the new value, no blend.
    let third = run(200, Pose::IDENTITY);
    assert_eq!(third.census.restarted, (W * H) as usize);
    assert_eq!(third.albedo[0], third.this_frame[0]);
    // A camera jump restarts everything, even an agreeing estimate. (The wall moves with the
    // camera here, so the same pixels see the same colour after the jump.)
    let jumped = run(200, Pose::from_translation(Vec3::new(0.5, 0.0, 0.0)));
    assert!(matches!(jumped.reset, Some(ResetReason::PoseJump { .. })));
    assert_eq!(jumped.census.continued, 0);
    assert_eq!(jumped.albedo[0], jumped.this_frame[0]);
}

#[test]
fn skipped_pixels_keep_their_history() {
    let (points, normal_map) = wall(1.0);
    let lit = [oblique_light(Vec3::splat(8.0))];
    let mut estimator = estimator();
    let image = colour(|_| [120; 3]);
    let input = AlbedoInput {
        color: &image,
        positions: &points,
        normals: &normal_map,
        camera: &camera(),
        world_from_camera: Pose::IDENTITY,
        lights: &lit,
        indirect_irradiance: &[],
    };
    let first = estimator.estimate(&input, fully_visible).unwrap();
    // Everything in shadow next frame: nothing new is estimated, the old values stay.
    let shadowed = estimator.estimate(&input, |_| 0.0).unwrap();
    assert_eq!(shadowed.census.shadowed, (W * H) as usize);
    assert_eq!(shadowed.albedo, first.albedo);
    assert!(shadowed.this_frame.iter().all(Option::is_none));
}

#[test]
fn no_geometry_and_bad_inputs_do_not_panic() {
    let (points, normal_map) = wall(0.0);
    assert!(points.points_in_camera.iter().all(Option::is_none));
    let lights = [oblique_light(Vec3::splat(8.0))];
    let image = colour(|_| [120; 3]);
    let input = AlbedoInput {
        color: &image,
        positions: &points,
        normals: &normal_map,
        camera: &camera(),
        world_from_camera: Pose::IDENTITY,
        lights: &lights,
        indirect_irradiance: &[],
    };
    let frame = estimator().estimate(&input, fully_visible).unwrap();
    assert_eq!(frame.census.no_surface, (W * H) as usize);
    assert!(frame.albedo.iter().all(Option::is_none));

    // No lights at all: every surface pixel is unlit.
    let (points, normal_map) = wall(1.0);
    let dark = AlbedoInput {
        positions: &points,
        normals: &normal_map,
        lights: &[],
        ..input
    };
    let frame = estimator().estimate(&dark, fully_visible).unwrap();
    assert_eq!(frame.census.unlit, (W * H) as usize);

    let grey = Image::new(W, H, PixelFormat::Mono8);
    let wrong_format = AlbedoInput {
        color: &grey,
        ..dark
    };
    assert!(matches!(
        estimator().estimate(&wrong_format, fully_visible),
        Err(AlbedoError::ColorFormat { .. })
    ));
    let small = Image::new(W - 1, H, PixelFormat::Rgb8);
    let wrong_size = AlbedoInput {
        color: &small,
        ..dark
    };
    assert!(matches!(
        estimator().estimate(&wrong_size, fully_visible),
        Err(AlbedoError::SizeMismatch { .. })
    ));
    assert!(ColorDecoding::from_table(&[1.0; 10], 1.0).is_err());
    assert!(ColorDecoding::from_table(&[f32::NAN; 256], 1.0).is_err());
    assert!(ColorDecoding::srgb(0.0).is_err());
    assert!(ColorDecoding::srgb(f32::INFINITY).is_err());
    let bad = AlbedoEstimator::new(
        AlbedoSettings {
            shadow_ratio: f32::NAN,
            ..AlbedoSettings::default()
        },
        ColorDecoding::srgb(1.0).unwrap(),
    );
    assert!(bad.clone().estimate(&dark, fully_visible).is_err());
    // Non-finite lights are ignored rather than poisoning the estimate.
    let poisoned = [
        oblique_light(Vec3::splat(8.0)),
        Light::Point {
            position_in_world: Vec3::splat(f32::NAN),
            intensity: Vec3::ONE,
        },
        Light::Directional {
            direction_in_world: -Vec3::Z,
            irradiance: Vec3::splat(f32::INFINITY),
        },
    ];
    let frame = estimator()
        .estimate(
            &AlbedoInput {
                lights: &poisoned,
                ..dark
            },
            fully_visible,
        )
        .unwrap();
    assert!(frame.albedo.iter().flatten().all(|a| a.is_finite()));
    assert!(frame.census.estimated > 0);
}
