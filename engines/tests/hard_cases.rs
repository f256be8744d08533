//! Numerically hard scenes through every GPU engine (issue 18 §5, issue 20 §4): a 1e6:1
//! environment, a light grazing the floor, holes in the real geometry, the object sunk into the
//! floor, a mirror-like object, degenerate triangles, a light inside the object. Each frame must compute no NaN or ∞ anywhere
//! (`RelitFrame::non_finite`, counted before Δ is written), give a finite composite, and keep
//! the invariants that hold whatever the light: Δ = 0 without a virtual object.

mod support;

use std::sync::Arc;

use glam::Vec3;
use relight_core::light::Light;
use relight_core::scene::Scene;
use support::{add_sun, delta_of, engine_with, frame, load_scene, max_abs};

fn hard_scenes() -> Vec<(&'static str, Scene)> {
    let desk = load_scene("desk_box");
    let (lo, hi) = desk.virtual_bounds().unwrap();
    let mut scenes = Vec::new();

    let mut sun = load_scene("window_env");
    let env = sun.environment.as_mut().unwrap();
    let (x, y) = (env.width as usize / 3, env.height as usize / 4);
    add_sun(env, x, y, 1e6);
    scenes.push(("1e6:1 environment", sun));

    let mut grazing = desk.clone();
    grazing.lights = vec![Light::Directional {
        direction_in_world: Vec3::new(1.0, -0.002, 0.0).normalize(),
        irradiance: Vec3::splat(5.0),
    }];
    scenes.push(("grazing light", grazing));

    let mut holes = desk.clone();
    for mesh in holes.meshes.iter_mut().filter(|m| !m.is_virtual) {
        for p in mesh.positions_in_world.iter_mut().step_by(7) {
            *p = Vec3::NAN;
        }
    }
    scenes.push(("holes in the real geometry", holes));

    let mut sunk = desk.clone();
    let depth = 0.5 * (hi.y - lo.y);
    for mesh in sunk.meshes.iter_mut().filter(|m| m.is_virtual) {
        for p in &mut mesh.positions_in_world {
            p.y -= depth;
        }
    }
    scenes.push(("object sunk into the floor", sunk));

    let mut mirror = desk.clone();
    let index = mirror.materials.len();
    let mut material = mirror.materials[0].clone();
    material.albedo = Vec3::ZERO;
    material.specular = Vec3::ONE;
    material.shininess = 4096.0;
    mirror.materials.push(material);
    for mesh in mirror.meshes.iter_mut().filter(|m| m.is_virtual) {
        mesh.material = index;
    }
    scenes.push(("mirror-like object", mirror));

    let mut degenerate = desk.clone();
    for mesh in &mut degenerate.meshes {
        let n = mesh.positions_in_world.len() as u32;
        let (a, b) = (0, n / 2);
        // Two corners the same, and three corners on one line: zero area, no normal.
        mesh.positions_in_world
            .push((mesh.positions_in_world[0] + mesh.positions_in_world[b as usize]) / 2.0);
        mesh.normals_in_world.push(Vec3::ZERO);
        mesh.triangles.extend([[a, a, b], [a, b, n], [b, n, a]]);
    }
    scenes.push(("degenerate triangles", degenerate));

    let mut inside = desk;
    inside.lights.push(Light::Point {
        position_in_world: (lo + hi) / 2.0,
        intensity: Vec3::splat(50.0),
    });
    scenes.push(("light inside the object", inside));
    scenes
}

#[test]
fn every_engine_stays_finite_on_hard_scenes() {
    let small = serde_json::json!({ "volume_size": 16, "steps": 8 });
    let engines = [
        ("differential", serde_json::json!({})),
        ("dlpv", small),
        ("dvct", serde_json::json!({ "volume_size": 16 })),
        ("dir", serde_json::json!({ "vpl_count": 64 })),
        ("ibl", serde_json::json!({ "map_size": 16 })),
        ("pt", serde_json::json!({ "spp": 4 })),
    ];
    for (case, scene) in hard_scenes() {
        let with_object = Arc::new(scene.clone());
        let without = Arc::new(scene.without_virtual());
        for (name, params) in &engines {
            let mut engine = engine_with(name, params.clone());
            let (delta, out) = delta_of(&mut engine, &frame(with_object.clone(), 32, 24));
            assert_eq!(out.non_finite, 0, "{name}, {case}: non-finite Δ values");
            assert!(delta.iter().all(|d| d.is_finite()), "{name}, {case}");
            assert_eq!(out.composite.width(), 32, "{name}, {case}");
            let (delta, out) = delta_of(&mut engine, &frame(without.clone(), 32, 24));
            assert_eq!(out.non_finite, 0, "{name}, {case} without the object");
            let largest = max_abs(&delta);
            assert!(
                largest == 0.0,
                "{name}, {case}: Δ {largest} without an object"
            );
        }
    }
}
