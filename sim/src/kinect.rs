//! Kinect v1 (structured light) depth from true depth.
//!
//! The sensor measures disparity between its IR camera and projector (baseline b ≈ 7.5 cm,
//! f ≈ 580 px at 640×480) and reports z = f·b / d. Its defects follow from that:
//! - **Noise** is Gaussian in disparity; its depth standard deviation grows with z²
//!   (Nguyen, Izadi & Lovell 2012: σ_z(z) = 1.2 mm + 1.9 mm·(z − 0.4 m)² for z in metres,
//!   measured head-on). We draw σ_d = σ_z(z) · f·b / z² so that σ_z matches that model.
//! - **Quantisation**: disparity is reported in 1/8 px, so depth steps are z²/(8 f b)
//!   (≈ 2.9 mm at 1 m, 2.6 cm at 3 m — Khoshelham & Elberink 2012).
//! - **Holes**: surfaces the projector cannot see (the shadow beside every foreground edge, on its −x side since the projector sits at +x,
//!   found with a z-buffer in the projector's view), surfaces too dark in the IR, specular
//!   surfaces seen near the mirror direction, grazing surfaces, and anything outside the
//!   working range. Invalid depth is 0, as the driver reports it.

use glam::Vec3;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_pcg::Pcg64Mcg;
use relight_core::camera::Pinhole;
use relight_core::{Image, PixelFormat};

/// Parameters of the depth model; defaults are a Kinect v1 at 640×480.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KinectModel {
    /// IR camera focal length at the simulated resolution, pixels.
    pub focal_px: f32,
    /// Camera–projector baseline, metres. The projector sits at +x in the camera frame.
    pub baseline_m: f32,
    /// Disparity quantisation step, pixels (Kinect v1: 1/8).
    pub disparity_step_px: f32,
    /// σ_z(z) = `noise_a_m` + `noise_b_per_m` · (z − `noise_z0_m`)².
    pub noise_a_m: f32,
    pub noise_b_per_m: f32,
    pub noise_z0_m: f32,
    pub min_range_m: f32,
    pub max_range_m: f32,
    /// IR albedo below which a surface returns no pattern.
    pub dark_albedo: f32,
    /// Specular reflectance above which a surface seen within `specular_cone_deg` of the mirror
    /// direction of the projector is lost.
    pub specular_threshold: f32,
    pub specular_cone_deg: f32,
    /// cos of the incidence angle below which a surface is too grazing to measure.
    pub min_cos_incidence: f32,
    /// Projector-shadow depth tolerance, metres (points this far behind the projector's
    /// z-buffer are shadowed).
    pub shadow_epsilon_m: f32,
}

impl Default for KinectModel {
    fn default() -> Self {
        Self {
            focal_px: 580.0,
            baseline_m: 0.075,
            disparity_step_px: 1.0 / 8.0,
            noise_a_m: 0.0012,
            noise_b_per_m: 0.0019,
            noise_z0_m: 0.4,
            min_range_m: 0.5,
            max_range_m: 4.5,
            dark_albedo: 0.03,
            specular_threshold: 0.5,
            specular_cone_deg: 10.0,
            min_cos_incidence: 0.15,
            shadow_epsilon_m: 0.01,
        }
    }
}

/// What the simulator knows about each pixel of the depth camera.
#[derive(Debug, Clone, PartialEq)]
pub struct TrueSurface {
    pub width: u32,
    pub height: u32,
    /// z (along the optical axis) of the visible surface, metres; 0 where there is none.
    pub depth_m: Vec<f32>,
    /// Unit surface normals in the camera's optical frame (+z forward, +y down).
    pub normal: Vec<Vec3>,
    /// Diffuse albedo in the IR (use the luminance of the visible albedo).
    pub ir_albedo: Vec<f32>,
    /// Specular reflectance k_s (luminance).
    pub specular: Vec<f32>,
}

impl KinectModel {
    /// σ_z at depth z, metres.
    pub fn sigma_z_m(&self, z_m: f32) -> f32 {
        self.noise_a_m + self.noise_b_per_m * (z_m - self.noise_z0_m).powi(2)
    }

    /// The depth step at z, metres: z² · step / (f b).
    pub fn quantum_m(&self, z_m: f32) -> f32 {
        z_m * z_m * self.disparity_step_px / (self.focal_px * self.baseline_m)
    }

