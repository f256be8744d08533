//! A lens's vignetting, the radial fall-off of the light it passes (Goldman & Chen, ICCV 2005):
//! `V(r) = 1 + a1 r² + a2 r⁴ + a3 r⁶`, `r² = ((u − cx) / fx)² + ((v − cy) / fy)²` about the
//! camera model's principal point in units of its focal length (for a Kannala–Brandt lens `r` is
//! the distorted angle θ_d). A pixel that sees radiance `L` records `L · V(r)`. Fitted by
//! `relight-calibrate vignetting` and stored as the rig calibration's `probe_vignetting`.

use glam::DVec2;
use relight_core::camera::CameraModel;

use crate::hdr::HdrImage;

/// A lens's vignetting: `V(r) = 1 + a1 r² + a2 r⁴ + a3 r⁶` about `(cx, cy)`, `r` in units of
/// `(fx, fy)` (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vignetting {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `[a1, a2, a3]`.
    pub coefficients: [f64; 3],
}

impl Vignetting {
    /// The vignetting of `model` with coefficients `[a1, a2, a3]` (missing ones are 0, as an
    /// empty list means no vignetting).
    pub fn new(model: &CameraModel, coefficients: &[f32]) -> Self {
        let k = model.intrinsics();
        let a = |i: usize| coefficients.get(i).map_or(0.0, |&v| f64::from(v));
        Self {
            fx: k.x_axis.x,
            fy: k.y_axis.y,
            cx: k.z_axis.x,
            cy: k.z_axis.y,
            coefficients: [a(0), a(1), a(2)],
        }
    }

    /// Normalised radius of a pixel (module docs).
    pub fn radius(&self, pixel: DVec2) -> f64 {
        DVec2::new((pixel.x - self.cx) / self.fx, (pixel.y - self.cy) / self.fy).length()
    }

    /// `V(r)`.
    pub fn factor(&self, radius: f64) -> f64 {
        let r2 = radius * radius;
        let [a1, a2, a3] = self.coefficients;
        1.0 + r2 * (a1 + r2 * (a2 + r2 * a3))
    }

    /// `V` at pixel `(x, y)`; `None` where the polynomial is not positive (far outside the
    /// fitted field), where dividing by it would be meaningless.
    pub fn factor_at(&self, x: f64, y: f64) -> Option<f64> {
        let v = self.factor(self.radius(DVec2::new(x, y)));
        (v.is_finite() && v > 0.0).then_some(v)
    }

    /// `[a1, a2, a3]` as stored in a calibration file.
    pub fn coefficients_f32(&self) -> Vec<f32> {
        self.coefficients.iter().map(|&a| a as f32).collect()
    }
}

impl Vignetting {
    /// Divide `V` out of a merged image taken through this lens (pixels where `V` is not
    /// positive are left as they are).
    pub fn correct(&self, hdr: &mut HdrImage) {
        let width = hdr.width.max(1) as usize;
        for (i, radiance) in hdr.radiance.iter_mut().enumerate() {
            let (x, y) = ((i % width) as f64, (i / width) as f64);
            if let Some(v) = self.factor_at(x, y) {
                *radiance /= v as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use relight_core::camera::Pinhole;

    use super::*;

    #[test]
    fn correcting_undoes_the_fall_off() {
        let model = CameraModel::Pinhole(Pinhole {
            width: 4,
            height: 3,
            fx: 2.0,
            fy: 2.0,
            cx: 1.5,
            cy: 1.0,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        });
        let v = Vignetting::new(&model, &[-0.3, 0.05]);
        let mut hdr = HdrImage {
            width: 4,
            height: 3,
            radiance: (0..12)
                .map(|i| {
                    let f = v.factor_at(f64::from(i % 4), f64::from(i / 4)).unwrap() as f32;
                    glam::Vec3::splat(2.0 * f)
                })
                .collect(),
            saturated: vec![false; 12],
        };
        v.correct(&mut hdr);
        for l in &hdr.radiance {
            assert!(
                (*l - glam::Vec3::splat(2.0)).abs().max_element() < 1e-6,
                "{l}"
            );
        }
    }
}
