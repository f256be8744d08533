//! One light path: next-event estimation for point, spot and directional lights and for the
//! environment map (combined with BSDF sampling by MIS, power heuristic), emission on hit,
//! Russian roulette.
//!
//! A path consumes the same random numbers, in the same order, whatever it hits until the scene
//! makes it end or turn differently, so tracing one stream through the full and through the
//! real-only geometry gives L^ρ and L^μ that are bitwise equal wherever the virtual object plays
//! no part (correlated sampling). [`PathResult::touched_virtual`] says whether it played a part.

use glam::Vec3;
use relight_core::scene::{Material, Scene};

use crate::accel::Geometry;
use crate::brdf::Bsdf;
use crate::sampling::{EnvSampler, SampleRng, env_radiance};

/// What the path tracer needs besides the geometry.
#[derive(Debug)]
pub struct PathContext<'a> {
    pub scene: &'a Scene,
    /// Importance sampler of `scene.environment`; `None` when there is none or it is all black.
    pub env: Option<&'a EnvSampler>,
    pub max_bounces: u32,
    pub rr_start_bounce: u32,
}

/// The radiance one path carries to the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathResult {
    /// Finite, non-negative radiance.
    pub radiance: Vec3,
    /// True when a virtual triangle was the closest hit of one of the path's rays or the first
    /// blocker found for one of its shadow rays. When false, the same path traced through the
    /// real-only geometry meets the same triangles and makes the same decisions, so it returns
    /// bitwise the same radiance: the closest hit among all triangles was real, so it is also
    /// the closest among the real ones, and a shadow ray blocked by a real triangle is blocked
    /// in both geometries.
    pub touched_virtual: bool,
}

/// Power heuristic with β = 2 (Veach 1997), written with a ratio so that huge densities (very
/// sharp Phong lobes) cannot overflow to ∞/∞.
fn mis(a: f32, b: f32) -> f32 {
    if a.is_nan() || a <= 0.0 {
        return 0.0;
    }
    if a >= b {
        let r = b / a;
        1.0 / (1.0 + r * r)
    } else {
        let r = a / b;
        r * r / (1.0 + r * r)
    }
}

/// Moves a ray origin off the surface along the geometric normal, by an epsilon scaled to the
/// position's magnitude (f32 spacing grows with it).
fn offset(p: Vec3, normal: Vec3) -> Vec3 {
    p + normal * (1e-4 * (1.0 + p.abs().max_element()))
}

/// Stand-in for a material index that points past the scene's materials.
static BLACK: Material = Material {
    name: String::new(),
    albedo: Vec3::ZERO,
    specular: Vec3::ZERO,
    shininess: 0.0,
    emission: Vec3::ZERO,
};

