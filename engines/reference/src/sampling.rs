//! Random numbers and the sampling routines of the path tracer.

use std::f32::consts::{PI, TAU};

use glam::Vec3;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg32;
use relight_core::scene::EnvironmentMap;

/// The random stream of one pixel sample. Seeded from (seed, pixel, sample) only, so a render
/// is the same whatever the thread schedule, and L^ρ and L^μ of one sample can replay exactly
/// the same numbers (correlated sampling).
#[derive(Debug, Clone)]
pub struct SampleRng(Pcg32);

impl SampleRng {
    pub fn new(seed: u64, pixel: u64, sample: u64) -> Self {
        // SplitMix64 finaliser over the three words: decorrelates neighbouring seeds.
        let mut z = seed
            ^ pixel.wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ sample.wrapping_mul(0xD1B5_4A32_D192_ED03);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        Self(Pcg32::seed_from_u64(z ^ (z >> 31)))
    }

    /// Uniform in [0, 1).
    pub fn next(&mut self) -> f32 {
        self.0.random::<f32>()
    }
}

/// An orthonormal basis (t, b, n) around unit `n` (Duff et al. 2017).
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// Cosine-weighted direction around `n`; pdf = cos θ / π.
pub fn cosine_hemisphere(n: Vec3, u1: f32, u2: f32) -> Vec3 {
    let r = u1.sqrt();
    let phi = TAU * u2;
    let (t, b) = basis(n);
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u1).max(0.0).sqrt()).normalize()
}

/// Direction around `axis` with density (n+1)/(2π) cosⁿα; the Phong lobe.
pub fn phong_lobe(axis: Vec3, shininess: f32, u1: f32, u2: f32) -> Vec3 {
    let cos_alpha = u1.powf(1.0 / (shininess + 1.0));
    let sin_alpha = (1.0 - cos_alpha * cos_alpha).max(0.0).sqrt();
    let phi = TAU * u2;
    let (t, b) = basis(axis);
    (t * (sin_alpha * phi.cos()) + b * (sin_alpha * phi.sin()) + axis * cos_alpha).normalize()
}

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// Importance sampling of an equirectangular environment by luminance × sin θ: a marginal
/// distribution over rows and a conditional one per row (piecewise constant).
#[derive(Debug, Clone)]
pub struct EnvSampler {
    width: usize,
    height: usize,
    /// Cumulative distribution over rows (length height + 1).
    row_cdf: Vec<f32>,
    /// Per row, cumulative distribution over columns (height × (width + 1)).
    col_cdf: Vec<f32>,
    /// Normalised texel probabilities (height × width).
    texel_p: Vec<f32>,
}

impl EnvSampler {
    pub fn new(env: &EnvironmentMap) -> Option<Self> {
        let (w, h) = (env.width as usize, env.height as usize);
        if w == 0 || h == 0 || env.radiance.len() != w * h {
            return None;
        }
        let mut weights = vec![0f32; w * h];
        for y in 0..h {
            let sin_theta = (PI * (y as f32 + 0.5) / h as f32).sin();
            for x in 0..w {
                let l = luminance(env.radiance[y * w + x]);
                weights[y * w + x] = if l.is_finite() && l > 0.0 {
                    l * sin_theta
                } else {
                    0.0
                };
            }
        }
        let total: f64 = weights.iter().map(|&v| f64::from(v)).sum();
        if total.is_nan() || total <= 0.0 {
            return None;
        }
        let texel_p: Vec<f32> = weights
            .iter()
            .map(|&v| (f64::from(v) / total) as f32)
            .collect();
        let mut row_cdf = vec![0f32; h + 1];
        let mut col_cdf = vec![0f32; h * (w + 1)];
        for y in 0..h {
            let row = &texel_p[y * w..(y + 1) * w];
            let row_sum: f32 = row.iter().sum();
            row_cdf[y + 1] = row_cdf[y] + row_sum;
            let cdf = &mut col_cdf[y * (w + 1)..(y + 1) * (w + 1)];
            for x in 0..w {
                cdf[x + 1] = cdf[x]
                    + if row_sum > 0.0 {
                        row[x] / row_sum
                    } else {
                        1.0 / w as f32
                    };
            }
        }
        Some(Self {
            width: w,
            height: h,
            row_cdf,
            col_cdf,
            texel_p,
        })
    }

    /// The sampling tables in one array, as the GPU path tracer (`pt`) reads them: the
    /// marginal CDF over rows (height + 1 values), the conditional CDF of each row
    /// (height × (width + 1)), then each texel's probability (height × width).
    pub fn tables(&self) -> Vec<f32> {
        let mut tables = self.row_cdf.clone();
        tables.extend_from_slice(&self.col_cdf);
        tables.extend_from_slice(&self.texel_p);
        tables
    }

