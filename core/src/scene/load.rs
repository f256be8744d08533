//! Loading a scene directory: `scene.toml` (which nodes are virtual, lights, environment,
//! material overrides, camera size) beside a glTF 2.0 file.
//!
//! ```toml
//! gltf = "scene.gltf"          # relative to the directory
//! virtual = ["box"]            # glTF node names of the virtual object(s); all other meshes are real
//! [camera]                     # optional; pose and yfov come from the glTF camera node
//! width = 160
//! height = 120
//! # position = [0, 1, 2]; look_at = [0, 0, 0]; yfov_deg = 50   (required without a glTF camera)
//! [materials.floor]            # optional overrides of the glTF material of that name
//! specular = [0.4, 0.4, 0.4]
//! shininess = 200
//! [[lights]]                   # relight_core::light::Light
//! type = "point"
//! position_in_world = [0, 2, 0]
//! intensity = [5, 5, 5]
//! [environment]                # optional equirectangular linear EXR (+Y up, see EnvironmentMap)
//! file = "window.exr"
//! intensity_scale = 1.0
//! ```
//!
//! glTF's metallic-roughness materials map to the Phong model as: k_d = baseColor·(1 − metallic);
//! k_s = 0.04·(1 − metallic) + baseColor·metallic; shininess n = 2/α² − 2 with α = roughness²
//! (the Blinn–Phong/Beckmann correspondence), and no glossy lobe when roughness ≥ 0.9. Where that is
//! not what a scene wants, `[materials.NAME]` overrides it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{Mat3, Mat4, Vec3};
use serde::Deserialize;

