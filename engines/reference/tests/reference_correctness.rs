//! The reference path tracer against closed-form answers: white furnace, a diffuse plane under a
//! point light and under an environment map, and the claims of differential rendering about Δ
//! (exactly zero without influence, standard error falling as 1/√spp, black objects only darken).

use std::f32::consts::{FRAC_1_PI, PI};

use glam::Vec3;
use relight_core::Pose;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Material, Scene, SceneCamera};
use relight_reference::shapes::{cuboid, flipped, quad, uv_sphere};
use relight_reference::{ReferenceImages, ReferenceRenderer, ReferenceSettings, render_reference};

fn diffuse(albedo: Vec3) -> Material {
    Material {
        name: "diffuse".into(),
        albedo,
        ..Material::default()
    }
}

fn camera(eye: Vec3, target: Vec3, width: u32, height: u32) -> SceneCamera {
    SceneCamera {
        world_from_camera: Pose::look_at(eye, target, Vec3::Y),
        yfov_rad: 0.8,
        width,
        height,
    }
}

fn scene(name: &str, camera: SceneCamera) -> Scene {
    Scene {
        name: name.into(),
        meshes: Vec::new(),
        materials: Vec::new(),
        camera,
        lights: Vec::new(),
        environment: None,
        environment_lights: Vec::new(),
        shadow_proxy: None,
        surface_revision: None,
    }
}

/// Mean over all pixels and channels of `values`, and the standard error of that mean from the
/// per-pixel standard errors (pixels are independent).
fn pooled(values: &[Vec3], std_errors: &[Vec3]) -> (f64, f64) {
    let count = (values.len() * 3) as f64;
    let mean = values
        .iter()
        .flat_map(|v| v.to_array())
        .map(f64::from)
        .sum::<f64>()
        / count;
    let variance = std_errors
        .iter()
        .flat_map(|v| v.to_array())
        .map(|se| f64::from(se) * f64::from(se))
        .sum::<f64>();
    (mean, variance.sqrt() / count)
}

fn assert_all_finite(images: &ReferenceImages) {
    for image in [
        &images.l_rho,
        &images.l_mu,
        &images.delta,
        &images.delta_std_error,
        &images.l_rho_std_error,
    ] {
        assert!(image.iter().all(|v| v.is_finite()));
    }
}

#[test]
fn white_furnace_converges_to_emission_over_one_minus_albedo() {
    let albedo = 0.8;
    let emission = Vec3::new(1.0, 0.5, 0.25);
    let mut scene = scene("furnace", camera(Vec3::ZERO, Vec3::NEG_Z, 16, 16));
    scene.camera.yfov_rad = 2.0;
    scene.materials.push(Material {
        emission,
        ..diffuse(Vec3::splat(albedo))
    });
    // Flat shading (zero vertex normals fall back to the geometric normal): with interpolated
    // normals on a coarse sphere, cosine samples around the shading normal can dip below the
    // facet and end the path, a known shading-normal energy loss of about 1% here that is not
    // what this test is about.
    let mut shell = flipped(uv_sphere("shell", Vec3::ZERO, 1.0, 24, 12, 0, false));
    shell.normals_in_world.fill(Vec3::ZERO);
    scene.meshes.push(shell);
    let settings = ReferenceSettings {
        spp: 256,
        max_bounces: 128,
        rr_start_bounce: 3,
        ..ReferenceSettings::default()
    };
    let images = render_reference(&scene, settings).unwrap();
    assert_all_finite(&images);
    for (channel, e) in emission.to_array().into_iter().enumerate() {
        let values: Vec<Vec3> = images
            .l_rho
            .iter()
            .map(|v| Vec3::splat(v[channel]))
            .collect();
        let errors: Vec<Vec3> = images
            .l_rho_std_error
            .iter()
            .map(|v| Vec3::splat(v[channel]))
            .collect();
        let (mean, std_error) = pooled(&values, &errors);
        let expected = f64::from(e) / (1.0 - f64::from(albedo));
        let error = (mean - expected).abs();
        assert!(
            error < 3.0 * std_error.max(1e-9) && error < 0.01 * expected,
            "channel {channel}: {mean} vs {expected} (standard error {std_error})"
        );
    }
}

