//! What a scene needs, estimated on the CPU in a few milliseconds: how large each part of Δ will
//! be on the real pixels the camera sees, so the governor can tell a scene that needs only a
//! shadow from one whose picture is made by the object's indirect light.
//!
//! [`REAL_SAMPLES`] points spread over the real surface by area stand for it, those in view
//! weighted by the pixels their share covers (area × cos / distance², as the Δ norm sums over
//! pixels); [`OBJECT_PATCHES`] points spread over the object stand for it. The lights are the scene's
//! point, spot and directional lights and, for an environment map, 16 directional lights cut
//! from it (as `dir` cuts them). Per real sample p of albedo ρ_p:
//! - **shadow**: ρ_p/π Σ_l E_l(p) over the lights whose segment to p the object blocks (the
//!   direct light the object takes away);
//! - **bleeding**: ρ_p/π Σ_t L_t A_t cos θ_p cos θ_t / d², the light the object's patches t
//!   reflect onto p, each a Lambertian emitter of radiance L_t = ρ_o/π Σ_l E_l(t) (the object's
//!   albedo, its size and its distance to lit real surfaces, together), times
//!   `BLEEDING_SCALE`;
//! - **occlusion**: ρ_p/π Σ_t L_q A_t cos θ_p cos θ_t / d², where L_q is what the real surface
//!   behind patch t (seen from p) reflects of the lights: the real indirect light the object
//!   hides from p (the indirect shadow of an object touching a lit wall);
//! - **glossy**: k_s of a glossy real surface times the difference between the radiance of the
//!   object where the mirror direction of the camera ray meets it and what it hides there.
//!
//! Ray queries run against the real surface (the reference's BVH over the live surface's
//! decimated proxy, or the scene's real meshes): samples hidden from the camera, light the real
//! scene already blocks, and patches a real surface hides from p do not count. The reflected
//! light of real and virtual surfaces is their unshadowed direct light (one bounce), so the
//! indirect parts are estimates to compare with each other and with the shadow, not with the
//! reference.

use glam::Vec3;
use relight_core::light::Light;
use relight_core::scene::{Material, Mesh, Scene, SceneCamera};
use relight_reference::accel::{Geometry, Hit};
use serde::Serialize;

use crate::dir::environment_lights;

/// Points the real surface is sampled at.
pub const REAL_SAMPLES: usize = 1024;
/// Points the object is sampled at (as emitters and occluders of indirect light).
pub const OBJECT_PATCHES: usize = 32;
/// The one-bounce bleeding estimate, doubled: light the object reflects after more than one
/// bounce, and its own indirect light, are missing from it. Fitted on the five scenes
/// (docs/ALGORITHMS.md): with it, `differential`'s error shares on bleeding and occlusion come
/// out near 1, as they must for an engine that models no indirect light.
const BLEEDING_SCALE: f32 = 2.0;
/// Directional lights an environment map is cut into for the estimate.
const ENVIRONMENT_LIGHTS: u32 = 16;

/// The parts of Δ a scene will have, as L2 norms over the real pixels in view (radiance ×
/// √pixels), and what decides between engines besides them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct SceneFeatures {
    pub shadow: f64,
    pub bleeding: f64,
    pub occlusion: f64,
    pub glossy: f64,
    /// The real scene is lit by an environment map (soft light from everywhere).
    pub environment: bool,
    /// The object blocks some light from a real surface in view (else it casts no shadow).
    pub blocks_light: bool,
    /// The object's diffuse albedo (luminance) and its bounding box's diagonal, metres.
    pub object_albedo: f32,
    pub object_size_m: f32,
    /// From the object's box to the nearest real sample, metres.
    pub object_distance_m: f32,
    /// Real samples in view.
    pub samples: usize,
}

impl SceneFeatures {
    /// The share of Δ's norm that is indirect (bleeding and occlusion): 0 for a shadow-only
    /// scene, near 1 where the object's bounced light makes the picture.
    pub fn indirect_share(&self) -> f64 {
        let indirect = self.bleeding.hypot(self.occlusion);
        let total = (self.shadow.powi(2) + indirect.powi(2) + self.glossy.powi(2)).sqrt();
        if total > 0.0 { indirect / total } else { 0.0 }
    }

    /// ‖Δ‖ as the parts add up (independently).
    pub fn total(&self) -> f64 {
        (self.shadow.powi(2) + self.bleeding.powi(2) + self.occlusion.powi(2) + self.glossy.powi(2))
            .sqrt()
    }
}

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// A point of a surface standing for a share of its area: where, its unit normal (the outer
/// side), the area, the albedo and the glossy lobe's reflectance.
#[derive(Debug, Clone, Copy)]
struct Patch {
    centre: Vec3,
    normal: Vec3,
    area: f32,
    albedo: Vec3,
    specular: f32,
}

