//! The rig's extrinsics: depth ↔ colour registration, the light probe's pose in the world, and
//! the lamp's light centre in its marker's frame.
//!
//! # Conventions
//!
//! OpenCV's poses are between *optical* frames (+Y down, +Z forward); relight's
//! [`relight_core::rig::RigCalibration`] stores them between glTF camera frames (+Y up, −Z
//! forward), see [`crate::rigid`]. The world is relight's board frame of the target
//! ([`TargetGeometry::world_from_target`]: origin at the pattern's centre, +Y up and +Z out of the
//! print), so a target lying on the table defines a world with +Z up out of the table. A lamp's
//! marker frame is relight's marker frame (origin at the marker's centre, +X right, +Y up as
//! printed, +Z out of the print), as `relight-backends`' trackers report it.
//!
//! # Methods
//!
//! - **Depth ↔ colour** ([`calibrate_color_from_depth`]): `cv::stereoCalibrate` with both
//!   cameras' intrinsics fixed (`CALIB_FIX_INTRINSIC`) on views of one target seen by both at
//!   once; for a Kinect-class sensor the depth camera's image is its IR image (the projector
//!   covered, the scene lit by an IR-rich lamp), whose pixels are the depth image's.
//! - **Probe in the world** ([`locate_probe`]): the target that defines the world, seen by the
//!   fixed probe; its pose from all points of all such views at once: OpenCV's `solvePnP` on the
//!   probe's undistorted rays for a start, then Levenberg–Marquardt on the pixel residuals
//!   through relight's own camera model ([`estimate_pose`]), which works for any field of view.
//! - **Lamp light centre** ([`locate_lamp_light`]): what a lab can do with the lamp in a hand.
//!   With the colour camera still and its exposure short enough that the bulb (or the lamp's
//!   diffuser) is a compact bright blob and the marker's white is not clipped, hold the lamp, lit,
//!   in eight or more poses, turning it by 30° or more between them about different axes so that
//!   marker and bulb stay in view. Each image gives the marker's pose and, from the blob's
//!   centroid, a ray from the camera through the light centre. Expressed in the marker's frame,
//!   where the light centre `p` is fixed, the rays all pass through `p`; it is their
//!   least-squares intersection, `Σ (I − dᵢdᵢᵀ) p = Σ (I − dᵢdᵢᵀ) oᵢ` (origins `oᵢ`, unit
//!   directions `dᵢ`). The turns are what fixes `p` along the rays; without them the system is
//!   singular, which is reported rather than solved.

use glam::{DQuat, DVec2, DVec3};
use opencv::calib3d;
use opencv::core::{Mat, Point2d, Point2f, Point3d, Point3f, Size, Vector};
use opencv::prelude::*;
use relight_core::camera::{CameraModel, Pinhole};
use relight_core::{Image, Pose};
use serde::{Deserialize, Serialize};

use crate::detect::{Detection, detect_markers, luma};
use crate::error::CalibrationError;
use crate::intrinsics::{criteria, mat_values};
use crate::linalg::{solve, symmetric_eigenvalues_3};
use crate::rigid::{Rigid, frame_from_camera_gl, gl_from_optical_pair};
use crate::target::{Dictionary, TargetGeometry};

/// A target's pose fitted to one camera's points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseFit {
    /// Optical frame.
    pub camera_from_target: Rigid,
    pub rms_px: f64,
    pub points: usize,
}

