//! The reference path tracer against analytic results and the invariants of differential
//! rendering (DESIGN.md "Accuracy is part of the interface").

use std::f32::consts::PI;

use glam::{Quat, Vec3};
use relight_core::Pose;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Material, Mesh, Scene, SceneCamera};
use relight_engines::reference::{ReferenceImages, ReferenceSettings, render_reference};

fn material(name: &str, albedo: f32) -> Material {
    Material {
        name: name.into(),
        albedo: Vec3::splat(albedo),
        ..Material::default()
    }
}

fn mesh(
    name: &str,
    positions: Vec<Vec3>,
    triangles: Vec<[u32; 3]>,
    material: usize,
    is_virtual: bool,
) -> Mesh {
    let normals = vec![Vec3::ZERO; positions.len()];
    Mesh {
        name: name.into(),
        positions_in_world: positions,
        normals_in_world: normals,
        triangles,
        material,
        is_virtual,
    }
}

/// A horizontal square at height y, half-size s.
fn floor(y: f32, s: f32, material: usize) -> Mesh {
    mesh(
        "floor",
        vec![
            Vec3::new(-s, y, -s),
            Vec3::new(s, y, -s),
            Vec3::new(s, y, s),
            Vec3::new(-s, y, s),
        ],
        vec![[0, 2, 1], [0, 3, 2]],
        material,
        false,
    )
}

/// An axis-aligned box.
fn cube(name: &str, lo: Vec3, hi: Vec3, material: usize, is_virtual: bool) -> Mesh {
    let p = |x: f32, y: f32, z: f32| {
        Vec3::new(
            if x > 0.0 { hi.x } else { lo.x },
            if y > 0.0 { hi.y } else { lo.y },
            if z > 0.0 { hi.z } else { lo.z },
        )
    };
    let positions = vec![
        p(0., 0., 0.),
        p(1., 0., 0.),
        p(1., 1., 0.),
        p(0., 1., 0.),
        p(0., 0., 1.),
        p(1., 0., 1.),
        p(1., 1., 1.),
        p(0., 1., 1.),
    ];
    let triangles = vec![
        [0, 2, 1],
        [0, 3, 2],
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [3, 6, 2],
        [3, 7, 6],
        [0, 4, 7],
        [0, 7, 3],
        [1, 2, 6],
        [1, 6, 5],
    ];
    mesh(name, positions, triangles, material, is_virtual)
}

/// A UV sphere with outward vertex normals.
fn sphere(center: Vec3, radius: f32, material: usize) -> Mesh {
    let (rings, segments) = (24u32, 48u32);
    let mut positions = Vec::new();
    for r in 0..=rings {
        let theta = PI * r as f32 / rings as f32;
        for s in 0..=segments {
            let phi = 2.0 * PI * s as f32 / segments as f32;
            positions.push(
                center
                    + radius
                        * Vec3::new(
                            theta.sin() * phi.cos(),
                            theta.cos(),
                            theta.sin() * phi.sin(),
                        ),
            );
        }
    }
    let mut triangles = Vec::new();
    let row = segments + 1;
    for r in 0..rings {
        for s in 0..segments {
            let (a, b) = (r * row + s, (r + 1) * row + s);
            triangles.push([a, b, a + 1]);
            triangles.push([a + 1, b, b + 1]);
        }
    }
    let normals = positions
        .iter()
        .map(|p| (*p - center).normalize())
        .collect();
    Mesh {
        name: "sphere".into(),
        positions_in_world: positions,
        normals_in_world: normals,
        triangles,
        material,
        is_virtual: false,
    }
}

fn camera(eye: Vec3, target: Vec3, width: u32, height: u32) -> SceneCamera {
    SceneCamera {
        world_from_camera: Pose::look_at(eye, target, Vec3::Y),
        yfov_rad: 0.9,
        width,
        height,
    }
}

fn scene(
    meshes: Vec<Mesh>,
    materials: Vec<Material>,
    lights: Vec<Light>,
    camera: SceneCamera,
) -> Scene {
    Scene {
        name: "test".into(),
        meshes,
        materials,
        camera,
        lights,
        environment: None,
    }
}

fn settings(spp: u32, max_bounces: u32) -> ReferenceSettings {
    ReferenceSettings {
        spp,
        max_bounces,
        ..ReferenceSettings::default()
    }
}

