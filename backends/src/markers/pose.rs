//! A planar target's pose from its corners: IPPE initialisation, Levenberg–Marquardt refinement
//! through the full camera model, and the pose's covariance.
//!
//! 1. Every pixel is unprojected through the calibrated [`CameraModel`] (pinhole Brown–Conrady
//!    or Kannala–Brandt fish-eye), giving undistorted normalised coordinates `(X/Z, Y/Z)`.
//! 2. The homography from the target plane to the normalised plane gives, by IPPE (Collins &
//!    Bartoli, "Infinitesimal Plane-Based Pose Estimation", IJCV 2014, §4–5), the two rotations a
//!    plane seen under perspective can have: the planar two-fold ambiguity, which for a small tag
//!    seen nearly head-on is a genuine near-tie.
//! 3. Both candidates are refined by Levenberg–Marquardt on the reprojection error in pixels
//!    through the full camera model (distortion included); the one with the lower error wins and
//!    the other's error is kept as [`PoseFit::alternative_rms_px`], so a caller can see how
//!    ambiguous the choice was.
//! 4. The covariance of the 6 pose parameters is `σ² (JᵀJ)⁻¹` at the optimum (Gauss–Newton
//!    approximation of the Hessian; Hartley & Zisserman 2nd ed. §5.2), with `σ` the corner noise:
//!    the residual's own estimate, floored by [`PoseSettings::corner_sigma_px`] because four
//!    corners leave only two degrees of freedom to estimate it from.
//!
//! The maths runs in the OpenCV optical frame of [`relight_core::camera`] (+Z forward, +Y down);
//! [`PoseFit::camera_from_object`] converts to relight's glTF camera frame (−Z forward, +Y up),
//! the convention of [`MarkerDetection::camera_from_marker`] and of the simulator's truth.

use std::ops::Mul;

use glam::{DMat3, DQuat, DVec2, DVec3, Vec2};
use relight_core::camera::CameraModel;
use relight_core::{MarkerDetection, Pose};
use serde::{Deserialize, Serialize};

/// A rigid transform in double precision (pose estimation needs more than `f32`'s 7 digits:
/// the normal equations square the condition number).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DPose {
    pub rotation: DQuat,
    pub translation: DVec3,
}

impl Default for DPose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl DPose {
    pub const IDENTITY: DPose = DPose {
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
    };

    pub fn new(rotation: DQuat, translation: DVec3) -> Self {
        Self {
            rotation: rotation.normalize(),
            translation,
        }
    }

    pub fn from_pose(pose: &Pose) -> Self {
        Self::new(pose.rotation.as_dquat(), pose.translation.as_dvec3())
    }

    pub fn to_pose(&self) -> Pose {
        Pose::new(self.rotation.as_quat(), self.translation.as_vec3())
    }

    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        Self {
            rotation,
            translation: -(rotation * self.translation),
        }
    }

    pub fn transform_point(&self, point: DVec3) -> DVec3 {
        self.rotation * point + self.translation
    }

    pub fn transform_vector(&self, vector: DVec3) -> DVec3 {
        self.rotation * vector
    }

    /// Angle of the rotation between two poses' orientations, radians in [0, π].
    pub fn angle_to(&self, other: &DPose) -> f64 {
        rotation_angle(self.rotation.inverse() * other.rotation)
    }
}

/// `a_from_c = a_from_b * b_from_c`.
impl Mul for DPose {
    type Output = DPose;
    fn mul(self, rhs: DPose) -> DPose {
        DPose::new(
            self.rotation * rhs.rotation,
            self.rotation * rhs.translation + self.translation,
        )
    }
}

/// Angle of a rotation, radians in [0, π], accurate near zero.
pub fn rotation_angle(rotation: DQuat) -> f64 {
    2.0 * rotation.xyz().length().atan2(rotation.w.abs())
}

/// relight's glTF camera frame from the OpenCV optical frame: 180° about X (its own inverse).
pub const CAMERA_FROM_OPTICAL: DPose = DPose {
    rotation: DQuat::from_xyzw(1.0, 0.0, 0.0, 0.0),
    translation: DVec3::ZERO,
};

/// The corners of a square tag of edge `size_m` in its marker frame (origin at the centre, +y up
/// as printed), in [`MarkerDetection`] order: lower-left, lower-right, upper-right, upper-left
/// as printed, i.e. counter-clockwise seen from the front.
pub fn square_corners_in_marker(size_m: f64) -> [DVec3; 4] {
    let s = size_m / 2.0;
    [
        DVec3::new(-s, -s, 0.0),
        DVec3::new(s, -s, 0.0),
        DVec3::new(s, s, 0.0),
        DVec3::new(-s, s, 0.0),
    ]
}

/// How poses are fitted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PoseSettings {
    /// Corner noise assumed at least, pixels (1 σ per coordinate); the floor of the noise used
    /// for the covariance. Sub-pixel corner detectors reach 0.05–0.3 px on sharp images.
    pub corner_sigma_px: f64,
    /// Levenberg–Marquardt iterations at most.
    pub max_iterations: u32,
}

