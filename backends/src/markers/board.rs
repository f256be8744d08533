//! Rigid boards of several tags, whose pose is solved from every visible tag's corners at once.
//!
//! A single tag's pose is weak where it matters most for AR: its out-of-plane rotation is set by
//! a few pixels of perspective across a small square, and a far tag's depth by its apparent size
//! alone. A board spreads the same corner noise over a wider baseline, and keeps its pose when
//! some of its tags are occluded or out of view.
//!
//! The board frame is the one of the simulator's printed board: origin at the board's centre,
//! tags in its x–y plane (+x right, +y up as printed), +z out of the print. Its detection is a
//! [`MarkerDetection`] whose `family` is the board's name, whose `corners_px` are the board's
//! outline (the rectangle around its tags in the board plane, lower-left first, counter-clockwise)
//! and whose `camera_from_marker` is `camera_from_board`.

use glam::{DVec2, DVec3, Quat, Vec2, Vec3};
use relight_core::camera::CameraModel;
use relight_core::rig::BoardLayout;
use relight_core::{MarkerDetection, Pose};
use serde::{Deserialize, Serialize};

use super::pose::{
    DPose, PoseError, PoseFit, PoseSettings, estimate_planar_pose, estimate_square_pose,
    refine_pose, square_corners_in_marker,
};
use super::tag36h11::TAG36H11;

/// One tag of a board.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardTag {
    pub marker_id: u32,
    /// The tag's frame in the board frame: `rotation` quaternion `[x, y, z, w]`, `translation`
    /// `[x, y, z]` metres.
    pub board_from_marker: Pose,
    /// Edge of the tag's detected square, metres.
    pub size_m: f64,
}

/// The `board` table of a marker tracker: either a printed grid (the simulator's layout) or a
/// free list of tags.
///
/// ```toml
/// [markers.board]
/// layout = "grid"     # cols × rows tags, consecutive ids left to right from the top row
/// first_id = 0
/// cols = 2
/// rows = 2
/// tag_size_m = 0.12   # edge of each tag's detected square
/// gap_m = 0.03        # between neighbouring tags' squares
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "layout", rename_all = "snake_case", deny_unknown_fields)]
pub enum BoardConfig {
    Grid {
        /// Reported as the board detection's `family` (default `board`).
        #[serde(default = "default_board_name")]
        name: String,
        /// Family of the board's tags (default `tag36h11`).
        #[serde(default = "default_board_family")]
        family: String,
        first_id: u32,
        cols: u32,
        rows: u32,
        tag_size_m: f64,
        gap_m: f64,
    },
    Tags {
        #[serde(default = "default_board_name")]
        name: String,
        #[serde(default = "default_board_family")]
        family: String,
        /// Reported as the board detection's `marker_id` (default: the first tag's id).
        #[serde(default)]
        marker_id: Option<u32>,
        tags: Vec<BoardTag>,
    },
}

fn default_board_name() -> String {
    "board".into()
}

