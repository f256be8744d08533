//! The reference never returns NaN or ∞, whatever the scene throws at it: degenerate and
//! broken triangles, missing or zero normals, lights inside geometry or on a surface, grazing
//! light, extreme Phong exponents, out-of-range material indices, and an environment with a
//! 1e6:1 range plus NaN and negative texels.

use glam::Vec3;
use relight_core::Pose;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Material, Mesh, Scene, SceneCamera};
use relight_reference::shapes::{cuboid, quad, uv_sphere};
use relight_reference::{ReferenceImages, ReferenceSettings, render_reference};

fn material(albedo: f32, specular: f32, shininess: f32) -> Material {
    Material {
        name: "m".into(),
        albedo: Vec3::splat(albedo),
        specular: Vec3::splat(specular),
        shininess,
        emission: Vec3::ZERO,
    }
}

fn nasty_scene() -> Scene {
    let degenerate = Mesh {
        name: "degenerate".into(),
        positions_in_world: vec![
            Vec3::new(0.2, 0.3, 0.0),
            Vec3::new(0.2, 0.3, 0.0),
            Vec3::new(0.2, 0.3, 0.0),
            // Collinear: zero area, non-zero edges.
            Vec3::new(-0.5, 0.2, 0.0),
            Vec3::new(0.0, 0.2, 0.0),
            Vec3::new(0.5, 0.2, 0.0),
            Vec3::new(f32::NAN, 0.0, 0.0),
        ],
        // Fewer normals than positions, and the ones there are zero.
        normals_in_world: vec![Vec3::ZERO; 3],
        triangles: vec![[0, 1, 2], [3, 4, 5], [0, 3, 6], [0, 1, 99]],
        material: 1,
        is_virtual: true,
        vertex_albedo: Vec::new(),
    };
    let mut zero_normals = quad(
        "zero-normals",
        Vec3::new(-0.8, 0.4, -0.5),
        Vec3::X * 0.3,
        Vec3::Y * 0.3,
        2,
        true,
    );
    zero_normals.normals_in_world.fill(Vec3::ZERO);
    let mut nan_normals = cuboid(
        "nan-normals",
        Vec3::new(0.5, 0.0, -0.8),
        Vec3::new(0.9, 0.4, -0.4),
        3,
        false,
    );
    nan_normals.normals_in_world.fill(Vec3::NAN);
    let mut back_facing = uv_sphere("back-facing", Vec3::new(0.0, 0.3, 0.6), 0.25, 8, 5, 1, true);
    // Shading normals pointing into the sphere, against the geometric ones.
    for n in &mut back_facing.normals_in_world {
        *n = -*n;
    }
    let mut environment = EnvironmentMap {
        width: 16,
        height: 8,
        radiance: vec![Vec3::splat(1e-2); 128],
    };
    environment.radiance[35] = Vec3::splat(1e4);
    environment.radiance[36] = Vec3::new(1e4, 0.0, 0.0);
    environment.radiance[3] = Vec3::NAN;
    environment.radiance[4] = Vec3::splat(-5.0);
    environment.radiance[5] = Vec3::INFINITY;
    Scene {
        name: "nasty".into(),
        meshes: vec![
            quad(
                "floor",
                Vec3::ZERO,
                Vec3::X * 2.0,
                Vec3::NEG_Z * 2.0,
                0,
                false,
            ),
            degenerate,
            zero_normals,
            nan_normals,
            back_facing,
            // A lamp boxed in: its light must not leak, and nothing may divide by zero.
            cuboid(
                "lamp-box",
                Vec3::new(-1.5, 0.0, -1.5),
                Vec3::new(-1.1, 0.4, -1.1),
                7,
                false,
            ),
        ],
        materials: vec![
            material(0.7, 0.2, 1e6),
            material(0.5, 0.5, 1e30),
            Material {
                emission: Vec3::splat(f32::NAN),
                ..material(0.3, 0.0, f32::NAN)
            },
            Material {
                emission: Vec3::splat(50.0),
                ..material(0.0, 0.9, 0.5)
            },
        ],
        camera: SceneCamera {
            world_from_camera: Pose::look_at(Vec3::new(0.0, 1.5, 2.0), Vec3::ZERO, Vec3::Y),
            yfov_rad: 1.2,
            width: 24,
            height: 16,
        },
        lights: vec![
            // Inside the lamp box.
            Light::Point {
                position_in_world: Vec3::new(-1.3, 0.2, -1.3),
                intensity: Vec3::splat(100.0),
            },
            // Exactly on the floor.
            Light::Point {
                position_in_world: Vec3::new(0.7, 0.0, 0.3),
                intensity: Vec3::splat(5.0),
            },
            // Grazing the floor.
            Light::Directional {
                direction_in_world: Vec3::new(1.0, -1e-6, 0.0).normalize(),
                irradiance: Vec3::splat(3.0),
            },
            Light::Spot {
                position_in_world: Vec3::new(0.0, 1.0, 0.0),
                direction_in_world: Vec3::NEG_Y,
                intensity: Vec3::splat(10.0),
                inner_angle_rad: 0.2,
                outer_angle_rad: 0.2,
            },
            // Invalid: skipped, not propagated.
            Light::Point {
                position_in_world: Vec3::new(f32::NAN, 1.0, 0.0),
                intensity: Vec3::splat(1.0),
            },
        ],
        environment: Some(environment),
        environment_lights: Vec::new(),
        shadow_proxy: None,
        surface_revision: None,
    }
}

fn assert_all_finite(images: &ReferenceImages) {
    for (name, image) in [
        ("l_rho", &images.l_rho),
        ("l_mu", &images.l_mu),
        ("delta", &images.delta),
        ("delta_std_error", &images.delta_std_error),
        ("l_rho_std_error", &images.l_rho_std_error),
    ] {
        for (i, v) in image.iter().enumerate() {
            assert!(v.is_finite(), "{name}[{i}] = {v}");
        }
    }
}

#[test]
fn nasty_scene_renders_finite_images() {
    let images = render_reference(
        &nasty_scene(),
        ReferenceSettings {
            spp: 8,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    assert_all_finite(&images);
    assert!(images.l_rho.iter().all(|v| v.min_element() >= 0.0));
    assert!(images.l_rho.iter().any(|v| v.max_element() > 0.0));
    assert!(images.delta.iter().any(|v| *v != Vec3::ZERO));
}

#[test]
fn environment_with_a_million_to_one_range_stays_finite() {
    let mut scene = nasty_scene();
    scene.lights.clear();
    scene.meshes.truncate(1);
    let environment = scene.environment.as_mut().unwrap();
    environment.radiance.fill(Vec3::splat(1e-3));
    environment.radiance[40] = Vec3::splat(1e3);
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 4,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    assert_all_finite(&images);
    assert!(images.l_rho.iter().any(|v| v.max_element() > 0.0));
}

#[test]
fn empty_and_black_scenes_render_black() {
    let mut scene = nasty_scene();
    scene.meshes.clear();
    scene.lights.clear();
    scene.environment = None;
    let images = render_reference(&scene, ReferenceSettings::default()).unwrap();
    assert!(images.l_rho.iter().all(|v| *v == Vec3::ZERO));
    assert!(images.delta.iter().all(|v| *v == Vec3::ZERO));

    // An all-black environment has nothing to importance-sample; it must still render.
    let mut scene = nasty_scene();
    scene
        .environment
        .as_mut()
        .unwrap()
        .radiance
        .fill(Vec3::ZERO);
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 2,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    assert_all_finite(&images);
}
