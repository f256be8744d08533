//! Scene geometry for ray queries: every triangle in world space with its material and
//! real/virtual flag, behind a BVH from the `bvh` crate.
//!
//! The crate gives candidate traversal (every triangle whose box the ray crosses); the triangle
//! test and the closest-hit choice are ours. The crate's own closest-hit helpers return the shape
//! but not the barycentrics we need for normal interpolation, and — more important for
//! correlated sampling — our choice (smallest t, ties to the lower triangle index, with the same
//! Möller–Trumbore arithmetic per triangle) depends only on the set of triangles the ray meets,
//! not on the tree's shape. The full and the real-only BVH therefore agree bitwise on every ray
//! that does not meet a virtual triangle, which is what makes Δ exactly zero there.

use bvh::aabb::{Aabb, Bounded};
use bvh::bounding_hierarchy::BHShape;
use bvh::bvh::{Bvh, BvhNode};
use glam::Vec3;
use nalgebra::{Point3, Vector3};
use relight_core::scene::{Mesh, Scene};

/// One world-space triangle.
#[derive(Debug, Clone)]
pub struct Triangle {
    pub v0: Vec3,
    pub e1: Vec3,
    pub e2: Vec3,
    pub normals: [Vec3; 3],
    /// Unit geometric normal (zero-area triangles are left out of the geometry).
    pub geometric_normal: Vec3,
    pub material: usize,
    /// The corners' measured albedo ([`relight_core::scene::Mesh::vertex_albedo`]), in place
    /// of the material's.
    pub albedo: Option<[Vec3; 3]>,
    pub is_virtual: bool,
    /// Position in [`Geometry::triangles`].
    pub index: usize,
    node_index: usize,
}

impl Triangle {
    /// The geometric normal on the side a ray travelling along `dir` meets it (triangles are
    /// two-sided).
    pub fn normal_against(&self, dir: Vec3) -> Vec3 {
        if self.geometric_normal.dot(dir) > 0.0 {
            -self.geometric_normal
        } else {
            self.geometric_normal
        }
    }

    /// The measured albedo at barycentrics (`u`, `v`), where the corners have one.
    pub fn measured_albedo_at(&self, u: f32, v: f32) -> Option<Vec3> {
        self.albedo
            .map(|[a, b, c]| a * (1.0 - u - v) + b * u + c * v)
    }
}

impl Bounded<f32, 3> for Triangle {
    fn aabb(&self) -> Aabb<f32, 3> {
        let corners = [self.v0, self.v0 + self.e1, self.v0 + self.e2];
        let lo = corners.iter().fold(Vec3::INFINITY, |a, c| a.min(*c));
        let hi = corners.iter().fold(Vec3::NEG_INFINITY, |a, c| a.max(*c));
        // Pad flat boxes so axis-aligned triangles are never missed by the slab test.
        let pad = Vec3::splat(1e-5);
        Aabb::with_bounds(point(lo - pad), point(hi + pad))
    }
}

impl BHShape<f32, 3> for Triangle {
    fn set_bh_node_index(&mut self, index: usize) {
        self.node_index = index;
    }
    fn bh_node_index(&self) -> usize {
        self.node_index
    }
}

fn point(v: Vec3) -> Point3<f32> {
    Point3::new(v.x, v.y, v.z)
}

/// A child of a [`FlatNode`]: another inner node (its position in the list) or a triangle (its
/// position in [`Geometry::triangles`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Child {
    Inner(u32),
    Triangle(u32),
}

/// An inner node of [`Geometry::flat_bvh`]: the boxes of its two children, and the children.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlatNode {
    pub min: [Vec3; 2],
    pub max: [Vec3; 2],
    pub children: [Child; 2],
}

/// A ray hit: distance, which triangle, and its barycentric coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub triangle: usize,
    pub u: f32,
    pub v: f32,
}

/// The triangles of a scene (optionally without its virtual objects) and their BVH.
#[derive(Debug)]
pub struct Geometry {
    triangles: Vec<Triangle>,
    bvh: Option<Bvh<f32, 3>>,
}

impl Geometry {
    /// All meshes, or the real ones only. Real triangles come first, in mesh order, so a
    /// triangle index means the same triangle in both geometries.
    pub fn new(scene: &Scene, include_virtual: bool) -> Self {
        Self::of_meshes(&scene.meshes, include_virtual)
    }

    /// [`Geometry::new`] of a scene made of `meshes`.
    pub fn of_meshes(meshes: &[Mesh], include_virtual: bool) -> Self {
        let mut triangles = Vec::new();
        for want_virtual in [false, true] {
            if want_virtual && !include_virtual {
                break;
            }
            for mesh in meshes.iter().filter(|m| m.is_virtual == want_virtual) {
                let vertex = |i: u32| mesh.positions_in_world.get(i as usize).copied();
                let normal = |i: u32| {
                    mesh.normals_in_world
                        .get(i as usize)
                        .copied()
                        .unwrap_or(Vec3::ZERO)
                };
                for tri in &mesh.triangles {
                    let (Some(a), Some(b), Some(c)) =
                        (vertex(tri[0]), vertex(tri[1]), vertex(tri[2]))
                    else {
                        continue;
                    };
                    if !(a.is_finite() && b.is_finite() && c.is_finite()) {
                        continue;
                    }
                    let (e1, e2) = (b - a, c - a);
                    let geometric_normal = e1.cross(e2).normalize_or_zero();
                    if geometric_normal == Vec3::ZERO {
                        // Zero area: no ray can hit it, and it has no normal to shade with.
                        continue;
                    }
                    triangles.push(Triangle {
                        v0: a,
                        e1,
                        e2,
                        normals: [normal(tri[0]), normal(tri[1]), normal(tri[2])],
                        geometric_normal,
                        material: mesh.material,
                        albedo: tri
                            .iter()
                            .map(|v| mesh.measured_albedo(*v))
                            .collect::<Option<Vec<_>>>()
                            .and_then(|a| <[Vec3; 3]>::try_from(a).ok()),
                        is_virtual: mesh.is_virtual,
                        index: triangles.len(),
                        node_index: 0,
                    });
                }
            }
        }
        let bvh = (!triangles.is_empty()).then(|| Bvh::build(&mut triangles));
        Self { triangles, bvh }
    }