fn default_board_family() -> String {
    TAG36H11.into()
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoardError {
    #[error("board configuration: {0}")]
    Config(String),
    #[error("none of the board's tags was detected")]
    NoTags,
    #[error("board pose: {0}")]
    Pose(#[from] PoseError),
}

/// A rigid board of tags.
#[derive(Debug, Clone, PartialEq)]
pub struct Board {
    name: String,
    family: String,
    marker_id: u32,
    tags: Vec<BoardTag>,
    /// Every tag corner lies on the board's z = 0 plane (IPPE applies to all of them at once).
    planar: bool,
    outline_in_board: [DVec3; 4],
}

/// A board pose with what went into it.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardFit {
    /// The board in the camera's optical frame, with its quality.
    pub fit: PoseFit,
    /// Tags whose corners the pose was fitted to.
    pub tags_used: Vec<u32>,
    /// Tags left out because their corners disagreed with the others (occlusion, a misdetected
    /// corner, a tag that is not where the layout says).
    pub tags_rejected: Vec<u32>,
}

/// Corner residual (RMS over a tag's four corners, pixels) above which a tag is an outlier:
/// ten times a sloppy corner detector's noise, far below what a moved or occluded tag gives.
const OUTLIER_RMS_PX: f64 = 3.0;

impl Board {
    /// A board from explicit tags; checks ids are unique and sizes positive.
    pub fn new(
        name: impl Into<String>,
        family: impl Into<String>,
        marker_id: Option<u32>,
        tags: Vec<BoardTag>,
    ) -> Result<Self, BoardError> {
        let first = tags
            .first()
            .ok_or_else(|| BoardError::Config("a board needs at least one tag".into()))?;
        let marker_id = marker_id.unwrap_or(first.marker_id);
        for (i, tag) in tags.iter().enumerate() {
            if !(tag.size_m.is_finite() && tag.size_m > 0.0) {
                return Err(BoardError::Config(format!(
                    "tag {} has size {} m; sizes must be positive",
                    tag.marker_id, tag.size_m
                )));
            }
            if !(tag.board_from_marker.translation.is_finite()
                && tag.board_from_marker.rotation.is_finite()
                && tag.board_from_marker.rotation.length() > 0.5)
            {
                return Err(BoardError::Config(format!(
                    "tag {} has no valid pose on the board",
                    tag.marker_id
                )));
            }
            if tags[..i].iter().any(|t| t.marker_id == tag.marker_id) {
                return Err(BoardError::Config(format!(
                    "tag {} is listed twice",
                    tag.marker_id
                )));
            }
        }
        let corners: Vec<DVec3> = tags.iter().flat_map(corners_in_board).collect();
        let extent = corners
            .iter()
            .map(|c| c.truncate().length())
            .fold(0.0, f64::max);
        let planar = corners.iter().all(|c| c.z.abs() <= 1e-6 * extent.max(1e-6));
        let (min, max) = corners.iter().fold(
            (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY)),
            |(lo, hi), c| (lo.min(c.truncate()), hi.max(c.truncate())),
        );
        Ok(Self {
            name: name.into(),
            family: family.into(),
            marker_id,
            tags,
            planar,
            outline_in_board: [
                DVec3::new(min.x, min.y, 0.0),
                DVec3::new(max.x, min.y, 0.0),
                DVec3::new(max.x, max.y, 0.0),
                DVec3::new(min.x, max.y, 0.0),
            ],
        })
    }

    /// The board a `board` config table describes.
    pub fn from_config(config: &BoardConfig) -> Result<Self, BoardError> {
        match config {
            BoardConfig::Grid {
                name,
                family,
                first_id,
                cols,
                rows,
                tag_size_m,
                gap_m,
            } => {
                if *cols == 0 || *rows == 0 {
                    return Err(BoardError::Config("a grid needs cols, rows ≥ 1".into()));
                }
                if !(gap_m.is_finite() && *gap_m >= 0.0) {
                    return Err(BoardError::Config(format!(
                        "gap_m must be ≥ 0, got {gap_m}"
                    )));
                }
                Self::grid(name, family, *first_id, *cols, *rows, *tag_size_m, *gap_m)
            }
            BoardConfig::Tags {
                name,
                family,
                marker_id,
                tags,
            } => Self::new(name.clone(), family.clone(), *marker_id, tags.clone()),
        }
    }

    /// The grid a rig's calibration describes, named `board`.
    pub fn from_layout(layout: &BoardLayout) -> Result<Self, BoardError> {
        Self::from_config(&BoardConfig::Grid {
            name: default_board_name(),
            family: layout.family.clone(),
            first_id: layout.first_id,
            cols: layout.cols,
            rows: layout.rows,
            tag_size_m: layout.tag_size_m,
            gap_m: layout.gap_m,
        })
    }

    /// A printed grid: rows from the top, IDs left to right, centred on the board's origin.
    fn grid(
        name: &str,
        family: &str,
        first_id: u32,
        cols: u32,
        rows: u32,
        tag_size_m: f64,
        gap_m: f64,
    ) -> Result<Self, BoardError> {
        let pitch = tag_size_m + gap_m;
        let (width, height) = (f64::from(cols) * pitch, f64::from(rows) * pitch);
        let tags = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (r, c)))
            .map(|(r, c)| BoardTag {
                marker_id: first_id + r * cols + c,
                board_from_marker: Pose::new(
                    Quat::IDENTITY,
                    Vec3::new(
                        (-width / 2.0 + (f64::from(c) + 0.5) * pitch) as f32,
                        (height / 2.0 - (f64::from(r) + 0.5) * pitch) as f32,
                        0.0,
                    ),
                ),
                size_m: tag_size_m,
            })
            .collect();
        Self::new(name, family, Some(first_id), tags)
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn family(&self) -> &str {
        &self.family
    }

    pub fn marker_id(&self) -> u32 {
        self.marker_id
    }

    pub fn tags(&self) -> &[BoardTag] {
        &self.tags
    }

    pub fn tag(&self, marker_id: u32) -> Option<&BoardTag> {
        self.tags.iter().find(|t| t.marker_id == marker_id)
    }

    /// The rectangle around the tags in the board plane: lower-left, lower-right, upper-right,
    /// upper-left.
    pub fn outline_in_board(&self) -> [DVec3; 4] {
        self.outline_in_board
    }

    /// The board's pose from detected tags of its family (`(marker_id, corners_px)` in
    /// [`MarkerDetection`] order; ids not on the board are ignored, an id seen twice is not
    /// trusted). All corners are fitted jointly; tags that disagree with the rest are dropped
    /// one at a time, worst first, and the pose refitted.
    pub fn estimate(
        &self,
        detections: &[(u32, [DVec2; 4])],
        camera: &CameraModel,
        settings: &PoseSettings,
    ) -> Result<BoardFit, BoardError> {
        let mut used: Vec<(&BoardTag, [DVec2; 4])> = detections
            .iter()
            .filter(|(id, _)| detections.iter().filter(|(other, _)| other == id).count() == 1)
            .filter_map(|(id, corners)| self.tag(*id).map(|tag| (tag, *corners)))
            .collect();
        let mut rejected = Vec::new();
        loop {
            if used.is_empty() {
                return Err(BoardError::NoTags);
            }
            let fit = self.fit(&used, camera, settings)?;
            let worst = used
                .iter()
                .enumerate()
                .map(|(i, (tag, corners))| {
                    (
                        i,
                        tag_rms_px(&fit.optical_from_object, tag, corners, camera),
                    )
                })
                .max_by(|a, b| a.1.total_cmp(&b.1));
            match worst {
                Some((i, rms)) if rms > OUTLIER_RMS_PX && used.len() > 1 => {
                    rejected.push(used.remove(i).0.marker_id);
                }
                _ => {
                    return Ok(BoardFit {
                        fit,
                        tags_used: used.iter().map(|(tag, _)| tag.marker_id).collect(),
                        tags_rejected: rejected,
                    });
                }
            }
        }
    }

    fn fit(
        &self,
        used: &[(&BoardTag, [DVec2; 4])],
        camera: &CameraModel,
        settings: &PoseSettings,
    ) -> Result<PoseFit, BoardError> {
        let points: Vec<DVec3> = used
            .iter()
            .flat_map(|(tag, _)| corners_in_board(tag))
            .collect();
        let pixels: Vec<DVec2> = used.iter().flat_map(|(_, corners)| *corners).collect();
        if self.planar {
            // IPPE on the plane z = 0; corners off it by rounding of the layout's f32 poses
            // (≤ 1e-6 of the board) are then fitted as they are.
            let flat: Vec<DVec3> = points.iter().map(|p| p.truncate().extend(0.0)).collect();
            let fit = estimate_planar_pose(&flat, &pixels, camera, settings)?;
            if flat == points {
                return Ok(fit);
            }
            let mut refined =
                refine_pose(&fit.optical_from_object, &points, &pixels, camera, settings)?;
            refined.alternative_rms_px = fit.alternative_rms_px;
            return Ok(refined);
        }
        // Not coplanar: start from the tag that looks largest, refine on every corner.
        let (tag, corners) = used
            .iter()
            .max_by(|a, b| quad_area(&a.1).total_cmp(&quad_area(&b.1)))
            .ok_or(BoardError::NoTags)?;
        let tag_fit = estimate_square_pose(corners, tag.size_m, camera, settings)?;
        let board_from_marker = DPose::from_pose(&tag.board_from_marker);
        let initial = tag_fit.optical_from_object * board_from_marker.inverse();
        Ok(refine_pose(&initial, &points, &pixels, camera, settings)?)
    }

    /// The board's detection: its pose and its outline in the image. An outline corner that does
    /// not project (out of a fish-eye's field) is reported at the mean of the corners the pose
    /// was fitted to.
    pub fn detection(
        &self,
        fit: &BoardFit,
        corners_used_px: &[DVec2],
        camera: &CameraModel,
    ) -> MarkerDetection {
        let fallback = if corners_used_px.is_empty() {
            DVec2::ZERO
        } else {
            corners_used_px.iter().sum::<DVec2>() / corners_used_px.len() as f64
        };
        let corners_px = self.outline_in_board.map(|corner| {
            camera
                .project(fit.fit.optical_from_object.transform_point(corner))
                .unwrap_or(fallback)
                .as_vec2()
        });
        fit.fit.detection(&self.name, self.marker_id, corners_px)
    }
}