/// Exact camera ray through the centre of pixel (x, y), as the reference documents it.
fn pixel_centre_ray(camera: &SceneCamera, x: u32, y: u32) -> Vec3 {
    let tan_half = (camera.yfov_rad / 2.0).tan();
    let aspect = camera.width as f32 / camera.height as f32;
    let ndc_x = (2.0 * (x as f32 + 0.5) / camera.width as f32 - 1.0) * tan_half * aspect;
    let ndc_y = (1.0 - 2.0 * (y as f32 + 0.5) / camera.height as f32) * tan_half;
    camera
        .world_from_camera
        .transform_vector(Vec3::new(ndc_x, ndc_y, -1.0).normalize())
}

#[test]
fn diffuse_plane_under_point_light_matches_inverse_square_cosine_law() {
    let (albedo, intensity, height_m) = (Vec3::new(0.5, 0.7, 0.3), Vec3::new(10.0, 8.0, 6.0), 2.0);
    let light_in_world = Vec3::new(0.3, height_m, -0.5);
    let eye = Vec3::new(0.0, 4.0, 3.0);
    let mut scene = scene("plane", camera(eye, Vec3::ZERO, 32, 24));
    scene.materials.push(diffuse(albedo));
    scene.meshes.push(quad(
        "floor",
        Vec3::ZERO,
        Vec3::X * 20.0,
        Vec3::NEG_Z * 20.0,
        0,
        false,
    ));
    scene.lights.push(Light::Point {
        position_in_world: light_in_world,
        intensity,
    });
    let settings = ReferenceSettings {
        spp: 2,
        max_bounces: 0,
        pixel_jitter: false,
        ..ReferenceSettings::default()
    };
    let images = render_reference(&scene, settings).unwrap();
    assert_all_finite(&images);
    let mut worst = 0.0f32;
    for y in 0..24 {
        for x in 0..32 {
            let dir = pixel_centre_ray(&scene.camera, x, y);
            let point = eye + dir * (-eye.y / dir.y);
            let r = light_in_world.distance(point);
            let cos_theta = height_m / r;
            let expected = albedo * FRAC_1_PI * intensity * cos_theta / (r * r);
            let got = images.l_rho[(y * 32 + x) as usize];
            let relative = ((got - expected) / expected).abs().max_element();
            worst = worst.max(relative);
        }
    }
    assert!(worst < 0.01, "worst relative error {worst}");
}

/// A measured surface's per-vertex albedo takes the place of its material's, interpolated across
/// each triangle: a quad facing the camera and a head-on distant light of irradiance E reflects
/// L = a · E / π with no bounce (one surface), exactly at every pixel. Corners of one colour
/// give that colour; a non-finite corner leaves its triangles with the material's albedo.
#[test]
fn measured_vertex_albedo_replaces_the_material() {
    let (red, grey, irradiance) = (Vec3::new(0.8, 0.2, 0.1), 0.5, 2.0);
    let mut scene = scene("measured wall", camera(Vec3::ZERO, Vec3::NEG_Z, 8, 6));
    scene.materials.push(diffuse(Vec3::splat(grey)));
    let mut wall = quad(
        "wall",
        Vec3::new(0.0, 0.0, -2.0),
        Vec3::new(3.0, 0.0, 0.0),
        Vec3::new(0.0, 3.0, 0.0),
        0,
        false,
    );
    wall.vertex_albedo = vec![red; wall.positions_in_world.len()];
    scene.meshes.push(wall);
    scene.lights.push(Light::Directional {
        direction_in_world: Vec3::NEG_Z,
        irradiance: Vec3::splat(irradiance),
    });
    let settings = ReferenceSettings {
        spp: 2,
        max_bounces: 0,
        // Pixel centres: each pixel sees one triangle.
        pixel_jitter: false,
        ..ReferenceSettings::default()
    };
    let images = render_reference(&scene, settings).unwrap();
    let expected = red * irradiance * FRAC_1_PI;
    for l in &images.l_mu {
        assert!(
            (*l - expected).abs().max_element() < 1e-5,
            "{l} for {expected}"
        );
    }
    // Vertex 1 is in the first triangle only.
    scene.meshes[0].vertex_albedo[1] = Vec3::NAN;
    let images = render_reference(&scene, settings).unwrap();
    let material = grey * irradiance * FRAC_1_PI;
    let (material_lit, measured): (Vec<Vec3>, Vec<Vec3>) = images
        .l_mu
        .iter()
        .partition(|l| (l.x - material).abs() < 1e-5);
    assert!(
        !material_lit.is_empty() && !measured.is_empty(),
        "{:?}",
        images.l_mu
    );
    assert!(
        measured
            .iter()
            .all(|l| (*l - expected).abs().max_element() < 1e-5)
    );
}

