//! Offline scene description: a glTF 2.0 file (geometry, materials, camera) plus a `scene.toml`
//! that says which nodes are the virtual object(s) and lists the lights.
//!
//! Everything is flattened into world space on load, so renderers (the reference path tracer,
//! the simulator, the engines' offline path) never walk a node hierarchy.

use std::sync::Arc;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::light::Light;
use crate::pose::Pose;

/// A surface's reflectance: Lambertian albedo plus an energy-conserving Phong lobe
/// (f_r = k_d/π + k_s (n+1)/(2π) cosⁿα, α measured from the mirror direction).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub name: String,
    /// Diffuse albedo k_d, linear RGB in [0, 1].
    pub albedo: Vec3,
    /// Specular reflectance k_s, linear RGB; k_d + k_s ≤ 1 per channel.
    pub specular: Vec3,
    /// Phong exponent n (0 = no glossy lobe).
    pub shininess: f32,
    /// Emitted radiance, linear RGB, W/(sr·m²).
    pub emission: Vec3,
}

impl Default for Material {
    fn default() -> Self {
        Self {
            name: "default".into(),
            albedo: Vec3::splat(0.8),
            specular: Vec3::ZERO,
            shininess: 0.0,
            emission: Vec3::ZERO,
        }
    }
}

/// A triangle mesh in world space, from one glTF node (one primitive).
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// The glTF node name (unique within a scene; `scene.toml` refers to it).
    pub name: String,
    pub positions_in_world: Vec<Vec3>,
    /// Unit vertex normals in world space (same length as positions).
    pub normals_in_world: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    /// Index into [`Scene::materials`].
    pub material: usize,
    /// True for the inserted virtual object(s) O; false for the reconstructed real scene.
    pub is_virtual: bool,
    /// Diffuse albedo per vertex (linear RGB, same length as positions), in place of the
    /// material's: what albedo estimation measured on a depth-derived surface. Empty: the
    /// material's albedo everywhere.
    pub vertex_albedo: Vec<Vec3>,
}

/// The camera whose image is relit, glTF convention (looks down −Z, +Y up).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SceneCamera {
    pub world_from_camera: Pose,
    /// Vertical field of view, radians.
    pub yfov_rad: f32,
    pub width: u32,
    pub height: u32,
}

/// An HDR environment: equirectangular linear radiance around the scene, +Y up; the u axis
/// starts at −Z and turns towards +X (longitude φ = atan2(x, −z)), v = 0 is straight up.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvironmentMap {
    pub width: u32,
    pub height: u32,
    /// Row-major, `width × height` texels of linear RGB radiance.
    pub radiance: Vec<Vec3>,
}

/// A loaded scene: every mesh flattened into world space, with its materials, camera and lights.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub name: String,
    pub meshes: Vec<Mesh>,
    pub materials: Vec<Material>,
    pub camera: SceneCamera,
    /// Point, spot and directional lights (an environment light is in `environment`).
    pub lights: Vec<Light>,
    pub environment: Option<EnvironmentMap>,
    /// `environment` as a few directional lights (the light probe's median cut), for the engines
    /// that light only with discrete lights. Engines that sample `environment` themselves
    /// ignore these, so the environment's light is counted once either way. Empty for a scene
    /// file.
    pub environment_lights: Vec<Light>,
    /// The real meshes as the light-space passes (shadow maps, reflective shadow maps) draw
    /// them, in their place: the live depth surface decimated, and kept while the real surface
    /// holds, so the maps of a still scene need not be redrawn. `None`: the real meshes
    /// themselves. Only the rasterising engines use it; the reference ignores it.
    pub shadow_proxy: Option<Arc<Mesh>>,
    /// For a live depth surface: a count the temporal depth merge advances whenever it resets
    /// (the real surface materially changed). Equal revisions are the same surface up to
    /// sensor noise, so an engine that accumulates over frames (`pt`) keeps what it traced.
    /// `None` for a scene file: its real meshes are compared themselves.
    pub surface_revision: Option<u64>,
}