#[test]
fn white_furnace_converges_to_emission_over_one_minus_albedo() {
    let albedo = 0.5;
    let emission = 0.25;
    let mut glowing = material("inside", albedo);
    glowing.emission = Vec3::splat(emission);
    let camera = SceneCamera {
        world_from_camera: Pose::IDENTITY,
        yfov_rad: 1.2,
        width: 8,
        height: 8,
    };
    let scene = scene(
        vec![sphere(Vec3::ZERO, 1.0, 0)],
        vec![glowing],
        vec![],
        camera,
    );
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 256,
            max_bounces: 64,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    let expected = emission / (1.0 - albedo);
    let n = images.l_rho.len() as f32;
    let mean = images.l_rho.iter().map(|l| l.x).sum::<f32>() / n;
    let std_error = (images
        .l_rho_std_error
        .iter()
        .map(|e| e.x * e.x)
        .sum::<f32>())
    .sqrt()
        / n;
    assert!(
        (mean - expected).abs() < 0.01 * expected,
        "furnace {mean} vs {expected}"
    );
    assert!(
        (mean - expected).abs() < 3.0 * std_error + 1e-4,
        "furnace {mean} vs {expected} ± {std_error}"
    );
}

#[test]
fn diffuse_plane_under_a_point_light_matches_the_analytic_irradiance() {
    let (rho, intensity, h) = (0.6, 2.0, 1.0);
    let light = Light::Point {
        position_in_world: Vec3::new(0.0, h, 0.0),
        intensity: Vec3::splat(intensity),
    };
    let camera = SceneCamera {
        world_from_camera: Pose::new(Quat::from_rotation_x(-PI / 2.0), Vec3::new(0.3, 2.0, 0.0)),
        yfov_rad: 0.8,
        width: 24,
        height: 24,
    };
    let scene = scene(
        vec![floor(0.0, 10.0, 0)],
        vec![material("floor", rho)],
        vec![light],
        camera,
    );
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 1,
            max_bounces: 0,
            pixel_jitter: false,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    let tan_half = (0.8f32 / 2.0).tan();
    for y in 0..24 {
        for x in 0..24 {
            // Where the pixel-centre ray meets the floor (camera looks straight down from 2 m,
            // image up = world −Z).
            let ndc_x = (2.0 * (x as f32 + 0.5) / 24.0 - 1.0) * tan_half;
            let ndc_y = (1.0 - 2.0 * (y as f32 + 0.5) / 24.0) * tan_half;
            let hit = Vec3::new(0.3 + ndc_x * 2.0, 0.0, -ndc_y * 2.0);
            let r2 = (Vec3::new(0.0, h, 0.0) - hit).length_squared();
            let cos = h / r2.sqrt();
            let expected = rho / PI * intensity * cos / r2;
            let got = images.l_rho[y * 24 + x].x;
            assert!(
                (got / expected - 1.0).abs() < 0.01,
                "pixel ({x},{y}): {got} vs {expected}"
            );
        }
    }
}

fn shadow_scene(object_albedo: f32, object_lo: Vec3, object_hi: Vec3) -> Scene {
    let light = Light::Point {
        position_in_world: Vec3::new(0.4, 1.5, 0.3),
        intensity: Vec3::splat(3.0),
    };
    let camera = camera(Vec3::new(0.0, 1.2, 1.6), Vec3::new(0.0, 0.1, 0.0), 32, 24);
    scene(
        vec![
            floor(0.0, 2.0, 0),
            cube(
                "wall",
                Vec3::new(-2.0, 0.0, -1.2),
                Vec3::new(2.0, 1.5, -1.1),
                0,
                false,
            ),
            cube("object", object_lo, object_hi, 1, true),
        ],
        vec![material("white", 0.8), material("object", object_albedo)],
        vec![light],
        camera,
    )
}

#[test]
fn delta_is_exactly_zero_without_a_virtual_object_or_with_one_out_of_reach() {
    let mut without = shadow_scene(
        0.8,
        Vec3::new(-0.15, 0.0, -0.15),
        Vec3::new(0.15, 0.3, 0.15),
    );
    without.meshes.retain(|m| !m.is_virtual);
    // 1 km below the floor: no camera ray, shadow ray or bounce can reach it.
    let far = shadow_scene(
        0.8,
        Vec3::new(-0.1, -1000.1, -0.1),
        Vec3::new(0.1, -1000.0, 0.1),
    );
    for scene in [without, far] {
        let images = render_reference(&scene, settings(8, 3)).unwrap();
        assert!(
            images.delta.iter().all(|d| *d == Vec3::ZERO),
            "Δ must be exactly 0"
        );
        assert!(images.delta_std_error.iter().all(|e| *e == Vec3::ZERO));
        assert_eq!(images.l_rho, images.l_mu);
        assert!(images.l_rho.iter().any(|l| l.x > 0.0), "the scene is lit");
    }
}