    /// Measure `truth` with `camera` (its focal length should match `focal_px`) into a
    /// `DepthU16Mm` image. Deterministic for a given `seed`.
    pub fn measure(&self, truth: &TrueSurface, camera: &Pinhole, seed: u64, out: &mut Image) {
        let (w, h) = (truth.width, truth.height);
        out.reshape(w, h, PixelFormat::DepthU16Mm);
        let shadowed = self.projector_shadow(truth, camera);
        let mut rng = Pcg64Mcg::seed_from_u64(seed);
        let fb = self.focal_px * self.baseline_m;
        let Some(depth_mm) = out.as_u16_mut() else {
            return;
        };
        for (i, d_out) in depth_mm.iter_mut().enumerate() {
            *d_out = 0;
            let z = truth.depth_m.get(i).copied().unwrap_or(0.0);
            if !(z.is_finite() && z >= self.min_range_m && z <= self.max_range_m) || shadowed[i] {
                continue;
            }
            let x = (i % w as usize) as f64;
            let y = (i / w as usize) as f64;
            let ray = Vec3::new(
                ((x - camera.cx) / camera.fx) as f32,
                ((y - camera.cy) / camera.fy) as f32,
                1.0,
            )
            .normalize();
            let normal = truth.normal.get(i).copied().unwrap_or(Vec3::ZERO);
            let cos_incidence = normal.dot(-ray);
            // NaN (a degenerate normal) counts as grazing.
            if cos_incidence.is_nan() || cos_incidence < self.min_cos_incidence {
                continue;
            }
            if truth.ir_albedo.get(i).copied().unwrap_or(0.0) < self.dark_albedo {
                continue;
            }
            // The projector is (nearly) beside the camera: the mirror direction of the viewing
            // ray about the normal points back at the sensor when the surface faces it.
            let mirror = ray - 2.0 * ray.dot(normal) * normal;
            let off_mirror = mirror.dot(-ray).clamp(-1.0, 1.0).acos().to_degrees();
            if truth.specular.get(i).copied().unwrap_or(0.0) > self.specular_threshold
                && off_mirror < self.specular_cone_deg
            {
                continue;
            }
            let disparity = fb / z;
            let sigma_d = self.sigma_z_m(z) * fb / (z * z);
            let noisy = match Normal::new(disparity, sigma_d) {
                Ok(normal) => normal.sample(&mut rng),
                Err(_) => disparity,
            };
            let step = self.disparity_step_px;
            let quantised = (noisy / step).round() * step;
            if quantised <= 0.0 {
                continue;
            }
            let z_measured = fb / quantised;
            if z_measured >= self.min_range_m && z_measured <= self.max_range_m {
                *d_out = (z_measured * 1000.0).round().clamp(1.0, 65535.0) as u16;
            }
        }
    }