/// `count` points spread over the virtual (or the real) meshes by area: point k lies in the
/// triangle that holds the (k + ½)/count quantile of the total area, at the k-th Halton (2, 3)
/// barycentric point, and stands for an equal share of the area.
fn patches(
    meshes: &[Mesh],
    materials: &[Material],
    virtual_object: bool,
    count: usize,
) -> Vec<Patch> {
    struct Source {
        corners: [Vec3; 3],
        /// The corners' mean vertex normal (zero without): the outer side.
        outward: Vec3,
        area: f32,
        albedo: Vec3,
        specular: f32,
    }
    let mut sources = Vec::new();
    for mesh in meshes.iter().filter(|m| m.is_virtual == virtual_object) {
        let material = materials.get(mesh.material);
        let specular = material.map_or(0.0, |m| {
            if m.shininess > 0.0 {
                luminance(m.specular)
            } else {
                0.0
            }
        });
        for tri in &mesh.triangles {
            let corner = |i: u32| mesh.positions_in_world.get(i as usize).copied();
            let (Some(a), Some(b), Some(c)) = (corner(tri[0]), corner(tri[1]), corner(tri[2]))
            else {
                continue;
            };
            let area = 0.5 * (b - a).cross(c - a).length();
            if !(area.is_finite() && area > 0.0) {
                continue;
            }
            let albedo = tri
                .iter()
                .map(|v| mesh.measured_albedo(*v))
                .collect::<Option<Vec<_>>>()
                .map(|a| (a[0] + a[1] + a[2]) / 3.0)
                .or_else(|| material.map(|m| m.albedo))
                .unwrap_or(Vec3::splat(0.5))
                .clamp(Vec3::ZERO, Vec3::ONE);
            let outward = tri
                .iter()
                .filter_map(|v| mesh.normals_in_world.get(*v as usize))
                .sum::<Vec3>();
            sources.push(Source {
                corners: [a, b, c],
                outward,
                area,
                albedo,
                specular,
            });
        }
    }
    let cumulative: Vec<f32> = sources
        .iter()
        .scan(0.0, |sum, s| {
            *sum += s.area;
            Some(*sum)
        })
        .collect();
    let Some(&total) = cumulative.last() else {
        return Vec::new();
    };
    let radical_inverse = |mut i: usize, base: usize| {
        let (mut f, mut r) = (1.0f32, 0.0f32);
        while i > 0 {
            f /= base as f32;
            r += f * (i % base) as f32;
            i /= base;
        }
        r
    };
    (0..count)
        .map(|k| {
            let at = (k as f32 + 0.5) / count as f32 * total;
            let i = cumulative
                .partition_point(|&c| c < at)
                .min(sources.len() - 1);
            let source = &sources[i];
            let (mut u, mut v) = (radical_inverse(k + 1, 2), radical_inverse(k + 1, 3));
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            let [a, b, c] = source.corners;
            let normal = (b - a).cross(c - a).normalize();
            Patch {
                centre: a + (b - a) * u + (c - a) * v,
                // The winding's normal, turned to the vertex normals' side where they say.
                normal: if normal.dot(source.outward) < 0.0 {
                    -normal
                } else {
                    normal
                },
                area: total / count as f32,
                albedo: source.albedo,
                specular: source.specular,
            }
        })
        .collect()
}

/// Where `p` lands on the camera's image, in pixels from the top-left (`None` behind it or
/// outside the image), and its distance.
fn project(camera: &SceneCamera, p: Vec3) -> Option<(f32, f32, f32)> {
    let in_camera = camera.world_from_camera.inverse().transform_point(p);
    if in_camera.z >= -1e-3 {
        return None;
    }
    let tan_half = (camera.yfov_rad / 2.0).tan();
    let aspect = camera.width as f32 / camera.height.max(1) as f32;
    let x = in_camera.x / (-in_camera.z * tan_half * aspect);
    let y = in_camera.y / (-in_camera.z * tan_half);
    ((-1.0..=1.0).contains(&x) && (-1.0..=1.0).contains(&y)).then(|| {
        (
            (x + 1.0) / 2.0 * camera.width as f32,
            (1.0 - y) / 2.0 * camera.height as f32,
            in_camera.length(),
        )
    })
}