impl Default for PoseSettings {
    fn default() -> Self {
        Self {
            corner_sigma_px: 0.2,
            max_iterations: 50,
        }
    }
}

/// A fitted pose with its quality.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseFit {
    /// The target in the OpenCV optical frame of the camera.
    pub optical_from_object: DPose,
    /// RMS distance between the observed and reprojected pixels.
    pub reprojection_rms_px: f64,
    /// RMS of the other planar solution after refinement (`None` when it did not converge to a
    /// pose in front of the camera). Close to `reprojection_rms_px` means the choice between
    /// the two is uncertain.
    pub alternative_rms_px: Option<f64>,
    /// Covariance of (rotation vector of a left perturbation, radians; translation, metres),
    /// both in the optical frame: `optical_from_object = (exp(ω) R, t + τ)`.
    pub covariance: [[f64; 6]; 6],
    /// Noise per corner coordinate the covariance was scaled with, pixels.
    pub sigma_px: f64,
    /// Correspondences used.
    pub points: usize,
}

impl PoseFit {
    /// The target in relight's camera frame (glTF convention), as in
    /// [`MarkerDetection::camera_from_marker`].
    pub fn camera_from_object(&self) -> DPose {
        CAMERA_FROM_OPTICAL * self.optical_from_object
    }

    /// 1-σ error of the translation (square root of the covariance's trace), metres.
    pub fn translation_sigma_m(&self) -> f64 {
        (self.covariance[3][3] + self.covariance[4][4] + self.covariance[5][5])
            .max(0.0)
            .sqrt()
    }

    /// 1-σ error of the rotation angle (square root of the covariance's trace), degrees.
    pub fn rotation_sigma_deg(&self) -> f64 {
        (self.covariance[0][0] + self.covariance[1][1] + self.covariance[2][2])
            .max(0.0)
            .sqrt()
            .to_degrees()
    }

    /// The detection of a marker with this pose.
    pub fn detection(
        &self,
        family: &str,
        marker_id: u32,
        corners_px: [Vec2; 4],
    ) -> MarkerDetection {
        MarkerDetection {
            family: family.to_owned(),
            marker_id,
            corners_px,
            camera_from_marker: self.camera_from_object().to_pose(),
            reprojection_rms_px: self.reprojection_rms_px as f32,
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("a pose needs at least {needed} correspondences, got {got}")]
    TooFewPoints { needed: usize, got: usize },
    #[error("{points} object points but {pixels} pixels")]
    LengthMismatch { points: usize, pixels: usize },
    #[error("object points or pixels are not finite")]
    NonFinite,
    #[error("object point {index} is off the target's z = 0 plane (z = {z} m)")]
    NotPlanar { index: usize, z: f64 },
    #[error("pixel ({x}, {y}) has no ray in front of the camera", x = pixel.x, y = pixel.y)]
    NoRay { pixel: DVec2 },
    #[error(
        "corners are not a convex quadrilateral running counter-clockwise on screen \
         (a tag seen from its front)"
    )]
    NotAQuad,
    #[error("degenerate correspondences: {0}")]
    Degenerate(&'static str),
    #[error("no pose puts every point in front of the camera")]
    NoSolution,
}

/// The pose of a square tag of edge `size_m` from its corners in [`MarkerDetection`] order.
/// The corners must form a convex quadrilateral that runs counter-clockwise on screen (rows
/// growing downwards), as the front of a tag does.
pub fn estimate_square_pose(
    corners_px: &[DVec2; 4],
    size_m: f64,
    camera: &CameraModel,
    settings: &PoseSettings,
) -> Result<PoseFit, PoseError> {
    if !corners_px.iter().all(|c| c.is_finite()) {
        return Err(PoseError::NonFinite);
    }
    if !is_front_facing_quad(corners_px) {
        return Err(PoseError::NotAQuad);
    }
    estimate_planar_pose(
        &square_corners_in_marker(size_m),
        corners_px,
        camera,
        settings,
    )
}