use super::{EnvironmentMap, Material, Mesh, Scene, SceneCamera};
use crate::light::Light;
use crate::pose::Pose;

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: {message}", path.display())]
    Toml { path: PathBuf, message: String },
    #[error("{}: {message}", path.display())]
    Gltf { path: PathBuf, message: String },
    #[error("{}: node `{node}`: {message}", path.display())]
    Node {
        path: PathBuf,
        node: String,
        message: String,
    },
    #[error("{}: {key}: {message}", path.display())]
    Invalid {
        path: PathBuf,
        key: String,
        message: String,
    },
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneToml {
    gltf: PathBuf,
    #[serde(default, rename = "virtual")]
    virtual_nodes: Vec<String>,
    #[serde(default)]
    camera: CameraToml,
    #[serde(default)]
    materials: BTreeMap<String, MaterialToml>,
    #[serde(default)]
    lights: Vec<Light>,
    environment: Option<EnvironmentToml>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraToml {
    width: Option<u32>,
    height: Option<u32>,
    position: Option<Vec3>,
    look_at: Option<Vec3>,
    yfov_deg: Option<f32>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MaterialToml {
    albedo: Option<Vec3>,
    specular: Option<Vec3>,
    shininess: Option<f32>,
    emission: Option<Vec3>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct EnvironmentToml {
    file: PathBuf,
    #[serde(default = "one")]
    intensity_scale: f32,
}

fn one() -> f32 {
    1.0
}

impl Scene {
    /// Load `dir/scene.toml` and the glTF it names.
    pub fn load(dir: &Path) -> Result<Scene, SceneError> {
        let toml_path = dir.join("scene.toml");
        let text = read_regular(&toml_path).and_then(|bytes| {
            String::from_utf8(bytes).map_err(|_| SceneError::Io {
                path: toml_path.clone(),
                source: std::io::Error::new(std::io::ErrorKind::InvalidData, "not UTF-8 text"),
            })
        })?;
        let desc: SceneToml = toml::from_str(&text).map_err(|e| SceneError::Toml {
            path: toml_path.clone(),
            message: e.to_string(),
        })?;
        let gltf_path = inside(dir, &desc.gltf, &toml_path, "gltf")?;
        let gltf_error = |message: String| SceneError::Gltf {
            path: gltf_path.clone(),
            message,
        };
        let gltf::Gltf { document, blob } =
            gltf::Gltf::from_slice_without_validation(&read_regular(&gltf_path)?)
                .map_err(|e| gltf_error(e.to_string()))?;
        position_accessors_exist(document.as_json()).map_err(gltf_error)?;
        let document = gltf::Document::from_json(document.into_json())
            .map_err(|e| gltf_error(e.to_string()))?;
        // Buffers only: images are not used, and a buffer file must lie beside the glTF.
        let gltf_dir = gltf_path.parent().unwrap_or(dir);
        for buffer in document.buffers() {
            if let gltf::buffer::Source::Uri(uri) = buffer.source()
                && !uri.starts_with("data:")
            {
                let path = inside(gltf_dir, Path::new(uri), &gltf_path, "buffers.uri")?;
                read_regular_check(&path)?;
            }
        }
        let buffers = gltf::import_buffers(&document, Some(gltf_dir), blob)
            .map_err(|e| gltf_error(e.to_string()))?;

        let mut materials: Vec<Material> = document
            .materials()
            .map(|m| material_from_gltf(&m))
            .collect();
        let default_material = materials.len();
        materials.push(Material::default());
        for (name, overrides) in &desc.materials {
            let material = materials
                .iter_mut()
                .find(|m| &m.name == name)
                .ok_or_else(|| SceneError::Invalid {
                    path: toml_path.clone(),
                    key: format!("materials.{name}"),
                    message: "no glTF material has this name".into(),
                })?;
            if let Some(v) = overrides.albedo {
                material.albedo = v;
            }
            if let Some(v) = overrides.specular {
                material.specular = v;
            }
            if let Some(v) = overrides.shininess {
                material.shininess = v;
            }
            if let Some(v) = overrides.emission {
                material.emission = v;
            }
        }
        for (i, material) in materials.iter().enumerate() {
            check_material(material).map_err(|message| SceneError::Invalid {
                path: toml_path.clone(),
                key: format!(
                    "materials.{}",
                    if material.name.is_empty() {
                        i.to_string()
                    } else {
                        material.name.clone()
                    }
                ),
                message,
            })?;
        }

        let mut meshes = Vec::new();
        let mut gltf_camera = None;
        let scene = document
            .default_scene()
            .or_else(|| document.scenes().next())
            .ok_or_else(|| SceneError::Gltf {
                path: gltf_path.clone(),
                message: "the file has no scene".into(),
            })?;
        let mut stack: Vec<(gltf::Node<'_>, Mat4)> =
            scene.nodes().map(|n| (n, Mat4::IDENTITY)).collect();
        while let Some((node, parent)) = stack.pop() {
            let world_from_node = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
            let name = node
                .name()
                .map_or_else(|| format!("node{}", node.index()), str::to_owned);
            if let (Some(camera), None) = (node.camera(), &gltf_camera)
                && let gltf::camera::Projection::Perspective(p) = camera.projection()
            {
                let (_, rotation, translation) = world_from_node.to_scale_rotation_translation();
                gltf_camera = Some((Pose::new(rotation, translation), p.yfov()));
            }
            if let Some(mesh) = node.mesh() {
                let primitives: Vec<_> = mesh.primitives().collect();
                for (k, primitive) in primitives.iter().enumerate() {
                    let mesh_name = if primitives.len() > 1 {
                        format!("{name}#{k}")
                    } else {
                        name.clone()
                    };
                    let node_error = |message: String| SceneError::Node {
                        path: gltf_path.clone(),
                        node: mesh_name.clone(),
                        message,
                    };
                    if primitive.mode() != gltf::mesh::Mode::Triangles {
                        return Err(node_error(format!(
                            "primitive mode {:?}; only triangles are supported",
                            primitive.mode()
                        )));
                    }
                    let reader = primitive.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
                    let positions: Vec<Vec3> = reader
                        .read_positions()
                        .ok_or_else(|| node_error("no POSITION attribute".into()))?
                        .map(|p| world_from_node.transform_point3(Vec3::from(p)))
                        .collect();
                    if positions.iter().any(|p| !p.is_finite()) {
                        return Err(node_error("non-finite vertex position".into()));
                    }
                    let indices: Vec<u32> = match reader.read_indices() {
                        Some(indices) => indices.into_u32().collect(),
                        None => (0..positions.len() as u32).collect(),
                    };
                    if let Some(bad) = indices.iter().find(|&&i| i as usize >= positions.len()) {
                        return Err(node_error(format!(
                            "index {bad} beyond {} vertices",
                            positions.len()
                        )));
                    }
                    let triangles: Vec<[u32; 3]> = indices
                        .chunks_exact(3)
                        .map(|t| [t[0], t[1], t[2]])
                        .collect();
                    let normal_matrix = Mat3::from_mat4(world_from_node).inverse().transpose();
                    let normals = match reader.read_normals() {
                        Some(normals) => normals
                            .map(|n| (normal_matrix * Vec3::from(n)).normalize_or_zero())
                            .collect(),
                        None => flat_normals(&positions, &triangles),
                    };
                    meshes.push(Mesh {
                        name: mesh_name.clone(),
                        positions_in_world: positions,
                        normals_in_world: normals,
                        triangles,
                        material: primitive.material().index().unwrap_or(default_material),
                        is_virtual: desc
                            .virtual_nodes
                            .iter()
                            .any(|v| *v == name || *v == mesh_name),
                        vertex_albedo: Vec::new(),
                    });
                }
            }
            stack.extend(node.children().map(|child| (child, world_from_node)));
        }
        for name in &desc.virtual_nodes {
            if !meshes
                .iter()
                .any(|m| &m.name == name || m.name.split('#').next() == Some(name))
            {
                let known: Vec<&str> = meshes.iter().map(|m| m.name.as_str()).collect();
                return Err(SceneError::Invalid {
                    path: toml_path,
                    key: "virtual".into(),
                    message: format!(
                        "no mesh node named `{name}`; mesh nodes: {}",
                        known.join(", ")
                    ),
                });
            }
        }
        meshes.sort_by(|a, b| a.name.cmp(&b.name));

        let invalid = |key: &str, message: String| SceneError::Invalid {
            path: toml_path.clone(),
            key: key.into(),
            message,
        };
        let (width, height) = (
            desc.camera.width.unwrap_or(160),
            desc.camera.height.unwrap_or(120),
        );
        let camera = match (desc.camera.position, desc.camera.look_at, gltf_camera) {
            (Some(position), Some(look_at), _) => SceneCamera {
                world_from_camera: Pose::look_at(position, look_at, Vec3::Y),
                yfov_rad: desc.camera.yfov_deg.unwrap_or(50.0).to_radians(),
                width,
                height,
            },
            (None, None, Some((pose, yfov_rad))) => SceneCamera {
                world_from_camera: pose,
                yfov_rad,
                width,
                height,
            },
            _ => {
                return Err(invalid(
                    "camera",
                    "give both position and look_at, or a glTF camera node".into(),
                ));
            }
        };
        if width == 0
            || height == 0
            || !(camera.yfov_rad > 0.0 && camera.yfov_rad < std::f32::consts::PI)
        {
            return Err(invalid(
                "camera",
                format!(
                    "{width}×{height}, yfov {} rad is not a usable camera",
                    camera.yfov_rad
                ),
            ));
        }
        for (i, light) in desc.lights.iter().enumerate() {
            light
                .validate()
                .map_err(|e| invalid(&format!("lights[{i}]"), e.to_string()))?;
        }
        let environment = match &desc.environment {
            None => None,
            Some(env) => {
                let path = inside(dir, &env.file, &toml_path, "environment.file")?;
                read_regular_check(&path)?;
                Some(load_environment(&path, env.intensity_scale)?)
            }
        };
        Ok(Scene {
            name: dir
                .file_name()
                .map_or_else(|| "scene".into(), |n| n.to_string_lossy().into_owned()),
            meshes,
            materials,
            camera,
            lights: desc.lights,
            environment,
            environment_lights: Vec::new(),
            shadow_proxy: None,
            surface_revision: None,
        })
    }
}

fn material_from_gltf(m: &gltf::Material<'_>) -> Material {
    let pbr = m.pbr_metallic_roughness();
    let [r, g, b, _] = pbr.base_color_factor();
    let base = Vec3::new(r, g, b);
    let metallic = pbr.metallic_factor().clamp(0.0, 1.0);
    let roughness = pbr.roughness_factor().clamp(0.0, 1.0);
    let alpha = (roughness * roughness).max(1e-3);
    let glossy = roughness < 0.9;
    Material {
        name: m.name().unwrap_or_default().to_owned(),
        albedo: base * (1.0 - metallic),
        specular: if glossy {
            Vec3::splat(0.04 * (1.0 - metallic)) + base * metallic
        } else {
            Vec3::ZERO
        },
        shininess: if glossy {
            (2.0 / (alpha * alpha) - 2.0).clamp(1.0, 10_000.0)
        } else {
            0.0
        },
        emission: Vec3::from(m.emissive_factor()),
    }
}

fn check_material(m: &Material) -> Result<(), String> {
    let finite = m.albedo.is_finite()
        && m.specular.is_finite()
        && m.emission.is_finite()
        && m.shininess.is_finite();
    if !finite {
        return Err("non-finite value".into());
    }
    if m.albedo.min_element() < 0.0
        || m.specular.min_element() < 0.0
        || m.emission.min_element() < 0.0
        || m.shininess < 0.0
    {
        return Err("negative value".into());
    }
    if (m.albedo + m.specular).max_element() > 1.0 + 1e-6 {
        return Err(format!(
            "albedo + specular = {} exceeds 1: the surface would create energy",
            m.albedo + m.specular
        ));
    }
    Ok(())
}

fn flat_normals(positions: &[Vec3], triangles: &[[u32; 3]]) -> Vec<Vec3> {
    let mut normals = vec![Vec3::ZERO; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| positions[i as usize]);
        let n = (b - a).cross(c - a);
        for i in t {
            normals[*i as usize] += n;
        }
    }
    normals.into_iter().map(Vec3::normalize_or_zero).collect()
}

/// `relative` under `dir`: a scene's files lie in its directory, so an absolute path, a `..` or
/// a URL scheme is refused (a scene from elsewhere cannot make the loader read `/dev/zero`).
fn inside(dir: &Path, relative: &Path, named_in: &Path, key: &str) -> Result<PathBuf, SceneError> {
    let text = relative.to_string_lossy();
    let escapes = relative.is_absolute()
        || text.contains("://")
        || relative
            .components()
            .any(|c| c == std::path::Component::ParentDir);
    if escapes {
        return Err(SceneError::Invalid {
            path: named_in.to_owned(),
            key: key.to_owned(),
            message: format!("{text:?} must be a path inside the scene directory"),
        });
    }
    Ok(dir.join(relative))
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> SceneError + '_ {
    move |source| SceneError::Io {
        path: path.to_owned(),
        source,
    }
}

/// gltf-json 1.4 reads a primitive's POSITION accessor by index, unchecked, while validating
/// (`primitive_validate_hook` in its `mesh.rs`) and panics on an index past the accessors; the
/// scene fuzzer found it. Such a file is refused here, before validation.
fn position_accessors_exist(root: &gltf::json::Root) -> Result<(), String> {
    let positions = gltf::json::validation::Checked::Valid(gltf::Semantic::Positions);
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            if let Some(index) = primitive.attributes.get(&positions)
                && index.value() >= root.accessors.len()
            {
                return Err(format!(
                    "meshes[{m}].primitives[{p}].attributes.POSITION: accessor {} does not exist ({} accessors)",
                    index.value(),
                    root.accessors.len()
                ));
            }
        }
    }
    Ok(())
}

/// The bytes of `path`, a regular file ([`crate::input_file`]).
fn read_regular(path: &Path) -> Result<Vec<u8>, SceneError> {
    crate::input_file::read_regular(path).map_err(io_error(path))
}

fn read_regular_check(path: &Path) -> Result<std::fs::File, SceneError> {
    crate::input_file::open_regular(path).map_err(io_error(path))
}

fn load_environment(path: &Path, scale: f32) -> Result<EnvironmentMap, SceneError> {
    let image = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |resolution, _| {
            (
                resolution.width(),
                vec![Vec3::ZERO; resolution.width() * resolution.height()],
            )
        },
        |(w, buffer): &mut (usize, Vec<Vec3>), position, (r, g, b, _a): (f32, f32, f32, f32)| {
            buffer[position.y() * *w + position.x()] = Vec3::new(r, g, b);
        },
    )
    .map_err(|e| SceneError::Invalid {
        path: path.to_owned(),
        key: "environment.file".into(),
        message: e.to_string(),
    })?;
    let size = image.layer_data.size;
    let (_, radiance) = image.layer_data.channel_data.pixels;
    if radiance
        .iter()
        .any(|p| !p.is_finite() || p.min_element() < 0.0)
    {
        return Err(SceneError::Invalid {
            path: path.to_owned(),
            key: "environment.file".into(),
            message: "negative or non-finite radiance".into(),
        });
    }
    Ok(EnvironmentMap {
        width: size.width() as u32,
        height: size.height() as u32,
        radiance: radiance.into_iter().map(|p| p * scale).collect(),
    })
}