/// An environment map with a 1e4:1 window, and the exact irradiance it gives a surface facing
/// +Y (the map is piecewise constant per texel; each texel is integrated on a fine grid).
fn window_environment() -> (EnvironmentMap, Vec3) {
    let (width, height) = (32, 16);
    let radiance: Vec<Vec3> = (0..width * height)
        .map(|i| {
            let (x, y) = (i % width, i / width);
            if (5..7).contains(&y) && (9..11).contains(&x) {
                Vec3::new(1e4, 0.9e4, 0.8e4)
            } else {
                Vec3::new(0.4, 0.5, 0.6)
            }
        })
        .collect();
    let sub = 32;
    let mut irradiance = glam::DVec3::ZERO;
    for y in 0..height {
        for x in 0..width {
            let texel = radiance[(y * width + x) as usize].as_dvec3();
            for j in 0..sub {
                let theta =
                    std::f64::consts::PI * (f64::from(y * sub + j) + 0.5) / f64::from(height * sub);
                let cos = theta.cos().max(0.0);
                let d_omega = theta.sin()
                    * (std::f64::consts::PI / f64::from(height * sub))
                    * (std::f64::consts::TAU / f64::from(width));
                irradiance += texel * (cos * d_omega);
            }
        }
    }
    let map = EnvironmentMap {
        width,
        height,
        radiance,
    };
    (map, irradiance.as_vec3())
}

/// A plane sees nothing but the sky, so its radiance is ρ/π · E at any bounce count. At
/// `max_bounces = 0` this checks that the last vertex counts both halves of the environment's
/// MIS (it used to count only the light-sampled half, 0.18× the answer under a constant sky).
#[test]
fn diffuse_plane_under_bright_window_environment_matches_its_irradiance() {
    let constant_sky = Vec3::new(0.4, 0.5, 0.6);
    let constant = EnvironmentMap {
        width: 8,
        height: 4,
        radiance: vec![constant_sky; 32],
    };
    for max_bounces in [0, 8] {
        diffuse_plane_under(window_environment(), max_bounces);
        // E = π L for a full hemisphere of constant radiance L.
        diffuse_plane_under((constant.clone(), PI * constant_sky), max_bounces);
    }
}

