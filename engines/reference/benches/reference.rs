//! Reference path tracer speed on a ~100-triangle scene at 160×120: a floor and a back wall, a
//! real crate, a virtual sphere and box (so both L^ρ and L^μ paths are traced where the objects
//! matter), a point light and an environment map with a bright window.
//!
//! Criterion reports samples per second (one sample = one L^ρ path and, where the virtual
//! objects touch it, one L^μ path) for one sample per pixel, and the time of a whole
//! 64-spp render. `cargo bench -p relight-engines --bench reference`; under `cargo test` it runs
//! a small smoke version.

use std::hint::black_box;

use criterion::{Criterion, Throughput};
use glam::Vec3;
use relight_core::Pose;
use relight_core::light::Light;
use relight_core::scene::{EnvironmentMap, Material, Scene, SceneCamera};
use relight_reference::shapes::{cuboid, quad, uv_sphere};
use relight_reference::{ReferenceRenderer, ReferenceSettings, render_reference};

fn bench_scene(width: u32, height: u32) -> Scene {
    let diffuse = |albedo: Vec3| Material {
        albedo,
        ..Material::default()
    };
    let (env_width, env_height) = (64, 32);
    let radiance = (0..env_width * env_height)
        .map(|i| {
            let (x, y) = (i % env_width, i / env_width);
            if (8..11).contains(&y) && (20..24).contains(&x) {
                Vec3::splat(2e3)
            } else {
                Vec3::new(0.1, 0.12, 0.15)
            }
        })
        .collect();
    Scene {
        name: "bench".into(),
        meshes: vec![
            quad(
                "floor",
                Vec3::ZERO,
                Vec3::X * 3.0,
                Vec3::NEG_Z * 3.0,
                0,
                false,
            ),
            quad(
                "wall",
                Vec3::new(0.0, 1.5, -3.0),
                Vec3::X * 3.0,
                Vec3::Y * 1.5,
                0,
                false,
            ),
            cuboid(
                "crate",
                Vec3::new(-1.4, 0.0, -1.2),
                Vec3::new(-0.8, 0.6, -0.6),
                1,
                false,
            ),
            uv_sphere("ball", Vec3::new(0.2, 0.4, 0.0), 0.4, 10, 5, 2, true),
            cuboid(
                "block",
                Vec3::new(0.8, 0.0, -0.7),
                Vec3::new(1.2, 0.5, -0.3),
                3,
                true,
            ),
        ],
        materials: vec![
            diffuse(Vec3::splat(0.7)),
            diffuse(Vec3::new(0.7, 0.3, 0.2)),
            Material {
                specular: Vec3::splat(0.4),
                shininess: 60.0,
                ..diffuse(Vec3::new(0.2, 0.3, 0.6))
            },
            diffuse(Vec3::new(0.2, 0.7, 0.2)),
        ],
        camera: SceneCamera {
            world_from_camera: Pose::look_at(
                Vec3::new(0.0, 1.6, 2.8),
                Vec3::new(0.0, 0.3, 0.0),
                Vec3::Y,
            ),
            yfov_rad: 0.9,
            width,
            height,
        },
        lights: vec![Light::Point {
            position_in_world: Vec3::new(1.0, 2.5, 1.0),
            intensity: Vec3::splat(20.0),
        }],
        environment: Some(EnvironmentMap {
            width: env_width,
            height: env_height,
            radiance,
        }),
        environment_lights: Vec::new(),
        shadow_proxy: None,
        surface_revision: None,
    }
}

fn main() {
    // `cargo bench` passes --bench; anything else (cargo test) gets a quick smoke run.
    let full = std::env::args().any(|arg| arg == "--bench");
    let (width, height, spp) = if full { (160, 120, 64) } else { (40, 30, 2) };
    let scene = bench_scene(width, height);
    let triangles: usize = scene.meshes.iter().map(|m| m.triangles.len()).sum();
    println!("reference bench scene: {triangles} triangles, {width}×{height}");

    let mut criterion = Criterion::default().configure_from_args();
    let mut group = criterion.benchmark_group("reference");
    group.sample_size(10);
    group.throughput(Throughput::Elements(u64::from(width * height)));
    let mut renderer = ReferenceRenderer::new(&scene, ReferenceSettings::default())
        .expect("the bench scene is valid");
    group.bench_function(format!("1 spp {width}x{height} (samples)"), |b| {
        b.iter(|| renderer.add_samples(1));
    });
    group.throughput(Throughput::Elements(1));
    group.bench_function(format!("{spp} spp {width}x{height} (renders)"), |b| {
        b.iter(|| {
            let settings = ReferenceSettings {
                spp,
                ..ReferenceSettings::default()
            };
            black_box(render_reference(&scene, settings).expect("the bench scene is valid"))
        });
    });
    group.finish();
    criterion.final_summary();
}
