//! Registration: where the colour camera is in the world, frame by frame (`[tracking]`).
//!
//! The world frame is the marker board's: the board on the table defines it, and the rig's
//! calibration says where the board lies in it (`world_from_board`, identity for a lab whose
//! world *is* the board). Every frame set whose markers include tags of the board gives
//!
//! `world_from_camera = world_from_board · camera_from_board⁻¹`,
//!
//! with `camera_from_board` fitted to every visible tag corner at once through the colour camera's
//! calibrated model ([`Board::estimate`]: IPPE, Levenberg–Marquardt, outlier tags dropped).
//! Between detections the last pose is held and its age tracked; past `max_age` the camera is
//! *untracked* and the pipeline draws no Δ rather than a wrong one. `source = "scene"` keeps the
//! scene file's camera pose (a tripod registered once).

use std::time::Duration;

use glam::DVec2;
use relight_backends::markers::board::{Board, BoardConfig};
use relight_backends::markers::one_euro::{OneEuroConfig, PoseFilter};
use relight_backends::markers::pose::{DPose, PoseSettings};
use relight_core::camera::CameraModel;
use relight_core::rig::RigCalibration;
use relight_core::{MarkerSet, Pose};
use serde::{Deserialize, Serialize};

/// Where the camera pose comes from (`[tracking] source`, `relightd replay --tracking`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum TrackingSource {
    /// The world-defining marker board, seen by the colour camera.
    Markers,
    /// The scene file's camera pose: a fixed rig, registered once.
    Scene,
}

impl TrackingSource {
    pub fn name(self) -> &'static str {
        match self {
            TrackingSource::Markers => "markers",
            TrackingSource::Scene => "scene",
        }
    }
}

/// `[tracking]`, validated.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackingConfig {
    /// `None`: markers when a board is known (here or in the rig's calibration), else the scene.
    pub source: Option<TrackingSource>,
    /// The board's layout; without it, the rig calibration's.
    pub board: Option<BoardConfig>,
    /// One-Euro smoothing of the camera pose (off by default: it trades jitter for lag).
    pub smoothing: OneEuroConfig,
    /// How long a pose is held without a detection before the camera is untracked.
    pub max_age: Duration,
    /// A board fit whose corner RMS is above this, pixels, is not used.
    pub max_rms_px: f64,
}

impl Default for TrackingConfig {
    fn default() -> Self {
        Self {
            source: None,
            board: None,
            smoothing: OneEuroConfig {
                enabled: false,
                ..OneEuroConfig::default()
            },
            max_age: Duration::from_millis(250),
            max_rms_px: 2.0,
        }
    }
}

/// What the tracker knows of the camera this frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackingState {
    /// The scene file's pose (`source = "scene"`).
    Fixed,
    /// The board was fitted in this frame set.
    Tracked,
    /// No fit in this frame set; the last pose is younger than `max_age`.
    Held,
    /// No pose, or one older than `max_age`: no Δ is drawn.
    Untracked,
}

impl TrackingState {
    /// The state as status and `relightd score` name it.
    pub fn name(self) -> &'static str {
        match self {
            TrackingState::Fixed => "fixed",
            TrackingState::Tracked => "tracked",
            TrackingState::Held => "held",
            TrackingState::Untracked => "untracked",
        }
    }
}

/// One frame's registration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrackingReport {
    pub source: TrackingSource,
    pub state: TrackingState,
    /// `None` when untracked.
    pub world_from_camera: Option<Pose>,
    /// Age of the pose: time since the frame set it was fitted in, milliseconds.
    pub pose_age_ms: Option<f64>,
    /// Corner reprojection RMS of the fit the pose comes from, pixels.
    pub reprojection_rms_px: Option<f64>,
    /// Tags the last fit used.
    pub tags_used: usize,
}

impl TrackingReport {
    /// Whether the engines may draw Δ with this pose.
    pub fn is_usable(&self) -> bool {
        self.world_from_camera.is_some()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TrackingError {
    #[error("[tracking] board: {0}")]
    Board(String),
    #[error(
        "[tracking] source = \"markers\" needs {0}; give it in the rig calibration or set source = \"scene\""
    )]
    Missing(&'static str),
}

struct Fitted {
    host_ns: u64,
    world_from_camera: Pose,
    rms_px: f64,
    tags: usize,
}

/// The camera's registration across frames.
pub struct Tracker {
    source: TrackingSource,
    scene_pose: Pose,
    markers: Option<MarkerTracking>,
    config: TrackingConfig,
    last: Option<Fitted>,
    warned_unseen: bool,
    frames: u64,
}

struct MarkerTracking {
    board: Board,
    camera: CameraModel,
    world_from_board: DPose,
    filter: PoseFilter,
}

impl std::fmt::Debug for Tracker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tracker")
            .field("source", &self.source)
            .finish_non_exhaustive()
    }
}