/// The pose of a planar target from `points_in_object` (all on the object's z = 0 plane, at
/// least 4, no 3 collinear) seen at `pixels`: IPPE, then both candidates refined, the better kept.
pub fn estimate_planar_pose(
    points_in_object: &[DVec3],
    pixels: &[DVec2],
    camera: &CameraModel,
    settings: &PoseSettings,
) -> Result<PoseFit, PoseError> {
    check_input(points_in_object, pixels, 4)?;
    let scale = points_in_object
        .iter()
        .map(|p| p.truncate().length())
        .fold(0.0, f64::max);
    if let Some((index, p)) = points_in_object
        .iter()
        .enumerate()
        .find(|(_, p)| p.z.abs() > 1e-9 * scale.max(1e-9))
    {
        return Err(PoseError::NotPlanar { index, z: p.z });
    }
    let normalized = pixels
        .iter()
        .map(|&pixel| normalized_point(camera, pixel))
        .collect::<Result<Vec<_>, _>>()?;
    let object_xy: Vec<DVec2> = points_in_object.iter().map(|p| p.truncate()).collect();
    let candidates = ippe(&object_xy, &normalized)?;
    let mut fits: Vec<PoseFit> = candidates
        .iter()
        .filter_map(|initial| refine_pose(initial, points_in_object, pixels, camera, settings).ok())
        .collect();
    fits.sort_by(|a, b| a.reprojection_rms_px.total_cmp(&b.reprojection_rms_px));
    let alternative = fits.get(1).map(|fit| fit.reprojection_rms_px);
    let mut best = *fits.first().ok_or(PoseError::NoSolution)?;
    best.alternative_rms_px = alternative;
    Ok(best)
}

/// Refines `initial` (optical frame) by Levenberg–Marquardt on the pixel reprojection error of
/// any rigid set of `points_in_object` (planar or not) and returns it with its covariance.
pub fn refine_pose(
    initial: &DPose,
    points_in_object: &[DVec3],
    pixels: &[DVec2],
    camera: &CameraModel,
    settings: &PoseSettings,
) -> Result<PoseFit, PoseError> {
    check_input(points_in_object, pixels, 3)?;
    let problem = Problem {
        points: points_in_object,
        pixels,
        camera,
    };
    let mut pose = *initial;
    let mut system = problem
        .normal_equations(&pose)
        .ok_or(PoseError::NoSolution)?;
    let mut lambda = 1e-3;
    for _ in 0..settings.max_iterations {
        let mut damped = system.jtj;
        for (k, row) in damped.iter_mut().enumerate() {
            row[k] += lambda * system.jtj[k][k].max(1e-12);
        }
        let Some(step) = solve(damped, system.jtr.map(|g| -g)) else {
            lambda *= 10.0;
            continue;
        };
        let candidate = DPose::new(
            DQuat::from_scaled_axis(DVec3::new(step[0], step[1], step[2])) * pose.rotation,
            pose.translation + DVec3::new(step[3], step[4], step[5]),
        );
        match problem.normal_equations(&candidate) {
            Some(next) if next.cost < system.cost => {
                let small = step[..3].iter().all(|w| w.abs() < 1e-12)
                    && step[3..]
                        .iter()
                        .all(|t| t.abs() < 1e-12 * pose.translation.length().max(1e-3));
                let stalled = system.cost - next.cost <= 1e-15 * system.cost;
                pose = candidate;
                system = next;
                lambda = (lambda / 10.0).max(1e-12);
                if small || stalled {
                    break;
                }
            }
            _ => {
                lambda *= 10.0;
                if lambda > 1e12 {
                    break;
                }
            }
        }
    }
    let n = pixels.len();
    let dof = 2 * n as i64 - 6;
    let residual_sigma = if dof > 0 {
        (system.cost / dof as f64).sqrt()
    } else {
        0.0
    };
    let sigma_px = residual_sigma.max(settings.corner_sigma_px);
    let covariance = invert(system.jtj)
        .ok_or(PoseError::Degenerate(
            "the reprojection error does not constrain every pose parameter",
        ))?
        .map(|row| row.map(|v| v * sigma_px * sigma_px));
    Ok(PoseFit {
        optical_from_object: pose,
        reprojection_rms_px: (system.cost / n as f64).sqrt(),
        alternative_rms_px: None,
        covariance,
        sigma_px,
        points: n,
    })
}

/// Convex and counter-clockwise on screen: in image coordinates (y down) every turn between
/// consecutive edges is negative, by more than rounding.
fn is_front_facing_quad(corners: &[DVec2; 4]) -> bool {
    let scale = (corners[2] - corners[0])
        .length()
        .max((corners[3] - corners[1]).length());
    (0..4).all(|i| {
        let a = corners[(i + 1) % 4] - corners[i];
        let b = corners[(i + 2) % 4] - corners[(i + 1) % 4];
        a.perp_dot(b) < -1e-9 * scale * scale
    })
}

fn check_input(points: &[DVec3], pixels: &[DVec2], needed: usize) -> Result<(), PoseError> {
    if points.len() != pixels.len() {
        return Err(PoseError::LengthMismatch {
            points: points.len(),
            pixels: pixels.len(),
        });
    }
    if points.len() < needed {
        return Err(PoseError::TooFewPoints {
            needed,
            got: points.len(),
        });
    }
    if !(points.iter().all(|p| p.is_finite()) && pixels.iter().all(|p| p.is_finite())) {
        return Err(PoseError::NonFinite);
    }
    Ok(())
}