fn diffuse_plane_under((environment, irradiance): (EnvironmentMap, Vec3), max_bounces: u32) {
    let albedo = Vec3::new(0.6, 0.5, 0.4);
    let mut scene = scene(
        "window",
        camera(Vec3::new(0.0, 3.0, 2.0), Vec3::ZERO, 16, 12),
    );
    scene.materials.push(diffuse(albedo));
    scene.meshes.push(quad(
        "floor",
        Vec3::ZERO,
        Vec3::X * 50.0,
        Vec3::NEG_Z * 50.0,
        0,
        false,
    ));
    scene.environment = Some(environment);
    let settings = ReferenceSettings {
        spp: 32,
        max_bounces,
        ..ReferenceSettings::default()
    };
    let images = render_reference(&scene, settings).unwrap();
    assert_all_finite(&images);
    let expected = albedo * FRAC_1_PI * irradiance;
    for channel in 0..3 {
        let values: Vec<Vec3> = images
            .l_rho
            .iter()
            .map(|v| Vec3::splat(v[channel]))
            .collect();
        let errors: Vec<Vec3> = images
            .l_rho_std_error
            .iter()
            .map(|v| Vec3::splat(v[channel]))
            .collect();
        let (mean, std_error) = pooled(&values, &errors);
        let e = f64::from(expected[channel]);
        let error = (mean - e).abs();
        assert!(
            error < 3.0 * std_error.max(1e-9) && error < 0.01 * e,
            "max_bounces {max_bounces}, channel {channel}: {mean} vs {e} (standard error {std_error})"
        );
        // MIS with environment sampling keeps the window from making fireflies: every pixel's
        // own standard error is below 10% after 32 samples.
        let worst_pixel_error = images
            .l_rho_std_error
            .iter()
            .map(|v| f64::from(v[channel]) / e)
            .fold(0.0, f64::max);
        assert!(worst_pixel_error < 0.1, "{worst_pixel_error}");
    }
}

/// A closed room (inward box) with a real crate and a point light inside; the camera inside.
fn closed_room(width: u32, height: u32) -> Scene {
    let mut scene = scene(
        "room",
        camera(
            Vec3::new(0.0, 1.5, 1.8),
            Vec3::new(0.0, 0.3, 0.0),
            width,
            height,
        ),
    );
    scene.materials = vec![diffuse(Vec3::splat(0.7)), diffuse(Vec3::new(0.8, 0.3, 0.2))];
    scene.meshes.push(flipped(cuboid(
        "room",
        Vec3::new(-2.0, 0.0, -2.0),
        Vec3::new(2.0, 2.5, 2.0),
        0,
        false,
    )));
    scene.meshes.push(cuboid(
        "crate",
        Vec3::new(-1.2, 0.0, -1.0),
        Vec3::new(-0.6, 0.6, -0.4),
        1,
        false,
    ));
    scene.lights.push(Light::Point {
        position_in_world: Vec3::new(0.5, 2.2, 0.3),
        intensity: Vec3::splat(8.0),
    });
    scene
}

fn assert_delta_exactly_zero(images: &ReferenceImages) {
    for i in 0..images.delta.len() {
        assert_eq!(
            images.delta[i].to_array().map(f32::to_bits),
            [0; 3],
            "pixel {i}"
        );
        assert_eq!(images.delta_std_error[i], Vec3::ZERO, "pixel {i}");
        assert_eq!(
            images.l_rho[i].to_array().map(f32::to_bits),
            images.l_mu[i].to_array().map(f32::to_bits),
            "pixel {i}"
        );
    }
}

#[test]
fn scene_without_virtual_object_has_exactly_zero_delta() {
    let mut scene = closed_room(16, 12);
    // Open the room's ceiling to an environment so escaping paths are covered too.
    scene.meshes.retain(|m| m.name != "room");
    scene.meshes.push(quad(
        "floor",
        Vec3::ZERO,
        Vec3::X * 3.0,
        Vec3::NEG_Z * 3.0,
        0,
        false,
    ));
    scene.environment = Some(window_environment().0);
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 8,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    assert!(images.l_rho.iter().any(|v| v.max_element() > 0.0));
    assert_delta_exactly_zero(&images);
}