/// Ray/box slab test over (0, t_max).
fn hits_box(origin: Vec3, dir: Vec3, (lo, hi): (Vec3, Vec3), t_max: f32) -> bool {
    let inv = dir.recip();
    let t0 = (lo - origin) * inv;
    let t1 = (hi - origin) * inv;
    let near = t0.min(t1).max_element().max(0.0);
    let far = t0.max(t1).min_element().min(t_max);
    near <= far
}

/// Möller–Trumbore, two-sided: the hit's t in (0, t_max).
fn hits_triangle(origin: Vec3, dir: Vec3, [a, b, c]: [Vec3; 3], t_max: f32) -> Option<f32> {
    let (e1, e2) = (b - a, c - a);
    let p = dir.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv = 1.0 / det;
    let s = origin - a;
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = dir.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(q) * inv;
    (t > 1e-4 && t < t_max).then_some(t)
}

/// The object's triangles as occluders, behind its box.
struct Occluder {
    bounds: (Vec3, Vec3),
    triangles: Vec<[Vec3; 3]>,
}

impl Occluder {
    fn new(scene: &Scene, bounds: (Vec3, Vec3)) -> Self {
        let triangles = scene
            .meshes
            .iter()
            .filter(|m| m.is_virtual)
            .flat_map(|m| {
                m.triangles.iter().filter_map(|t| {
                    let corner = |i: u32| m.positions_in_world.get(i as usize).copied();
                    Some([corner(t[0])?, corner(t[1])?, corner(t[2])?])
                })
            })
            .filter(|t| t.iter().all(|p| p.is_finite()))
            .collect();
        Self { bounds, triangles }
    }

    fn blocks(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        hits_box(origin, dir, self.bounds, t_max)
            && self
                .triangles
                .iter()
                .any(|t| hits_triangle(origin, dir, *t, t_max).is_some())
    }

    /// The nearest hit's distance.
    fn nearest(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        if !hits_box(origin, dir, self.bounds, f32::MAX) {
            return None;
        }
        self.triangles
            .iter()
            .filter_map(|t| hits_triangle(origin, dir, *t, f32::MAX))
            .min_by(f32::total_cmp)
    }
}

/// The lights the estimate uses: the scene's point, spot and directional lights, and its
/// environment as directional lights (the probe's, or cut from the map).
fn lights(scene: &Scene) -> Vec<Light> {
    let mut lights: Vec<Light> = scene
        .lights
        .iter()
        .filter(|l| l.validate().is_ok() && !matches!(l, Light::Environment { .. }))
        .copied()
        .collect();
    if !scene.environment_lights.is_empty() {
        lights.extend(scene.environment_lights.iter().copied());
    } else if let Some(env) = &scene.environment {
        lights.extend(environment_lights(env, ENVIRONMENT_LIGHTS));
    }
    lights
}

/// Irradiance on a surface at `p` with normal `n` from `light`, with the direction to it and
/// the distance; `None` when it does not reach the surface's front.
fn irradiance(light: &Light, p: Vec3, n: Vec3) -> Option<(Vec3, Vec3, f32)> {
    let incident = light.incident(p)?;
    let cos = incident.direction_to_light.dot(n);
    (cos > 0.0 && incident.irradiance.max_element() > 0.0).then(|| {
        (
            incident.irradiance * cos,
            incident.direction_to_light,
            incident.distance_m,
        )
    })
}

/// The real surface for ray queries: the live surface's shadow proxy (decimated) when the
/// scene has one, else its real meshes.
fn real_geometry(scene: &Scene) -> Geometry {
    match &scene.shadow_proxy {
        Some(proxy) => Geometry::of_meshes(std::slice::from_ref(proxy.as_ref()), false),
        None => Geometry::of_meshes(&scene.meshes, false),
    }
}

/// Radiance a real surface reflects back along `dir` at the hit `hit` of `geometry`
/// (unshadowed direct light on the side the ray meets).
fn reflected(
    scene: &Scene,
    geometry: &Geometry,
    lights: &[Light],
    hit: Hit,
    origin: Vec3,
    dir: Vec3,
) -> Vec3 {
    let Some(tri) = geometry.triangles().get(hit.triangle) else {
        return Vec3::ZERO;
    };
    let at = origin + dir * hit.t;
    let n = tri.normal_against(dir);
    let albedo = tri
        .measured_albedo_at(hit.u, hit.v)
        .or_else(|| scene.materials.get(tri.material).map(|m| m.albedo))
        .unwrap_or(Vec3::splat(0.5));
    let e: Vec3 = lights
        .iter()
        .filter_map(|l| irradiance(l, at, n).map(|(e, _, _)| e))
        .sum();
    albedo * e / std::f32::consts::PI
}