    /// Pixels whose surface the projector cannot see: rasterise every surface pixel's footprint
    /// into the projector's image (same intrinsics, offset by the baseline along +x; rows stay
    /// rows), keep the nearest depth per projector pixel, and mark points more than
    /// `shadow_epsilon_m` behind it.
    fn projector_shadow(&self, truth: &TrueSurface, camera: &Pinhole) -> Vec<bool> {
        let (w, h) = (truth.width as usize, truth.height as usize);
        let depth = |i: usize| {
            truth
                .depth_m
                .get(i)
                .copied()
                .filter(|z| z.is_finite() && *z > 0.0)
        };
        // Projector column of camera column x (fractional) for a point at depth z.
        let column = |x: f64, z: f32| {
            let point_x = ((x - camera.cx) / camera.fx) as f32 * z;
            camera.fx as f32 * (point_x - self.baseline_m) / z + camera.cx as f32
        };
        let mut zbuffer = vec![f32::INFINITY; w * h];
        for i in 0..w * h {
            let Some(z) = depth(i) else { continue };
            let (row, x) = (i / w, (i % w) as f64);
            let first = column(x - 0.5, z).ceil().max(0.0) as usize;
            let last = column(x + 0.5, z).ceil().min(w as f32) as usize;
            for p in first..last {
                let cell = &mut zbuffer[row * w + p];
                *cell = cell.min(z);
            }
        }
        (0..w * h)
            .map(|i| {
                depth(i).is_some_and(|z| {
                    let p = column((i % w) as f64, z).round();
                    p >= 0.0
                        && (p as usize) < w
                        && z > zbuffer[(i / w) * w + p as usize] + self.shadow_epsilon_m
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(w: u32, h: u32) -> Pinhole {
        Pinhole {
            width: w,
            height: h,
            fx: 580.0,
            fy: 580.0,
            cx: f64::from(w - 1) / 2.0,
            cy: f64::from(h - 1) / 2.0,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        }
    }

    /// A fronto-parallel wall at `z`, optionally with a nearer box over the columns `box_cols`.
    fn wall(w: u32, h: u32, z: f32, box_cols: Option<(u32, u32, f32)>) -> TrueSurface {
        let n = (w * h) as usize;
        let mut depth_m = vec![z; n];
        if let Some((c0, c1, zb)) = box_cols {
            for (i, d) in depth_m.iter_mut().enumerate() {
                let x = (i % w as usize) as u32;
                if (c0..c1).contains(&x) {
                    *d = zb;
                }
            }
        }
        TrueSurface {
            width: w,
            height: h,
            depth_m,
            normal: vec![Vec3::new(0.0, 0.0, -1.0); n],
            ir_albedo: vec![0.5; n],
            specular: vec![0.0; n],
        }
    }

    fn valid_m(image: &Image) -> Vec<f64> {
        image
            .as_u16()
            .unwrap()
            .iter()
            .filter(|&&d| d > 0)
            .map(|&d| f64::from(d) / 1000.0)
            .collect()
    }

    #[test]
    fn noise_and_quantisation_match_the_model() {
        let model = KinectModel::default();
        // Small, central patch so every ray is nearly head-on.
        let (w, h) = (40, 40);
        for z in [1.0f32, 2.0, 3.0] {
            let mut out = Image::default();
            model.measure(&wall(w, h, z, None), &camera(w, h), 7, &mut out);
            let values = valid_m(&out);
            assert_eq!(values.len(), (w * h) as usize);
            let mean = values.iter().sum::<f64>() / values.len() as f64;
            let var =
                values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (values.len() - 1) as f64;
            let sigma_model = f64::from(model.sigma_z_m(z));
            let quantum = f64::from(model.quantum_m(z));
            // Quantisation adds q²/12 of variance to the Gaussian noise; mm rounding adds 1/12 mm².
            let expected = (sigma_model.powi(2) + quantum.powi(2) / 12.0 + 1e-6 / 12.0).sqrt();
            let sigma = var.sqrt();
            assert!(
                (sigma / expected - 1.0).abs() < 0.1,
                "z {z}: σ {sigma} vs model {expected}"
            );
            assert!(
                (mean - f64::from(z)).abs()
                    < 3.0 * sigma / (values.len() as f64).sqrt() + quantum / 4.0,
                "z {z}: mean {mean}"
            );
            // At 3 m the disparity steps are visible as distinct levels ≈ one quantum apart.
            if z >= 3.0 {
                let mut levels: Vec<u16> = out.as_u16().unwrap().to_vec();
                levels.sort_unstable();
                levels.dedup();
                let gaps: Vec<f64> = levels
                    .windows(2)
                    .map(|p| f64::from(p[1] - p[0]) / 1000.0)
                    .collect();
                let median_gap = {
                    let mut g = gaps.clone();
                    g.sort_by(f64::total_cmp);
                    g[g.len() / 2]
                };
                assert!(
                    (median_gap / quantum - 1.0).abs() < 0.15,
                    "gap {median_gap} vs quantum {quantum}"
                );
            }
        }
    }

    #[test]
    fn foreground_edge_casts_a_projector_shadow_of_the_predicted_width() {
        let model = KinectModel::default();
        let (w, h) = (160, 8);
        let (z_box, z_wall) = (1.0, 2.0);
        let truth = wall(w, h, z_wall, Some((80, 120, z_box)));
        let mut out = Image::default();
        model.measure(&truth, &camera(w, h), 1, &mut out);
        let row = &out.as_u16().unwrap()[4 * w as usize..5 * w as usize];
        // The projector is at +x, so the box shadows the wall on its −x (left) side, over
        // f·b·(1/z_box − 1/z_wall) pixels — as in Kinect v1 images.
        let predicted =
            (model.focal_px * model.baseline_m * (1.0 / z_box - 1.0 / z_wall)).round() as usize;
        let holes = row[..80].iter().rev().take_while(|&&d| d == 0).count();
        assert!(
            holes.abs_diff(predicted) <= 1,
            "{holes} holes, predicted {predicted}"
        );
        assert!(
            row[..80 - holes].iter().all(|&d| d > 0),
            "one shadow band only"
        );
        assert!(
            row[120..].iter().all(|&d| d > 0),
            "no shadow right of the box"
        );
        assert!(
            row[80..120].iter().all(|&d| d > 0),
            "the box itself is measured"
        );
    }

    #[test]
    fn dark_specular_grazing_and_out_of_range_surfaces_are_holes() {
        let model = KinectModel::default();
        let (w, h) = (8, 1);
        let mut truth = wall(w, h, 1.5, None);
        truth.ir_albedo[0] = 0.01;
        truth.specular[1] = 0.9;
        truth.normal[2] = Vec3::new(0.99, 0.0, -0.14).normalize();
        truth.depth_m[3] = 0.3;
        truth.depth_m[4] = 6.0;
        truth.depth_m[5] = f32::NAN;
        truth.depth_m[6] = 0.0;
        let mut out = Image::default();
        model.measure(&truth, &camera(w, h), 3, &mut out);
        let d = out.as_u16().unwrap();
        assert_eq!(&d[..7], &[0; 7]);
        assert!(d[7] > 1400 && d[7] < 1600);
    }

    #[test]
    fn same_seed_same_image() {
        let model = KinectModel::default();
        let truth = wall(16, 16, 2.0, None);
        let (mut a, mut b, mut c) = (Image::default(), Image::default(), Image::default());
        model.measure(&truth, &camera(16, 16), 11, &mut a);
        model.measure(&truth, &camera(16, 16), 11, &mut b);
        model.measure(&truth, &camera(16, 16), 12, &mut c);
        assert_eq!(a, b);
        assert_ne!(a, c);
    }
}