impl Tracker {
    /// A tracker for a rig with `calibration`, whose scene file puts the camera at `scene_pose`.
    pub fn new(
        config: &TrackingConfig,
        calibration: Option<&RigCalibration>,
        scene_pose: Pose,
    ) -> Result<Self, TrackingError> {
        let board = match (&config.board, calibration.and_then(|c| c.board.as_ref())) {
            (Some(board), _) => Some(Board::from_config(board)),
            (None, Some(layout)) => Some(Board::from_layout(layout)),
            (None, None) => None,
        }
        .transpose()
        .map_err(|e| TrackingError::Board(e.to_string()))?;
        let camera = calibration.and_then(|c| c.color.or(c.depth));
        let source = config
            .source
            .unwrap_or(if board.is_some() && camera.is_some() {
                TrackingSource::Markers
            } else {
                TrackingSource::Scene
            });
        let markers = match source {
            TrackingSource::Scene => None,
            TrackingSource::Markers => Some(MarkerTracking {
                board: board.ok_or(TrackingError::Missing("a board layout"))?,
                camera: camera.ok_or(TrackingError::Missing("the colour camera's calibration"))?,
                world_from_board: DPose::from_pose(
                    &calibration.map_or(Pose::IDENTITY, |c| c.world_from_board),
                ),
                filter: PoseFilter::new(config.smoothing),
            }),
        };
        tracing::info!(source = source.name(), "camera tracking");
        Ok(Self {
            source,
            scene_pose,
            markers,
            config: config.clone(),
            last: None,
            warned_unseen: false,
            frames: 0,
        })
    }

    pub fn source(&self) -> TrackingSource {
        self.source
    }

    /// The registration of the frame set taken at host time `host_ns` with `markers`.
    pub fn update(&mut self, host_ns: u64, markers: Option<&MarkerSet>) -> TrackingReport {
        self.frames += 1;
        let Some(tracking) = &mut self.markers else {
            return TrackingReport {
                source: self.source,
                state: TrackingState::Fixed,
                world_from_camera: Some(self.scene_pose),
                pose_age_ms: None,
                reprojection_rms_px: None,
                tags_used: 0,
            };
        };
        let fitted = markers.and_then(|m| tracking.fit(m, self.config.max_rms_px));
        let state = match fitted {
            Some((pose, rms_px, tags)) => {
                let smoothed = tracking.filter.filter(host_ns, &DPose::from_pose(&pose));
                self.last = Some(Fitted {
                    host_ns,
                    world_from_camera: smoothed.to_pose(),
                    rms_px,
                    tags,
                });
                TrackingState::Tracked
            }
            None => TrackingState::Held,
        };
        let max_age_ns = u64::try_from(self.config.max_age.as_nanos()).unwrap_or(u64::MAX);
        let held = self
            .last
            .as_ref()
            .filter(|last| host_ns.saturating_sub(last.host_ns) <= max_age_ns);
        match held {
            Some(last) => TrackingReport {
                source: self.source,
                state,
                world_from_camera: Some(last.world_from_camera),
                pose_age_ms: Some(host_ns.saturating_sub(last.host_ns) as f64 * 1e-6),
                reprojection_rms_px: Some(last.rms_px),
                tags_used: last.tags,
            },
            None => {
                if self.last.is_none() && !self.warned_unseen && self.frames >= 30 {
                    self.warned_unseen = true;
                    tracing::warn!(
                        frames = self.frames,
                        board = tracking.board.name(),
                        "the marker board has not been seen: the camera is untracked and no Δ is drawn"
                    );
                }
                TrackingReport {
                    source: self.source,
                    state: TrackingState::Untracked,
                    world_from_camera: None,
                    pose_age_ms: self
                        .last
                        .as_ref()
                        .map(|last| host_ns.saturating_sub(last.host_ns) as f64 * 1e-6),
                    reprojection_rms_px: None,
                    tags_used: 0,
                }
            }
        }
    }
}

impl MarkerTracking {
    /// `world_from_camera`, the fit's corner RMS and the tags it used, from the board's tags among
    /// `markers` (other families and ids are ignored, non-finite corners never reach the fit).
    fn fit(&self, markers: &MarkerSet, max_rms_px: f64) -> Option<(Pose, f64, usize)> {
        let tags: Vec<(u32, [DVec2; 4])> = markers
            .detections
            .iter()
            .filter(|d| d.family == self.board.family())
            .filter(|d| d.corners_px.iter().all(|c| c.is_finite()))
            .map(|d| (d.marker_id, d.corners_px.map(|c| c.as_dvec2())))
            .collect();
        if tags.is_empty() {
            return None;
        }
        let fit = self
            .board
            .estimate(&tags, &self.camera, &PoseSettings::default())
            .inspect_err(|error| tracing::debug!(%error, "board not fitted"))
            .ok()?;
        let rms = fit.fit.reprojection_rms_px;
        let camera_from_board = fit.fit.camera_from_object();
        let world_from_camera = (self.world_from_board * camera_from_board.inverse()).to_pose();
        let finite = world_from_camera.translation.is_finite()
            && world_from_camera.rotation.is_finite()
            && rms.is_finite();
        (finite && rms <= max_rms_px).then_some((world_from_camera, rms, fit.tags_used.len()))
    }
}