fn mean_std_error(images: &ReferenceImages, mask: &[bool]) -> f32 {
    let errors: Vec<f32> = images
        .delta_std_error
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .map(|(e, _)| e.x)
        .collect();
    errors.iter().sum::<f32>() / errors.len() as f32
}

#[test]
fn delta_standard_error_falls_as_one_over_root_spp() {
    let scene = shadow_scene(
        0.8,
        Vec3::new(-0.15, 0.0, -0.15),
        Vec3::new(0.15, 0.3, 0.15),
    );
    let coarse = render_reference(&scene, settings(16, 2)).unwrap();
    let fine = render_reference(&scene, settings(64, 2)).unwrap();
    // Pixels where the object matters and that are not the object itself.
    let mask: Vec<bool> = coarse
        .delta_std_error
        .iter()
        .zip(&fine.delta_std_error)
        .zip(&coarse.virtual_mask)
        .map(|((c, f), v)| c.x > 0.0 && f.x > 0.0 && !v)
        .collect();
    assert!(mask.iter().filter(|m| **m).count() > 20);
    let ratio = mean_std_error(&fine, &mask) / mean_std_error(&coarse, &mask);
    assert!(
        (ratio - 0.5).abs() < 0.1,
        "std error ratio at 4× spp: {ratio}"
    );
}

#[test]
fn black_object_casts_only_negative_delta_and_white_object_adds_light() {
    let black = render_reference(
        &shadow_scene(
            0.0,
            Vec3::new(-0.15, 0.0, -0.15),
            Vec3::new(0.15, 0.3, 0.15),
        ),
        settings(16, 3),
    )
    .unwrap();
    for (d, v) in black.delta.iter().zip(&black.virtual_mask) {
        if !v {
            assert!(d.max_element() <= 0.0, "black object added light: {d}");
        }
    }
    assert!(black.delta.iter().any(|d| d.x < -0.01), "it casts a shadow");
    let white = render_reference(
        &shadow_scene(
            0.95,
            Vec3::new(-0.15, 0.0, -0.15),
            Vec3::new(0.15, 0.3, 0.15),
        ),
        settings(256, 3),
    )
    .unwrap();
    let brighter = white
        .delta
        .iter()
        .zip(&white.delta_std_error)
        .zip(&white.virtual_mask)
        .filter(|((d, e), v)| !**v && d.x > 5.0 * e.x && d.x > 1e-3)
        .count();
    let best = white
        .delta
        .iter()
        .zip(&white.delta_std_error)
        .zip(&white.virtual_mask)
        .filter(|(_, v)| !**v)
        .map(|((d, e), _)| (d.x, e.x))
        .fold((0.0f32, 0.0f32), |a, b| if b.0 > a.0 { b } else { a });
    assert!(
        brighter > 0,
        "a white object bounces light onto the real scene: best {best:?}"
    );
}

#[test]
fn no_nan_or_inf_for_hostile_input() {
    let mut scene = shadow_scene(
        0.8,
        Vec3::new(-0.15, 0.0, -0.15),
        Vec3::new(0.15, 0.3, 0.15),
    );
    // Degenerate and NaN triangles, an out-of-range index, zero normals, a light inside the
    // object, a grazing light, a very glossy material, and a 1e6:1 environment.
    scene.meshes.push(mesh(
        "degenerate",
        vec![Vec3::ZERO, Vec3::ZERO, Vec3::X],
        vec![[0, 1, 2], [0, 1, 7]],
        0,
        false,
    ));
    scene.meshes.push(mesh(
        "nan",
        vec![Vec3::NAN, Vec3::ONE, Vec3::X],
        vec![[0, 1, 2]],
        0,
        true,
    ));
    scene.lights.push(Light::Point {
        position_in_world: Vec3::new(0.0, 0.15, 0.0),
        intensity: Vec3::splat(5.0),
    });
    scene.lights.push(Light::Directional {
        direction_in_world: Vec3::new(1.0, -1e-4, 0.0).normalize(),
        irradiance: Vec3::splat(2.0),
    });
    scene.materials[0].specular = Vec3::splat(0.15);
    scene.materials[0].shininess = 5000.0;
    let (w, h) = (16, 8);
    scene.environment = Some(EnvironmentMap {
        width: w,
        height: h,
        radiance: (0..w * h)
            .map(|i| {
                if i == 20 {
                    Vec3::splat(1e6)
                } else {
                    Vec3::splat(1.0)
                }
            })
            .collect(),
    });
    let images = render_reference(&scene, settings(8, 4)).unwrap();
    for image in [
        &images.l_rho,
        &images.l_mu,
        &images.delta,
        &images.delta_std_error,
    ] {
        assert!(image.iter().all(|p| p.is_finite()), "non-finite pixel");
    }
}