/// Undistorted normalised coordinates `(X/Z, Y/Z)` of a pixel.
fn normalized_point(camera: &CameraModel, pixel: DVec2) -> Result<DVec2, PoseError> {
    camera
        .unproject(pixel)
        .filter(|ray| ray.z > 1e-6)
        .map(|ray| ray.truncate() / ray.z)
        .ok_or(PoseError::NoRay { pixel })
}

/// The two IPPE poses (optical frame) of planar points `object_xy` (on z = 0) seen at undistorted
/// normalised coordinates (Collins & Bartoli 2014, §4: the rotation from the homography's
/// Jacobian at the points' centroid; §5: the translation by linear least squares).
pub fn ippe(object_xy: &[DVec2], normalized: &[DVec2]) -> Result<[DPose; 2], PoseError> {
    if object_xy.len() != normalized.len() {
        return Err(PoseError::LengthMismatch {
            points: object_xy.len(),
            pixels: normalized.len(),
        });
    }
    if object_xy.len() < 4 {
        return Err(PoseError::TooFewPoints {
            needed: 4,
            got: object_xy.len(),
        });
    }
    // Centre the object points: IPPE's Jacobian is taken at the origin of the plane.
    let centroid = object_xy.iter().sum::<DVec2>() / object_xy.len() as f64;
    let centred: Vec<DVec2> = object_xy.iter().map(|p| *p - centroid).collect();
    let h = homography(&centred, normalized).ok_or(PoseError::Degenerate(
        "no homography: fewer than 4 points in general position",
    ))?;
    let h = h * (1.0 / h.z_axis.z);
    // Row r, column c of H.
    let at = |r: usize, c: usize| h.col(c)[r];
    let v = DVec2::new(at(0, 2), at(1, 2));
    let jacobian = [
        [at(0, 0) - at(2, 0) * v.x, at(0, 1) - at(2, 1) * v.x],
        [at(1, 0) - at(2, 0) * v.y, at(1, 1) - at(2, 1) * v.y],
    ];
    // Rv turns the optical axis onto the ray through the centroid's image.
    let rv = DMat3::from_quat(DQuat::from_rotation_arc(
        DVec3::Z,
        v.extend(1.0).normalize(),
    ));
    let rv_at = |r: usize, c: usize| rv.col(c)[r];
    // B = [I₂ | −v] Rv[:, 0..2]; A = B⁻¹ J.
    let b = [
        [
            rv_at(0, 0) - v.x * rv_at(2, 0),
            rv_at(0, 1) - v.x * rv_at(2, 1),
        ],
        [
            rv_at(1, 0) - v.y * rv_at(2, 0),
            rv_at(1, 1) - v.y * rv_at(2, 1),
        ],
    ];
    let det_b = b[0][0] * b[1][1] - b[0][1] * b[1][0];
    if det_b.abs() < 1e-15 {
        return Err(PoseError::Degenerate(
            "centroid ray parallel to the image plane",
        ));
    }
    let b_inv = [
        [b[1][1] / det_b, -b[0][1] / det_b],
        [-b[1][0] / det_b, b[0][0] / det_b],
    ];
    let a = [
        [
            b_inv[0][0] * jacobian[0][0] + b_inv[0][1] * jacobian[1][0],
            b_inv[0][0] * jacobian[0][1] + b_inv[0][1] * jacobian[1][1],
        ],
        [
            b_inv[1][0] * jacobian[0][0] + b_inv[1][1] * jacobian[1][0],
            b_inv[1][0] * jacobian[0][1] + b_inv[1][1] * jacobian[1][1],
        ],
    ];
    // γ: the largest singular value of A (largest eigenvalue of A Aᵀ).
    let aat00 = a[0][0] * a[0][0] + a[0][1] * a[0][1];
    let aat01 = a[0][0] * a[1][0] + a[0][1] * a[1][1];
    let aat11 = a[1][0] * a[1][0] + a[1][1] * a[1][1];
    let gamma =
        (0.5 * (aat00 + aat11 + ((aat00 - aat11).powi(2) + 4.0 * aat01 * aat01).sqrt())).sqrt();
    if !(gamma.is_finite() && gamma > 1e-12) {
        return Err(PoseError::Degenerate("the homography has no scale"));
    }
    let r = a.map(|row| row.map(|x| x / gamma));
    let b0 = (1.0 - r[0][0] * r[0][0] - r[1][0] * r[1][0])
        .max(0.0)
        .sqrt();
    let mut b1 = (1.0 - r[0][1] * r[0][1] - r[1][1] * r[1][1])
        .max(0.0)
        .sqrt();
    // Columns of a rotation are orthogonal: b0 b1 = −(r̃₁ · r̃₂).
    if -(r[0][0] * r[0][1] + r[1][0] * r[1][1]) < 0.0 {
        b1 = -b1;
    }
    let candidate = |sign: f64| -> Result<DPose, PoseError> {
        let c1 = DVec3::new(r[0][0], r[1][0], sign * b0);
        let c2 = DVec3::new(r[0][1], r[1][1], sign * b1);
        let rotation = orthonormalize(rv * DMat3::from_cols(c1, c2, c1.cross(c2)));
        let translation = ippe_translation(&rotation, &centred, normalized)?;
        // Undo the centring: p_centred = p − c.
        let centroid_3d = centroid.extend(0.0);
        Ok(DPose::new(
            DQuat::from_mat3(&rotation),
            translation - rotation * centroid_3d,
        ))
    };
    Ok([candidate(1.0)?, candidate(-1.0)?])
}