/// A tag's corners in the board frame, in [`MarkerDetection`] order.
pub fn corners_in_board(tag: &BoardTag) -> [DVec3; 4] {
    let board_from_marker = DPose::from_pose(&tag.board_from_marker);
    square_corners_in_marker(tag.size_m).map(|c| board_from_marker.transform_point(c))
}

fn tag_rms_px(
    optical_from_board: &DPose,
    tag: &BoardTag,
    corners_px: &[DVec2; 4],
    camera: &CameraModel,
) -> f64 {
    let sum: f64 = corners_in_board(tag)
        .iter()
        .zip(corners_px)
        .map(|(corner, observed)| {
            camera
                .project(optical_from_board.transform_point(*corner))
                .map_or(f64::INFINITY, |p| p.distance_squared(*observed))
        })
        .sum();
    (sum / 4.0).sqrt()
}

/// Area of a quadrilateral (shoelace), pixels².
fn quad_area(corners: &[DVec2; 4]) -> f64 {
    let twice: f64 = (0..4)
        .map(|i| corners[i].perp_dot(corners[(i + 1) % 4]))
        .sum();
    twice.abs() / 2.0
}

/// Corners as the `f32` pixels of a [`MarkerDetection`].
pub fn corners_f32(corners: &[DVec2; 4]) -> [Vec2; 4] {
    corners.map(|c| c.as_vec2())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::markers::pose::CAMERA_FROM_OPTICAL;
    use glam::DQuat;
    use relight_core::camera::Pinhole;

    fn camera() -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
            k1: -0.05,
            k2: 0.01,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })
    }

    /// A 3 × 2 grid from ID 4, as the simulator's demo board is laid out.
    fn grid_board() -> Board {
        Board::from_layout(&BoardLayout {
            family: TAG36H11.into(),
            first_id: 4,
            cols: 3,
            rows: 2,
            tag_size_m: 0.08,
            gap_m: 0.02,
        })
        .unwrap()
    }

    fn observe(board: &Board, camera_from_board: &DPose) -> Vec<(u32, [DVec2; 4])> {
        let optical_from_board = CAMERA_FROM_OPTICAL * *camera_from_board;
        board
            .tags()
            .iter()
            .map(|tag| {
                let corners = corners_in_board(tag).map(|c| {
                    camera()
                        .project(optical_from_board.transform_point(c))
                        .unwrap()
                });
                (tag.marker_id, corners)
            })
            .collect()
    }

    #[test]
    fn grid_layout_numbers_tags_and_outlines_them() {
        let board = grid_board();
        assert_eq!(board.tags().len(), 6);
        assert_eq!(board.marker_id(), 4);
        let first = board.tag(4).unwrap().board_from_marker.translation;
        assert!(
            (first - Vec3::new(-0.1, 0.05, 0.0)).length() < 1e-6,
            "{first}"
        );
        let outline = board.outline_in_board();
        assert!((outline[2].x - (0.15 - 0.01)).abs() < 1e-6, "{outline:?}");
        assert!((outline[0].y + (0.10 - 0.01)).abs() < 1e-6);
    }

    #[test]
    fn joint_pose_from_a_subset_of_tags_is_exact() {
        let board = grid_board();
        let truth = DPose::new(
            DQuat::from_rotation_x(-0.9) * DQuat::from_rotation_z(0.2),
            DVec3::new(0.05, -0.1, -1.1),
        );
        let seen = observe(&board, &truth);
        let fit = board
            .estimate(&seen[1..4], &camera(), &PoseSettings::default())
            .unwrap();
        let estimate = CAMERA_FROM_OPTICAL * fit.fit.optical_from_object;
        assert!(estimate.translation.distance(truth.translation) < 1e-9);
        assert!(estimate.angle_to(&truth) < 1e-9);
        assert_eq!(fit.tags_used, vec![5, 6, 7]);
        assert!(fit.tags_rejected.is_empty());
        assert_eq!(fit.fit.points, 12);
    }

    #[test]
    fn a_displaced_tag_is_rejected() {
        let board = grid_board();
        let truth = DPose::new(DQuat::from_rotation_x(-0.6), DVec3::new(0.0, 0.0, -1.0));
        let mut seen = observe(&board, &truth);
        for corner in &mut seen[2].1 {
            *corner += DVec2::new(9.0, -4.0);
        }
        // Unknown ids and duplicated ids are ignored.
        seen.push((99, seen[0].1));
        seen.push((seen[3].0, seen[3].1));
        let fit = board
            .estimate(&seen, &camera(), &PoseSettings::default())
            .unwrap();
        assert_eq!(fit.tags_rejected, vec![6]);
        assert_eq!(fit.tags_used, vec![4, 5, 8, 9]);
        let estimate = CAMERA_FROM_OPTICAL * fit.fit.optical_from_object;
        assert!(estimate.translation.distance(truth.translation) < 1e-9);
    }

    #[test]
    fn tags_turned_in_the_board_plane_keep_it_planar() {
        // f32 rotations about z leave corners within rounding of z = 0.
        let tags = (0..3)
            .map(|i| BoardTag {
                marker_id: 10 + i,
                board_from_marker: Pose::new(
                    Quat::from_rotation_z(0.7 * i as f32) * Quat::from_rotation_x(1e-7),
                    Vec3::new(0.1 * i as f32 - 0.1, 0.03 * i as f32, 0.0),
                ),
                size_m: 0.06,
            })
            .collect();
        let board = Board::new("turned", TAG36H11, None, tags).unwrap();
        assert!(board.planar);
        let truth = DPose::new(DQuat::from_rotation_y(0.5), DVec3::new(0.02, 0.0, -0.7));
        let fit = board
            .estimate(
                &observe(&board, &truth),
                &camera(),
                &PoseSettings::default(),
            )
            .unwrap();
        let estimate = CAMERA_FROM_OPTICAL * fit.fit.optical_from_object;
        assert!(estimate.translation.distance(truth.translation) < 1e-8);
        assert!(estimate.angle_to(&truth) < 1e-8);
    }

    #[test]
    fn non_coplanar_boards_start_from_one_tag() {
        // Two tags on the faces of a 90° fold.
        let tags = vec![
            BoardTag {
                marker_id: 1,
                board_from_marker: Pose::new(
                    Quat::from_rotation_y(-0.6),
                    Vec3::new(-0.06, 0.0, 0.0),
                ),
                size_m: 0.08,
            },
            BoardTag {
                marker_id: 2,
                board_from_marker: Pose::new(Quat::from_rotation_y(0.6), Vec3::new(0.06, 0.0, 0.0)),
                size_m: 0.08,
            },
        ];
        let board = Board::new("fold", TAG36H11, None, tags).unwrap();
        let truth = DPose::new(DQuat::from_rotation_x(0.3), DVec3::new(0.0, 0.05, -0.8));
        let fit = board
            .estimate(
                &observe(&board, &truth),
                &camera(),
                &PoseSettings::default(),
            )
            .unwrap();
        let estimate = CAMERA_FROM_OPTICAL * fit.fit.optical_from_object;
        assert!(estimate.translation.distance(truth.translation) < 1e-8);
        assert!(estimate.angle_to(&truth) < 1e-8);
        let detection = board.detection(&fit, &[], &camera());
        assert_eq!(
            (detection.family.as_str(), detection.marker_id),
            ("fold", 1)
        );
    }

    #[test]
    fn config_forms_parse_and_bad_ones_are_rejected() {
        let grid: BoardConfig = serde_json::from_str(
            r#"{"layout": "grid", "first_id": 0, "cols": 2, "rows": 2, "tag_size_m": 0.12, "gap_m": 0.03}"#,
        )
        .unwrap();
        let board = Board::from_config(&grid).unwrap();
        assert_eq!((board.name(), board.family()), ("board", "tag36h11"));
        assert_eq!(board.tags().len(), 4);
        let tags: BoardConfig = serde_json::from_str(
            r#"{"layout": "tags", "name": "lamp", "family": "tagStandard41h12", "tags": [
                {"marker_id": 3, "board_from_marker": {"rotation": [0, 0, 0, 1], "translation": [0, 0, 0]}, "size_m": 0.05}
            ]}"#,
        )
        .unwrap();
        let board = Board::from_config(&tags).unwrap();
        assert_eq!((board.name(), board.marker_id()), ("lamp", 3));
        assert!(
            serde_json::from_str::<BoardConfig>(
                r#"{"layout": "grid", "first_id": 0, "cols": 2, "rows": 2, "tag_size_m": 0.1, "gap_m": 0.0, "colour": 1}"#
            )
            .is_err()
        );
        let empty = BoardConfig::Tags {
            name: "x".into(),
            family: TAG36H11.into(),
            marker_id: None,
            tags: vec![],
        };
        assert!(matches!(
            Board::from_config(&empty),
            Err(BoardError::Config(_))
        ));
        let zero = BoardConfig::Grid {
            name: "x".into(),
            family: TAG36H11.into(),
            first_id: 0,
            cols: 0,
            rows: 1,
            tag_size_m: 0.1,
            gap_m: 0.0,
        };
        assert!(Board::from_config(&zero).is_err());
        assert_eq!(
            grid_board().estimate(&[], &camera(), &PoseSettings::default()),
            Err(BoardError::NoTags)
        );
    }
}
