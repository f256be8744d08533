//! Camera models: pinhole with Brown–Conrady distortion, and Kannala–Brandt fish-eye.
//!
//! # Frames
//!
//! Calibration comes from OpenCV, so these models work in the OpenCV *optical* frame: +X right,
//! +Y down, +Z forward (out of the lens). The rest of relight uses the glTF camera frame: +X right,
//! +Y up, −Z forward. The two differ by a 180° rotation about X (flip Y and Z); convert with
//! [`optical_from_gl`] / [`gl_from_optical`], [`OPTICAL_FROM_GL`] or [`OPTICAL_FROM_GL_ROTATION`]:
//!
//! ```
//! # use glam::DVec3;
//! # use relight_core::camera::{optical_from_gl, CameraModel, Pinhole};
//! # let camera = CameraModel::Pinhole(Pinhole { width: 640, height: 480, fx: 500.0, fy: 500.0,
//! #     cx: 319.5, cy: 239.5, k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 });
//! let point_in_gl_camera = DVec3::new(0.0, 0.0, -2.0); // two metres in front of the camera
//! let pixel = camera.project(optical_from_gl(point_in_gl_camera));
//! assert_eq!(pixel, Some(glam::DVec2::new(319.5, 239.5)));
//! ```
//!
//! # Pixels
//!
//! OpenCV convention: the centre of the pixel in column `i`, row `j` is at `(i, j)`, so an image
//! `width × height` covers `[-0.5, width - 0.5] × [-0.5, height - 0.5]` and the centre of the image
//! is `((width - 1) / 2, (height - 1) / 2)`.
//!
//! # Valid field
//!
//! A distortion polynomial is only invertible where it is monotonic in the radius (pinhole: radius
//! on the normalised image plane; fish-eye: angle θ from the optical axis). Beyond the first zero of
//! its derivative the model folds back onto itself and a projected point lands on a pixel that
//! belongs to a different ray. `project` returns `None` there and `unproject` never returns such a
//! ray. For the pinhole model the test uses the radial term only (tangential terms are three orders
//! of magnitude smaller for any real lens).

use glam::{DMat3, DVec2, DVec3, Quat};
use serde::{Deserialize, Serialize};

/// Pinhole camera with Brown–Conrady (OpenCV 5-parameter) distortion.
///
/// On the normalised plane `(x, y) = (X/Z, Y/Z)`, with `r² = x² + y²`:
/// `x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)`,
/// `y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y`,
/// then `u = fx x_d + cx`, `v = fy y_d + cy` (OpenCV `projectPoints`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pinhole {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub p1: f64,
    #[serde(default)]
    pub p2: f64,
    #[serde(default)]
    pub k3: f64,
}

/// Kannala–Brandt fish-eye model (OpenCV `fisheye`): θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸).
///
/// θ is the angle between the ray and the optical axis (+Z), φ its azimuth; the pixel is
/// `u = fx θ_d cos φ + cx`, `v = fy θ_d sin φ + cy`. Unlike OpenCV's implementation, which takes
/// θ = atan(r) and so only sees the front hemisphere, θ here comes from `atan2`, so rays past 90°
/// (a 185° lens) project correctly.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct KannalaBrandt {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub k3: f64,
    #[serde(default)]
    pub k4: f64,
}

/// Either camera model, tagged by `model = "pinhole" | "kannala_brandt"` in TOML/JSON.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case")]
pub enum CameraModel {
    Pinhole(Pinhole),
    KannalaBrandt(KannalaBrandt),
}

/// Why a camera's parameters are unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    #[error("camera parameter `{parameter}` is not finite")]
    NonFinite { parameter: &'static str },
    #[error("focal lengths must be positive, got fx = {fx}, fy = {fy}")]
    NonPositiveFocalLength { fx: f64, fy: f64 },
    #[error("image size {width}x{height} is empty")]
    EmptyImage { width: u32, height: u32 },
    #[error(
        "principal point ({cx}, {cy}) lies outside the {width}x{height} image \
         ([-0.5, width - 0.5] × [-0.5, height - 0.5])"
    )]
    PrincipalPointOutside {
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
    },
}

/// `point_in_optical = OPTICAL_FROM_GL * point_in_gl`: glTF camera frame (+Y up, −Z forward) to
/// OpenCV optical frame (+Y down, +Z forward). The matrix is its own inverse.
pub const OPTICAL_FROM_GL: DMat3 = DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));

/// The rotation of [`OPTICAL_FROM_GL`] as a quaternion (180° about X), for composing with
/// [`crate::Pose`]: `optical_from_world = Pose::new(OPTICAL_FROM_GL_ROTATION, Vec3::ZERO) * camera_from_world`.
pub const OPTICAL_FROM_GL_ROTATION: Quat = Quat::from_xyzw(1.0, 0.0, 0.0, 0.0);

/// A point or direction in the glTF camera frame, expressed in the OpenCV optical frame.
pub fn optical_from_gl(point_in_gl: DVec3) -> DVec3 {
    DVec3::new(point_in_gl.x, -point_in_gl.y, -point_in_gl.z)
}

/// A point or direction in the OpenCV optical frame, expressed in the glTF camera frame.
pub fn gl_from_optical(point_in_optical: DVec3) -> DVec3 {
    DVec3::new(point_in_optical.x, -point_in_optical.y, -point_in_optical.z)
}

/// Residual (normalised-plane units) at which the iterative inversions stop.
const CONVERGENCE_TOLERANCE: f64 = 1e-12;
/// Newton iterations before an inversion is declared failed.
const MAX_ITERATIONS: usize = 100;