#[cfg(test)]
mod tests {
    use glam::{Quat, Vec2, Vec3};
    use relight_backends::markers::board::corners_in_board;
    use relight_core::MarkerDetection;
    use relight_core::camera::{Pinhole, optical_from_gl};
    use relight_core::rig::BoardLayout;

    use super::*;

    fn rig() -> RigCalibration {
        RigCalibration {
            color: Some(CameraModel::Pinhole(Pinhole {
                width: 320,
                height: 240,
                fx: 260.0,
                fy: 260.0,
                cx: 159.5,
                cy: 119.5,
                k1: 0.0,
                k2: 0.0,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0,
            })),
            world_from_board: Pose::new(Quat::from_rotation_y(0.3), Vec3::new(0.2, 0.0, -0.1)),
            board: Some(BoardLayout {
                family: "tag36h11".into(),
                first_id: 0,
                cols: 2,
                rows: 2,
                tag_size_m: 0.1,
                gap_m: 0.02,
            }),
            ..RigCalibration::default()
        }
    }

    /// A camera 1 m above the board, looking down at it.
    fn world_from_camera(rig: &RigCalibration) -> Pose {
        let centre = rig.world_from_board.translation;
        Pose::look_at(centre + Vec3::new(0.1, 1.0, 0.3), centre, Vec3::Y)
    }

    /// The board's tags as a perfect detector sees them from `world_from_camera`.
    fn seen(rig: &RigCalibration, world_from_camera: &Pose) -> MarkerSet {
        let board = Board::from_layout(rig.board.as_ref().unwrap()).unwrap();
        let Some(CameraModel::Pinhole(camera)) = rig.color else {
            unreachable!()
        };
        let camera_from_board = world_from_camera.inverse() * rig.world_from_board;
        let detections = board
            .tags()
            .iter()
            .map(|tag| MarkerDetection {
                family: "tag36h11".into(),
                marker_id: tag.marker_id,
                corners_px: corners_in_board(tag).map(|p| {
                    let in_camera = camera_from_board.transform_point(p.as_vec3());
                    camera
                        .project(optical_from_gl(in_camera.as_dvec3()))
                        .unwrap()
                        .as_vec2()
                }),
                camera_from_marker: Pose::IDENTITY,
                reprojection_rms_px: 0.0,
            })
            .collect();
        MarkerSet { detections }
    }

    #[test]
    fn the_board_gives_the_world_pose_and_other_tags_and_nan_never_reach_it() {
        let rig = rig();
        let truth = world_from_camera(&rig);
        let mut tracker =
            Tracker::new(&TrackingConfig::default(), Some(&rig), Pose::IDENTITY).expect("markers");
        assert_eq!(tracker.source(), TrackingSource::Markers);
        let mut markers = seen(&rig, &truth);
        // A tag of another family with a board id, an id not on the board, a NaN corner.
        let mut foreign = markers.detections[0].clone();
        foreign.family = "aruco_4x4_50".into();
        foreign.corners_px[0] += Vec2::new(40.0, 0.0);
        let mut stranger = markers.detections[1].clone();
        stranger.marker_id = 99;
        let mut broken = markers.detections[2].clone();
        broken.corners_px[1] = Vec2::NAN;
        markers.detections.extend([foreign, stranger]);
        markers.detections[2] = broken;
        let report = tracker.update(1_000, Some(&markers));
        assert_eq!(report.state, TrackingState::Tracked);
        assert_eq!(report.tags_used, 3, "the NaN tag is left out");
        let pose = report.world_from_camera.expect("tracked");
        assert!(
            (pose.translation - truth.translation).length() < 1e-4,
            "{pose:?}"
        );
        assert!(pose.rotation.angle_between(truth.rotation) < 1e-3);
        assert!(report.reprojection_rms_px.unwrap() < 1e-2);
    }

    #[test]
    fn a_board_never_seen_is_untracked_and_the_scene_source_is_fixed() {
        let rig = rig();
        let mut tracker =
            Tracker::new(&TrackingConfig::default(), Some(&rig), Pose::IDENTITY).unwrap();
        for i in 0..40 {
            let report = tracker.update(i * 33_000_000, Some(&MarkerSet::default()));
            assert_eq!(report.state, TrackingState::Untracked);
            assert!(!report.is_usable());
        }
        let config = TrackingConfig {
            source: Some(TrackingSource::Scene),
            ..TrackingConfig::default()
        };
        let scene_pose = Pose::from_translation(Vec3::Y);
        let mut fixed = Tracker::new(&config, Some(&rig), scene_pose).unwrap();
        let report = fixed.update(0, None);
        assert_eq!(report.state, TrackingState::Fixed);
        assert_eq!(report.world_from_camera, Some(scene_pose));
        // Markers without a board to track: a clear error, not a silent tripod.
        let config = TrackingConfig {
            source: Some(TrackingSource::Markers),
            ..TrackingConfig::default()
        };
        let err = Tracker::new(&config, None, Pose::IDENTITY).unwrap_err();
        assert!(err.to_string().contains("board"), "{err}");
    }
}
