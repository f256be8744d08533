//! One light path: next-event estimation for point/spot/directional lights and the
//! environment (MIS with BSDF sampling, power heuristic), emission on hit, Russian roulette.
//!
//! The random numbers a path consumes do not depend on what it hits until the scene makes the
//! paths differ, so tracing the same stream through the full and the real-only geometry gives
//! L^ρ and L^μ that are bitwise equal wherever the virtual object plays no part.

use glam::Vec3;
use relight_core::scene::{Material, Scene};

use super::accel::Geometry;
use super::brdf::Bsdf;
use super::sampling::{EnvSampler, SampleRng, env_radiance};

/// What the path tracer needs besides the geometry.
#[derive(Debug)]
pub struct PathContext<'a> {
    pub scene: &'a Scene,
    pub env: Option<&'a EnvSampler>,
    pub max_bounces: u32,
    pub rr_start_bounce: u32,
}

/// Power heuristic (β = 2).
fn mis(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 { a2 / (a2 + b2) } else { 0.0 }
}

/// Offset a ray origin off the surface, scaled to the position's magnitude.
fn offset(p: Vec3, normal: Vec3) -> Vec3 {
    p + normal * (1e-4 * (1.0 + p.abs().max_element()))
}

static BLACK: Material = Material {
    name: String::new(),
    albedo: Vec3::ZERO,
    specular: Vec3::ZERO,
    shininess: 0.0,
    emission: Vec3::ZERO,
};

/// Radiance arriving at `origin` from direction `-dir`, never NaN or infinite.
pub fn radiance(
    ctx: &PathContext<'_>,
    geometry: &Geometry,
    mut origin: Vec3,
    mut dir: Vec3,
    rng: &mut SampleRng,
) -> Vec3 {
    let scene = ctx.scene;
    let mut radiance = Vec3::ZERO;
    let mut throughput = Vec3::ONE;
    // Density of the BSDF sample that produced `dir` (None for the camera ray).
    let mut last_bsdf_pdf: Option<f32> = None;
    for depth in 0..=ctx.max_bounces {
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
        let material = scene.materials.get(tri.material).unwrap_or(&BLACK);
        let p = origin + dir * hit.t;
        let wo = -dir;
        let mut ng = tri.geometric_normal;
        if ng == Vec3::ZERO {
            break;
        }
        if ng.dot(wo) < 0.0 {
            ng = -ng;
        }
        let interpolated = (tri.normals[0] * (1.0 - hit.u - hit.v)
            + tri.normals[1] * hit.u
            + tri.normals[2] * hit.v)
            .normalize_or_zero();
        let mut ns = if interpolated == Vec3::ZERO || !interpolated.is_finite() {
            ng
        } else {
            interpolated
        };
        if ns.dot(ng) < 0.0 {
            ns = -ns;
        }
        // Emitters are not light-sampled, so their emission counts on every hit.
        radiance += throughput * material.emission;
        let bsdf = Bsdf::new(material, ns, wo);
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
            if !geometry.occluded(from, wi, 0.0, t_max) {
                radiance += throughput * bsdf.eval(wi) * incident.irradiance * cos;
            }
        }
        if let (Some(env), Some(sampler)) = (&scene.environment, ctx.env) {
            // Always two numbers, whatever happens next, to keep correlated paths in step.
            let (wi, env_pdf) = sampler.sample(rng.next(), rng.next());
            let cos = wi.dot(ns);
            if env_pdf > 0.0
                && cos > 0.0
                && wi.dot(ng) > 0.0
                && !geometry.occluded(from, wi, 0.0, f32::INFINITY)
            {
                let weight = mis(env_pdf, bsdf.pdf(wi));
                radiance +=
                    throughput * bsdf.eval(wi) * env_radiance(env, wi) * (cos * weight / env_pdf);
            }
        }
        if depth == ctx.max_bounces {
            break;
        }
        let Some(wi) = bsdf.sample(rng) else { break };
        let pdf = bsdf.pdf(wi);
        let cos = wi.dot(ns);
        if pdf.is_nan() || pdf <= 0.0 || wi.dot(ng) <= 0.0 {
            break;
        }
        throughput *= bsdf.eval(wi) * (cos / pdf);
        last_bsdf_pdf = Some(pdf);
        if depth >= ctx.rr_start_bounce {
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
    if radiance.is_finite() {
        radiance
    } else {
        Vec3::ZERO
    }
}