    /// A direction and its solid-angle pdf.
    pub fn sample(&self, u1: f32, u2: f32) -> (Vec3, f32) {
        let y = find(&self.row_cdf, u1 * self.row_cdf[self.height]).min(self.height - 1);
        let cdf = &self.col_cdf[y * (self.width + 1)..(y + 1) * (self.width + 1)];
        let x = find(cdf, u2 * cdf[self.width]).min(self.width - 1);
        // Uniform within the texel (the density is constant there).
        let fu =
            ((u2 * cdf[self.width] - cdf[x]) / (cdf[x + 1] - cdf[x]).max(1e-12)).clamp(0.0, 1.0);
        let fv = ((u1 * self.row_cdf[self.height] - self.row_cdf[y])
            / (self.row_cdf[y + 1] - self.row_cdf[y]).max(1e-12))
        .clamp(0.0, 1.0);
        let phi = TAU * (x as f32 + fu) / self.width as f32;
        let theta = PI * (y as f32 + fv) / self.height as f32;
        let dir = Vec3::new(
            theta.sin() * phi.sin(),
            theta.cos(),
            -theta.sin() * phi.cos(),
        );
        (dir, self.pdf(dir))
    }

    /// Solid-angle density of sampling `dir`: p(texel) · w·h / (2π² sin θ).
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let phi = dir.x.atan2(-dir.z).rem_euclid(TAU);
        let theta = dir.y.clamp(-1.0, 1.0).acos();
        let x = ((phi / TAU * self.width as f32) as usize).min(self.width - 1);
        let y = ((theta / PI * self.height as f32) as usize).min(self.height - 1);
        let sin_theta = theta.sin();
        if sin_theta <= 1e-6 {
            return 0.0;
        }
        self.texel_p[y * self.width + x] * (self.width * self.height) as f32
            / (2.0 * PI * PI * sin_theta)
    }
}

/// Largest i with cdf[i] ≤ value (cdf non-decreasing, cdf[0] = 0).
fn find(cdf: &[f32], value: f32) -> usize {
    cdf.partition_point(|&c| c <= value).saturating_sub(1)
}

/// Radiance of `env` in direction `dir` (nearest texel, matching the sampler's density).
pub fn env_radiance(env: &EnvironmentMap, dir: Vec3) -> Vec3 {
    let (w, h) = (env.width as usize, env.height as usize);
    if w == 0 || h == 0 || env.radiance.len() != w * h {
        return Vec3::ZERO;
    }
    let phi = dir.x.atan2(-dir.z).rem_euclid(TAU);
    let theta = dir.y.clamp(-1.0, 1.0).acos();
    let x = ((phi / TAU * w as f32) as usize).min(w - 1);
    let y = ((theta / PI * h as f32) as usize).min(h - 1);
    env.radiance[y * w + x]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn env_pdf_integrates_to_one_and_matches_sampling() {
        let (w, h) = (16, 8);
        let radiance = (0..w * h)
            .map(|i| {
                if i == 37 {
                    Vec3::splat(1e4)
                } else {
                    Vec3::splat(1.0 + (i % 5) as f32)
                }
            })
            .collect();
        let env = EnvironmentMap {
            width: w as u32,
            height: h as u32,
            radiance,
        };
        let sampler = EnvSampler::new(&env).unwrap();
        // ∫ pdf dω over a fine grid.
        let n = 400;
        let mut integral = 0.0f64;
        for j in 0..n {
            let theta = PI * (j as f32 + 0.5) / n as f32;
            for i in 0..2 * n {
                let phi = TAU * (i as f32 + 0.5) / (2 * n) as f32;
                let dir = Vec3::new(
                    theta.sin() * phi.sin(),
                    theta.cos(),
                    -theta.sin() * phi.cos(),
                );
                integral += f64::from(sampler.pdf(dir) * theta.sin())
                    * f64::from(PI / n as f32)
                    * f64::from(TAU / (2 * n) as f32);
            }
        }
        assert!((integral - 1.0).abs() < 1e-2, "{integral}");
        let mut rng = SampleRng::new(1, 2, 3);
        for _ in 0..1000 {
            let (dir, pdf) = sampler.sample(rng.next(), rng.next());
            assert!((dir.length() - 1.0).abs() < 1e-4);
            assert!(
                (pdf - sampler.pdf(dir)).abs() <= 1e-3 * pdf.max(1.0),
                "{pdf} vs {}",
                sampler.pdf(dir)
            );
        }
    }

    #[test]
    fn lobes_stay_in_their_hemisphere() {
        let mut rng = SampleRng::new(0, 0, 0);
        let n = Vec3::new(0.3, -0.8, 0.52).normalize();
        for _ in 0..1000 {
            assert!(cosine_hemisphere(n, rng.next(), rng.next()).dot(n) >= -1e-5);
            assert!(phong_lobe(n, 50.0, rng.next(), rng.next()).dot(n) > 0.5);
        }
    }
}