impl Pinhole {
    /// Vertical field of view through the image's full height, radians (distortion ignored).
    pub fn yfov_rad(&self) -> f64 {
        2.0 * (f64::from(self.height) / 2.0 / self.fy).atan()
    }

    /// Intrinsic matrix `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    pub fn intrinsics(&self) -> DMat3 {
        intrinsics(self.fx, self.fy, self.cx, self.cy)
    }

    /// Brown–Conrady distortion of a point on the normalised plane (`z = 1`).
    pub fn distort_normalized(&self, undistorted: DVec2) -> DVec2 {
        let DVec2 { x, y } = undistorted;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        DVec2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Jacobian of [`Self::distort_normalized`] (columns ∂/∂x, ∂/∂y).
    fn distortion_jacobian(&self, undistorted: DVec2) -> [[f64; 2]; 2] {
        let DVec2 { x, y } = undistorted;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let d_radial_d_r2 = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let dxd_dx = radial + 2.0 * x * x * d_radial_d_r2 + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
        let dxd_dy = 2.0 * x * y * d_radial_d_r2 + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyd_dx = 2.0 * x * y * d_radial_d_r2 + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let dyd_dy = radial + 2.0 * y * y * d_radial_d_r2 + 6.0 * self.p1 * y + 2.0 * self.p2 * x;
        [[dxd_dx, dyd_dx], [dxd_dy, dyd_dy]]
    }

    /// `d(r·radial(r²))/dr` as a polynomial in `s = r²`: `1 + 3 k1 s + 5 k2 s² + 7 k3 s³`.
    fn radial_slope(&self) -> Poly {
        Poly::new(&[1.0, 3.0 * self.k1, 5.0 * self.k2, 7.0 * self.k3])
    }

    /// Largest squared radius on the normalised plane where the radial distortion is still
    /// monotonic; `f64::INFINITY` when it is monotonic everywhere.
    pub fn max_radius_sq(&self) -> f64 {
        self.radial_slope()
            .smallest_positive_root()
            .unwrap_or(f64::INFINITY)
    }

    fn in_valid_field(&self, radius_sq: f64) -> bool {
        radius_sq.is_finite() && self.radial_slope().positive_on(radius_sq)
    }

    /// Pixel of a point in the optical frame; `None` on or behind the image plane (`z ≤ 0`), or
    /// outside the valid field (see the module docs).
    pub fn project(&self, point_in_camera: DVec3) -> Option<DVec2> {
        if point_in_camera.z.is_nan() || point_in_camera.z <= 0.0 {
            return None;
        }
        let undistorted = point_in_camera.truncate() / point_in_camera.z;
        if !self.in_valid_field(undistorted.length_squared()) {
            return None;
        }
        let distorted = self.distort_normalized(undistorted);
        let pixel = DVec2::new(
            self.fx * distorted.x + self.cx,
            self.fy * distorted.y + self.cy,
        );
        pixel.is_finite().then_some(pixel)
    }

    /// Undistorted normalised-plane coordinates `(X/Z, Y/Z)` of a pixel, by damped Newton iteration
    /// on the full (radial + tangential) distortion, converged to 1e-12. `None` when the
    /// iteration does not converge or lands outside the valid field.
    pub fn undistort_point(&self, pixel: DVec2) -> Option<DVec2> {
        let target = DVec2::new((pixel.x - self.cx) / self.fx, (pixel.y - self.cy) / self.fy);
        if !target.is_finite() {
            return None;
        }
        let tolerance = CONVERGENCE_TOLERANCE * target.length().max(1.0);
        let mut estimate = target;
        let mut residual = self.distort_normalized(estimate) - target;
        for _ in 0..MAX_ITERATIONS {
            if residual.length() <= tolerance {
                return self
                    .in_valid_field(estimate.length_squared())
                    .then_some(estimate);
            }
            let [[a, c], [b, d]] = self.distortion_jacobian(estimate);
            let det = a * d - b * c;
            if det.is_nan() || det.abs() <= f64::MIN_POSITIVE {
                return None;
            }
            let step = DVec2::new(
                d * residual.x - b * residual.y,
                a * residual.y - c * residual.x,
            ) / det;
            // Backtrack until the residual shrinks, so a far-off start cannot make Newton diverge.
            let mut scale = 1.0;
            loop {
                let candidate = estimate - step * scale;
                let candidate_residual = self.distort_normalized(candidate) - target;
                if candidate_residual.length() < residual.length() || scale < 1e-6 {
                    estimate = candidate;
                    residual = candidate_residual;
                    break;
                }
                scale *= 0.5;
            }
            if !estimate.is_finite() {
                return None;
            }
        }
        None
    }

    /// The ray through a pixel on the `z = 1` plane of the optical frame.
    pub fn unproject_normalized(&self, pixel: DVec2) -> Option<DVec3> {
        self.undistort_point(pixel).map(|p| p.extend(1.0))
    }

    /// Unit ray (optical frame) through a pixel.
    pub fn unproject(&self, pixel: DVec2) -> Option<DVec3> {
        self.unproject_normalized(pixel).map(DVec3::normalize)
    }

    /// The same camera at `factor` times the resolution (width and height rounded).
    pub fn scaled(&self, factor: f64) -> Self {
        let (width, height) = scaled_size(self.width, self.height, factor);
        self.resized(width, height)
    }

    /// The same camera resampled to `width × height`; intrinsics scale with each axis,
    /// distortion is unchanged (it acts on the normalised plane).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let [fx, fy, cx, cy] = resize_intrinsics(
            [self.fx, self.fy, self.cx, self.cy],
            (self.width, self.height),
            (width, height),
        );
        Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            ..*self
        }
    }

    /// The camera that sees every `step`-th pixel of this one as its pixels
    /// ([`Image::subsampled`](crate::Image::subsampled)): pixel x is this camera's x · step,
    /// so the intrinsics divide by `step` exactly (not [`resized`](Self::resized)'s area
    /// resampling, which moves the pixel centres); distortion acts on the normalised plane and
    /// is kept.
    pub fn subsampled(&self, step: u32) -> Self {
        let step = step.max(1);
        let s = f64::from(step);
        Self {
            width: self.width.div_ceil(step),
            height: self.height.div_ceil(step),
            fx: self.fx / s,
            fy: self.fy / s,
            cx: self.cx / s,
            cy: self.cy / s,
            ..*self
        }
    }

    /// Whether a pixel lies inside the image rectangle.
    pub fn contains_pixel(&self, pixel: DVec2) -> bool {
        contains_pixel(self.width, self.height, pixel)
    }

    /// Checks focal lengths, finiteness and the principal point.
    pub fn validate(&self) -> Result<(), CameraError> {
        check_finite(&[
            ("k1", self.k1),
            ("k2", self.k2),
            ("p1", self.p1),
            ("p2", self.p2),
            ("k3", self.k3),
        ])?;
        validate_intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)
    }
}

