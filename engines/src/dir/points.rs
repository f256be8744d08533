//! The point sampling of the scene's surfaces that imperfect shadow maps are splatted from:
//! fixed per scene (the same points every frame, so shadows do not crawl), low-discrepancy
//! (area-stratified triangle choice, R2 barycentrics), the virtual object sampled apart from
//! the real scene so a small object still gets a dense cloud.

use glam::Vec3;
use relight_core::scene::Mesh;

/// Share of the points given to the virtual object at least (more when its area share is).
const MIN_VIRTUAL_SHARE: f64 = 0.25;

/// `count` points as `[x, y, z, r]`, r the radius of the disc of surface each stands for,
/// negated on the virtual object.
pub fn surface_points<'a>(
    meshes: impl Iterator<Item = &'a Mesh> + Clone,
    count: u32,
) -> Vec<[f32; 4]> {
    let triangles = |want_virtual: bool| -> Vec<(Vec3, Vec3, Vec3)> {
        meshes
            .clone()
            .filter(|m| m.is_virtual == want_virtual)
            .flat_map(|m| {
                m.triangles.iter().filter_map(|t| {
                    let [a, b, c] = t.map(|i| m.positions_in_world.get(i as usize).copied());
                    let (a, b, c) = (a?, b?, c?);
                    (a.is_finite() && b.is_finite() && c.is_finite()).then_some((a, b, c))
                })
            })
            .collect()
    };
    let area = |ts: &[(Vec3, Vec3, Vec3)]| -> f64 {
        ts.iter()
            .map(|(a, b, c)| f64::from((*b - *a).cross(*c - *a).length() / 2.0))
            .sum()
    };
    let (real, virt) = (triangles(false), triangles(true));
    let (real_area, virtual_area) = (area(&real), area(&virt));
    let total = real_area + virtual_area;
    if total <= 0.0 || count == 0 {
        return Vec::new();
    }
    let virtual_count = if virtual_area > 0.0 {
        let share = (virtual_area / total).max(MIN_VIRTUAL_SHARE);
        ((f64::from(count) * share).round() as u32).min(count)
    } else {
        0
    };
    let mut points = sample(&real, real_area, count - virtual_count, 1.0);
    points.extend(sample(&virt, virtual_area, virtual_count, -1.0));
    points
}

fn sample(triangles: &[(Vec3, Vec3, Vec3)], area: f64, count: u32, sign: f32) -> Vec<[f32; 4]> {
    if count == 0 || area <= 0.0 {
        return Vec::new();
    }
    let radius = sign * (area / (std::f64::consts::PI * f64::from(count))).sqrt() as f32;
    let mut cumulative = Vec::with_capacity(triangles.len());
    let mut sum = 0.0;
    for (a, b, c) in triangles {
        sum += f64::from((*b - *a).cross(*c - *a).length() / 2.0);
        cumulative.push(sum);
    }
    (0..count)
        .map(|i| {
            let target = (f64::from(i) + 0.5) / f64::from(count) * sum;
            let t = cumulative
                .partition_point(|&c| c < target)
                .min(triangles.len() - 1);
            let (a, b, c) = triangles[t];
            // R2 sequence (Roberts 2018), folded into the triangle.
            let mut u = (f64::from(i) * 0.754_877_666_2).fract() as f32;
            let mut v = (f64::from(i) * 0.569_840_290_9).fract() as f32;
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            let p = a + (b - a) * u + (c - a) * v;
            [p.x, p.y, p.z, radius]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad(name: &str, z: f32, size: f32, is_virtual: bool) -> Mesh {
        Mesh {
            name: name.into(),
            positions_in_world: vec![
                Vec3::new(0.0, 0.0, z),
                Vec3::new(size, 0.0, z),
                Vec3::new(size, size, z),
                Vec3::new(0.0, size, z),
            ],
            normals_in_world: vec![Vec3::Z; 4],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            material: 0,
            is_virtual,
            vertex_albedo: Vec::new(),
        }
    }

    #[test]
    fn points_cover_the_surfaces_evenly_and_the_object_gets_its_share() {
        let meshes = [
            quad("floor", 0.0, 2.0, false),
            quad("object", 1.0, 0.1, true),
        ];
        let points = surface_points(meshes.iter(), 4000);
        assert_eq!(points.len(), 4000);
        let virtual_points: Vec<_> = points.iter().filter(|p| p[3] < 0.0).collect();
        assert_eq!(virtual_points.len(), 1000);
        assert!(
            virtual_points
                .iter()
                .all(|p| p[2] == 1.0 && p[0] <= 0.1 && p[1] <= 0.1)
        );
        // Each quadrant of the floor holds a quarter of its points (±5 %).
        for (qx, qy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
            let n = points
                .iter()
                .filter(|p| {
                    p[3] > 0.0 && (p[0] >= qx && p[0] < qx + 1.0) && (p[1] >= qy && p[1] < qy + 1.0)
                })
                .count();
            assert!(
                (n as f32 - 750.0).abs() < 0.05 * 750.0,
                "quadrant ({qx}, {qy}): {n}"
            );
        }
        // Disc radius: the floor's 4 m² over 3000 discs.
        let r = (4.0 / (std::f32::consts::PI * 3000.0)).sqrt();
        assert!((points[0][3] - r).abs() < 1e-6);
        assert_eq!(surface_points(meshes.iter(), 4000), points, "deterministic");
    }
}