/// The pose of a set of target points seen by `camera`, for any camera model: OpenCV's
/// `solvePnP` (IPPE for a planar target, else iterative) on the points' undistorted rays for a
/// start, then Levenberg–Marquardt on the pixel residuals through `camera.project`.
pub fn estimate_pose(
    camera: &CameraModel,
    object_points: &[DVec3],
    image_points: &[DVec2],
) -> Result<PoseFit, CalibrationError> {
    let mut object = Vector::<Point3d>::new();
    let mut normalized = Vector::<Point2d>::new();
    for (p, pixel) in object_points.iter().zip(image_points) {
        // Rays more than ~84° off the axis make the normalised plane a poor place to start.
        if let Some(ray) = camera.unproject(*pixel).filter(|r| r.z > 0.1) {
            object.push(Point3d::new(p.x, p.y, p.z));
            normalized.push(Point2d::new(ray.x / ray.z, ray.y / ray.z));
        }
    }
    if object.len() < 4 {
        return Err(CalibrationError::TooFewCorners {
            view: "pose".into(),
            found: object.len(),
            minimum: 4,
        });
    }
    let planar = object_points.iter().all(|p| p.z.abs() < 1e-9);
    let identity = Mat::from_slice_2d(&[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
    let no_distortion = Mat::default();
    let mut rvec = Mat::default();
    let mut tvec = Mat::default();
    let method = if planar {
        calib3d::SOLVEPNP_IPPE
    } else {
        calib3d::SOLVEPNP_ITERATIVE
    };
    let solved = calib3d::solve_pnp(
        &object,
        &normalized,
        &identity,
        &no_distortion,
        &mut rvec,
        &mut tvec,
        false,
        method,
    )?;
    if !solved {
        return Err(CalibrationError::IllConditioned {
            what: "target pose".into(),
            hint: "solvePnP found no pose; are the points collinear?".into(),
        });
    }
    let r = mat_values(&rvec)?;
    let t = mat_values(&tvec)?;
    if r.len() != 3 || t.len() != 3 {
        return Err(CalibrationError::Diverged(
            "solvePnP returned no pose".into(),
        ));
    }
    let start = Rigid::from_rvec_tvec([r[0], r[1], r[2]], [t[0], t[1], t[2]]);
    let camera_from_target = refine_pose(camera, object_points, image_points, start);
    let rms_px = pose_rms_px(camera, object_points, image_points, &camera_from_target);
    if !rms_px.is_finite() {
        return Err(CalibrationError::Diverged(
            "a target point projects outside the camera's field at the fitted pose".into(),
        ));
    }
    Ok(PoseFit {
        camera_from_target,
        rms_px,
        points: object_points.len(),
    })
}

fn pose_rms_px(
    camera: &CameraModel,
    object_points: &[DVec3],
    image_points: &[DVec2],
    pose: &Rigid,
) -> f64 {
    let sum_sq: f64 = object_points
        .iter()
        .zip(image_points)
        .map(|(p, pixel)| {
            camera
                .project(pose.transform_point(*p))
                .map_or(f64::INFINITY, |q| q.distance_squared(*pixel))
        })
        .sum();
    (sum_sq / object_points.len().max(1) as f64).sqrt()
}

/// Levenberg–Marquardt on `Σ |project(pose · P) − p|²` over the pose (rotation-vector increment
/// and translation), numeric Jacobian.
fn refine_pose(
    camera: &CameraModel,
    object_points: &[DVec3],
    image_points: &[DVec2],
    start: Rigid,
) -> Rigid {
    const H: f64 = 1e-7;
    let cost = |pose: &Rigid| {
        let rms = pose_rms_px(camera, object_points, image_points, pose);
        rms * rms
    };
    let perturb = |pose: &Rigid, delta: &[f64; 6]| {
        Rigid::new(
            DQuat::from_scaled_axis(DVec3::new(delta[0], delta[1], delta[2])) * pose.rotation,
            pose.translation + DVec3::new(delta[3], delta[4], delta[5]),
        )
    };
    let mut pose = start;
    let mut current = cost(&pose);
    let mut lambda = 1e-3;
    for _ in 0..50 {
        let mut normal = [[0.0; 6]; 6];
        let mut rhs = [0.0; 6];
        for (p, pixel) in object_points.iter().zip(image_points) {
            let Some(base) = camera.project(pose.transform_point(*p)) else {
                continue;
            };
            let mut jacobian = [DVec2::ZERO; 6];
            let mut usable = true;
            for (k, column) in jacobian.iter_mut().enumerate() {
                let mut delta = [0.0; 6];
                delta[k] = H;
                match camera.project(perturb(&pose, &delta).transform_point(*p)) {
                    Some(moved) => *column = (moved - base) / H,
                    None => usable = false,
                }
            }
            if !usable {
                continue;
            }
            let residual = *pixel - base;
            for i in 0..6 {
                for j in 0..6 {
                    normal[i][j] += jacobian[i].dot(jacobian[j]);
                }
                rhs[i] += jacobian[i].dot(residual);
            }
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut damped = normal;
            for (i, row) in damped.iter_mut().enumerate() {
                row[i] += lambda * normal[i][i].max(1e-12);
            }
            let Some(step) = solve(damped, rhs) else {
                lambda *= 10.0;
                continue;
            };
            let candidate = perturb(&pose, &step);
            let candidate_cost = cost(&candidate);
            if candidate_cost < current {
                let gain = current - candidate_cost;
                pose = candidate;
                current = candidate_cost;
                lambda = (lambda * 0.3).max(1e-9);
                improved = gain > 1e-14 * current.max(1e-20);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    pose
}

/// Result of [`calibrate_color_from_depth`].
#[derive(Debug, Clone, PartialEq)]
pub struct StereoCalibration {
    /// `point_in_color = color_from_depth * point_in_depth`, glTF camera frames (what
    /// `RigCalibration::color_from_depth` stores).
    pub color_from_depth: Pose,
    /// The same between the optical frames, as OpenCV reports it.
    pub color_optical_from_depth_optical: Rigid,
    /// RMS reprojection error over both cameras' points.
    pub rms_px: f64,
    /// Per view pair: (depth view, colour view, shared points, RMS in depth, RMS in colour).
    pub pairs: Vec<PairFit>,
    /// Pairs left out (too few shared points), with the reason.
    pub skipped: Vec<String>,
}

/// How one view pair fits the stereo calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct PairFit {
    pub depth_view: String,
    pub color_view: String,
    pub points: usize,
    pub depth_rms_px: f64,
    pub color_rms_px: f64,
}

/// Fewest pairs for a registration, and fewest shared points per pair.
const MIN_PAIRS: usize = 3;
const MIN_SHARED_POINTS: usize = 8;

/// Registers the depth camera to the colour camera from views of one target taken by both at
/// once: `pairs[i] = (depth detection, colour detection)`. Both cameras' intrinsics are fixed.
pub fn calibrate_color_from_depth(
    depth_camera: &Pinhole,
    color_camera: &Pinhole,
    pairs: &[(Detection, Detection)],
) -> Result<StereoCalibration, CalibrationError> {
    let mut object_points = Vector::<Vector<Point3f>>::new();
    let mut depth_points = Vector::<Vector<Point2f>>::new();
    let mut color_points = Vector::<Vector<Point2f>>::new();
    let mut used = Vec::new();
    let mut skipped = Vec::new();
    for (depth, color) in pairs {
        if (depth.width, depth.height) != (depth_camera.width, depth_camera.height)
            || (color.width, color.height) != (color_camera.width, color_camera.height)
        {
            return Err(CalibrationError::Unpaired(format!(
                "`{}` is {}x{} and `{}` is {}x{}, but the cameras are {}x{} (depth) and {}x{} \
                 (colour)",
                depth.view,
                depth.width,
                depth.height,
                color.view,
                color.width,
                color.height,
                depth_camera.width,
                depth_camera.height,
                color_camera.width,
                color_camera.height
            )));
        }
        let mut object = Vector::<Point3f>::new();
        let mut in_depth = Vector::<Point2f>::new();
        let mut in_color = Vector::<Point2f>::new();
        for ((id, p), pixel) in depth
            .ids
            .iter()
            .zip(&depth.object_points)
            .zip(&depth.image_points)
        {
            if let Some(q) = color.pixel_of(*id) {
                object.push(Point3f::new(p.x as f32, p.y as f32, p.z as f32));
                in_depth.push(Point2f::new(pixel.x as f32, pixel.y as f32));
                in_color.push(Point2f::new(q.x as f32, q.y as f32));
            }
        }
        if object.len() < MIN_SHARED_POINTS {
            skipped.push(format!(
                "`{}` + `{}`: {} shared points, at least {MIN_SHARED_POINTS} needed",
                depth.view,
                color.view,
                object.len()
            ));
            continue;
        }
        used.push((depth.view.clone(), color.view.clone(), object.len()));
        object_points.push(object);
        depth_points.push(in_depth);
        color_points.push(in_color);
    }
    if used.len() < MIN_PAIRS {
        return Err(CalibrationError::TooFewViews {
            what: "a depth-to-colour registration",
            found: used.len(),
            minimum: MIN_PAIRS,
        });
    }
    let matrix =
        |c: &Pinhole| Mat::from_slice_2d(&[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]]);
    let coefficients = |c: &Pinhole| -> Result<Mat, opencv::Error> {
        Mat::from_slice(&[c.k1, c.k2, c.p1, c.p2, c.k3])?.try_clone()
    };
    let mut k1 = matrix(depth_camera)?;
    let mut d1 = coefficients(depth_camera)?;
    let mut k2 = matrix(color_camera)?;
    let mut d2 = coefficients(color_camera)?;
    let mut r = Mat::default();
    let mut t = Mat::default();
    let mut e = Mat::default();
    let mut f = Mat::default();
    let mut per_view = Mat::default();
    let rms_px = calib3d::stereo_calibrate_extended(
        &object_points,
        &depth_points,
        &color_points,
        &mut k1,
        &mut d1,
        &mut k2,
        &mut d2,
        Size::new(depth_camera.width as i32, depth_camera.height as i32),
        &mut r,
        &mut t,
        &mut e,
        &mut f,
        &mut per_view,
        calib3d::CALIB_FIX_INTRINSIC,
        criteria(100, 1e-10),
    )?;
    if !rms_px.is_finite() {
        return Err(CalibrationError::Diverged(format!(
            "stereo reprojection RMS is {rms_px}"
        )));
    }
    let r = mat_values(&r)?;
    let t = mat_values(&t)?;
    if r.len() != 9 || t.len() != 3 {
        return Err(CalibrationError::Diverged(
            "stereoCalibrate returned no rotation".into(),
        ));
    }
    let rotation = DQuat::from_mat3(&glam::DMat3::from_cols_array(&[
        r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8],
    ]));
    let color_optical_from_depth_optical = Rigid::new(rotation, DVec3::new(t[0], t[1], t[2]));
    let errors = mat_values(&per_view)?;
    let pairs = used
        .into_iter()
        .enumerate()
        .map(|(i, (depth_view, color_view, points))| PairFit {
            depth_view,
            color_view,
            points,
            depth_rms_px: errors.get(2 * i).copied().unwrap_or(f64::NAN),
            color_rms_px: errors.get(2 * i + 1).copied().unwrap_or(f64::NAN),
        })
        .collect();
    Ok(StereoCalibration {
        color_from_depth: gl_from_optical_pair(&color_optical_from_depth_optical).to_pose(),
        color_optical_from_depth_optical,
        rms_px,
        pairs,
        skipped,
    })
}

/// Result of [`locate_probe`].
#[derive(Debug, Clone, PartialEq)]
pub struct ProbePose {
    /// The probe's pose in the world (relight's board frame of the target), glTF convention:
    /// what `RigCalibration::world_from_probe` stores.
    pub world_from_probe: Pose,
    /// The target's pose in the probe's optical frame.
    pub probe_from_target: Rigid,
    pub rms_px: f64,
    pub points: usize,
}

/// The fixed probe's pose in the world from its views of the target that defines the world
/// (all points of all views fitted to one pose: the probe and the target do not move).
pub fn locate_probe(
    probe: &CameraModel,
    geometry: &TargetGeometry,
    views: &[Detection],
) -> Result<ProbePose, CalibrationError> {
    let object: Vec<DVec3> = views.iter().flat_map(|v| v.object_points.clone()).collect();
    let image: Vec<DVec2> = views.iter().flat_map(|v| v.image_points.clone()).collect();
    if views.is_empty() {
        return Err(CalibrationError::TooFewViews {
            what: "locating the probe",
            found: 0,
            minimum: 1,
        });
    }
    let fit = estimate_pose(probe, &object, &image)?;
    Ok(ProbePose {
        world_from_probe: frame_from_camera_gl(
            &geometry.world_from_target(),
            &fit.camera_from_target,
        )
        .to_pose(),
        probe_from_target: fit.camera_from_target,
        rms_px: fit.rms_px,
        points: fit.points,
    })
}

/// The square marker on the lamp (config keys `dictionary`, `marker_id`, `size_m`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LampMarker {
    /// Marker family, e.g. `tag36h11` (the default) or `aruco_4x4_50`.
    #[serde(default = "default_lamp_dictionary")]
    pub dictionary: Dictionary,
    pub marker_id: u32,
    /// Edge of the marker's black square, metres.
    pub size_m: f64,
}

fn default_lamp_dictionary() -> Dictionary {
    Dictionary::AprilTag36h11
}

impl LampMarker {
    /// The marker's corners in relight's marker frame (centre, +X right, +Y up as printed, +Z
    /// out of the print), in OpenCV's detection order: top-left, top-right, bottom-right,
    /// bottom-left as printed.
    pub fn corners_in_marker(&self) -> [DVec3; 4] {
        let s = 0.5 * self.size_m;
        [
            DVec3::new(-s, s, 0.0),
            DVec3::new(s, s, 0.0),
            DVec3::new(s, -s, 0.0),
            DVec3::new(-s, -s, 0.0),
        ]
    }
}

/// One image of the lamp: its marker's pose and the light centre's pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct LampObservation {
    pub view: String,
    /// Optical frame of the camera, relight's marker frame.
    pub camera_from_marker: Rigid,
    pub marker_rms_px: f64,
    /// Centroid of the bright blob (the bulb), pixels.
    pub bulb_px: DVec2,
}

