//! Writes the test scenes under `tests/scenes/` (glTF 2.0 + .bin + scene.toml, and the window
//! EXR): `cargo run -p relight-core --example make_scenes -- tests/scenes`.

use std::path::Path;

use glam::Vec3;
use relight_core::Pose;
use relight_core::scene::Mesh;
use serde_json::{Value, json};

struct Object {
    name: &'static str,
    lo: Vec3,
    hi: Vec3,
    material: usize,
}

struct Gltf {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Gltf {
    fn push(&mut self, bytes: &[u8], target: u32) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len(), "target": target}));
        self.bin.extend_from_slice(bytes);
        self.views.len() - 1
    }

    fn vec3s(&mut self, values: &[Vec3], with_bounds: bool) -> usize {
        let bytes: Vec<u8> = values
            .iter()
            .flat_map(|v| v.to_array())
            .flat_map(f32::to_le_bytes)
            .collect();
        let view = self.push(&bytes, 34962);
        let mut accessor = json!({"bufferView": view, "componentType": 5126, "count": values.len(), "type": "VEC3"});
        if with_bounds {
            let lo = values.iter().fold(Vec3::INFINITY, |a, v| a.min(*v));
            let hi = values.iter().fold(Vec3::NEG_INFINITY, |a, v| a.max(*v));
            accessor["min"] = json!(lo.to_array());
            accessor["max"] = json!(hi.to_array());
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    fn indices(&mut self, values: &[u32]) -> usize {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.push(&bytes, 34963);
        self.accessors.push(json!({"bufferView": view, "componentType": 5125, "count": values.len(), "type": "SCALAR"}));
        self.accessors.len() - 1
    }
}

/// A box as 6 faces with their own vertices (flat normals), counter-clockwise from outside.
/// (name, base colour, metallic, roughness, emission)
type MaterialSpec = (&'static str, [f32; 3], f32, f32);

fn write_scene(
    dir: &Path,
    objects: &[Object],
    materials: &[MaterialSpec],
    eye: Vec3,
    target: Vec3,
    toml_tail: &str,
    virtual_nodes: &[&str],
) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut g = Gltf {
        bin: Vec::new(),
        views: Vec::new(),
        accessors: Vec::new(),
    };
    let mut nodes = Vec::new();
    let mut meshes = Vec::new();
    for object in objects {
        let mesh = Mesh::cuboid(object.name, object.lo, object.hi, object.material, false);
        let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
        let (pos, nrm, idx) = (
            g.vec3s(&mesh.positions_in_world, true),
            g.vec3s(&mesh.normals_in_world, false),
            g.indices(&indices),
        );
        meshes.push(json!({"name": object.name, "primitives": [{"attributes": {"POSITION": pos, "NORMAL": nrm}, "indices": idx, "material": object.material}]}));
        nodes.push(json!({"name": object.name, "mesh": meshes.len() - 1}));
    }
    let camera_pose = Pose::look_at(eye, target, Vec3::Y);
    nodes.push(json!({"name": "camera", "camera": 0, "translation": camera_pose.translation.to_array(), "rotation": camera_pose.rotation.to_array()}));
    let materials: Vec<Value> = materials
        .iter()
        .map(|(name, color, metallic, roughness)| {
            json!({"name": name, "pbrMetallicRoughness": {"baseColorFactor": [color[0], color[1], color[2], 1.0], "metallicFactor": metallic, "roughnessFactor": roughness}})
        })
        .collect();
    let document = json!({
        "asset": {"version": "2.0", "generator": "relight make_scenes"},
        "scene": 0,
        "scenes": [{"nodes": (0..nodes.len()).collect::<Vec<_>>()}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "cameras": [{"type": "perspective", "perspective": {"yfov": 50f32.to_radians(), "znear": 0.01, "aspectRatio": 4.0 / 3.0}}],
        "buffers": [{"uri": "scene.bin", "byteLength": g.bin.len()}],
        "bufferViews": g.views,
        "accessors": g.accessors,
    });
    std::fs::write(dir.join("scene.bin"), &g.bin)?;
    std::fs::write(
        dir.join("scene.gltf"),
        serde_json::to_string_pretty(&document).unwrap_or_default(),
    )?;
    let names: Vec<String> = virtual_nodes.iter().map(|n| format!("\"{n}\"")).collect();
    std::fs::write(
        dir.join("scene.toml"),
        format!(
            "gltf = \"scene.gltf\"\nvirtual = [{}]\n\n[camera]\nwidth = 160\nheight = 120\n{toml_tail}",
            names.join(", ")
        ),
    )
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "tests/scenes".into());
    let root = Path::new(&root);
    let rough = 1.0;
    let floor = |m| Object {
        name: "floor",
        lo: Vec3::new(-1.0, -0.02, -1.0),
        hi: Vec3::new(1.0, 0.0, 1.0),
        material: m,
    };
    let back_wall = |m| Object {
        name: "back_wall",
        lo: Vec3::new(-1.0, 0.0, -1.02),
        hi: Vec3::new(1.0, 1.2, -1.0),
        material: m,
    };
    let point = |p: [f32; 3], i: f32| {
        format!(
            "\n[[lights]]\ntype = \"point\"\nposition_in_world = {p:?}\nintensity = [{i}, {i}, {i}]\n"
        )
    };

    write_scene(
        &root.join("desk_box"),
        &[
            floor(0),
            back_wall(0),
            Object {
                name: "left_wall",
                lo: Vec3::new(-1.02, 0.0, -1.0),
                hi: Vec3::new(-1.0, 1.2, 1.0),
                material: 1,
            },
            Object {
                name: "right_wall",
                lo: Vec3::new(1.0, 0.0, -1.0),
                hi: Vec3::new(1.02, 1.2, 1.0),
                material: 2,
            },
            Object {
                name: "box",
                lo: Vec3::new(-0.15, 0.0, -0.25),
                hi: Vec3::new(0.15, 0.3, 0.05),
                material: 3,
            },
        ],
        &[
            ("white", [0.75; 3], 0.0, rough),
            ("red", [0.7, 0.1, 0.08], 0.0, rough),
            ("green", [0.1, 0.6, 0.12], 0.0, rough),
            ("box", [0.7, 0.7, 0.65], 0.0, rough),
        ],
        Vec3::new(0.0, 0.9, 1.9),
        Vec3::new(0.0, 0.25, -0.3),
        &point([0.0, 1.1, 0.2], 2.0),
        &["box"],
    )?;
    write_scene(
        &root.join("spot_bleed"),
        &[
            floor(0),
            Object {
                name: "orange_box",
                lo: Vec3::new(-0.12, 0.0, -0.12),
                hi: Vec3::new(0.12, 0.35, 0.12),
                material: 1,
            },
        ],
        &[
            ("white", [0.8; 3], 0.0, rough),
            ("orange", [0.9, 0.4, 0.05], 0.0, rough),
        ],
        Vec3::new(0.6, 0.8, 1.2),
        Vec3::new(0.0, 0.1, 0.0),
        "\n[[lights]]\ntype = \"spot\"\nposition_in_world = [-0.6, 1.0, 0.5]\ndirection_in_world = [0.4867, -0.7787, -0.3958]\nintensity = [6.0, 6.0, 6.0]\ninner_angle_rad = 0.3\nouter_angle_rad = 0.5\n",
        &["orange_box"],
    )?;
    write_scene(
        &root.join("touching_wall"),
        &[
            floor(0),
            back_wall(0),
            Object {
                name: "box",
                lo: Vec3::new(-0.2, 0.0, -1.0),
                hi: Vec3::new(0.1, 0.4, -0.7),
                material: 1,
            },
        ],
        &[
            ("white", [0.75; 3], 0.0, rough),
            ("box", [0.2, 0.35, 0.8], 0.0, rough),
        ],
        Vec3::new(0.5, 0.9, 0.9),
        Vec3::new(-0.05, 0.2, -0.8),
        &point([0.6, 1.0, -0.2], 2.0),
        &["box"],
    )?;
    write_scene(
        &root.join("glossy_floor"),
        &[
            floor(0),
            Object {
                name: "box",
                lo: Vec3::new(-0.15, 0.0, -0.15),
                hi: Vec3::new(0.15, 0.3, 0.15),
                material: 1,
            },
        ],
        &[
            ("floor", [0.5; 3], 0.0, 0.3),
            ("box", [0.8, 0.75, 0.2], 0.0, rough),
        ],
        Vec3::new(0.0, 0.6, 1.4),
        Vec3::new(0.0, 0.1, 0.0),
        &format!(
            "\n[materials.floor]\nalbedo = [0.5, 0.5, 0.5]\nspecular = [0.4, 0.4, 0.4]\nshininess = 200.0\n{}",
            point([0.0, 1.2, -0.8], 3.0)
        ),
        &["box"],
    )?;
    write_scene(
        &root.join("window_env"),
        &[
            floor(0),
            Object {
                name: "box",
                lo: Vec3::new(-0.15, 0.0, -0.15),
                hi: Vec3::new(0.15, 0.3, 0.15),
                material: 1,
            },
        ],
        &[
            ("floor", [0.7; 3], 0.0, rough),
            ("box", [0.8; 3], 0.0, rough),
        ],
        Vec3::new(0.0, 0.9, 1.4),
        Vec3::new(0.0, 0.1, 0.0),
        "\n[environment]\nfile = \"window.exr\"\nintensity_scale = 1.0\n",
        &["box"],
    )?;
    // The window: a bright rectangle 35–70° from the zenith towards −Z in a dim room, 1e4:1.
    let (w, h) = (64usize, 32usize);
    exr::prelude::write_rgb_file(root.join("window_env/window.exr"), w, h, |x, y| {
        let phi = (x as f32 + 0.5) / w as f32 * 360.0;
        let theta = (y as f32 + 0.5) / h as f32 * 180.0;
        let window = !(25.0..=335.0).contains(&phi) && (35.0..70.0).contains(&theta);
        let v = if window {
            20.0
        } else {
            0.001 * (1.0 + (theta.to_radians()).cos().max(0.0))
        };
        (v, v, v)
    })?;
    Ok(())
}
