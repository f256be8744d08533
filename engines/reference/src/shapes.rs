//! Procedural meshes for test and benchmark scenes built in code (quads, boxes, spheres), so
//! tests of the reference and of the engines need no glTF file.

use std::f32::consts::{PI, TAU};

use glam::Vec3;
use relight_core::scene::Mesh;

/// A parallelogram centred on `center_in_world` with half-edges `half_u` and `half_v`; it faces
/// `half_u × half_v` (the flat vertex normals point that way).
pub fn quad(
    name: &str,
    center_in_world: Vec3,
    half_u: Vec3,
    half_v: Vec3,
    material: usize,
    is_virtual: bool,
) -> Mesh {
    let normal = half_u.cross(half_v).normalize_or_zero();
    let c = center_in_world;
    Mesh {
        name: name.into(),
        positions_in_world: vec![
            c - half_u - half_v,
            c + half_u - half_v,
            c + half_u + half_v,
            c - half_u + half_v,
        ],
        normals_in_world: vec![normal; 4],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
        material,
        is_virtual,
        vertex_albedo: Vec::new(),
    }
}

/// An axis-aligned box between `min_in_world` and `max_in_world`, 12 triangles with flat
/// normals pointing out ([`flipped`] turns it into a room seen from inside). Faces share
/// bit-identical corner positions, so the box is closed for a ray tracer.
pub fn cuboid(
    name: &str,
    min_in_world: Vec3,
    max_in_world: Vec3,
    material: usize,
    is_virtual: bool,
) -> Mesh {
    // Corner i takes the maximum along axis k when bit k of i is set.
    let corner = |i: u32| {
        Vec3::new(
            if i & 1 != 0 {
                max_in_world.x
            } else {
                min_in_world.x
            },
            if i & 2 != 0 {
                max_in_world.y
            } else {
                min_in_world.y
            },
            if i & 4 != 0 {
                max_in_world.z
            } else {
                min_in_world.z
            },
        )
    };
    // (normal, bit of the face's own axis if on the max side, bits of u and v) with u × v
    // along the normal.
    let faces = [
        (Vec3::X, 1, 2, 4),
        (Vec3::NEG_X, 0, 4, 2),
        (Vec3::Y, 2, 4, 1),
        (Vec3::NEG_Y, 0, 1, 4),
        (Vec3::Z, 4, 1, 2),
        (Vec3::NEG_Z, 0, 2, 1),
    ];
    let mut mesh = Mesh {
        name: name.into(),
        positions_in_world: Vec::with_capacity(24),
        normals_in_world: Vec::with_capacity(24),
        triangles: Vec::with_capacity(12),
        material,
        is_virtual,
        vertex_albedo: Vec::new(),
    };
    for (normal, base, u, v) in faces {
        let first = mesh.positions_in_world.len() as u32;
        for i in [base, base | u, base | u | v, base | v] {
            mesh.positions_in_world.push(corner(i));
            mesh.normals_in_world.push(normal);
        }
        mesh.triangles.push([first, first + 1, first + 2]);
        mesh.triangles.push([first, first + 2, first + 3]);
    }
    mesh
}

/// A UV sphere with smooth vertex normals pointing out ([`flipped`] turns them in):
/// `segments` around the +Y axis (at least 3), `rings` from pole to pole (at least 2).
/// It has 2 · segments · (rings − 1) triangles.
pub fn uv_sphere(
    name: &str,
    center_in_world: Vec3,
    radius_m: f32,
    segments: u32,
    rings: u32,
    material: usize,
    is_virtual: bool,
) -> Mesh {
    let (segments, rings) = (segments.max(3), rings.max(2));
    let mut positions = Vec::new();
    let mut normals = Vec::new();
    for ring in 0..=rings {
        let theta = PI * ring as f32 / rings as f32;
        for segment in 0..=segments {
            // The seam and the poles repeat exactly the same positions, so the mesh is closed.
            let phi = TAU * (segment % segments) as f32 / segments as f32;
            let n = match ring {
                0 => Vec3::Y,
                r if r == rings => Vec3::NEG_Y,
                _ => Vec3::new(
                    theta.sin() * phi.cos(),
                    theta.cos(),
                    theta.sin() * phi.sin(),
                ),
            };
            positions.push(center_in_world + n * radius_m);
            normals.push(n);
        }
    }
    let stride = segments + 1;
    let mut triangles = Vec::new();
    for ring in 0..rings {
        for segment in 0..segments {
            let a = ring * stride + segment;
            let (b, c, d) = (a + 1, a + stride, a + stride + 1);
            // Skip the zero-area triangles at the poles.
            if ring != 0 {
                triangles.push([a, b, c]);
            }
            if ring != rings - 1 {
                triangles.push([b, d, c]);
            }
        }
    }
    Mesh {
        name: name.into(),
        positions_in_world: positions,
        normals_in_world: normals,
        triangles,
        material,
        is_virtual,
        vertex_albedo: Vec::new(),
    }
}

/// The same surface facing the other way: reversed winding and negated normals.
pub fn flipped(mut mesh: Mesh) -> Mesh {
    for tri in &mut mesh.triangles {
        tri.swap(1, 2);
    }
    for normal in &mut mesh.normals_in_world {
        *normal = -*normal;
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cuboid_faces_point_out_or_in() {
        for inward in [false, true] {
            let mesh = cuboid("box", Vec3::ZERO, Vec3::new(2.0, 4.0, 6.0), 0, false);
            let mesh = if inward { flipped(mesh) } else { mesh };
            let center = Vec3::new(1.0, 2.0, 3.0);
            assert_eq!(mesh.triangles.len(), 12);
            for tri in &mesh.triangles {
                let [a, b, c] = tri.map(|i| mesh.positions_in_world[i as usize]);
                let face_normal = (b - a).cross(c - a).normalize();
                let outwards = face_normal.dot((a + b + c) / 3.0 - center) > 0.0;
                assert_eq!(outwards, !inward);
                assert!(mesh.normals_in_world[tri[0] as usize].dot(face_normal) > 0.99);
            }
        }
    }

    #[test]
    fn sphere_triangles_face_their_normals() {
        let mesh = uv_sphere("ball", Vec3::ONE, 2.0, 12, 8, 0, false);
        assert_eq!(mesh.triangles.len(), 2 * 12 * 7);
        for tri in &mesh.triangles {
            let [a, b, c] = tri.map(|i| mesh.positions_in_world[i as usize]);
            let face_normal = (b - a).cross(c - a);
            assert!(face_normal.length() > 0.0);
            assert!(face_normal.dot((a + b + c) / 3.0 - Vec3::ONE) > 0.0);
        }
    }
}