/// IPPE's translation for a known rotation: linear least squares of the cross-multiplied
/// projection equations `t_x − u t_z = u (R p)_z − (R p)_x` (and likewise for y).
fn ippe_translation(
    rotation: &DMat3,
    object_xy: &[DVec2],
    normalized: &[DVec2],
) -> Result<DVec3, PoseError> {
    let mut ata = [[0.0; 3]; 3];
    let mut atb = [0.0; 3];
    for (p, m) in object_xy.iter().zip(normalized) {
        let q = *rotation * p.extend(0.0);
        for (row, rhs) in [
            ([1.0, 0.0, -m.x], m.x * q.z - q.x),
            ([0.0, 1.0, -m.y], m.y * q.z - q.y),
        ] {
            for i in 0..3 {
                for j in 0..3 {
                    ata[i][j] += row[i] * row[j];
                }
                atb[i] += row[i] * rhs;
            }
        }
    }
    solve(ata, atb)
        .map(DVec3::from_array)
        .ok_or(PoseError::Degenerate("translation undetermined"))
}

/// The nearest rotation by Gram–Schmidt on the first two columns (IPPE's matrices are rotations
/// up to rounding).
fn orthonormalize(m: DMat3) -> DMat3 {
    let x = m.x_axis.normalize();
    let y = (m.y_axis - x * x.dot(m.y_axis)).normalize();
    DMat3::from_cols(x, y, x.cross(y))
}

/// The homography taking plane points `from` to `to` (≥ 4 correspondences), by the normalised
/// DLT (Hartley & Zisserman 2nd ed., Algorithm 4.2) with `h₃₃ = 1`; `None` when degenerate.
pub fn homography(from: &[DVec2], to: &[DVec2]) -> Option<DMat3> {
    if from.len() != to.len() || from.len() < 4 {
        return None;
    }
    let t_from = normalizing_similarity(from)?;
    let t_to = normalizing_similarity(to)?;
    let mut ata = [[0.0; 8]; 8];
    let mut atb = [0.0; 8];
    for (p, q) in from.iter().zip(to) {
        let p = t_from.transform_point2(*p);
        let q = t_to.transform_point2(*q);
        for (row, rhs) in [
            ([p.x, p.y, 1.0, 0.0, 0.0, 0.0, -q.x * p.x, -q.x * p.y], q.x),
            ([0.0, 0.0, 0.0, p.x, p.y, 1.0, -q.y * p.x, -q.y * p.y], q.y),
        ] {
            for i in 0..8 {
                for j in 0..8 {
                    ata[i][j] += row[i] * row[j];
                }
                atb[i] += row[i] * rhs;
            }
        }
    }
    let h = solve(ata, atb)?;
    let normalized = DMat3::from_cols(
        DVec3::new(h[0], h[3], h[6]),
        DVec3::new(h[1], h[4], h[7]),
        DVec3::new(h[2], h[5], 1.0),
    );
    let result = t_to.inverse() * normalized * t_from;
    result.is_finite().then_some(result)
}

/// Translate to the centroid and scale to mean distance √2 (Hartley's normalisation).
fn normalizing_similarity(points: &[DVec2]) -> Option<DMat3> {
    let centroid = points.iter().sum::<DVec2>() / points.len() as f64;
    let mean_distance =
        points.iter().map(|p| p.distance(centroid)).sum::<f64>() / points.len() as f64;
    if !(mean_distance.is_finite() && mean_distance > 0.0) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_distance;
    Some(DMat3::from_cols(
        DVec3::new(s, 0.0, 0.0),
        DVec3::new(0.0, s, 0.0),
        DVec3::new(-s * centroid.x, -s * centroid.y, 1.0),
    ))
}

/// The least-squares problem of [`refine_pose`].
struct Problem<'a> {
    points: &'a [DVec3],
    pixels: &'a [DVec2],
    camera: &'a CameraModel,
}

/// `JᵀJ`, `Jᵀr` and the cost `Σ r²` at one pose.
struct NormalEquations {
    jtj: [[f64; 6]; 6],
    jtr: [f64; 6],
    cost: f64,
}