impl KannalaBrandt {
    /// Intrinsic matrix `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    pub fn intrinsics(&self) -> DMat3 {
        intrinsics(self.fx, self.fy, self.cx, self.cy)
    }

    /// θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸).
    pub fn distort_theta(&self, theta: f64) -> f64 {
        let t2 = theta * theta;
        theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))
    }

    /// dθ_d/dθ as a polynomial in `s = θ²`.
    fn theta_slope(&self) -> Poly {
        Poly::new(&[
            1.0,
            3.0 * self.k1,
            5.0 * self.k2,
            7.0 * self.k3,
            9.0 * self.k4,
        ])
    }

    /// Largest angle from the optical axis (radians, at most π) up to which θ_d(θ) increases.
    pub fn max_theta(&self) -> f64 {
        let pi_sq = std::f64::consts::PI * std::f64::consts::PI;
        match self.theta_slope().smallest_positive_root() {
            Some(s) if s < pi_sq => s.sqrt(),
            _ => std::f64::consts::PI,
        }
    }

    fn in_valid_field(&self, theta: f64) -> bool {
        theta <= std::f64::consts::PI && self.theta_slope().positive_on(theta * theta)
    }

    /// Inverts [`Self::distort_theta`] on `[0, max_theta]` by safeguarded Newton iteration,
    /// converged to 1e-12; `None` when θ_d is beyond the valid field or negative.
    pub fn undistort_theta(&self, theta_d: f64) -> Option<f64> {
        if theta_d.is_nan() || theta_d < 0.0 {
            return None;
        }
        let pi = std::f64::consts::PI;
        let theta_max = if self.theta_slope().positive_on(pi * pi) {
            pi
        } else {
            self.max_theta()
        };
        let tolerance = CONVERGENCE_TOLERANCE * theta_d.max(1.0);
        if theta_d > self.distort_theta(theta_max) + tolerance {
            return None;
        }
        let (mut low, mut high) = (0.0, theta_max);
        let mut theta = theta_d.clamp(low, high);
        for _ in 0..MAX_ITERATIONS {
            let residual = self.distort_theta(theta) - theta_d;
            if residual.abs() <= tolerance {
                return Some(theta);
            }
            if residual > 0.0 {
                high = theta;
            } else {
                low = theta;
            }
            let slope = self.theta_slope().eval(theta * theta);
            let newton = theta - residual / slope;
            theta = if newton > low && newton < high {
                newton
            } else {
                0.5 * (low + high)
            };
            if high - low <= f64::EPSILON * high {
                return Some(theta);
            }
        }
        None
    }

    /// Pixel of a point in the optical frame; `None` for the origin, for a point straight behind
    /// the camera (θ = π, where the azimuth is undefined) and beyond [`Self::max_theta`].
    pub fn project(&self, point_in_camera: DVec3) -> Option<DVec2> {
        let direction = point_in_camera.try_normalize()?;
        let radius = direction.truncate().length();
        let theta = radius.atan2(direction.z);
        if !self.in_valid_field(theta) {
            return None;
        }
        let offset = if radius > 0.0 {
            direction.truncate() * (self.distort_theta(theta) / radius)
        } else if direction.z > 0.0 {
            DVec2::ZERO
        } else {
            return None;
        };
        let pixel = DVec2::new(self.fx * offset.x + self.cx, self.fy * offset.y + self.cy);
        pixel.is_finite().then_some(pixel)
    }

    /// Unit ray (optical frame) through a pixel; `None` outside the valid field.
    pub fn unproject(&self, pixel: DVec2) -> Option<DVec3> {
        let offset = DVec2::new((pixel.x - self.cx) / self.fx, (pixel.y - self.cy) / self.fy);
        let theta_d = offset.length();
        let theta = self.undistort_theta(theta_d)?;
        if theta_d == 0.0 {
            return Some(DVec3::Z);
        }
        let azimuth = offset / theta_d;
        Some((azimuth * theta.sin()).extend(theta.cos()))
    }

    /// The same camera at `factor` times the resolution (width and height rounded).
    pub fn scaled(&self, factor: f64) -> Self {
        let (width, height) = scaled_size(self.width, self.height, factor);
        self.resized(width, height)
    }

    /// The same camera resampled to `width × height`; intrinsics scale with each axis,
    /// distortion is unchanged (it acts on θ).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let [fx, fy, cx, cy] = resize_intrinsics(
            [self.fx, self.fy, self.cx, self.cy],
            (self.width, self.height),
            (width, height),
        );
        Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            ..*self
        }
    }

    /// Whether a pixel lies inside the image rectangle.
    pub fn contains_pixel(&self, pixel: DVec2) -> bool {
        contains_pixel(self.width, self.height, pixel)
    }

    /// Checks focal lengths, finiteness and the principal point.
    pub fn validate(&self) -> Result<(), CameraError> {
        check_finite(&[
            ("k1", self.k1),
            ("k2", self.k2),
            ("k3", self.k3),
            ("k4", self.k4),
        ])?;
        validate_intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)
    }
}

