//! The reflectance model of the reference: Lambert + normalised Phong,
//! f_r = k_d/π + k_s (n+1)/(2π) cosⁿα, α from the mirror direction (as in papers.md).

use std::f32::consts::{FRAC_1_PI, PI};

use glam::Vec3;
use relight_core::scene::Material;

use crate::sampling::{SampleRng, cosine_hemisphere, phong_lobe};

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// A material at one shading point: its diffuse albedo there (the material's, or what a
/// measured surface carries at that point), normal facing the viewer, view direction `wo`
/// (towards the viewer).
#[derive(Debug, Clone, Copy)]
pub struct Bsdf<'m> {
    pub material: &'m Material,
    pub albedo: Vec3,
    pub normal: Vec3,
    pub wo: Vec3,
    /// Probability of sampling the glossy lobe.
    specular_weight: f32,
}

impl<'m> Bsdf<'m> {
    pub fn new(material: &'m Material, albedo: Vec3, normal: Vec3, wo: Vec3) -> Self {
        let kd = luminance(albedo).max(0.0);
        let ks = if material.shininess > 0.0 {
            luminance(material.specular).max(0.0)
        } else {
            0.0
        };
        let specular_weight = if kd + ks > 0.0 { ks / (kd + ks) } else { 0.0 };
        Self {
            material,
            albedo,
            normal,
            wo,
            specular_weight,
        }
    }

    /// True when the surface reflects nothing (paths end here).
    pub fn is_black(&self) -> bool {
        self.albedo.max_element() <= 0.0
            && (self.material.specular.max_element() <= 0.0 || self.material.shininess <= 0.0)
    }

    fn mirror(&self) -> Vec3 {
        2.0 * self.wo.dot(self.normal) * self.normal - self.wo
    }

    fn phong(&self, wi: Vec3) -> f32 {
        let n = self.material.shininess;
        let cos_alpha = self.mirror().dot(wi).max(0.0);
        (n + 1.0) / (2.0 * PI) * cos_alpha.powf(n)
    }

    /// f_r(wo, wi).
    pub fn eval(&self, wi: Vec3) -> Vec3 {
        if wi.dot(self.normal) <= 0.0 {
            return Vec3::ZERO;
        }
        let mut f = self.albedo * FRAC_1_PI;
        if self.material.shininess > 0.0 {
            f += self.material.specular * self.phong(wi);
        }
        f
    }

    /// Solid-angle density of [`Bsdf::sample`] producing `wi`.
    pub fn pdf(&self, wi: Vec3) -> f32 {
        let cos = wi.dot(self.normal);
        if cos <= 0.0 {
            return 0.0;
        }
        let diffuse = cos * FRAC_1_PI;
        if self.specular_weight > 0.0 {
            (1.0 - self.specular_weight) * diffuse + self.specular_weight * self.phong(wi)
        } else {
            diffuse
        }
    }

    /// A direction by the lobes' weights; `None` when it falls below the surface.
    pub fn sample(&self, rng: &mut SampleRng) -> Option<Vec3> {
        let (choice, u1, u2) = (rng.next(), rng.next(), rng.next());
        let wi = if choice < self.specular_weight {
            phong_lobe(self.mirror(), self.material.shininess, u1, u2)
        } else {
            cosine_hemisphere(self.normal, u1, u2)
        };
        (wi.dot(self.normal) > 0.0 && wi.is_finite()).then_some(wi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∫ f cos dω ≤ 1 (energy conservation), and = albedo for a Lambertian surface.
    #[test]
    fn reflectance_is_energy_conserving() {
        let n = Vec3::Y;
        for (albedo, specular, shininess, expected) in [
            (Vec3::splat(0.7), Vec3::ZERO, 0.0, Some(0.7)),
            (Vec3::splat(0.3), Vec3::splat(0.6), 80.0, None),
        ] {
            let material = Material {
                albedo,
                specular,
                shininess,
                ..Material::default()
            };
            let wo = Vec3::new(0.0, 1.0, 0.0);
            let bsdf = Bsdf::new(&material, material.albedo, n, wo);
            let mut rng = SampleRng::new(4, 5, 6);
            let (mut sum, count) = (0.0f64, 200_000);
            for _ in 0..count {
                if let Some(wi) = bsdf.sample(&mut rng) {
                    sum += f64::from(bsdf.eval(wi).x * wi.dot(n) / bsdf.pdf(wi));
                }
            }
            let reflectance = sum / f64::from(count);
            match expected {
                Some(e) => assert!((reflectance - e).abs() < 0.01, "{reflectance}"),
                None => assert!(reflectance <= 0.91 && reflectance > 0.8, "{reflectance}"),
            }
        }
    }
}
