//! The scene as the GPU passes see it: each mesh's vertices once and one index buffer of
//! triangles (real meshes first, then virtual, so the real-only draws are a prefix), the
//! materials, the camera, and every light with its shadow-map faces. Layouts match
//! `shaders/common.wgsl`.
//!
//! Indexed, because a depth mesh shares each vertex among six triangles: drawn as a triangle
//! soup, the raster passes shaded and fetched every vertex six times and uploaded six copies.

use std::ops::Range;

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec2, Vec3};
use relight_core::light::Light;
use relight_core::scene::{Mesh, Scene, SceneCamera, box_corners, point_bounds};

use crate::deferred::KeptInputs;
use crate::gpu::GpuContext;

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuVertex {
    pub position: [f32; 3],
    pub normal: [f32; 3],
    pub material: u32,
    pub flags: u32,
}

impl GpuVertex {
    pub const LAYOUT: wgpu::VertexBufferLayout<'static> = wgpu::VertexBufferLayout {
        array_stride: size_of::<GpuVertex>() as u64,
        step_mode: wgpu::VertexStepMode::Vertex,
        attributes: &wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Uint32, 3 => Uint32],
    };
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuMaterial {
    pub albedo: [f32; 4],
    pub specular: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuCamera {
    pub view_proj: [[f32; 4]; 4],
    pub position: [f32; 4],
    pub size: [f32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuLight {
    pub position: [f32; 4],
    pub direction: [f32; 4],
    pub intensity: [f32; 4],
    pub faces: [u32; 4],
}

#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuFace {
    pub view_proj: [[f32; 4]; 4],
    pub axis: [f32; 4],
    /// The light's index, and [`FACE_ORTHOGRAPHIC`] for a directional light's map (else 0).
    pub light: [u32; 4],
}

/// `GpuFace::light[1]` of a directional light's orthographic map (`face.light.y` in the shaders).
pub const FACE_ORTHOGRAPHIC: u32 = 1;

const FLAG_VIRTUAL: u32 = 1;
const FLAG_MEASURED_ALBEDO: u32 = 2;

/// A vertex's measured albedo in its flags, as `shaders/common.wgsl` `measured_albedo` reads it:
/// the flag, and √albedo per channel in bytes 1–3 (8 bits: a step of at most 1.6 % of an albedo
/// of 0.05, where a linear byte would step 8 %).
pub fn pack_measured_albedo(albedo: Vec3) -> u32 {
    let byte = |c: f32| (c.clamp(0.0, 1.0).sqrt() * 255.0).round() as u32;
    FLAG_MEASURED_ALBEDO | byte(albedo.x) << 8 | byte(albedo.y) << 16 | byte(albedo.z) << 24
}

/// A spot light wider than this (half angle) gets a cube of shadow maps like a point light.
const MAX_SPOT_HALF_ANGLE_RAD: f32 = 80.0 * std::f32::consts::PI / 180.0;

/// The scene's geometry and materials on the GPU.
#[derive(Debug)]
pub struct GpuScene {
    /// Every mesh's vertices with a finite position, each once.
    pub vertices: wgpu::Buffer,
    /// Three indices into [`Self::vertices`] per triangle.
    pub indices: wgpu::Buffer,
    /// Indices of the real meshes' triangles (drawn first).
    pub real_indices: u32,
    pub all_indices: u32,
    pub materials: wgpu::Buffer,
    /// Indices the light-space passes draw for the real meshes: the [`Scene::shadow_proxy`]'s
    /// (after every mesh's) when the scene has one, else the real meshes'.
    pub shadow_real: Range<u32>,
    /// World-space bounds of every mesh.
    pub bounds: (Vec3, Vec3),
    /// Bounds of what the light-space passes draw (the shadow maps' frusta enclose them).
    pub light_bounds: (Vec3, Vec3),
    /// Hashes of what the light-space passes draw: the real part (with the materials) and the
    /// virtual part. Equal hashes, equal lights: equal shadow maps.
    pub light_fingerprint: [u64; 2],
    /// Bounds of the virtual object(s), if any.
    pub virtual_bounds: Option<(Vec3, Vec3)>,
    /// The real meshes' vertex positions (the first of [`Self::vertices`]) and their
    /// triangles' indices (`0..real_indices` of [`Self::indices`]), kept on the CPU to pick
    /// the triangles a part of the camera's image needs (`shadow_reach::triangles_within`).
    pub real_positions: Vec<Vec3>,
    pub real_triangles: Vec<u32>,
}

impl GpuScene {
    /// Upload `scene`. Triangles with missing or non-finite vertices are skipped; missing or
    /// zero normals become zero (the passes then use the facet normal); material indices out of
    /// range fall back to a default grey. A vertex's measured albedo, where the mesh has one,
    /// takes the place of its material's diffuse albedo.
    pub fn new(ctx: &GpuContext, scene: &Scene) -> Self {
        let mut materials: Vec<GpuMaterial> = scene
            .materials
            .iter()
            .map(|m| {
                let clean = |v: Vec3| {
                    let v = if v.is_finite() { v } else { Vec3::ZERO };
                    v.max(Vec3::ZERO)
                };
                let shininess = if m.shininess.is_finite() {
                    m.shininess.max(0.0)
                } else {
                    0.0
                };
                GpuMaterial {
                    albedo: clean(m.albedo).extend(shininess).to_array(),
                    specular: clean(m.specular).extend(0.0).to_array(),
                }
            })
            .collect();
        let fallback = materials.len() as u32;
        materials.push(GpuMaterial {
            albedo: [0.5, 0.5, 0.5, 0.0],
            specular: [0.0; 4],
        });
        let mut vertices = Vec::new();
        let mut indices: Vec<u32> = Vec::new();
        // Each mesh's vertices, then its triangles as indices into them (a triangle with a
        // vertex whose position is not finite is left out); returns where its vertices end.
        let push_mesh = |mesh: &Mesh, vertices: &mut Vec<GpuVertex>, indices: &mut Vec<u32>| {
            let material = if mesh.material < scene.materials.len() {
                mesh.material as u32
            } else {
                fallback
            };
            let virtual_flag = if mesh.is_virtual { FLAG_VIRTUAL } else { 0 };
            let index_of: Vec<Option<u32>> = mesh
                .positions_in_world
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    if !p.is_finite() {
                        return None;
                    }
                    let n = mesh.normals_in_world.get(i).copied();
                    let n = n.filter(|n| n.is_finite()).unwrap_or(Vec3::ZERO);
                    vertices.push(GpuVertex {
                        position: p.to_array(),
                        normal: n.normalize_or_zero().to_array(),
                        material,
                        flags: virtual_flag
                            | mesh
                                .measured_albedo(i as u32)
                                .map_or(0, pack_measured_albedo),
                    });
                    Some(vertices.len() as u32 - 1)
                })
                .collect();
            indices.reserve(3 * mesh.triangles.len());
            for tri in &mesh.triangles {
                if let [Some(a), Some(b), Some(c)] =
                    tri.map(|i| index_of.get(i as usize).copied().flatten())
                {
                    indices.extend([a, b, c]);
                }
            }
            vertices.len() as u32
        };
        // The index ranges of the real meshes, the virtual ones and the proxy, and the vertex
        // ranges each draws from.
        let mut real_indices = 0;
        let mut vertex_ranges = [0..0, 0..0, 0..0];
        for want_virtual in [false, true] {
            let first = vertices.len() as u32;
            for mesh in scene.meshes.iter().filter(|m| m.is_virtual == want_virtual) {
                push_mesh(mesh, &mut vertices, &mut indices);
            }
            vertex_ranges[usize::from(want_virtual)] = first..vertices.len() as u32;
            if !want_virtual {
                real_indices = indices.len() as u32;
            }
        }
        let all_indices = indices.len() as u32;
        let shadow_real = match &scene.shadow_proxy {
            Some(proxy) => {
                let first = vertices.len() as u32;
                vertex_ranges[2] = first..push_mesh(proxy, &mut vertices, &mut indices);
                all_indices..indices.len() as u32
            }
            None => {
                vertex_ranges[2] = vertex_ranges[0].clone();
                0..real_indices
            }
        };
        let corners = |r: Range<u32>| &indices[r.start as usize..r.end as usize];
        let bounds_of = |r: Range<u32>| {
            point_bounds(
                corners(r)
                    .iter()
                    .map(|&i| Vec3::from(vertices[i as usize].position)),
            )
        };
        let bounds = bounds_of(0..all_indices).unwrap_or((Vec3::ZERO, Vec3::ZERO));
        let light_bounds = [
            bounds_of(shadow_real.clone()),
            bounds_of(real_indices..all_indices),
        ]
        .into_iter()
        .flatten()
        .reduce(|(lo, hi), (l, h)| (lo.min(l), hi.max(h)))
        .unwrap_or((Vec3::ZERO, Vec3::ZERO));
        // The triangles of an index range and the vertices they draw from, with the indices
        // relative to the first of those: a held proxy hashes alike whatever precedes it.
        let geometry_hash = |r: Range<u32>, from: &Range<u32>, extra: &[u8]| {
            let relative: Vec<u32> = corners(r).iter().map(|i| i - from.start).collect();
            KeptInputs::hash_of(&[
                bytemuck::cast_slice(&relative),
                bytemuck::cast_slice(&vertices[from.start as usize..from.end as usize]),
                extra,
            ])
        };
        let light_fingerprint = [
            geometry_hash(
                shadow_real.clone(),
                &vertex_ranges[2],
                bytemuck::cast_slice(&materials),
            ),
            geometry_hash(real_indices..all_indices, &vertex_ranges[1], &[]),
        ];
        // wgpu refuses zero-sized buffers; one degenerate triangle is never drawn.
        if vertices.is_empty() {
            vertices.push(GpuVertex::zeroed());
        }
        if indices.is_empty() {
            indices.extend([0; 3]);
        }
        let all_indices = if scene.meshes.is_empty() {
            0
        } else {
            all_indices
        };
        Self {
            // Storage too: DVCT voxelises the triangles in a compute pass.
            vertices: ctx.buffer_with(
                "scene vertices",
                bytemuck::cast_slice(&vertices),
                wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::STORAGE,
            ),
            indices: ctx.buffer_with(
                "scene triangles",
                bytemuck::cast_slice(&indices),
                wgpu::BufferUsages::INDEX | wgpu::BufferUsages::STORAGE,
            ),
            real_indices,
            all_indices,
            shadow_real,
            materials: ctx.buffer_with(
                "materials",
                bytemuck::cast_slice(&materials),
                wgpu::BufferUsages::STORAGE,
            ),
            bounds,
            light_bounds,
            light_fingerprint,
            virtual_bounds: scene.virtual_bounds(),
            real_positions: vertices
                [vertex_ranges[0].start as usize..vertex_ranges[0].end as usize]
                .iter()
                .map(|v| Vec3::from(v.position))
                .collect(),
            real_triangles: indices[..real_indices as usize].to_vec(),
        }
    }
}