impl CameraModel {
    pub fn width(&self) -> u32 {
        match self {
            Self::Pinhole(c) => c.width,
            Self::KannalaBrandt(c) => c.width,
        }
    }

    pub fn height(&self) -> u32 {
        match self {
            Self::Pinhole(c) => c.height,
            Self::KannalaBrandt(c) => c.height,
        }
    }

    /// Intrinsic matrix `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    pub fn intrinsics(&self) -> DMat3 {
        match self {
            Self::Pinhole(c) => c.intrinsics(),
            Self::KannalaBrandt(c) => c.intrinsics(),
        }
    }

    /// Pixel of a point in the optical frame (+Z forward, +Y down); see the models' `project`.
    pub fn project(&self, point_in_camera: DVec3) -> Option<DVec2> {
        match self {
            Self::Pinhole(c) => c.project(point_in_camera),
            Self::KannalaBrandt(c) => c.project(point_in_camera),
        }
    }

    /// Unit ray in the optical frame through a pixel; see the models' `unproject`.
    pub fn unproject(&self, pixel: DVec2) -> Option<DVec3> {
        match self {
            Self::Pinhole(c) => c.unproject(pixel),
            Self::KannalaBrandt(c) => c.unproject(pixel),
        }
    }

    /// The same camera at `factor` times the resolution (width and height rounded).
    pub fn scaled(&self, factor: f64) -> Self {
        match self {
            Self::Pinhole(c) => Self::Pinhole(c.scaled(factor)),
            Self::KannalaBrandt(c) => Self::KannalaBrandt(c.scaled(factor)),
        }
    }

    /// The same camera resampled to `width × height`.
    pub fn resized(&self, width: u32, height: u32) -> Self {
        match self {
            Self::Pinhole(c) => Self::Pinhole(c.resized(width, height)),
            Self::KannalaBrandt(c) => Self::KannalaBrandt(c.resized(width, height)),
        }
    }

    /// Whether a pixel lies inside the image rectangle.
    pub fn contains_pixel(&self, pixel: DVec2) -> bool {
        contains_pixel(self.width(), self.height(), pixel)
    }

    pub fn validate(&self) -> Result<(), CameraError> {
        match self {
            Self::Pinhole(c) => c.validate(),
            Self::KannalaBrandt(c) => c.validate(),
        }
    }
}

fn intrinsics(fx: f64, fy: f64, cx: f64, cy: f64) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(fx, 0.0, 0.0),
        DVec3::new(0.0, fy, 0.0),
        DVec3::new(cx, cy, 1.0),
    )
}

fn scaled_size(width: u32, height: u32, factor: f64) -> (u32, u32) {
    // `as` saturates: a negative or NaN factor gives 0, which `validate` rejects.
    let scale = |size: u32| (f64::from(size) * factor).round() as u32;
    (scale(width), scale(height))
}

/// Rescales `[fx, fy, cx, cy]` between resolutions. Pixel centres sit at integer coordinates, so
/// the image edge `-0.5` is what stays fixed: `c' = (c + 0.5) s - 0.5`.
fn resize_intrinsics(
    [fx, fy, cx, cy]: [f64; 4],
    (old_width, old_height): (u32, u32),
    (new_width, new_height): (u32, u32),
) -> [f64; 4] {
    let sx = f64::from(new_width) / f64::from(old_width);
    let sy = f64::from(new_height) / f64::from(old_height);
    [
        fx * sx,
        fy * sy,
        (cx + 0.5) * sx - 0.5,
        (cy + 0.5) * sy - 0.5,
    ]
}

fn contains_pixel(width: u32, height: u32, pixel: DVec2) -> bool {
    (-0.5..=f64::from(width) - 0.5).contains(&pixel.x)
        && (-0.5..=f64::from(height) - 0.5).contains(&pixel.y)
}