/// Finds the lamp's marker and bulb in one image (`threshold`: the 8-bit level above which a
/// pixel belongs to the bulb; the largest such blob is the bulb).
pub fn observe_lamp(
    camera: &CameraModel,
    marker: &LampMarker,
    view: &str,
    image: &Image,
    threshold: u8,
) -> Result<LampObservation, CalibrationError> {
    let found = detect_markers(view, image, marker.dictionary)?
        .into_iter()
        .find(|m| m.marker_id == marker.marker_id)
        .ok_or_else(|| CalibrationError::NoTargetDetected {
            view: view.to_owned(),
            target: format!("lamp marker {} {}", marker.dictionary, marker.marker_id),
        })?;
    let fit = estimate_pose(camera, &marker.corners_in_marker(), &found.corners)?;
    let bytes = luma(view, image)?;
    let bulb_px = bulb_centroid(
        &bytes,
        image.width() as usize,
        image.height() as usize,
        threshold,
    )
    .ok_or_else(|| CalibrationError::NoTargetDetected {
        view: view.to_owned(),
        target: format!("lamp bulb (no pixel at or above {threshold})"),
    })?;
    Ok(LampObservation {
        view: view.to_owned(),
        camera_from_marker: fit.camera_from_target,
        marker_rms_px: fit.rms_px,
        bulb_px,
    })
}