/// The virtual ball sits 1000 m below the floor of a closed room. Every camera ray, bounce ray
/// and shadow ray starts inside the room and ends on one of its walls or at the light inside
/// it, so no ray can reach the ball: each path consumes the same random numbers, meets the same
/// triangles with the same arithmetic in both geometries, and L^ρ = L^μ bit for bit.
#[test]
fn virtual_object_no_path_can_reach_gives_exactly_zero_delta() {
    let settings = ReferenceSettings {
        spp: 8,
        ..ReferenceSettings::default()
    };
    let mut scene = closed_room(16, 12);
    scene.materials.push(diffuse(Vec3::ONE));
    let far_ball = uv_sphere("ball", Vec3::new(0.0, -1000.0, 0.0), 0.3, 12, 6, 2, true);
    scene.meshes.push(far_ball.clone());
    let images = render_reference(&scene, settings).unwrap();
    assert!(images.l_rho.iter().any(|v| v.max_element() > 0.0));
    assert_delta_exactly_zero(&images);

    // The same ball inside the room changes the image, so the test above is not vacuous.
    let mut near_ball = far_ball;
    for p in &mut near_ball.positions_in_world {
        p.y += 1000.3;
    }
    scene.meshes.retain(|m| !m.is_virtual);
    scene.meshes.push(near_ball);
    let images = render_reference(&scene, settings).unwrap();
    assert!(images.delta.iter().any(|d| d.abs().max_element() > 1e-3));
}

/// A real floor lit by a point light and a dim environment, and a virtual box that shadows it.
fn shadow_scene(box_albedo: Vec3, light_in_world: Vec3) -> Scene {
    let mut scene = scene(
        "shadow",
        camera(Vec3::new(0.0, 2.5, 2.5), Vec3::new(0.0, 0.2, 0.0), 32, 24),
    );
    scene.materials = vec![diffuse(Vec3::splat(0.8)), diffuse(box_albedo)];
    scene.meshes.push(quad(
        "floor",
        Vec3::ZERO,
        Vec3::X * 3.0,
        Vec3::NEG_Z * 3.0,
        0,
        false,
    ));
    scene.meshes.push(cuboid(
        "box",
        Vec3::new(-0.4, 0.0, -0.4),
        Vec3::new(0.4, 0.8, 0.4),
        1,
        true,
    ));
    scene.lights.push(Light::Point {
        position_in_world: light_in_world,
        intensity: Vec3::splat(15.0),
    });
    scene.environment = Some(EnvironmentMap {
        width: 8,
        height: 4,
        radiance: vec![Vec3::splat(0.3); 32],
    });
    scene
}

#[test]
fn delta_standard_error_falls_as_one_over_sqrt_spp() {
    let scene = shadow_scene(Vec3::splat(0.5), Vec3::new(1.0, 2.5, 0.5));
    let mut renderer = ReferenceRenderer::new(&scene, ReferenceSettings::default()).unwrap();
    let mean_std_error = |images: &ReferenceImages| {
        images
            .delta_std_error
            .iter()
            .map(|v| f64::from(v.element_sum()) / 3.0)
            .sum::<f64>()
            / images.delta_std_error.len() as f64
    };
    renderer.add_samples(32);
    let before = mean_std_error(&renderer.images());
    renderer.add_samples(96);
    let after = mean_std_error(&renderer.images());
    assert!(before > 0.0);
    let ratio = after / before;
    assert!(
        (ratio - 0.5).abs() < 0.1,
        "ratio {ratio} ({before} → {after})"
    );
}

#[test]
fn black_object_casts_only_negative_delta() {
    let scene = shadow_scene(Vec3::ZERO, Vec3::new(1.0, 2.5, 0.5));
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 8,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    assert_all_finite(&images);
    // Per sample, the black object can only end paths and block shadow rays, so every sample's
    // Δ is ≤ 0 exactly (sums of non-negative terms round monotonically), and so is the mean.
    for (i, d) in images.delta.iter().enumerate() {
        assert!(d.max_element() <= 0.0, "pixel {i}: {d}");
    }
    let shadowed = images
        .delta
        .iter()
        .zip(&images.delta_std_error)
        .filter(|(d, se)| d.x < -0.05 && d.x < -5.0 * se.x)
        .count();
    assert!(shadowed > 20, "only {shadowed} pixels darkened");
}