impl Problem<'_> {
    /// `None` when a point leaves the camera's valid field.
    fn normal_equations(&self, pose: &DPose) -> Option<NormalEquations> {
        let mut jtj = [[0.0; 6]; 6];
        let mut jtr = [0.0; 6];
        let mut cost = 0.0;
        for (point, observed) in self.points.iter().zip(self.pixels) {
            let rotated = pose.rotation * *point;
            let in_camera = rotated + pose.translation;
            let residual = self.camera.project(in_camera)? - *observed;
            let d_pixel = self.projection_jacobian(in_camera)?;
            // ∂X/∂ω_k = e_k × (R p) for X = exp(ω) R p + t; ∂X/∂τ_k = e_k.
            let mut rows = [[0.0; 6]; 2];
            for k in 0..3 {
                let axis = DVec3::AXES[k];
                let dx_dw = axis.cross(rotated);
                for (r, row) in rows.iter_mut().enumerate() {
                    row[k] = d_pixel[r].dot(dx_dw);
                    row[k + 3] = d_pixel[r][k];
                }
            }
            for (row, r) in rows.iter().zip([residual.x, residual.y]) {
                for i in 0..6 {
                    for j in 0..6 {
                        jtj[i][j] += row[i] * row[j];
                    }
                    jtr[i] += row[i] * r;
                }
                cost += r * r;
            }
        }
        cost.is_finite()
            .then_some(NormalEquations { jtj, jtr, cost })
    }

    /// ∂pixel/∂X (rows u, v) by central differences through the full camera model; the step is
    /// relative to the point's distance, so the truncation error stays ~1e-12 of the value.
    fn projection_jacobian(&self, point: DVec3) -> Option<[DVec3; 2]> {
        let h = 1e-6 * point.length().max(1e-3);
        let mut columns = [DVec2::ZERO; 3];
        for (k, column) in columns.iter_mut().enumerate() {
            let step = DVec3::AXES[k] * h;
            let plus = self.camera.project(point + step)?;
            let minus = self.camera.project(point - step)?;
            *column = (plus - minus) / (2.0 * h);
        }
        Some([
            DVec3::new(columns[0].x, columns[1].x, columns[2].x),
            DVec3::new(columns[0].y, columns[1].y, columns[2].y),
        ])
    }
}