/// The features of `scene` as its camera sees it.
pub fn scene_features(scene: &Scene) -> SceneFeatures {
    let Some(object_bounds) = scene.virtual_bounds() else {
        return SceneFeatures::default();
    };
    let camera = &scene.camera;
    let eye = camera.world_from_camera.translation;
    let lights = lights(scene);
    let occluder = Occluder::new(scene, object_bounds);
    let real = real_geometry(scene);
    let lit = |p: Vec3, n: Vec3, light: &Light| {
        let (e, to_light, distance) = irradiance(light, p, n)?;
        let start = p + n * (1e-4 * (1.0 + p.abs().max_element()));
        real.occluder(start, to_light, 0.0, distance * (1.0 - 1e-4))
            .is_none()
            .then_some((e, start, to_light, distance))
    };
    // Each object patch as a Lambertian emitter, on its outer side, of what it reflects of
    // the lights.
    let object = patches(&scene.meshes, &scene.materials, true, OBJECT_PATCHES);
    let emitted: Vec<Vec3> = object
        .iter()
        .map(|t| {
            let e: Vec3 = lights
                .iter()
                .filter_map(|l| lit(t.centre, t.normal, l).map(|(e, ..)| e))
                .sum();
            t.albedo * e / std::f32::consts::PI
        })
        .collect();
    let object_area: f32 = object.iter().map(|p| p.area).sum();
    let mean = |values: &mut dyn Iterator<Item = (f32, Vec3)>| {
        let (w, sum) = values.fold((0.0, Vec3::ZERO), |(w, sum), (a, v)| (w + a, sum + v * a));
        if w > 0.0 { sum / w } else { Vec3::ZERO }
    };
    let object_albedo = luminance(mean(&mut object.iter().map(|t| (t.area, t.albedo))));
    let object_radiance = mean(&mut object.iter().zip(&emitted).map(|(t, l)| (t.area, *l)));
    let focal_px = camera.height as f32 / (2.0 * (camera.yfov_rad / 2.0).tan());
    let (lo, hi) = object_bounds;
    let mut sums = [0.0f64; 4];
    let mut samples = 0;
    let mut object_distance = f32::INFINITY;
    for patch in patches(&scene.meshes, &scene.materials, false, REAL_SAMPLES) {
        let p = patch.centre;
        let Some((_, _, distance)) = project(camera, p) else {
            continue;
        };
        let to_eye = (eye - p) / distance;
        // Triangles are two-sided: the side the camera sees.
        let normal = if patch.normal.dot(to_eye) < 0.0 {
            -patch.normal
        } else {
            patch.normal
        };
        let cos_view = normal.dot(to_eye);
        let seen = real
            .intersect(eye, -to_eye, 0.0, f32::INFINITY)
            .is_none_or(|hit| hit.t >= distance * (1.0 - 1e-3))
            && !occluder.blocks(eye, -to_eye, distance * (1.0 - 1e-3));
        if cos_view <= 1e-3 || !seen {
            continue;
        }
        samples += 1;
        object_distance = object_distance.min(p.clamp(lo, hi).distance(p));
        let rho = patch.albedo / std::f32::consts::PI;
        let mut shadow = Vec3::ZERO;
        for light in &lights {
            if let Some((e, start, to_light, distance)) = lit(p, normal, light)
                && occluder.blocks(start, to_light, distance)
            {
                shadow += e;
            }
        }
        let start = p + normal * (1e-4 * (1.0 + p.abs().max_element()));
        let (mut bleeding, mut occlusion) = (Vec3::ZERO, Vec3::ZERO);
        for (t, radiance) in object.iter().zip(&emitted) {
            let d = t.centre - start;
            let d2 = d.length_squared().max(t.area);
            let dir = d / d2.sqrt();
            // Only the object's side facing p emits towards p and hides what lies behind it.
            let (cos_p, cos_t) = (normal.dot(dir), t.normal.dot(-dir));
            if cos_p <= 0.0 || cos_t <= 0.0 {
                continue;
            }
            // What a real surface shows along this direction: before the patch it hides the
            // patch; behind it, it is what the object hides.
            let hit = real.intersect(start, dir, 0.0, f32::INFINITY);
            if hit.is_some_and(|h| h.t * h.t < d2) {
                continue;
            }
            let form = t.area * cos_p * cos_t / d2;
            bleeding += *radiance * form;
            if let Some(hit) = hit {
                occlusion += reflected(scene, &real, &lights, hit, start, dir) * form;
            }
        }
        let mirror = 2.0 * normal.dot(to_eye) * normal - to_eye;
        let glossy = match occluder.nearest(start, mirror) {
            Some(t) if patch.specular > 0.0 => {
                // What the mirror ray meets on the object: the nearest patch's radiance.
                let at = start + mirror * t;
                let seen = object
                    .iter()
                    .zip(&emitted)
                    .min_by(|a, b| {
                        a.0.centre
                            .distance_squared(at)
                            .total_cmp(&b.0.centre.distance_squared(at))
                    })
                    .map_or(object_radiance, |(_, l)| *l);
                let behind = real
                    .intersect(start, mirror, 0.0, f32::INFINITY)
                    .map_or(Vec3::ZERO, |h| {
                        reflected(scene, &real, &lights, h, start, mirror)
                    });
                Vec3::splat(patch.specular) * (seen - behind).abs()
            }
            _ => Vec3::ZERO,
        };
        // Pixels the sample's share of the surface covers.
        let weight = patch.area * cos_view / (distance * distance) * focal_px * focal_px;
        for (sum, part) in sums.iter_mut().zip([
            rho * shadow,
            rho * bleeding * BLEEDING_SCALE,
            rho * occlusion,
            glossy,
        ]) {
            *sum += f64::from(part.length_squared() * weight);
        }
    }
    if samples == 0 || object_area <= 0.0 {
        return SceneFeatures::default();
    }
    let [shadow, bleeding, occlusion, glossy] = sums.map(f64::sqrt);
    SceneFeatures {
        shadow,
        bleeding,
        occlusion,
        glossy,
        environment: scene.environment.is_some() || !scene.environment_lights.is_empty(),
        blocks_light: shadow > 0.0,
        object_albedo,
        object_size_m: (hi - lo).length(),
        object_distance_m: object_distance,
        samples,
    }
}