#[test]
fn white_object_adds_light_to_the_floor_beside_it() {
    // Light low on the +x side: the box's lit +x face bounces light onto the floor in front of it.
    let scene = shadow_scene(Vec3::ONE, Vec3::new(2.0, 1.2, 0.0));
    let images = render_reference(
        &scene,
        ReferenceSettings {
            spp: 32,
            ..ReferenceSettings::default()
        },
    )
    .unwrap();
    assert_all_finite(&images);
    // The floor to the right of the box in the image (+x, towards the light), real pixels only.
    let region: Vec<usize> = (8..20)
        .flat_map(|y| (20..28).map(move |x| y * 32 + x))
        .filter(|&i| !images.virtual_mask[i])
        .collect();
    let pick = |image: &[Vec3]| region.iter().map(|&i| image[i]).collect::<Vec<_>>();
    let (mean, std_error) = pooled(&pick(&images.delta), &pick(&images.delta_std_error));
    assert!(
        mean > 0.02 && mean > 5.0 * std_error,
        "mean Δ beside the box {mean} ± {std_error}"
    );
    assert!(
        images.delta.iter().any(|d| d.x < -0.05),
        "the box should also shadow the floor"
    );
}

#[test]
fn same_seed_gives_the_same_image_and_another_seed_a_different_one() {
    let scene = shadow_scene(Vec3::splat(0.5), Vec3::new(1.0, 2.5, 0.5));
    let settings = ReferenceSettings {
        spp: 2,
        seed: 7,
        size: Some((20, 10)),
        ..ReferenceSettings::default()
    };
    let a = render_reference(&scene, settings).unwrap();
    let b = render_reference(&scene, settings).unwrap();
    assert_eq!(a, b);
    assert_eq!((a.width, a.height, a.l_rho.len()), (20, 10, 200));
    let c = render_reference(
        &scene,
        ReferenceSettings {
            seed: 8,
            ..settings
        },
    )
    .unwrap();
    assert_ne!(a.l_rho, c.l_rho);
}

#[test]
fn glossy_plane_under_directional_light_matches_the_phong_brdf() {
    let (albedo, specular, shininess) = (Vec3::new(0.3, 0.2, 0.1), Vec3::splat(0.5), 20.0);
    let irradiance = Vec3::new(3.0, 2.0, 1.0);
    let to_light = Vec3::new(0.0, 1.0, -0.8).normalize();
    let eye = Vec3::new(0.0, 2.0, 3.0);
    let mut scene = scene("glossy", camera(eye, Vec3::ZERO, 32, 24));
    scene.materials.push(Material {
        specular,
        shininess,
        ..diffuse(albedo)
    });
    scene.meshes.push(quad(
        "floor",
        Vec3::ZERO,
        Vec3::X * 20.0,
        Vec3::NEG_Z * 20.0,
        0,
        false,
    ));
    scene.lights.push(Light::Directional {
        direction_in_world: -to_light,
        irradiance,
    });
    let settings = ReferenceSettings {
        spp: 2,
        max_bounces: 0,
        pixel_jitter: false,
        ..ReferenceSettings::default()
    };
    let images = render_reference(&scene, settings).unwrap();
    let mut worst = 0.0f32;
    let mut brightest = 0.0f32;
    for y in 0..24 {
        for x in 0..32 {
            let dir = pixel_centre_ray(&scene.camera, x, y);
            let to_eye = -dir;
            let mirror = 2.0 * to_eye.y * Vec3::Y - to_eye;
            let cos_alpha = mirror.dot(to_light).max(0.0);
            let brdf = albedo * FRAC_1_PI
                + specular * (shininess + 1.0) / (2.0 * PI) * cos_alpha.powf(shininess);
            let expected = brdf * irradiance * to_light.y;
            let got = images.l_rho[(y * 32 + x) as usize];
            worst = worst.max(((got - expected) / expected).abs().max_element());
            brightest = brightest.max(got.x);
        }
    }
    assert!(worst < 0.01, "worst relative error {worst}");
    // The highlight is in view, so the glossy term was exercised.
    assert!(brightest > 2.0 * (albedo.x * FRAC_1_PI * irradiance.x * to_light.y));
}
