//! The real surface as the light-space passes draw it
//! ([`Scene::shadow_proxy`](relight_core::scene::Scene::shadow_proxy)): the live depth mesh
//! decimated, and held while the real surface holds.
//!
//! **Why decimate.** The depth mesh has two triangles per 2 × 2 block of depth samples: about
//! 38 000 at 320 × 240 and stride 2. Every shadow-map face rasterises all of them, so the live
//! RSM pass was bound by triangles, not pixels. A desk and its walls are a few planes; a
//! shadow-map texel of a 512² cube face is 3.9 mm wide at 1 m. [`decimate`] collapses edges
//! while the surface stays within [`SHADOW_PROXY_ERROR_M`] of the measured one: half a texel at
//! 1 m and under the shading's depth bias (1.5 texels, `shadow_bias`), so a shadow test that
//! compares a full-resolution G-buffer point with the proxy's depth cannot tell them apart.
//! The simplifier is meshoptimizer's quadric edge collapse (the `meshopt` crate), which keeps
//! the vertices it does not collapse, so per-vertex normals and measured albedo carry over.
//!
//! **Why hold.** The maps depend on the real surface and the lights, not on the camera. While
//! the temporal depth merge says the surface has not changed (it did not reset), the camera
//! stayed within [`ProxyHold`]'s reach of where the proxy was built, and the proxy is younger
//! than its age limit, the same proxy (the same `Arc`) goes into every frame; the engines then
//! find the R^μ maps' inputs unchanged and do not redraw them (`Deferred::prepare`). The limits
//! bound what a held proxy can miss: surface the camera has uncovered since, or a change too
//! slow for the merge to reset on.

use std::sync::Arc;

use relight_core::Pose;
use relight_core::scene::Mesh;

/// How far the decimated surface may move from the measured one, metres.
pub const SHADOW_PROXY_ERROR_M: f32 = 0.002;

/// meshoptimizer bounds the quadric error, the distance of the kept vertices from the planes
/// of the triangles they stand for, not the distance between the surfaces: on a smooth bump
/// the measured worst deviation was 2.1× the quadric bound. The simplifier is asked for this
/// share of the error wanted.
const QUADRIC_ERROR_SHARE: f32 = 0.4;

/// `mesh` with its triangles decimated to within `max_error_m` (absolute) of its surface, the
/// vertices it still uses compacted. Topological borders (depth edges, holes, the image's
/// edge) may move along themselves only, so the outline stays.
pub fn decimate(mesh: &Mesh, max_error_m: f32) -> Mesh {
    let positions: Vec<[f32; 3]> = mesh
        .positions_in_world
        .iter()
        .map(|p| p.to_array())
        .collect();
    let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let kept = meshopt::simplify_decoder(
        &indices,
        &positions,
        0,
        max_error_m * QUADRIC_ERROR_SHARE,
        meshopt::SimplifyOptions::ErrorAbsolute,
        None,
    );
    let mut remap = vec![u32::MAX; positions.len()];
    let mut out = Mesh {
        name: format!("{} (shadow proxy)", mesh.name),
        positions_in_world: Vec::new(),
        normals_in_world: Vec::new(),
        triangles: Vec::with_capacity(kept.len() / 3),
        material: mesh.material,
        is_virtual: mesh.is_virtual,
        vertex_albedo: Vec::new(),
    };
    let mut vertex = |i: u32| -> u32 {
        let slot = &mut remap[i as usize];
        if *slot == u32::MAX {
            *slot = out.positions_in_world.len() as u32;
            let i = i as usize;
            out.positions_in_world.push(mesh.positions_in_world[i]);
            if let Some(n) = mesh.normals_in_world.get(i) {
                out.normals_in_world.push(*n);
            }
            if let Some(a) = mesh.vertex_albedo.get(i) {
                out.vertex_albedo.push(*a);
            }
        }
        *slot
    };
    let triangles: Vec<[u32; 3]> = kept
        .chunks_exact(3)
        .map(|t| [vertex(t[0]), vertex(t[1]), vertex(t[2])])
        .collect();
    out.triangles = triangles;
    out
}

/// When a built proxy may be kept; see the module docs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProxyHold {
    /// Camera motion since the proxy was built beyond which it is rebuilt.
    pub max_translation_m: f32,
    pub max_rotation_rad: f32,
    /// Frames a proxy is used at most (it is rebuilt on the next).
    pub max_frames: u32,
    /// Simplification error, metres.
    pub max_error_m: f32,
}