fn check_finite(parameters: &[(&'static str, f64)]) -> Result<(), CameraError> {
    match parameters.iter().find(|(_, value)| !value.is_finite()) {
        Some(&(parameter, _)) => Err(CameraError::NonFinite { parameter }),
        None => Ok(()),
    }
}

fn validate_intrinsics(
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
) -> Result<(), CameraError> {
    check_finite(&[("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)])?;
    if width == 0 || height == 0 {
        return Err(CameraError::EmptyImage { width, height });
    }
    if !(fx > 0.0 && fy > 0.0) {
        return Err(CameraError::NonPositiveFocalLength { fx, fy });
    }
    if !contains_pixel(width, height, DVec2::new(cx, cy)) {
        return Err(CameraError::PrincipalPointOutside {
            cx,
            cy,
            width,
            height,
        });
    }
    Ok(())
}

/// A real polynomial of degree ≤ 4 in `s`, with `p(0) = 1` in every use here: the slope of a
/// distortion curve, whose first positive root bounds the valid field.
#[derive(Debug, Clone, Copy)]
struct Poly {
    coeffs: [f64; 5],
    degree: usize,
}

impl Poly {
    fn new(coeffs: &[f64]) -> Self {
        let mut padded = [0.0; 5];
        for (slot, &c) in padded.iter_mut().zip(coeffs) {
            *slot = c;
        }
        let degree = padded.iter().rposition(|&c| c != 0.0).unwrap_or(0);
        Self {
            coeffs: padded,
            degree,
        }
    }

    fn eval(&self, s: f64) -> f64 {
        self.coeffs[..=self.degree]
            .iter()
            .rev()
            .fold(0.0, |acc, &c| acc * s + c)
    }

    fn derivative(&self) -> Self {
        let mut coeffs = [0.0; 5];
        for i in 1..=self.degree {
            coeffs[i - 1] = self.coeffs[i] * i as f64;
        }
        Self::new(&coeffs)
    }

    /// All real roots in `[low, high]`, ascending: the roots of the derivative split the interval
    /// into monotonic pieces, each holding at most one root, found by bisection.
    fn roots_in(&self, low: f64, high: f64) -> ([f64; 4], usize) {
        let mut roots = [0.0; 4];
        let mut count = 0;
        let push = |root: f64, roots: &mut [f64; 4], count: &mut usize| {
            if *count < roots.len() && (*count == 0 || roots[*count - 1] < root) {
                roots[*count] = root;
                *count += 1;
            }
        };
        match self.degree {
            0 => {}
            1 => {
                let root = -self.coeffs[0] / self.coeffs[1];
                if (low..=high).contains(&root) {
                    push(root, &mut roots, &mut count);
                }
            }
            _ => {
                let (critical, critical_count) = self.derivative().roots_in(low, high);
                let mut knots = [low; 5];
                knots[1..=critical_count].copy_from_slice(&critical[..critical_count]);
                knots[critical_count + 1] = high;
                for pair in knots[..critical_count + 2].windows(2) {
                    let (mut a, mut b) = (pair[0], pair[1]);
                    let (mut fa, fb) = (self.eval(a), self.eval(b));
                    if fa == 0.0 {
                        push(a, &mut roots, &mut count);
                        continue;
                    }
                    if fb == 0.0 {
                        push(b, &mut roots, &mut count);
                        continue;
                    }
                    if (fa < 0.0) == (fb < 0.0) {
                        continue;
                    }
                    loop {
                        let mid = 0.5 * (a + b);
                        if !(mid > a && mid < b) {
                            break;
                        }
                        let fm = self.eval(mid);
                        if (fm < 0.0) == (fa < 0.0) {
                            a = mid;
                            fa = fm;
                        } else {
                            b = mid;
                        }
                    }
                    push(b, &mut roots, &mut count);
                }
            }
        }
        (roots, count)
    }

    /// Smallest root in `(0, ∞)`. Roots are bounded by Cauchy's bound `1 + max |a_i / a_n|`.
    fn smallest_positive_root(&self) -> Option<f64> {
        if self.degree == 0 {
            return None;
        }
        let leading = self.coeffs[self.degree];
        let bound = 1.0
            + self.coeffs[..self.degree]
                .iter()
                .map(|c| (c / leading).abs())
                .fold(0.0, f64::max);
        let (roots, count) = self.roots_in(0.0, bound);
        roots[..count].iter().copied().find(|&r| r > 0.0)
    }

    /// Whether `p > 0` on all of `[0, s_max]`. Fast path: if every Bernstein coefficient of `p` on
    /// an interval is positive, so is `p` there (convex-hull property); intervals where that is
    /// inconclusive are halved a few times (de Casteljau) before falling back to root finding.
    fn positive_on(&self, s_max: f64) -> bool {
        // No negative coefficient and a positive constant: positive on all of [0, ∞) (a lens
        // without distortion, per point of every projection).
        if s_max >= 0.0 && self.coeffs[0] > 0.0 && self.coeffs[1..].iter().all(|&c| c >= 0.0) {
            return true;
        }
        let mut budget = 16;
        match self.bernstein_positive_on(0.0, s_max, &mut budget) {
            Some(positive) => positive,
            None => self
                .smallest_positive_root()
                .is_none_or(|root| root > s_max),
        }
    }

    /// `Some(true)`: positive on `[low, high]`; `Some(false)`: not positive at an end point;
    /// `None`: undecided within `budget` subdivisions.
    fn bernstein_positive_on(&self, low: f64, high: f64, budget: &mut u32) -> Option<bool> {
        const BINOMIAL: [[f64; 5]; 5] = [
            [1.0, 0.0, 0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0, 0.0, 0.0],
            [1.0, 2.0, 1.0, 0.0, 0.0],
            [1.0, 3.0, 3.0, 1.0, 0.0],
            [1.0, 4.0, 6.0, 4.0, 1.0],
        ];
        if self.eval(low) <= 0.0 || self.eval(high) <= 0.0 {
            return Some(false);
        }
        // Coefficients of q(t) = p(low + (high − low) t) on t ∈ [0, 1]: repeated synthetic
        // division gives the Taylor shift by `low`, then scale by powers of the width.
        let n = self.degree;
        let mut shifted = self.coeffs;
        for i in 0..n {
            for j in (i..n).rev() {
                shifted[j] += low * shifted[j + 1];
            }
        }
        let width = high - low;
        let mut power = 1.0;
        for c in &mut shifted[..=n] {
            *c *= power;
            power *= width;
        }
        let all_positive = (0..=n).all(|j| {
            (0..=j)
                .map(|i| BINOMIAL[j][i] / BINOMIAL[n][i] * shifted[i])
                .sum::<f64>()
                > 0.0
        });
        if all_positive {
            return Some(true);
        }
        if *budget == 0 {
            return None;
        }
        *budget -= 1;
        let mid = 0.5 * (low + high);
        match self.bernstein_positive_on(low, mid, budget)? {
            true => self.bernstein_positive_on(mid, high, budget),
            false => Some(false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Kinect-like colour camera with strong distortion.
    fn kinect_like() -> Pinhole {
        Pinhole {
            width: 640,
            height: 480,
            fx: 525.0,
            fy: 523.0,
            cx: 319.5,
            cy: 239.5,
            k1: 0.2,
            k2: -0.5,
            p1: 1e-3,
            p2: -1e-3,
            k3: 0.3,
        }
    }

    /// ~185° fish-eye light probe.
    fn probe_185() -> KannalaBrandt {
        KannalaBrandt {
            width: 1280,
            height: 1024,
            fx: 330.0,
            fy: 331.0,
            cx: 639.5,
            cy: 511.5,
            k1: -0.01,
            k2: 0.005,
            k3: -0.002,
            k4: 0.0005,
        }
    }

    /// Pixel grid covering the image rectangle, edges and corners included.
    fn pixel_grid(width: u32, height: u32, step: usize) -> impl Iterator<Item = DVec2> {
        let xs = (0..)
            .map(move |i| -0.5 + (i * step) as f64)
            .take_while(move |&x| x < f64::from(width) - 0.5)
            .chain([f64::from(width) - 0.5]);
        let ys: Vec<f64> = (0..)
            .map(move |j| -0.5 + (j * step) as f64)
            .take_while(move |&y| y < f64::from(height) - 0.5)
            .chain([f64::from(height) - 0.5])
            .collect();
        xs.flat_map(move |x| ys.clone().into_iter().map(move |y| DVec2::new(x, y)))
    }

    /// Angle between two vectors, accurate near zero (unlike `acos` of the dot product).
    fn angle_rad(a: DVec3, b: DVec3) -> f64 {
        a.cross(b).length().atan2(a.dot(b))
    }

    fn assert_pixel_round_trip(camera: &CameraModel) {
        let mut worst_px: f64 = 0.0;
        let mut count = 0;
        for pixel in pixel_grid(camera.width(), camera.height(), 7) {
            let ray = camera
                .unproject(pixel)
                .unwrap_or_else(|| panic!("unproject failed at {pixel}"));
            assert!((ray.length() - 1.0).abs() < 1e-12);
            let back = camera
                .project(ray)
                .unwrap_or_else(|| panic!("project failed for ray {ray} from {pixel}"));
            worst_px = worst_px.max(back.distance(pixel));
            count += 1;
        }
        assert!(count > 5000);
        assert!(worst_px < 1e-6, "worst pixel round-trip error {worst_px}");
    }

    #[test]
    fn pinhole_pixel_round_trip_covers_image() {
        assert_pixel_round_trip(&CameraModel::Pinhole(kinect_like()));
    }

    #[test]
    fn fisheye_pixel_round_trip_covers_image() {
        assert_pixel_round_trip(&CameraModel::KannalaBrandt(probe_185()));
    }

    #[test]
    fn pinhole_ray_round_trip() {
        let camera = kinect_like();
        // Rays across the field of view (corners are at ~33°/25° off-axis).
        for i in 0..=20 {
            for j in 0..=20 {
                let ray = DVec3::new(
                    -0.6 + 0.06 * f64::from(i),
                    -0.45 + 0.045 * f64::from(j),
                    1.0,
                )
                .normalize();
                let pixel = camera.project(ray).expect("ray in field");
                let back = camera.unproject(pixel).expect("pixel unprojects");
                assert!(angle_rad(back, ray) < 1e-9, "{ray} -> {back}");
            }
        }
    }

    #[test]
    fn fisheye_ray_round_trip_up_to_92_5_degrees() {
        let camera = probe_185();
        let max_theta = 92.5_f64.to_radians();
        for i in 0..=40 {
            let theta = max_theta * f64::from(i) / 40.0;
            for j in 0..24 {
                let phi = std::f64::consts::TAU * f64::from(j) / 24.0;
                let ray = DVec3::new(
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                );
                let pixel = camera.project(ray).expect("ray in field");
                // The image circle (r ≈ 530 px at 92.5°) is clipped only at the top and bottom.
                let horizontal = DVec2::new(pixel.x, camera.cy);
                assert!(camera.contains_pixel(horizontal), "{pixel} outside image");
                let back = camera.unproject(pixel).expect("pixel unprojects");
                assert!(angle_rad(back, ray) < 1e-9, "{ray} -> {back}");
            }
        }
    }

    #[test]
    fn fisheye_projects_the_sideways_horizon() {
        let camera = probe_185();
        let theta_d = camera.distort_theta(std::f64::consts::FRAC_PI_2);
        for (point, expected) in [
            (
                DVec3::X,
                DVec2::new(camera.cx + camera.fx * theta_d, camera.cy),
            ),
            (
                DVec3::NEG_Y * 3.0,
                DVec2::new(camera.cx, camera.cy - camera.fy * theta_d),
            ),
        ] {
            let pixel = camera.project(point).expect("θ = 90° is in the field");
            assert!(pixel.distance(expected) < 1e-9, "{pixel} vs {expected}");
        }
    }

    #[test]
    fn pinhole_rejects_points_behind_or_on_the_image_plane() {
        let camera = kinect_like();
        assert_eq!(camera.project(DVec3::new(0.1, 0.2, -1.0)), None);
        assert_eq!(camera.project(DVec3::new(0.1, 0.2, 0.0)), None);
        assert_eq!(camera.project(DVec3::ZERO), None);
        assert_eq!(camera.project(DVec3::new(f64::NAN, 0.0, 1.0)), None);
        // Barrel distortion 1 − 0.3 r² turns back at r² = 1/0.9: beyond, the image folds over.
        let barrel = Pinhole {
            k1: -0.3,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
            ..camera
        };
        assert!((barrel.max_radius_sq() - 1.0 / 0.9).abs() < 1e-12);
        assert!(barrel.project(DVec3::new(1.0, 0.0, 1.0)).is_some());
        assert!(barrel.project(DVec3::new(1.1, 0.0, 1.0)).is_none());
        // The Kinect-like polynomial is monotonic everywhere, so far-off points still project.
        assert_eq!(camera.max_radius_sq(), f64::INFINITY);
        assert!(camera.project(DVec3::new(5.0, 0.0, 1.0)).is_some());
    }

    #[test]
    fn fisheye_rejects_angles_past_the_monotonic_range() {
        // dθ_d/dθ = 1 − 0.3 θ² vanishes at θ = √(1/0.3) ≈ 1.826 rad.
        let camera = KannalaBrandt {
            k1: -0.1,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
            ..probe_185()
        };
        assert!((camera.max_theta() - (1.0_f64 / 0.3).sqrt()).abs() < 1e-12);
        let at = |theta: f64| DVec3::new(theta.sin(), 0.0, theta.cos());
        assert!(camera.project(at(1.80)).is_some());
        assert!(camera.project(at(1.85)).is_none());
        assert!(probe_185().project(DVec3::NEG_Z).is_none());
        assert!(probe_185().project(DVec3::ZERO).is_none());
        // A pixel beyond θ_d(θ_max) has no ray.
        let beyond = camera.cx + camera.fx * (camera.distort_theta(camera.max_theta()) + 1e-3);
        assert!(camera.unproject(DVec2::new(beyond, camera.cy)).is_none());
    }

    #[test]
    fn pinhole_matches_opencv_formula_by_hand() {
        // (0.3, -0.2, 1.5): x = 0.2, y = -0.13333.., r² = 0.0577777..
        let (x, y) = (0.3 / 1.5, -0.2 / 1.5);
        let r2 = x * x + y * y;
        let radial = 1.0 + 0.2 * r2 - 0.5 * r2 * r2 + 0.3 * r2 * r2 * r2;
        let xd = x * radial + 2.0 * 1e-3 * x * y + -1e-3 * (r2 + 2.0 * x * x);
        let yd = y * radial + 1e-3 * (r2 + 2.0 * y * y) + 2.0 * -1e-3 * x * y;
        let expected = DVec2::new(525.0 * xd + 319.5, 523.0 * yd + 239.5);
        // The same number from OpenCV 5.0 `cv2.projectPoints`.
        let opencv = DVec2::new(425.44381639506173, 169.1499253232373);
        assert!(expected.distance(opencv) < 1e-9);
        let pixel = kinect_like().project(DVec3::new(0.3, -0.2, 1.5)).unwrap();
        assert!(pixel.distance(expected) < 1e-9, "{pixel} vs {expected}");
        // `cv2.undistortPoints` of pixel (600, 50).
        let normalized = kinect_like()
            .undistort_point(DVec2::new(600.0, 50.0))
            .unwrap();
        let opencv = DVec2::new(0.5256266256684249, -0.3565880649842208);
        assert!(
            normalized.distance(opencv) < 1e-7,
            "{normalized} vs {opencv}"
        );
    }

    #[test]
    fn fisheye_matches_opencv_formula_by_hand() {
        // (0.8, -0.5, 0.6): a = 4/3, b = -5/6, r = |(a, b)|, θ = atan(r).
        let (a, b): (f64, f64) = (0.8 / 0.6, -0.5 / 0.6);
        let r = (a * a + b * b).sqrt();
        let t = r.atan();
        let theta_d = t
            * (1.0 - 0.01 * t.powi(2) + 0.005 * t.powi(4) - 0.002 * t.powi(6) + 0.0005 * t.powi(8));
        let expected = DVec2::new(
            330.0 * theta_d / r * a + 639.5,
            331.0 * theta_d / r * b + 511.5,
        );
        // The same number from OpenCV 5.0 `cv2.fisheye.projectPoints`.
        let opencv = DVec2::new(918.7137381964129, 336.46259972914265);
        assert!(expected.distance(opencv) < 1e-9);
        let pixel = probe_185().project(DVec3::new(0.8, -0.5, 0.6)).unwrap();
        assert!(pixel.distance(expected) < 1e-9, "{pixel} vs {expected}");
        // `cv2.fisheye.undistortPoints` of pixel (900, 700) gives (X/Z, Y/Z).
        let ray = probe_185().unproject(DVec2::new(900.0, 700.0)).unwrap();
        let normalized = ray.truncate() / ray.z;
        let opencv = DVec2::new(1.2080506875603498, 0.8715147261505188);
        assert!(
            normalized.distance(opencv) < 1e-7,
            "{normalized} vs {opencv}"
        );
    }

    #[test]
    fn gl_and_optical_frames_flip_y_and_z() {
        let point_in_gl = DVec3::new(0.1, 0.2, -3.0);
        let point_in_optical = optical_from_gl(point_in_gl);
        assert_eq!(point_in_optical, DVec3::new(0.1, -0.2, 3.0));
        assert_eq!(OPTICAL_FROM_GL * point_in_gl, point_in_optical);
        let rotated = OPTICAL_FROM_GL_ROTATION.as_dquat() * point_in_gl;
        assert!(rotated.distance(point_in_optical) < 1e-12);
        assert_eq!(gl_from_optical(point_in_optical), point_in_gl);
        // Above the optical axis in glTF (+Y) is a smaller row index in the image.
        let pixel = kinect_like().project(point_in_optical).unwrap();
        assert!(pixel.y < kinect_like().cy && pixel.x > kinect_like().cx);
    }

    #[test]
    fn scaling_keeps_rays_on_the_same_image_location() {
        let full = CameraModel::KannalaBrandt(probe_185());
        let half = full.scaled(0.5);
        assert_eq!((half.width(), half.height()), (640, 512));
        let ray = DVec3::new(0.3, -0.4, 0.5);
        let full_px = full.project(ray).unwrap();
        let half_px = half.project(ray).unwrap();
        assert!(half_px.distance((full_px + 0.5) * 0.5 - 0.5) < 1e-9);
        let k = half.intrinsics();
        assert_eq!(k.z_axis, DVec3::new(319.5, 255.5, 1.0));
        assert_eq!((k.x_axis.x, k.y_axis.y), (165.0, 165.5));
        assert_eq!(full.resized(1280, 1024), full);
    }

    #[test]
    fn validation_rejects_bad_parameters() {
        assert_eq!(kinect_like().validate(), Ok(()));
        assert_eq!(probe_185().validate(), Ok(()));
        assert_eq!(
            Pinhole {
                fx: 0.0,
                ..kinect_like()
            }
            .validate(),
            Err(CameraError::NonPositiveFocalLength { fx: 0.0, fy: 523.0 })
        );
        assert_eq!(
            KannalaBrandt {
                k3: f64::NAN,
                ..probe_185()
            }
            .validate(),
            Err(CameraError::NonFinite { parameter: "k3" })
        );
        assert!(matches!(
            Pinhole {
                cx: 700.0,
                ..kinect_like()
            }
            .validate(),
            Err(CameraError::PrincipalPointOutside { .. })
        ));
        assert_eq!(
            CameraModel::Pinhole(kinect_like()).scaled(-1.0).validate(),
            Err(CameraError::EmptyImage {
                width: 0,
                height: 0
            })
        );
    }

    #[test]
    fn camera_model_toml_layout() {
        let camera = CameraModel::KannalaBrandt(probe_185());
        let text = toml::to_string(&camera).unwrap();
        assert!(text.contains("model = \"kannala_brandt\""), "{text}");
        assert_eq!(toml::from_str::<CameraModel>(&text).unwrap(), camera);
        let minimal: CameraModel = toml::from_str(
            "model = \"pinhole\"\nwidth = 4\nheight = 3\nfx = 2.0\nfy = 2.0\ncx = 1.5\ncy = 1.0\n",
        )
        .unwrap();
        let CameraModel::Pinhole(pinhole) = minimal else {
            panic!("tag selects the pinhole model");
        };
        assert_eq!(pinhole.k1, 0.0);
    }

    #[test]
    fn slope_polynomial_roots() {
        // (1 − s)(1 − s/4) = 1 − 1.25 s + 0.25 s²: first root at 1.
        let p = Poly::new(&[1.0, -1.25, 0.25]);
        assert!((p.smallest_positive_root().unwrap() - 1.0).abs() < 1e-14);
        assert!(p.positive_on(0.99) && !p.positive_on(1.01) && !p.positive_on(5.0));
        // Barely positive, (s − 1)² + 1e-9: Bernstein subdivision stays undecided near s = 1 and
        // the root finder settles it.
        let barely = Poly::new(&[1.0 + 1e-9, -2.0, 1.0]);
        assert!(barely.positive_on(3.0) && barely.smallest_positive_root().is_none());
        // Agreement with dense sampling on the probe's slope and perturbations of it.
        let probe = probe_185().theta_slope();
        for scale in [1.0, 2.0, 3.0, 4.0] {
            let perturbed = Poly::new(&[
                1.0,
                probe.coeffs[1] * scale,
                probe.coeffs[2],
                probe.coeffs[3] * scale,
                probe.coeffs[4],
            ]);
            for s_max in [0.5, 2.0, 5.0, 9.8] {
                let sampled =
                    (0..=20_000).all(|i| perturbed.eval(s_max * f64::from(i) / 20_000.0) > 0.0);
                assert_eq!(
                    perturbed.positive_on(s_max),
                    sampled,
                    "scale {scale}, s_max {s_max}"
                );
            }
        }
        // 1 + s² never vanishes.
        let q = Poly::new(&[1.0, 0.0, 1.0]);
        assert!(q.smallest_positive_root().is_none() && q.positive_on(1e6));
        // Kinect-like radial slope 1 + 0.6 s − 2.5 s² + 2.1 s³ stays positive (its minimum is ~0.91).
        assert!(
            kinect_like()
                .radial_slope()
                .smallest_positive_root()
                .is_none()
        );
    }
}
