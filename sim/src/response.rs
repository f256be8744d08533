//! A camera's photometric response: linear exposure → 8-bit code, with a known closed-form
//! inverse, so photometric calibration (Robertson / Debevec) can be scored against the truth.
//!
//! f(X) = ((1 + s)·X / (1 + s·X))^(1/γ) for X = radiance × exposure time × gain in [0, 1],
//! clipped above 1: a gamma curve with a soft shoulder s, like a consumer camera's.

/// The response curve; `Default` is γ = 2.2 with a mild shoulder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraResponse {
    pub gamma: f32,
    pub shoulder: f32,
}

impl Default for CameraResponse {
    fn default() -> Self {
        Self {
            gamma: 2.2,
            shoulder: 0.6,
        }
    }
}

impl CameraResponse {
    /// Normalised response in [0, 1] of exposure `x` (≥ 1 saturates).
    pub fn apply(&self, x: f32) -> f32 {
        if x.is_nan() || x <= 0.0 {
            return 0.0;
        }
        let x = x.min(1.0);
        let s = self.shoulder;
        ((1.0 + s) * x / (1.0 + s * x)).powf(1.0 / self.gamma)
    }

    /// The 8-bit code the camera writes for exposure `x`.
    pub fn to_code(&self, x: f32) -> u8 {
        (self.apply(x) * 255.0).round() as u8
    }

    /// Exposure that produces normalised response `y` in [0, 1] (the exact inverse of `apply`).
    pub fn inverse(&self, y: f32) -> f32 {
        let z = y.clamp(0.0, 1.0).powf(self.gamma);
        z / (1.0 + self.shoulder - self.shoulder * z)
    }

    /// Relative exposure of each 8-bit code (what `RigCalibration::probe_response` holds).
    pub fn inverse_table(&self) -> Vec<f32> {
        (0..=255u8)
            .map(|code| self.inverse(f32::from(code) / 255.0))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_undoes_the_curve_and_the_curve_rises() {
        let r = CameraResponse::default();
        for i in 0..=1000 {
            let x = i as f32 / 1000.0;
            assert!((r.inverse(r.apply(x)) - x).abs() < 1e-5, "x {x}");
        }
        let table = r.inverse_table();
        assert_eq!(table.len(), 256);
        assert!(table.windows(2).all(|w| w[1] > w[0]));
        assert_eq!(r.to_code(2.0), 255);
        assert_eq!(r.to_code(-1.0), 0);
        assert_eq!(r.to_code(f32::NAN), 0);
    }
}