/// Centroid of the largest 4-connected blob of pixels at or above `threshold`, each pixel of the
/// blob and its 2-pixel surround weighted by how far it rises above the surround's level, so
/// that the partly covered pixels on its rim count by their coverage.
pub fn bulb_centroid(luma: &[u8], width: usize, height: usize, threshold: u8) -> Option<DVec2> {
    let mut label = vec![0u32; luma.len()];
    let mut best: Option<(usize, [usize; 4])> = None;
    let mut next = 0u32;
    let mut stack = Vec::new();
    for start in 0..luma.len() {
        if luma[start] < threshold || label[start] != 0 {
            continue;
        }
        next += 1;
        label[start] = next;
        stack.push(start);
        let mut size = 0usize;
        let mut bounds = [usize::MAX, usize::MAX, 0, 0];
        while let Some(i) = stack.pop() {
            size += 1;
            let (x, y) = (i % width, i / width);
            bounds = [
                bounds[0].min(x),
                bounds[1].min(y),
                bounds[2].max(x),
                bounds[3].max(y),
            ];
            let mut visit = |j: usize| {
                if luma[j] >= threshold && label[j] == 0 {
                    label[j] = next;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < width {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - width);
            }
            if y + 1 < height {
                visit(i + width);
            }
        }
        if best.is_none_or(|(best_size, _)| size > best_size) {
            best = Some((size, bounds));
        }
    }
    let (_, [x0, y0, x1, y1]) = best?;
    let (x0, y0) = (x0.saturating_sub(2), y0.saturating_sub(2));
    let (x1, y1) = ((x1 + 2).min(width - 1), (y1 + 2).min(height - 1));
    let mut ring: Vec<u8> = Vec::new();
    for y in y0..=y1 {
        for x in x0..=x1 {
            if x == x0 || x == x1 || y == y0 || y == y1 {
                ring.push(luma[y * width + x]);
            }
        }
    }
    ring.sort_unstable();
    let surround = f64::from(ring[ring.len() / 2]);
    let mut total = 0.0;
    let mut centroid = DVec2::ZERO;
    for y in y0..=y1 {
        for x in x0..=x1 {
            let weight = (f64::from(luma[y * width + x]) - surround).max(0.0);
            total += weight;
            centroid += weight * DVec2::new(x as f64, y as f64);
        }
    }
    (total > 0.0).then(|| centroid / total)
}

/// Result of [`locate_lamp_light`].
#[derive(Debug, Clone, PartialEq)]
pub struct LampCalibration {
    /// The light centre in the marker's frame (identity rotation: the light is a point); what
    /// `RigCalibration::lamp_marker_from_light` stores.
    pub lamp_marker_from_light: Pose,
    pub light_in_marker: DVec3,
    /// Distance of the light centre from each view's ray, metres.
    pub residuals_m: Vec<f64>,
    pub rms_m: f64,
    /// Largest angle between two views' rays in the marker's frame, degrees: how much the
    /// lamp was turned.
    pub spread_deg: f64,
}

/// Smallest ratio of the weakest to the strongest direction of the normal equations: below it
/// the rays are too close to parallel to place the light centre along them.
const MIN_RAY_CONDITIONING: f64 = 0.02;

/// The light centre in the marker's frame: the least-squares intersection of the rays towards
/// the bulb, each expressed in the marker's frame (see the module docs for the procedure).
pub fn locate_lamp_light(
    camera: &CameraModel,
    observations: &[LampObservation],
) -> Result<LampCalibration, CalibrationError> {
    let mut rays = Vec::with_capacity(observations.len());
    for observation in observations {
        let ray_in_camera = camera.unproject(observation.bulb_px).ok_or_else(|| {
            CalibrationError::IllConditioned {
                what: "lamp view".into(),
                hint: format!(
                    "`{}`: the bulb's pixel {} has no ray in this camera",
                    observation.view, observation.bulb_px
                ),
            }
        })?;
        let marker_from_camera = observation.camera_from_marker.inverse();
        rays.push((
            marker_from_camera.translation,
            marker_from_camera
                .transform_vector(ray_in_camera)
                .normalize(),
        ));
    }
    const MIN_VIEWS: usize = 3;
    if rays.len() < MIN_VIEWS {
        return Err(CalibrationError::TooFewViews {
            what: "locating the lamp's light centre",
            found: rays.len(),
            minimum: MIN_VIEWS,
        });
    }
    let mut normal = [[0.0; 3]; 3];
    let mut rhs = [0.0; 3];
    for (origin, direction) in &rays {
        for i in 0..3 {
            for j in 0..3 {
                let a = f64::from(u8::from(i == j)) - direction[i] * direction[j];
                normal[i][j] += a;
                rhs[i] += a * origin[j];
            }
        }
    }
    let spread_deg = rays
        .iter()
        .flat_map(|(_, a)| rays.iter().map(move |(_, b)| a.angle_between(*b)))
        .fold(0.0, f64::max)
        .to_degrees();
    let [weakest, _, strongest] = symmetric_eigenvalues_3(normal);
    if weakest.is_nan() || weakest <= MIN_RAY_CONDITIONING * strongest {
        return Err(CalibrationError::IllConditioned {
            what: "lamp light centre".into(),
            hint: format!(
                "the rays towards the bulb span only {spread_deg:.1}° in the marker's frame; \
                 turn the lamp by 30° or more between views, about different axes"
            ),
        });
    }
    let light =
        solve(normal, rhs)
            .map(DVec3::from)
            .ok_or_else(|| CalibrationError::IllConditioned {
                what: "lamp light centre".into(),
                hint: "the rays towards the bulb do not meet".into(),
            })?;
    let residuals_m: Vec<f64> = rays
        .iter()
        .map(|(origin, direction)| {
            let offset = light - *origin;
            (offset - direction * offset.dot(*direction)).length()
        })
        .collect();
    let rms_m = (residuals_m.iter().map(|r| r * r).sum::<f64>() / residuals_m.len() as f64).sqrt();
    Ok(LampCalibration {
        lamp_marker_from_light: Pose::from_translation(light.as_vec3()),
        light_in_marker: light,
        residuals_m,
        rms_m,
        spread_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bulb_centroid_weights_the_rim_by_coverage() {
        // A 2 × 2 saturated block with half-covered pixels to its right: the centroid moves
        // right by the half pixels' weight.
        let (w, h) = (10, 8);
        let mut image = vec![20u8; w * h];
        for (x, y) in [(3, 3), (4, 3), (3, 4), (4, 4)] {
            image[y * w + x] = 255;
        }
        for y in [3, 4] {
            image[y * w + 5] = 20 + (255 - 20) / 2;
        }
        let c = bulb_centroid(&image, w, h, 200).unwrap();
        // Weights: four pixels of 235 at x = 3, 4 and two of 117 at x = 5.
        let expected_x = (2.0 * 235.0 * 3.0 + 2.0 * 235.0 * 4.0 + 2.0 * 117.0 * 5.0)
            / (4.0 * 235.0 + 2.0 * 117.0);
        assert!(
            (c.x - expected_x).abs() < 1e-9 && (c.y - 3.5).abs() < 1e-9,
            "{c}"
        );
        // A second, smaller blob does not pull it.
        image[0] = 255;
        assert_eq!(bulb_centroid(&image, w, h, 200), Some(c));
        assert_eq!(bulb_centroid(&vec![0u8; w * h], w, h, 200), None);
    }

    #[test]
    fn lamp_marker_corners_follow_opencv_order_in_relights_marker_frame() {
        let marker = LampMarker {
            dictionary: Dictionary::AprilTag36h11,
            marker_id: 3,
            size_m: 0.06,
        };
        let [top_left, top_right, bottom_right, bottom_left] = marker.corners_in_marker();
        assert!(top_left.y > 0.0 && top_left.x < 0.0);
        assert!(top_right.x > 0.0 && bottom_right.y < 0.0 && bottom_left.x < 0.0);
        // +Z = X × Y points out of the print (towards a viewer of the print).
        let normal = (top_right - top_left).cross(top_left - bottom_left);
        assert!(normal.z > 0.0);
        let parsed: LampMarker = toml::from_str("marker_id = 3\nsize_m = 0.06\n").unwrap();
        assert_eq!(parsed, marker);
    }

    #[test]
    fn parallel_rays_are_reported_not_solved() {
        let camera = CameraModel::Pinhole(Pinhole {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        });
        // The lamp only slides sideways: every ray has (nearly) the same direction.
        let observations: Vec<LampObservation> = (0..5)
            .map(|i| LampObservation {
                view: format!("slide-{i}"),
                camera_from_marker: Rigid::new(
                    DQuat::from_rotation_x(std::f64::consts::PI),
                    DVec3::new(0.01 * f64::from(i), 0.0, 0.5),
                ),
                marker_rms_px: 0.1,
                bulb_px: DVec2::new(319.5 + 10.0 * f64::from(i), 200.0),
            })
            .collect();
        let err = locate_lamp_light(&camera, &observations)
            .unwrap_err()
            .to_string();
        assert!(err.contains("turn the lamp"), "{err}");
    }
}