impl Mesh {
    /// An axis-aligned box from `lo` to `hi`: four vertices per face with the face's outward
    /// normal, two triangles per face (what the test scenes and hand-built test cases use).
    pub fn cuboid(name: &str, lo: Vec3, hi: Vec3, material: usize, is_virtual: bool) -> Mesh {
        let c = |x: usize, y: usize, z: usize| {
            Vec3::new([lo.x, hi.x][x], [lo.y, hi.y][y], [lo.z, hi.z][z])
        };
        let faces = [
            ([c(0, 0, 1), c(1, 0, 1), c(1, 1, 1), c(0, 1, 1)], Vec3::Z),
            ([c(1, 0, 0), c(0, 0, 0), c(0, 1, 0), c(1, 1, 0)], -Vec3::Z),
            ([c(1, 0, 1), c(1, 0, 0), c(1, 1, 0), c(1, 1, 1)], Vec3::X),
            ([c(0, 0, 0), c(0, 0, 1), c(0, 1, 1), c(0, 1, 0)], -Vec3::X),
            ([c(0, 1, 1), c(1, 1, 1), c(1, 1, 0), c(0, 1, 0)], Vec3::Y),
            ([c(0, 0, 0), c(1, 0, 0), c(1, 0, 1), c(0, 0, 1)], -Vec3::Y),
        ];
        let mut mesh = Mesh {
            name: name.into(),
            positions_in_world: Vec::new(),
            normals_in_world: Vec::new(),
            triangles: Vec::new(),
            material,
            is_virtual,
            vertex_albedo: Vec::new(),
        };
        for (quad, normal) in faces {
            let base = mesh.positions_in_world.len() as u32;
            mesh.positions_in_world.extend(quad);
            mesh.normals_in_world.extend([normal; 4]);
            mesh.triangles
                .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        }
        mesh
    }
}

impl Mesh {
    /// The measured albedo of `vertex`, if the mesh carries one for it and it is finite
    /// (clamped to [0, 1]); `None`: the material's.
    pub fn measured_albedo(&self, vertex: u32) -> Option<Vec3> {
        self.vertex_albedo
            .get(vertex as usize)
            .filter(|a| a.is_finite())
            .map(|a| a.clamp(Vec3::ZERO, Vec3::ONE))
    }
}

impl Scene {
    /// The real scene alone (what L^μ is rendered from).
    pub fn without_virtual(&self) -> Scene {
        Scene {
            meshes: self
                .meshes
                .iter()
                .filter(|m| !m.is_virtual)
                .cloned()
                .collect(),
            ..self.clone()
        }
    }

    /// World-space bounding box (min, max) of the meshes the light-space passes draw: the
    /// virtual ones, and the real scene's [`Scene::shadow_proxy`] where it has one (held while
    /// the live surface holds, so these bounds do not move with the sensor's noise), else the
    /// real meshes. `None` without any.
    pub fn light_space_bounds(&self) -> Option<(Vec3, Vec3)> {
        let virtual_meshes = self.meshes.iter().filter(|m| m.is_virtual);
        match &self.shadow_proxy {
            Some(proxy) => bounds(std::iter::once(&**proxy).chain(virtual_meshes)),
            None => bounds(self.meshes.iter()),
        }
    }

    /// World-space bounding box (min, max) of the real meshes, `None` without any.
    pub fn real_bounds(&self) -> Option<(Vec3, Vec3)> {
        bounds(self.meshes.iter().filter(|m| !m.is_virtual))
    }

    /// World-space bounding box (min, max) of the virtual object(s), `None` without any.
    pub fn virtual_bounds(&self) -> Option<(Vec3, Vec3)> {
        bounds(self.meshes.iter().filter(|m| m.is_virtual))
    }
}

/// The eight corners of the box `(lo, hi)`; bit 0 of the index picks x, bit 1 y, bit 2 z.
pub fn box_corners((lo, hi): (Vec3, Vec3)) -> [Vec3; 8] {
    std::array::from_fn(|i| {
        Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    })
}

/// The axis-aligned box (lowest and highest corner) around every vertex of `meshes`; `None`
/// without one.
pub fn bounds<'a>(meshes: impl Iterator<Item = &'a Mesh>) -> Option<(Vec3, Vec3)> {
    point_bounds(meshes.flat_map(|m| m.positions_in_world.iter().copied()))
}

/// The axis-aligned box (lowest and highest corner) around `points`; `None` without one.
pub fn point_bounds(points: impl IntoIterator<Item = Vec3>) -> Option<(Vec3, Vec3)> {
    points.into_iter().fold(None, |acc, p| match acc {
        None => Some((p, p)),
        Some((lo, hi)) => Some((lo.min(p), hi.max(p))),
    })
}

mod load;

pub use load::SceneError;
