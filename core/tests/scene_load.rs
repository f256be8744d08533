//! The shipped scenes load, and bad scene directories fail with errors naming file and node/key.

use std::path::{Path, PathBuf};

use glam::Vec3;
use relight_core::scene::Scene;

fn scenes_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes")
}

const SCENES: [&str; 5] = [
    "desk_box",
    "spot_bleed",
    "touching_wall",
    "glossy_floor",
    "window_env",
];

#[test]
fn every_shipped_scene_loads_with_real_and_virtual_geometry_in_view() {
    for name in SCENES {
        let scene = Scene::load(&scenes_dir().join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(
            scene.meshes.iter().any(|m| m.is_virtual),
            "{name}: no virtual mesh"
        );
        assert!(
            scene.meshes.iter().any(|m| !m.is_virtual),
            "{name}: no real mesh"
        );
        for mesh in &scene.meshes {
            assert!(mesh.positions_in_world.iter().all(|p| p.is_finite()));
            assert!(
                mesh.normals_in_world
                    .iter()
                    .all(|n| (n.length() - 1.0).abs() < 1e-4),
                "{name}/{}",
                mesh.name
            );
            assert!(mesh.material < scene.materials.len());
        }
        assert_eq!((scene.camera.width, scene.camera.height), (160, 120));
        // The virtual object's centre lies inside the camera's view.
        let (lo, hi) = scene.virtual_bounds().unwrap();
        let centre_in_camera = scene
            .camera
            .world_from_camera
            .inverse()
            .transform_point((lo + hi) / 2.0);
        assert!(centre_in_camera.z < 0.0, "{name}: object behind the camera");
        let tan_half = (scene.camera.yfov_rad / 2.0).tan();
        let ndc_y = centre_in_camera.y / -centre_in_camera.z / tan_half;
        let ndc_x = centre_in_camera.x / -centre_in_camera.z / (tan_half * 160.0 / 120.0);
        assert!(
            ndc_x.abs() < 1.0 && ndc_y.abs() < 1.0,
            "{name}: object outside the image ({ndc_x}, {ndc_y})"
        );
        assert!(
            !scene.lights.is_empty() || scene.environment.is_some(),
            "{name}: unlit"
        );
    }
}

#[test]
fn window_environment_spans_at_least_ten_thousand_to_one() {
    let scene = Scene::load(&scenes_dir().join("window_env")).unwrap();
    let env = scene.environment.unwrap();
    let lum = |c: &Vec3| c.max_element();
    let max = env.radiance.iter().map(lum).fold(0.0f32, f32::max);
    let min = env.radiance.iter().map(lum).fold(f32::INFINITY, f32::min);
    assert!(min > 0.0 && max / min >= 1e4, "dynamic range {}", max / min);
}

#[test]
fn glossy_floor_override_and_metallic_roughness_mapping_apply() {
    let scene = Scene::load(&scenes_dir().join("glossy_floor")).unwrap();
    let floor = scene.materials.iter().find(|m| m.name == "floor").unwrap();
    assert_eq!((floor.specular, floor.shininess), (Vec3::splat(0.4), 200.0));
    let desk = Scene::load(&scenes_dir().join("desk_box")).unwrap();
    let red = desk.materials.iter().find(|m| m.name == "red").unwrap();
    assert_eq!(red.shininess, 0.0, "roughness 1 has no glossy lobe");
    assert!((red.albedo - Vec3::new(0.7, 0.1, 0.08)).length() < 1e-6);
}

/// Copy a shipped scene into a temporary directory so a test can break it.
fn copy_scene(name: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(scenes_dir().join(name)).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.path().join(entry.file_name())).unwrap();
    }
    dir
}

fn edit(path: &Path, from: &str, to: &str) {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.contains(from), "{from}");
    std::fs::write(path, text.replacen(from, to, 1)).unwrap();
}

#[test]
fn errors_name_the_file_and_the_node_or_key() {
    let unknown = copy_scene("desk_box");
    edit(
        &unknown.path().join("scene.toml"),
        "virtual = [\"box\"]",
        "virtual = [\"teapot\"]",
    );
    let err = Scene::load(unknown.path()).unwrap_err().to_string();
    assert!(
        err.contains("scene.toml") && err.contains("teapot") && err.contains("box"),
        "{err}"
    );

    let missing = copy_scene("desk_box");
    std::fs::remove_file(missing.path().join("scene.gltf")).unwrap();
    let err = Scene::load(missing.path()).unwrap_err().to_string();
    assert!(err.contains("scene.gltf"), "{err}");

    let bad_light = copy_scene("desk_box");
    edit(
        &bad_light.path().join("scene.toml"),
        "intensity = [2, 2, 2]",
        "intensity = [-2, 2, 2]",
    );
    let err = Scene::load(bad_light.path()).unwrap_err().to_string();
    assert!(
        err.contains("scene.toml") && err.contains("lights[0]"),
        "{err}"
    );

    let lines = copy_scene("desk_box");
    edit(
        &lines.path().join("scene.gltf"),
        "\"material\": 0",
        "\"material\": 0, \"mode\": 1",
    );
    let err = Scene::load(lines.path()).unwrap_err().to_string();
    assert!(
        err.contains("scene.gltf") && err.contains("node `floor`") && err.contains("triangles"),
        "{err}"
    );

    let typo = copy_scene("desk_box");
    edit(
        &typo.path().join("scene.toml"),
        "width = 160",
        "widht = 160",
    );
    let err = Scene::load(typo.path()).unwrap_err().to_string();
    assert!(
        err.contains("scene.toml") && err.contains("widht") && err.contains("line"),
        "{err}"
    );
}

/// Inputs the `scene` fuzz target crashed on (fuzz/regressions/scene: `scene.toml`, a 0xFF
/// byte, then `scene.gltf`, as the target splits them): each loads or is refused, without a
/// panic. The first named a POSITION accessor past the file's accessors, on which gltf-json's
/// own validation indexes out of bounds.
#[test]
fn fuzz_regressions_load_without_panicking() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/regressions/scene");
    let mut inputs = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let data = std::fs::read(&path).unwrap();
        let (toml, gltf) = match data.iter().position(|&b| b == 0xff) {
            Some(at) => (&data[..at], &data[at + 1..]),
            None => (&data[..], &[][..]),
        };
        let scene = tempfile::tempdir().unwrap();
        std::fs::write(scene.path().join("scene.toml"), toml).unwrap();
        std::fs::write(scene.path().join("scene.gltf"), gltf).unwrap();
        let result = Scene::load(scene.path());
        inputs += 1;
        if path.ends_with("gltf_position_accessor_out_of_range") {
            let error = result
                .expect_err("an accessor that does not exist")
                .to_string();
            assert!(error.contains("POSITION"), "{error}");
        }
    }
    assert!(inputs > 0, "no inputs in {}", dir.display());
}