/// Radiance arriving at `origin` from the direction `-dir`, estimated by one path.
///
/// Emissive surfaces are not light-sampled: their emission counts (with weight 1) wherever a
/// camera or BSDF-sampled ray hits them. `max_bounces` counts the vertices after the first hit
/// that may still scatter; 0 gives emission plus direct light at the first hit, the
/// environment's included in full (both halves of its MIS).
pub fn radiance(
    ctx: &PathContext<'_>,
    geometry: &Geometry,
    mut origin: Vec3,
    mut dir: Vec3,
    rng: &mut SampleRng,
) -> PathResult {
    let scene = ctx.scene;
    let mut radiance = Vec3::ZERO;
    let mut throughput = Vec3::ONE;
    let mut touched_virtual = false;
    // Solid-angle density of the BSDF sample that produced `dir`; `None` for the camera ray.
    let mut last_bsdf_pdf: Option<f32> = None;
    // One ray more than the path has vertices: the last vertex's BSDF-sampled ray, which only
    // finishes that vertex's environment MIS (its light-sampled half was weighted as if this
    // ray would follow). Whatever it hits adds nothing.
    for depth in 0..=ctx.max_bounces.saturating_add(1) {
        let finishing_environment_mis = depth > ctx.max_bounces;
        let Some(hit) = geometry.intersect(origin, dir, 0.0, f32::INFINITY) else {
            if let Some(env) = &scene.environment {
                let weight = match (last_bsdf_pdf, ctx.env) {
                    (Some(bsdf_pdf), Some(sampler)) => mis(bsdf_pdf, sampler.pdf(dir)),
                    _ => 1.0,
                };
                radiance += throughput * env_radiance(env, dir) * weight;
            }
            break;
        };
        let Some(tri) = geometry.triangles().get(hit.triangle) else {
            break;
        };
        touched_virtual |= tri.is_virtual;
        if finishing_environment_mis {
            break;
        }
        let material = scene.materials.get(tri.material).unwrap_or(&BLACK);
        let p = origin + dir * hit.t;
        let wo = -dir;
        // Both normals face the side the ray came from.
        let ng = tri.normal_against(dir);
        let w = 1.0 - hit.u - hit.v;
        let interpolated = (tri.normals[0] * w + tri.normals[1] * hit.u + tri.normals[2] * hit.v)
            .normalize_or_zero();
        let mut ns = if interpolated.is_finite() && interpolated != Vec3::ZERO {
            interpolated
        } else {
            ng
        };
        if ns.dot(ng) < 0.0 {
            ns = -ns;
        }
        radiance += throughput * material.emission;
        let albedo = tri
            .measured_albedo_at(hit.u, hit.v)
            .unwrap_or(material.albedo);
        let bsdf = Bsdf::new(material, albedo, ns, wo);
        if bsdf.is_black() {
            break;
        }
        let from = offset(p, ng);
        for light in &scene.lights {
            let Some(incident) = light.incident(p) else {
                continue;
            };
            let wi = incident.direction_to_light;
            let cos = wi.dot(ns);
            if cos <= 0.0 || wi.dot(ng) <= 0.0 || incident.irradiance.max_element() <= 0.0 {
                continue;
            }
            let t_max = if incident.distance_m.is_finite() {
                incident.distance_m * (1.0 - 1e-4)
            } else {
                f32::INFINITY
            };
            match geometry.occluder(from, wi, 0.0, t_max) {
                Some(blocker) => touched_virtual |= blocker.is_virtual,
                None => radiance += throughput * bsdf.eval(wi) * incident.irradiance * cos,
            }
        }
        if let (Some(env), Some(sampler)) = (&scene.environment, ctx.env) {
            // Always two numbers, whatever follows, so correlated paths stay in step.
            let (wi, env_pdf) = sampler.sample(rng.next(), rng.next());
            let cos = wi.dot(ns);
            if env_pdf > 0.0 && cos > 0.0 && wi.dot(ng) > 0.0 {
                match geometry.occluder(from, wi, 0.0, f32::INFINITY) {
                    Some(blocker) => touched_virtual |= blocker.is_virtual,
                    None => {
                        let weight = mis(env_pdf, bsdf.pdf(wi));
                        radiance += throughput
                            * bsdf.eval(wi)
                            * env_radiance(env, wi)
                            * (cos * weight / env_pdf);
                    }
                }
            }
        }
        if depth == ctx.max_bounces && ctx.env.is_none() {
            break;
        }
        let Some(wi) = bsdf.sample(rng) else {
            break;
        };
        let pdf = bsdf.pdf(wi);
        let cos = wi.dot(ns);
        if pdf.is_nan() || pdf <= 0.0 || wi.dot(ng) <= 0.0 {
            break;
        }
        throughput *= bsdf.eval(wi) * (cos / pdf);
        last_bsdf_pdf = Some(pdf);
        if depth >= ctx.rr_start_bounce {
            // Russian roulette: survive with probability ≤ 0.95 from the throughput, and divide
            // by it, so the estimate stays unbiased.
            let survive = throughput.max_element().min(0.95);
            if rng.next() >= survive {
                break;
            }
            throughput /= survive;
        }
        if !throughput.is_finite() {
            break;
        }
        origin = from;
        dir = wi;
    }
    PathResult {
        radiance: if radiance.is_finite() {
            radiance
        } else {
            Vec3::ZERO
        },
        touched_virtual,
    }
}