#[cfg(test)]
mod tests {
    use relight_core::Pose;

    use super::*;

    /// A grey floor seen from above, a box on it, one point light: `albedo` the box's,
    /// `light` where the light is.
    fn floor_and_box(albedo: f32, light: Vec3) -> Scene {
        let mut floor = Mesh::cuboid(
            "floor",
            Vec3::new(-1.0, -0.01, -1.0),
            Vec3::new(1.0, 0.0, 1.0),
            0,
            false,
        );
        floor.name = "floor".into();
        Scene {
            name: "floor and box".into(),
            meshes: vec![
                floor,
                Mesh::cuboid(
                    "box",
                    Vec3::new(-0.1, 0.0, -0.1),
                    Vec3::new(0.1, 0.2, 0.1),
                    1,
                    true,
                ),
            ],
            materials: vec![
                Material {
                    albedo: Vec3::splat(0.6),
                    ..Material::default()
                },
                Material {
                    albedo: Vec3::splat(albedo),
                    ..Material::default()
                },
            ],
            camera: SceneCamera {
                world_from_camera: Pose::look_at(Vec3::new(0.0, 1.5, 1.5), Vec3::ZERO, Vec3::Y),
                yfov_rad: 0.9,
                width: 64,
                height: 48,
            },
            lights: vec![Light::Point {
                position_in_world: light,
                intensity: Vec3::splat(5.0),
            }],
            environment: None,
            environment_lights: Vec::new(),
            shadow_proxy: None,
            surface_revision: None,
        }
    }

    #[test]
    fn a_black_object_casts_only_a_shadow_and_a_white_one_bleeds() {
        let black = scene_features(&floor_and_box(0.0, Vec3::new(0.5, 1.0, 0.0)));
        assert!(black.blocks_light && black.shadow > 0.0, "{black:?}");
        assert_eq!(black.bleeding, 0.0);
        let white = scene_features(&floor_and_box(0.9, Vec3::new(0.5, 1.0, 0.0)));
        assert!(white.bleeding > 0.0);
        assert!(white.indirect_share() > black.indirect_share());
        assert_eq!(white.shadow, black.shadow);
        // It stands on the floor: the nearest floor sample is within the sampling's spacing.
        assert!(white.object_distance_m < 0.05, "{white:?}");
    }

    #[test]
    fn an_object_that_blocks_no_light_casts_no_shadow() {
        // A light under the floor: the floor's top, all the camera sees, faces away from it.
        let low = scene_features(&floor_and_box(0.5, Vec3::new(0.0, -0.5, 0.0)));
        assert!(!low.blocks_light, "{low:?}");
        assert_eq!(low.shadow, 0.0);
        let without = scene_features(&floor_and_box(0.5, Vec3::Y).without_virtual());
        assert_eq!(without, SceneFeatures::default());
    }
}