    pub fn triangles(&self) -> &[Triangle] {
        &self.triangles
    }

    /// The hierarchy as a list of inner nodes, each with both children's boxes, and where
    /// traversal starts (`None` without triangles): what the GPU path tracer (`pt`) uploads,
    /// so that it traverses this same tree.
    pub fn flat_bvh(&self) -> (Vec<FlatNode>, Option<Child>) {
        let Some(bvh) = &self.bvh else {
            return (Vec::new(), None);
        };
        let mut inner = vec![0u32; bvh.nodes.len()];
        let mut count = 0;
        for (i, node) in bvh.nodes.iter().enumerate() {
            if matches!(node, BvhNode::Node { .. }) {
                inner[i] = count;
                count += 1;
            }
        }
        let child = |i: usize| match bvh.nodes[i] {
            BvhNode::Leaf { shape_index, .. } => Child::Triangle(shape_index as u32),
            BvhNode::Node { .. } => Child::Inner(inner[i]),
        };
        let vec3 = |p: Point3<f32>| Vec3::new(p.x, p.y, p.z);
        let nodes = bvh
            .nodes
            .iter()
            .filter_map(|node| match *node {
                BvhNode::Node {
                    child_l_index,
                    child_l_aabb,
                    child_r_index,
                    child_r_aabb,
                    ..
                } => Some(FlatNode {
                    min: [vec3(child_l_aabb.min), vec3(child_r_aabb.min)],
                    max: [vec3(child_l_aabb.max), vec3(child_r_aabb.max)],
                    children: [child(child_l_index), child(child_r_index)],
                }),
                BvhNode::Leaf { .. } => None,
            })
            .collect();
        (nodes, Some(child(0)))
    }

    /// Closest hit with t in (t_min, t_max); ties go to the lower triangle index.
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Option<Hit> {
        let bvh = self.bvh.as_ref()?;
        let ray = culling_ray(origin, dir)?;
        let mut best: Option<Hit> = None;
        for tri in bvh.traverse_iterator(&ray, &self.triangles) {
            let index = tri.index;
            if let Some((t, u, v)) = moller_trumbore(tri, origin, dir)
                && t > t_min
                && t < t_max
                && best.is_none_or(|b| t < b.t || (t == b.t && index < b.triangle))
            {
                best = Some(Hit {
                    t,
                    triangle: index,
                    u,
                    v,
                });
            }
        }
        best
    }

    /// The first triangle found on the segment (t_min, t_max), `None` when it is clear.
    ///
    /// Which blocker is reported depends on the traversal order, but whether there is one does
    /// not. The integrator uses the answer to know whether a virtual triangle decided a shadow
    /// test: when a real triangle is reported, the real-only geometry is blocked too.
    pub fn occluder(&self, origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Option<&Triangle> {
        let bvh = self.bvh.as_ref()?;
        let ray = culling_ray(origin, dir)?;
        bvh.traverse_iterator(&ray, &self.triangles).find(|tri| {
            moller_trumbore(tri, origin, dir).is_some_and(|(t, _, _)| t > t_min && t < t_max)
        })
    }
}

/// The ray the `bvh` crate culls boxes with. Its slab test treats 0 · ∞ (a direction component
/// of exactly zero with the origin on a box plane) as a miss, so zero components are replaced by
/// a tiny one of the same sign: the culling ray then differs from the true one by less than
/// 1e-17 m over a kilometre, and only the culling uses it. `None` for a non-finite ray.
fn culling_ray(origin: Vec3, dir: Vec3) -> Option<bvh::ray::Ray<f32, 3>> {
    if !(origin.is_finite() && dir.is_finite()) || dir == Vec3::ZERO {
        return None;
    }
    let nudge = |d: f32| {
        if d.abs() < 1e-20 {
            1e-20f32.copysign(d)
        } else {
            d
        }
    };
    Some(bvh::ray::Ray::new(
        point(origin),
        Vector3::new(nudge(dir.x), nudge(dir.y), nudge(dir.z)),
    ))
}

/// Möller–Trumbore ray/triangle intersection: (t, u, v), two-sided.
fn moller_trumbore(tri: &Triangle, origin: Vec3, dir: Vec3) -> Option<(f32, f32, f32)> {
    let p = dir.cross(tri.e2);
    let det = tri.e1.dot(p);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv = 1.0 / det;
    let s = origin - tri.v0;
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(tri.e1);
    let v = dir.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = tri.e2.dot(q) * inv;
    t.is_finite().then_some((t, u, v))
}