/// Solves `a x = b` by Gaussian elimination with partial pivoting; `None` when `a` is singular
/// to working precision.
pub(crate) fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    let scale = a
        .iter()
        .flat_map(|row| row.iter())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    for col in 0..N {
        let pivot = (col..N).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() <= 1e-14 * scale {
            return None;
        }
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..N {
            let f = a[row][col] / a[col][col];
            if f == 0.0 {
                continue;
            }
            let pivot_row = a[col];
            for (value, pivot_value) in a[row].iter_mut().zip(pivot_row).skip(col) {
                *value -= f * pivot_value;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let tail: f64 = (row + 1..N).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - tail) / a[row][row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Inverse of a square matrix, column by column with [`solve`].
fn invert<const N: usize>(a: [[f64; N]; N]) -> Option<[[f64; N]; N]> {
    let mut inverse = [[0.0; N]; N];
    for col in 0..N {
        let mut unit = [0.0; N];
        unit[col] = 1.0;
        let x = solve(a, unit)?;
        for row in 0..N {
            inverse[row][col] = x[row];
        }
    }
    Some(inverse)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rand_pcg::Pcg64Mcg;
    use relight_core::camera::{KannalaBrandt, Pinhole};

    fn distorted_pinhole() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 640,
            height: 480,
            fx: 520.0,
            fy: 518.0,
            cx: 322.0,
            cy: 236.0,
            k1: 0.12,
            k2: -0.25,
            p1: 5e-4,
            p2: -3e-4,
            k3: 0.1,
        })
    }

    fn fisheye() -> CameraModel {
        CameraModel::KannalaBrandt(KannalaBrandt {
            width: 640,
            height: 480,
            fx: 230.0,
            fy: 230.0,
            cx: 319.5,
            cy: 239.5,
            k1: -0.02,
            k2: 0.004,
            k3: -0.001,
            k4: 0.0002,
        })
    }

    /// A marker at `distance_m` in front of the camera (glTF frame), tilted about an in-plane
    /// axis, offset sideways.
    fn camera_from_marker(distance_m: f64, tilt_deg: f64, axis_deg: f64, offset: DVec2) -> DPose {
        let axis = DVec3::new(
            axis_deg.to_radians().cos(),
            axis_deg.to_radians().sin(),
            0.0,
        );
        DPose::new(
            DQuat::from_axis_angle(axis, tilt_deg.to_radians()) * DQuat::from_rotation_z(0.4),
            DVec3::new(offset.x, offset.y, -distance_m),
        )
    }

    fn project_all(
        camera: &CameraModel,
        camera_from_object: &DPose,
        points: &[DVec3],
    ) -> Vec<DVec2> {
        let optical_from_object = CAMERA_FROM_OPTICAL * *camera_from_object;
        points
            .iter()
            .map(|p| {
                camera
                    .project(optical_from_object.transform_point(*p))
                    .expect("test point projects")
            })
            .collect()
    }

    #[test]
    fn exact_corners_give_the_exact_pose_through_distortion() {
        let corners = square_corners_in_marker(0.12);
        for camera in [distorted_pinhole(), fisheye()] {
            for (distance, tilt, axis) in [(0.5, 0.0, 0.0), (1.0, 35.0, 20.0), (2.0, 60.0, 100.0)] {
                let truth = camera_from_marker(distance, tilt, axis, DVec2::new(0.08, -0.05));
                let pixels: [DVec2; 4] = project_all(&camera, &truth, &corners).try_into().unwrap();
                let fit =
                    estimate_square_pose(&pixels, 0.12, &camera, &PoseSettings::default()).unwrap();
                let estimate = fit.camera_from_object();
                assert!(
                    estimate.translation.distance(truth.translation) < 1e-9,
                    "{camera:?} {distance} {tilt}: {estimate:?} vs {truth:?}"
                );
                assert!(estimate.angle_to(&truth) < 1e-9);
                assert!(fit.reprojection_rms_px < 1e-8);
            }
        }
    }

    #[test]
    fn a_tag_facing_the_camera_upright_has_identity_rotation() {
        // glTF camera frame: the tag 1 m ahead (−Z), its +z (out of the print) towards the
        // camera (+Z), its +y up like the camera's.
        let camera = distorted_pinhole();
        let truth = DPose::new(DQuat::IDENTITY, DVec3::new(0.0, 0.0, -1.0));
        let corners = square_corners_in_marker(0.1);
        let pixels: [DVec2; 4] = project_all(&camera, &truth, &corners).try_into().unwrap();
        // Lower-left as printed is left of and below the image centre (larger row).
        let centre = camera.project(DVec3::Z).unwrap();
        assert!(pixels[0].x < centre.x && pixels[0].y > centre.y);
        assert!(pixels[2].x > centre.x && pixels[2].y < centre.y);
        let fit = estimate_square_pose(&pixels, 0.1, &camera, &PoseSettings::default()).unwrap();
        let pose = fit.camera_from_object().to_pose();
        assert!(pose.rotation.angle_between(glam::Quat::IDENTITY) < 1e-5);
        assert!((pose.translation - glam::Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
    }

    #[test]
    fn the_planar_ambiguity_yields_both_mirror_poses() {
        // Without noise IPPE's two rotations are the true one and its mirror about the line of
        // sight; the true one reprojects exactly, the other does not.
        let camera = distorted_pinhole();
        let truth = camera_from_marker(1.0, 40.0, 30.0, DVec2::ZERO);
        let corners = square_corners_in_marker(0.12);
        let pixels = project_all(&camera, &truth, &corners);
        let normalized: Vec<DVec2> = pixels
            .iter()
            .map(|p| normalized_point(&camera, *p).unwrap())
            .collect();
        let xy: Vec<DVec2> = corners.iter().map(|c| c.truncate()).collect();
        let [a, b] = ippe(&xy, &normalized).unwrap();
        let optical_truth = CAMERA_FROM_OPTICAL * truth;
        let (near, far) = if a.angle_to(&optical_truth) < b.angle_to(&optical_truth) {
            (a, b)
        } else {
            (b, a)
        };
        assert!(near.angle_to(&optical_truth) < 1e-9);
        assert!(far.angle_to(&optical_truth) > 10f64.to_radians());
        let fit = estimate_square_pose(
            &pixels.clone().try_into().unwrap(),
            0.12,
            &camera,
            &PoseSettings::default(),
        )
        .unwrap();
        assert!(fit.alternative_rms_px.is_some_and(|rms| rms > 0.05));
    }

    #[test]
    fn many_coplanar_points_off_centre_fit_exactly() {
        let camera = fisheye();
        // An irregular planar target whose origin is not its centroid.
        let points: Vec<DVec3> = (0..9)
            .map(|i| {
                let i = f64::from(i);
                DVec3::new(
                    0.3 + 0.05 * (i * 1.3).sin() + 0.02 * i,
                    0.1 + 0.04 * (i * 0.7).cos() * i,
                    0.0,
                )
            })
            .collect();
        let truth = camera_from_marker(1.5, 50.0, -30.0, DVec2::new(-0.3, 0.1));
        let pixels = project_all(&camera, &truth, &points);
        let fit =
            estimate_planar_pose(&points, &pixels, &camera, &PoseSettings::default()).unwrap();
        assert!(
            fit.camera_from_object()
                .translation
                .distance(truth.translation)
                < 1e-9
        );
        assert!(fit.camera_from_object().angle_to(&truth) < 1e-9);
        assert_eq!(fit.points, 9);
    }

    /// The covariance predicts the scatter of the estimate under corner noise (Monte Carlo).
    #[test]
    fn covariance_matches_monte_carlo_scatter() {
        let camera = distorted_pinhole();
        let corners = square_corners_in_marker(0.12);
        let sigma_px = 0.3;
        let settings = PoseSettings {
            corner_sigma_px: sigma_px,
            ..PoseSettings::default()
        };
        let mut rng = Pcg64Mcg::seed_from_u64(7);
        let noise = Normal::new(0.0, sigma_px).unwrap();
        for (distance, tilt) in [(0.6, 45.0), (1.2, 35.0)] {
            let truth = camera_from_marker(distance, tilt, 10.0, DVec2::new(0.05, 0.02));
            let optical_truth = CAMERA_FROM_OPTICAL * truth;
            let exact = project_all(&camera, &truth, &corners);
            let predicted =
                estimate_square_pose(&exact.clone().try_into().unwrap(), 0.12, &camera, &settings)
                    .unwrap();
            let trials = 400;
            let (mut t_sq, mut r_sq) = (0.0, 0.0);
            for _ in 0..trials {
                let noisy: Vec<DVec2> = exact
                    .iter()
                    .map(|p| *p + DVec2::new(noise.sample(&mut rng), noise.sample(&mut rng)))
                    .collect();
                let fit =
                    estimate_square_pose(&noisy.try_into().unwrap(), 0.12, &camera, &settings)
                        .unwrap();
                t_sq += fit
                    .optical_from_object
                    .translation
                    .distance_squared(optical_truth.translation);
                r_sq += fit.optical_from_object.angle_to(&optical_truth).powi(2);
            }
            let t_rms = (t_sq / f64::from(trials)).sqrt();
            let r_rms_deg = (r_sq / f64::from(trials)).sqrt().to_degrees();
            // With σ fixed at the floor (exact corners leave no residual), the prediction is the
            // linearised propagation of the injected noise; 400 trials estimate an RMS to ~4 %.
            let t_ratio = t_rms / predicted.translation_sigma_m();
            let r_ratio = r_rms_deg / predicted.rotation_sigma_deg();
            assert!((0.8..1.25).contains(&t_ratio), "translation {t_ratio}");
            assert!((0.8..1.25).contains(&r_ratio), "rotation {r_ratio}");
        }
    }

    #[test]
    fn bad_input_is_a_typed_error() {
        let camera = distorted_pinhole();
        let settings = PoseSettings::default();
        let square = square_corners_in_marker(0.1);
        let pixels = [DVec2::new(300.0, 200.0); 4];
        assert!(matches!(
            estimate_planar_pose(&square[..3], &pixels[..3], &camera, &settings),
            Err(PoseError::TooFewPoints { .. })
        ));
        assert!(matches!(
            estimate_planar_pose(&square, &pixels[..3], &camera, &settings),
            Err(PoseError::LengthMismatch { .. })
        ));
        assert_eq!(
            estimate_square_pose(&pixels, 0.1, &camera, &settings),
            Err(PoseError::NotAQuad)
        );
        let mut nan = pixels;
        nan[1].x = f64::NAN;
        assert_eq!(
            estimate_square_pose(&nan, 0.1, &camera, &settings).unwrap_err(),
            PoseError::NonFinite
        );
        let mut lifted = square;
        lifted[2].z = 0.01;
        assert!(matches!(
            estimate_planar_pose(&lifted, &pixels, &camera, &settings),
            Err(PoseError::NotPlanar { index: 2, .. })
        ));
        let collinear = [
            DVec2::new(100.0, 100.0),
            DVec2::new(200.0, 100.0),
            DVec2::new(300.0, 100.0),
            DVec2::new(400.0, 100.0),
        ];
        assert_eq!(
            estimate_square_pose(&collinear, 0.1, &camera, &settings),
            Err(PoseError::NotAQuad)
        );
        // A tag seen from behind runs clockwise on screen.
        let truth = DPose::new(DQuat::from_rotation_y(3.0), DVec3::new(0.0, 0.0, -1.0));
        let mirrored: [DVec2; 4] = project_all(&camera, &truth, &square).try_into().unwrap();
        assert_eq!(
            estimate_square_pose(&mirrored, 0.1, &camera, &settings),
            Err(PoseError::NotAQuad)
        );
        // Points all at one pixel are no homography.
        assert!(matches!(
            estimate_planar_pose(&square, &pixels, &camera, &settings),
            Err(PoseError::Degenerate(_))
        ));
    }

    #[test]
    fn solver_handles_pivoting_and_singularity() {
        let x = solve([[0.0, 2.0], [3.0, 1.0]], [4.0, 5.0]).unwrap();
        assert!((x[0] - 1.0).abs() < 1e-15 && (x[1] - 2.0).abs() < 1e-15);
        assert!(solve([[1.0, 2.0], [2.0, 4.0]], [1.0, 2.0]).is_none());
        let inverse = invert([[4.0, 7.0], [2.0, 6.0]]).unwrap();
        assert!((inverse[0][0] - 0.6).abs() < 1e-15 && (inverse[1][0] + 0.2).abs() < 1e-15);
    }
}