impl GpuScene {
    /// Every triangle the light-space passes draw, as one range of indices: the virtual
    /// object's and the shadow proxy's, which follows it, or every mesh's when there is no
    /// proxy.
    pub fn light_space_indices(&self) -> Range<u32> {
        if self.shadow_real.start == self.all_indices {
            self.real_indices..self.shadow_real.end
        } else {
            0..self.all_indices
        }
    }

    /// A hash of [`Self::light_space_indices`] and the materials.
    pub fn light_space_fingerprint(&self) -> u64 {
        KeptInputs::hash_of(&[
            &self.light_fingerprint[0].to_le_bytes(),
            &self.light_fingerprint[1].to_le_bytes(),
        ])
    }
}

/// The camera uniform for an image of `width` × `height` with the scene camera's vertical field
/// of view; its depth reversed (1 at the near plane, 0 at infinity, see `gbuffer::DepthOrder`),
/// the near plane at 1e-4 of the distance to `bounds`' farthest corner.
pub fn camera_uniform(
    camera: &SceneCamera,
    width: u32,
    height: u32,
    bounds: (Vec3, Vec3),
) -> GpuCamera {
    let pose = camera.world_from_camera;
    let eye = pose.translation;
    let far = box_corners(bounds)
        .iter()
        .map(|c| c.distance(eye))
        .fold(1.0f32, f32::max)
        * 1.5;
    let view = Mat4::from_rotation_translation(pose.rotation, pose.translation).inverse();
    let aspect = width as f32 / height.max(1) as f32;
    let proj = Mat4::perspective_infinite_reverse_rh(camera.yfov_rad, aspect, far * 1e-4);
    GpuCamera {
        view_proj: (proj * view).to_cols_array_2d(),
        position: eye.extend(1.0).to_array(),
        size: [
            width as f32,
            height as f32,
            1.0 / width.max(1) as f32,
            1.0 / height.max(1) as f32,
        ],
    }
}