impl Default for ProxyHold {
    /// 20 cm, 15° and 30 frames (a second at the sensor's rate: the longest a slow change
    /// waits to show in the shadows). A walking camera moves about 2 cm a frame, so 5 cm and 5°
    /// (the temporal merge's reset for one frame's motion) rebuilt the proxy, and every light's
    /// maps, every third frame; on the bundled walk 20 cm and 15° changed no score by more
    /// than 0.002 (`docs/live-loop.md`, stop 44): the object's shadows and bounces fall on
    /// surface both views see, and what a held proxy misses is at the image's edges.
    fn default() -> Self {
        Self {
            max_translation_m: 0.2,
            max_rotation_rad: 15f32.to_radians(),
            max_frames: 30,
            max_error_m: SHADOW_PROXY_ERROR_M,
        }
    }
}

/// The proxy in use and where it was built.
#[derive(Debug, Clone)]
pub struct HeldProxy {
    hold: ProxyHold,
    held: Option<(Arc<Mesh>, Pose, u32)>,
    built: u64,
}

impl HeldProxy {
    pub fn new(hold: ProxyHold) -> Self {
        Self {
            hold,
            held: None,
            built: 0,
        }
    }

    /// The proxy for a frame whose real surface is `mesh`, seen from `world_from_camera`;
    /// `surface_held`: the depth merge says the surface has not changed since the last frame.
    /// The held proxy when it may be kept, else `mesh` decimated anew.
    pub fn proxy(
        &mut self,
        mesh: &Mesh,
        world_from_camera: &Pose,
        surface_held: bool,
    ) -> Arc<Mesh> {
        if let Some((proxy, built_at, frames)) = &mut self.held {
            let moved = world_from_camera.translation.distance(built_at.translation);
            let turned = world_from_camera.rotation.angle_between(built_at.rotation);
            if surface_held
                && *frames < self.hold.max_frames
                && moved <= self.hold.max_translation_m
                && turned <= self.hold.max_rotation_rad
            {
                *frames += 1;
                return proxy.clone();
            }
        }
        let proxy = Arc::new(decimate(mesh, self.hold.max_error_m));
        self.held = Some((proxy.clone(), *world_from_camera, 1));
        self.built += 1;
        proxy
    }

    /// Forget the held proxy (the real surface is no longer the depth's).
    pub fn drop_held(&mut self) {
        self.held = None;
    }

    /// Proxies built so far.
    pub fn built(&self) -> u64 {
        self.built
    }
}

#[cfg(test)]
mod tests {
    use glam::{Quat, Vec3};

    use super::*;

    /// A `n` × `n` grid of unit spacing `step` at height `z(x, y)`.
    fn grid(n: u32, step: f32, z: impl Fn(f32, f32) -> f32) -> Mesh {
        let mut positions = Vec::new();
        for y in 0..n {
            for x in 0..n {
                let (fx, fy) = (x as f32 * step, y as f32 * step);
                positions.push(Vec3::new(fx, fy, z(fx, fy)));
            }
        }
        let mut triangles = Vec::new();
        for y in 0..n - 1 {
            for x in 0..n - 1 {
                let i = y * n + x;
                triangles.push([i, i + n, i + 1]);
                triangles.push([i + 1, i + n, i + n + 1]);
            }
        }
        Mesh {
            name: "grid".into(),
            normals_in_world: vec![Vec3::Z; positions.len()],
            vertex_albedo: vec![Vec3::splat(0.3); positions.len()],
            positions_in_world: positions,
            triangles,
            material: 3,
            is_virtual: false,
        }
    }

