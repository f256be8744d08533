//! The scene as `pt` traces it on the GPU: the reference's own triangle list and BVH
//! ([`relight_reference::accel::Geometry`], built once per upload) flattened into buffers, the
//! materials with their emission, the lights in `shaders/common.wgsl`'s layout, and the
//! environment map with the reference's importance-sampling tables. Sharing the triangle
//! preparation and the tree with the CPU reference means both trace the same triangles (the
//! same ones dropped as degenerate or non-finite, the same measured albedo), and the cleaning
//! of materials, lights and the map is the reference's [`relight_reference::sanitized`].

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use relight_core::scene::Scene;
use relight_reference::EnvSampler;
use relight_reference::accel::{Child, Geometry};
use wgpu::util::DeviceExt;

use crate::gpu::GpuContext;
use crate::gpu_scene::{GpuLight, light_faces};

/// `LEAF` in `shaders/pt_trace.wgsl`: a child reference with this bit is a triangle.
const LEAF: u32 = 0x8000_0000;
const FLAG_TRI_VIRTUAL: u32 = 1;
const FLAG_TRI_ALBEDO: u32 = 2;
/// `NONE` in `shaders/pt_trace.wgsl`: a root that every ray misses (no triangles).
const NOTHING: u32 = u32::MAX;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Tri {
    v0: [f32; 4],
    e1: [f32; 4],
    e2: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct TriShade {
    ng: [f32; 4],
    normals: [[f32; 4]; 3],
    albedo: [[f32; 4]; 3],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct Node {
    lmin: [f32; 4],
    lmax: [f32; 4],
    rmin: [f32; 4],
    rmax: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
struct PtMaterial {
    albedo: [f32; 4],
    specular: [f32; 4],
    emission: [f32; 4],
}

/// One upload of a scene.
#[derive(Debug)]
pub struct PtScene {
    pub tris: wgpu::Buffer,
    pub shades: wgpu::Buffer,
    pub nodes: wgpu::Buffer,
    pub materials: wgpu::Buffer,
    pub lights: wgpu::Buffer,
    pub env_radiance: wgpu::Buffer,
    pub env_tables: wgpu::Buffer,
    pub light_count: u32,
    /// Where traversal starts: an inner node's index or `LEAF | triangle` (`NOTHING` without
    /// triangles).
    pub root: u32,
    /// The environment map's size, (0, 0) without one (or an all-black one).
    pub env_size: (u32, u32),
    pub triangles: u32,
    /// The virtual object's triangles (0: Δ is zero on every pixel).
    pub virtual_triangles: u32,
}

impl PtScene {
    pub fn new(ctx: &GpuContext, scene: &Scene) -> Self {
        let scene = relight_reference::sanitized(scene);
        let geometry = Geometry::new(&scene, true);
        let fallback = scene.materials.len() as u32;
        let tris: Vec<Tri> = geometry
            .triangles()
            .iter()
            .map(|t| {
                let material = if t.material < scene.materials.len() {
                    t.material as u32
                } else {
                    fallback
                };
                let virtual_flag = if t.is_virtual { FLAG_TRI_VIRTUAL } else { 0 };
                let albedo_flag = if t.albedo.is_some() {
                    FLAG_TRI_ALBEDO
                } else {
                    0
                };
                let flags = virtual_flag | albedo_flag;
                Tri {
                    v0: t.v0.extend(f32::from_bits(material)).to_array(),
                    e1: t.e1.extend(f32::from_bits(flags)).to_array(),
                    e2: t.e2.extend(0.0).to_array(),
                }
            })
            .collect();
        let shades: Vec<TriShade> = geometry
            .triangles()
            .iter()
            .map(|t| TriShade {
                ng: t.geometric_normal.extend(0.0).to_array(),
                normals: t.normals.map(|n| n.extend(0.0).to_array()),
                albedo: t
                    .albedo
                    .unwrap_or([Vec3::ZERO; 3])
                    .map(|a| a.extend(0.0).to_array()),
            })
            .collect();
        let (nodes, root) = flatten(&geometry);
        let mut materials: Vec<PtMaterial> = scene
            .materials
            .iter()
            .map(|m| PtMaterial {
                albedo: m.albedo.extend(m.shininess).to_array(),
                specular: m.specular.extend(0.0).to_array(),
                emission: m.emission.extend(0.0).to_array(),
            })
            .collect();
        // The reference's stand-in for a material index past the list: black.
        materials.push(PtMaterial::zeroed());
        let bounds = scene
            .real_bounds()
            .into_iter()
            .chain(scene.virtual_bounds())
            .reduce(|(lo, hi), (l, h)| (lo.min(l), hi.max(h)))
            .unwrap_or((Vec3::ZERO, Vec3::ZERO));
        let (lights, _) = light_faces(&scene.lights, bounds);
        let sampler = scene.environment.as_ref().and_then(EnvSampler::new);
        let (env_size, env_radiance, env_tables) = match (&scene.environment, &sampler) {
            (Some(env), Some(sampler)) => (
                (env.width, env.height),
                env.radiance
                    .iter()
                    .map(|c| c.extend(0.0).to_array())
                    .collect(),
                sampler.tables(),
            ),
            _ => ((0, 0), Vec::new(), Vec::new()),
        };
        let storage = |label: &str, bytes: &[u8]| {
            // wgpu refuses empty bindings: one zeroed element stands in, never read.
            let bytes = if bytes.is_empty() {
                &[0u8; 64][..]
            } else {
                bytes
            };
            ctx.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents: bytes,
                    usage: wgpu::BufferUsages::STORAGE,
                })
        };
        Self {
            tris: storage("pt triangles", bytemuck::cast_slice(&tris)),
            shades: storage("pt shading", bytemuck::cast_slice(&shades)),
            nodes: storage("pt bvh", bytemuck::cast_slice(&nodes)),
            materials: storage("pt materials", bytemuck::cast_slice(&materials)),
            lights: storage("pt lights", bytemuck::cast_slice::<GpuLight, u8>(&lights)),
            env_radiance: storage("pt environment", bytemuck::cast_slice(&env_radiance)),
            env_tables: storage("pt environment tables", bytemuck::cast_slice(&env_tables)),
            light_count: lights.len() as u32,
            root,
            env_size,
            triangles: tris.len() as u32,
            virtual_triangles: geometry.triangles().iter().filter(|t| t.is_virtual).count() as u32,
        }
    }
}

/// The reference's BVH as `Node`s, children referenced by inner-node index or
/// `LEAF | triangle`, and the root's reference.
fn flatten(geometry: &Geometry) -> (Vec<Node>, u32) {
    let (flat, root) = geometry.flat_bvh();
    let reference = |child: Child| match child {
        Child::Inner(i) => i,
        Child::Triangle(t) => LEAF | t,
    };
    let corner = |p: Vec3, child: u32| p.extend(f32::from_bits(child)).to_array();
    let nodes = flat
        .iter()
        .map(|n| Node {
            lmin: corner(n.min[0], reference(n.children[0])),
            lmax: corner(n.max[0], 0),
            rmin: corner(n.min[1], reference(n.children[1])),
            rmax: corner(n.max[1], 0),
        })
        .collect();
    (nodes, root.map_or(NOTHING, reference))
}