impl GpuCamera {
    /// The camera with its image moved by `offset_px` pixels (x right, y down): each pixel's
    /// centre sample then sees what lay `offset_px` from it before, so frames drawn at offsets
    /// spread over a pixel average to the pixel's area.
    pub fn jittered(mut self, offset_px: Vec2) -> Self {
        let [width, height] = [self.size[0].max(1.0), self.size[1].max(1.0)];
        let shift = Mat4::from_translation(Vec3::new(
            2.0 * offset_px.x / width,
            -2.0 * offset_px.y / height,
            0.0,
        ));
        self.view_proj = (shift * Mat4::from_cols_array_2d(&self.view_proj)).to_cols_array_2d();
        self
    }
}

/// Whether the passes shade and shadow `light` (point, spot, directional): environment lights
/// and invalid ones are left out.
pub fn is_shadowed(light: &Light) -> bool {
    light.validate().is_ok() && !matches!(light, Light::Environment { .. })
}

/// Lights the passes can shadow ([`is_shadowed`]) and their shadow-map faces. A face is the
/// same at every map size (the shadow maps and a VPL engine's RSM may differ): its `axis.w` is
/// tan(fov/2) for a perspective face and the cross-section's area (m²) for an orthographic one,
/// which the shaders divide into texels.
pub fn light_faces(lights: &[Light], bounds: (Vec3, Vec3)) -> (Vec<GpuLight>, Vec<GpuFace>) {
    let mut gpu_lights = Vec::new();
    let mut faces = Vec::new();
    let reach = |from: Vec3| {
        box_corners(bounds)
            .iter()
            .map(|c| c.distance(from))
            .fold(0.0f32, f32::max)
            * 1.05
            + 0.01
    };
    for light in lights.iter().filter(|l| is_shadowed(l)) {
        let index = gpu_lights.len() as u32;
        let first = faces.len() as u32;
        let cube = |position: Vec3, faces: &mut Vec<GpuFace>| {
            let far = reach(position);
            let proj = Mat4::perspective_rh(std::f32::consts::FRAC_PI_2, 1.0, far * 1e-4, far);
            for (dir, up) in [
                (Vec3::X, Vec3::NEG_Y),
                (Vec3::NEG_X, Vec3::NEG_Y),
                (Vec3::Y, Vec3::Z),
                (Vec3::NEG_Y, Vec3::NEG_Z),
                (Vec3::Z, Vec3::NEG_Y),
                (Vec3::NEG_Z, Vec3::NEG_Y),
            ] {
                let view = Mat4::look_at_rh(position, position + dir, up);
                faces.push(GpuFace {
                    view_proj: (proj * view).to_cols_array_2d(),
                    axis: dir.extend(1.0).to_array(),
                    light: [index, 0, 0, 0],
                });
            }
        };
        let gpu = match *light {
            Light::Point {
                position_in_world,
                intensity,
            } => {
                cube(position_in_world, &mut faces);
                GpuLight {
                    position: position_in_world.extend(0.0).to_array(),
                    direction: [0.0, -1.0, 0.0, -1.0],
                    intensity: intensity.extend(1.0).to_array(),
                    faces: [first, 6, 0, 0],
                }
            }
            Light::Spot {
                position_in_world,
                direction_in_world,
                intensity,
                inner_angle_rad,
                outer_angle_rad,
            } => {
                let axis = direction_in_world.normalize();
                if outer_angle_rad <= MAX_SPOT_HALF_ANGLE_RAD {
                    let half = (outer_angle_rad * 1.05 + 0.01).min(MAX_SPOT_HALF_ANGLE_RAD + 0.05);
                    let far = reach(position_in_world);
                    let proj = Mat4::perspective_rh(2.0 * half, 1.0, far * 1e-4, far);
                    let up = axis.any_orthonormal_vector();
                    let view = Mat4::look_at_rh(position_in_world, position_in_world + axis, up);
                    faces.push(GpuFace {
                        view_proj: (proj * view).to_cols_array_2d(),
                        axis: axis.extend(half.tan()).to_array(),
                        light: [index, 0, 0, 0],
                    });
                } else {
                    cube(position_in_world, &mut faces);
                }
                GpuLight {
                    position: position_in_world.extend(1.0).to_array(),
                    direction: axis.extend(outer_angle_rad.cos()).to_array(),
                    intensity: intensity.extend(inner_angle_rad.cos()).to_array(),
                    faces: [first, faces.len() as u32 - first, 0, 0],
                }
            }
            Light::Directional {
                direction_in_world,
                irradiance,
            } => {
                let dir = direction_in_world.normalize();
                let center = (bounds.0 + bounds.1) / 2.0;
                let radius = (bounds.1 - bounds.0).length() / 2.0 + 0.01;
                let eye = center - dir * radius * 2.0;
                let view = Mat4::look_at_rh(eye, center, dir.any_orthonormal_vector());
                let proj =
                    Mat4::orthographic_rh(-radius, radius, -radius, radius, 0.0, radius * 4.0);
                let edge = 2.0 * radius;
                faces.push(GpuFace {
                    view_proj: (proj * view).to_cols_array_2d(),
                    axis: dir.extend(edge * edge).to_array(),
                    light: [index, FACE_ORTHOGRAPHIC, 0, 0],
                });
                GpuLight {
                    position: Vec3::ZERO.extend(2.0).to_array(),
                    direction: dir.extend(-1.0).to_array(),
                    intensity: irradiance.extend(1.0).to_array(),
                    faces: [first, 1, 0, 0],
                }
            }
            Light::Environment { .. } => continue,
        };
        gpu_lights.push(gpu);
    }
    (gpu_lights, faces)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What `shaders/common.wgsl` `measured_albedo` reads back: bytes 1–3 as unorm, squared.
    fn unpack(flags: u32) -> Vec3 {
        let byte = |shift: u32| ((flags >> shift) & 0xff) as f32 / 255.0;
        Vec3::new(byte(8), byte(16), byte(24)).powf(2.0)
    }

    #[test]
    fn measured_albedo_packs_into_the_flags_within_its_step() {
        for albedo in [
            Vec3::new(0.05, 0.5, 1.0),
            Vec3::new(0.7, 0.1, 0.08),
            Vec3::ZERO,
        ] {
            let flags = pack_measured_albedo(albedo);
            assert_eq!(
                flags & (FLAG_VIRTUAL | FLAG_MEASURED_ALBEDO),
                FLAG_MEASURED_ALBEDO
            );
            let back = unpack(flags);
            // Half a step of √a is 1/510, so a moves by at most 2√a/510 + (1/510)².
            let bound = albedo.map(|a| 2.0 * a.sqrt() / 510.0 + 1.0 / (510.0 * 510.0));
            assert!(
                (back - albedo).abs().cmple(bound).all(),
                "{albedo} → {back}"
            );
        }
        assert_eq!(unpack(pack_measured_albedo(Vec3::splat(7.0))), Vec3::ONE);
    }
}