    /// Distance from `p` to the triangle `abc` (Ericson, *Real-Time Collision Detection*, 5.1.5).
    fn distance_to_triangle(p: Vec3, [a, b, c]: [Vec3; 3]) -> f32 {
        let (ab, ac, ap) = (b - a, c - a, p - a);
        let (d1, d2) = (ab.dot(ap), ac.dot(ap));
        if d1 <= 0.0 && d2 <= 0.0 {
            return p.distance(a);
        }
        let bp = p - b;
        let (d3, d4) = (ab.dot(bp), ac.dot(bp));
        if d3 >= 0.0 && d4 <= d3 {
            return p.distance(b);
        }
        let vc = d1 * d4 - d3 * d2;
        if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
            return p.distance(a + ab * (d1 / (d1 - d3)));
        }
        let cp = p - c;
        let (d5, d6) = (ab.dot(cp), ac.dot(cp));
        if d6 >= 0.0 && d5 <= d6 {
            return p.distance(c);
        }
        let vb = d5 * d2 - d1 * d6;
        if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
            return p.distance(a + ac * (d2 / (d2 - d6)));
        }
        let va = d3 * d6 - d5 * d4;
        if va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
            return p.distance(b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6))));
        }
        let denom = 1.0 / (va + vb + vc);
        p.distance(a + ab * (vb * denom) + ac * (vc * denom))
    }

    fn max_deviation(full: &Mesh, proxy: &Mesh) -> f32 {
        full.positions_in_world
            .iter()
            .map(|p| {
                proxy
                    .triangles
                    .iter()
                    .map(|t| {
                        distance_to_triangle(*p, t.map(|i| proxy.positions_in_world[i as usize]))
                    })
                    .fold(f32::INFINITY, f32::min)
            })
            .fold(0.0, f32::max)
    }

    #[test]
    fn a_plane_becomes_a_few_triangles_with_its_attributes() {
        let full = grid(40, 0.01, |x, y| 1.0 + 0.2 * x - 0.1 * y);
        let proxy = decimate(&full, SHADOW_PROXY_ERROR_M);
        assert!(
            proxy.triangles.len() <= 8,
            "{} triangles",
            proxy.triangles.len()
        );
        assert!(max_deviation(&full, &proxy) < 1e-4);
        assert_eq!(proxy.normals_in_world.len(), proxy.positions_in_world.len());
        assert_eq!(
            proxy.vertex_albedo,
            vec![Vec3::splat(0.3); proxy.positions_in_world.len()]
        );
        assert_eq!((proxy.material, proxy.is_virtual), (3, false));
        assert!(
            proxy
                .triangles
                .iter()
                .flatten()
                .all(|i| (*i as usize) < proxy.positions_in_world.len())
        );
    }

    #[test]
    fn a_curved_surface_stays_within_the_error() {
        // A bump 3 cm high over a 39 cm square: it cannot be flattened within 2 mm.
        let full = grid(40, 0.01, |x, y| {
            let r2 = (x - 0.2).powi(2) + (y - 0.2).powi(2);
            0.03 * (-r2 / 0.005).exp()
        });
        let proxy = decimate(&full, SHADOW_PROXY_ERROR_M);
        assert!(
            proxy.triangles.len() < full.triangles.len() / 4,
            "{}",
            proxy.triangles.len()
        );
        assert!(proxy.triangles.len() > 8, "the bump was flattened");
        let deviation = max_deviation(&full, &proxy);
        eprintln!("{} triangles, {deviation} m", proxy.triangles.len());
        assert!(deviation <= SHADOW_PROXY_ERROR_M, "{deviation} m");
    }

    #[test]
    fn a_proxy_is_held_while_the_surface_and_camera_hold() {
        let hold = ProxyHold::default();
        let mut held = HeldProxy::new(hold);
        let full = grid(8, 0.1, |_, _| 0.0);
        let at = |x: f32, yaw_deg: f32| Pose {
            rotation: Quat::from_rotation_y(yaw_deg.to_radians()),
            translation: Vec3::new(x, 0.0, 2.0),
        };
        let first = held.proxy(&full, &at(0.0, 0.0), false);
        let same = held.proxy(&full, &at(0.19, 14.0), true);
        assert!(Arc::ptr_eq(&first, &same), "within 20 cm and 15°");
        assert!(
            !Arc::ptr_eq(&first, &held.proxy(&full, &at(0.0, 0.0), false)),
            "the merge reset"
        );
        let base = held.proxy(&full, &at(0.0, 0.0), true);
        assert!(
            !Arc::ptr_eq(&base, &held.proxy(&full, &at(0.21, 0.0), true)),
            "moved 21 cm"
        );
        let base = held.proxy(&full, &at(0.0, 0.0), false);
        assert!(
            !Arc::ptr_eq(&base, &held.proxy(&full, &at(0.0, 16.0), true)),
            "turned 16°"
        );
        let base = held.proxy(&full, &at(0.0, 0.0), false);
        for _ in 1..hold.max_frames {
            assert!(Arc::ptr_eq(&base, &held.proxy(&full, &at(0.0, 0.0), true)));
        }
        assert!(
            !Arc::ptr_eq(&base, &held.proxy(&full, &at(0.0, 0.0), true)),
            "aged out"
        );
        assert_eq!(held.built(), 7);
    }
}
